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


def command_time(argv: list[str], repeat: int = 3, warmup: int = 1) -> float:
    """Median wall time of a whole command (a new process each run)."""
    def run():
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL)
    return median_time(run, repeat=repeat, warmup=warmup)


def volwarp_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "volwarp_cli", *args]


def row(name: str, ours: float, peer: float | None = None, peer_name: str = "peer") -> None:
    """Print one comparison row: our time, the peer's, and ours / peer."""
    if peer is None:
        print(f"  {name:<48} volwarp {ours:8.3f} s", flush=True)
    else:
        print(f"  {name:<48} volwarp {ours:8.3f} s   {peer_name} {peer:8.3f} s   "
              f"ratio {ours / peer:6.2f}x", flush=True)
