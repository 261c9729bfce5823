"""Benchmark label-map warping against the intensity warp of the same volume.

    python benchmarks/bench_labels.py [--n 256] [--repeat 3]

A ``n^3`` uint16 label map (a ball cut into 8 or 150 Voronoi cells, background
0 around it), the default 9^3 lattice at oversample 2, one control point moved
by (6, -4, 5) voxels. Each case runs in its own process (peak memory, VmHWM):
``intensity`` is the one-shot intensity warp core (deferred capture + streamed
render), ``labels`` the label warp core (capture_labels + warp_labels); times
are medians of ``--repeat`` runs after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))

import common  # noqa: E402


def label_map(n: int, cells: int) -> np.ndarray:
    """A ball of ``cells`` Voronoi cells (labels 1..cells, shuffled ids), 0 outside."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(cells)
    c = 64
    z, y, x = (np.indices((c, c, c)).reshape(3, -1) + 0.5) / c - 0.5
    seeds = rng.uniform(-0.35, 0.35, (cells, 3))
    _, idx = cKDTree(seeds).query(np.stack([z, y, x], axis=1))
    ids = rng.permutation(np.arange(1, cells + 1) * 7)  # non-consecutive ids
    coarse = ids[idx].reshape(c, c, c).astype(np.uint16)
    r = (z * z + y * y + x * x).reshape(c, c, c)
    coarse[r > 0.4 ** 2] = 0
    k = -(-n // c)
    full = coarse.repeat(k, 0).repeat(k, 1).repeat(k, 2)[:n, :n, :n]
    return np.ascontiguousarray(full)


def peak_rss_mib() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def case(kind: str, n: int, cells: int, repeat: int) -> dict:
    from volwarp_cli.bspline.capture import capture_volume
    from volwarp_cli.bspline.scene import Scene
    from volwarp_cli.volume import Volume
    from volwarp_cli.warp.labels import capture_labels, warp_labels

    lab = label_map(n, cells)
    vol = Volume(lab)
    base = peak_rss_mib()

    def dq_of(cap):
        dq = cap.dq.copy()
        dq[4, 4, 4] += (6.0, -4.0, 5.0)
        return dq

    def intensity():
        cap = capture_volume(vol, lattice=(9, 9, 9), oversample=2, mean=False, defer=True)
        return common.one_shot(Scene(cap.voxmap, cap.grid, dq_of(cap), 8,
                                     domain_range=cap.stats[:2]))

    def labels():
        cap = capture_labels(vol, lattice=(9, 9, 9), oversample=2)
        scene = Scene(cap.voxmap, cap.grid, dq_of(cap), 8, domain_range=(0.0, 1.0))
        return warp_labels(lab, scene).target

    fn = intensity if kind == "intensity" else labels
    out = fn()  # warm-up
    del out
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
        del out
    return {"kind": kind, "cells": cells, "seconds": statistics.median(times),
            "peak_mib": peak_rss_mib(), "input_mib": lab.nbytes / 2 ** 20,
            "before_mib": base}


def main(quick: bool = False, argv: list[str] | None = None) -> None:
    """``benchmarks/run.py labels`` calls this with ``quick`` (128^3) and no arguments."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=128 if quick else 256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--case", default=None)
    ap.add_argument("--cells", type=int, default=8)
    a = ap.parse_args([] if argv is None else argv)
    if a.case:
        print(json.dumps(case(a.case, a.n, a.cells, a.repeat)))
        return
    res = {}
    for cells in (8, 150):
        for kind in ("intensity", "labels"):
            p = subprocess.run([sys.executable, __file__, "--case", kind, "--cells", str(cells),
                                "--n", str(a.n), "--repeat", str(a.repeat)],
                               capture_output=True, text=True, check=True)
            res[kind, cells] = json.loads(p.stdout.strip().splitlines()[-1])
    print(f"{a.n}^3 uint16 label map, 9^3 lattice, oversample 2, one point moved")
    for cells in (8, 150):
        i, lab = res["intensity", cells], res["labels", cells]
        print(f"{cells:>3} labels: intensity {i['seconds']:.3f} s, peak {i['peak_mib']:.0f} MiB "
              f"(map built: {i['before_mib']:.0f}); labels {lab['seconds']:.3f} s, peak "
              f"{lab['peak_mib']:.0f} MiB (map built: {lab['before_mib']:.0f}); "
              f"time {lab['seconds'] / i['seconds']:.2f}x, memory "
              f"{(lab['peak_mib'] - lab['before_mib']) / max(i['peak_mib'] - i['before_mib'], 1):.2f}x "
              "(above the built map)")


if __name__ == "__main__":
    main(argv=sys.argv[1:])
