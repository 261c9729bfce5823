"""Timing helpers shared by the benchmarks (public tools only: time.perf_counter, subprocess)."""

from __future__ import annotations

import statistics
import subprocess
import sys
import time


def median_time(fn, repeat: int = 5, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeat`` runs after ``warmup`` runs."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def process(argv: list[str], env: dict | None = None):
    """A callable that runs ``argv`` as a new process (its output dropped; a failure raises)."""
    def run():
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, env=env)
    return run


def command_time(argv: list[str], repeat: int = 3, warmup: int = 1) -> float:
    """Median wall time of a whole command (a new process each run)."""
    return median_time(process(argv), repeat=repeat, warmup=warmup)


def paired_times(ours, peer, pairs: int) -> tuple[float, float, float]:
    """Run ``ours()`` and ``peer()`` in turn ``pairs`` times (A B A B ...).

    Returns the medians of both and the median of the pair-by-pair ratios
    ours / peer, which stays meaningful when the machine's speed drifts
    during the run (this machine's drifts by 20-30% within minutes).
    """
    a, b = [], []
    for _ in range(pairs):
        for fn, times in ((ours, a), (peer, b)):
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
    ratio = statistics.median(x / y for x, y in zip(a, b, strict=True))
    return statistics.median(a), statistics.median(b), ratio


def volwarp_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "volwarp_cli", *args]


def row(name: str, ours: float, peer: float | None = None, peer_name: str = "peer",
        ratio: float | None = None) -> None:
    """Print one comparison row: our time, the peer's, and ours / peer.

    ``ratio``: the median of paired ratios (see :func:`paired_times`) instead
    of the ratio of the medians.
    """
    if peer is None:
        print(f"  {name:<48} volwarp {ours:8.3f} s", flush=True)
    else:
        r = ours / peer if ratio is None else ratio
        paired = f"{r:6.3f}x (paired)" if ratio is not None else f"{r:6.2f}x"
        print(f"  {name:<48} volwarp {ours:8.3f} s   {peer_name} {peer:8.3f} s   "
              f"ratio {paired}", flush=True)


def one_shot(scene):
    """The one-shot warp of ``scene`` (built from a deferred capture): the command's renderer.

    The whole target as one block of :func:`volwarp_cli.warp.blocks.warp_block`,
    the ring stream every warp command runs (``Scene.render_once`` is gone).
    """
    from volwarp_cli.warp.blocks import warp_block

    return warp_block(scene, scene.sampler, scene.target_box)
