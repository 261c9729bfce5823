"""Benchmark the resampling-field inverse (`warp --displacement-to`): F^-1(y) - y per output voxel.

    python benchmarks/bench_export.py [--quick]

A ``n^3`` input (spacing 1, 1.2, 1.5), the 9^3 lattice at oversample 2, every
control point offset by N(0, 1.5 voxel); the output grid is the input's.
Rows: the numba kernel (:meth:`ForwardMap.resampling_field`, warm: loaded from
numba's cache), the vectorised numpy reference it replaced
(``_resampling_field_numpy``, the same Newton iteration; 64^3 only in a quick
run), and SimpleITK's ``InvertDisplacementField`` on the forward field as a
peer (a different method: a fixed-point iteration on the sampled field, default
settings, 20 iterations). The first-call compile time is measured in a fresh
process with an empty ``NUMBA_CACHE_DIR``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))

from common import median_time, row  # noqa: E402


def forward_map(n: int, sigma: float = 1.5, seed: int = 0):
    from volwarp_cli.bspline.lattice import Lattice
    from volwarp_cli.volume import Volume
    from volwarp_cli.warp.export import ForwardMap

    grid = Lattice.create((n, n, n), (9, 9, 9), 2)
    dq = np.random.default_rng(seed).normal(0, sigma, grid.lattice[::-1] + (3,))
    return ForwardMap(grid, dq, Volume(np.zeros((n, n, n), np.uint8), spacing=(1.0, 1.2, 1.5)))


COMPILE = """
import sys, time
sys.path.insert(0, {root!r})
t = time.perf_counter()
import numpy as np
from benchmarks.bench_export import forward_map
fm = forward_map(16)
t0 = time.perf_counter()
fm.resampling_field((16, 16, 16), np.zeros(3))
print(time.perf_counter() - t0)
"""


def compile_time() -> float:
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        out = subprocess.run([sys.executable, "-c", COMPILE.format(root=str(ROOT))], env=env,
                             capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def sitk_peer(fm):
    """SimpleITK's InvertDisplacementField of the forward field (input grid, world mm)."""
    import SimpleITK as sitk

    fwd = fm.forward_field().astype(np.float64)
    img = sitk.GetImageFromArray(fwd, isVector=True)
    img.SetSpacing(tuple(float(v) for v in fm.geometry.spacing))
    img.SetOrigin(tuple(float(v) for v in fm.geometry.origin))
    img.SetDirection(tuple(float(v) for v in fm.geometry.direction.ravel()))
    return lambda: sitk.InvertDisplacementField(img, maximumNumberOfIterations=20,
                                                maxErrorToleranceThreshold=0.01,
                                                meanErrorToleranceThreshold=0.0001,
                                                enforceBoundaryCondition=True)


def main(quick: bool = False) -> None:
    shift = np.zeros(3)
    print("resampling field F^-1(y) - y: n^3 input and output, 9^3 lattice, "
          "offsets N(0, 1.5 voxel)")
    t = compile_time()
    print(f"  first call in a new process, empty numba cache (compile + 16^3): {t:.2f} s")
    for n in ((64,) if quick else (64, 128)):
        fm = forward_map(n)
        shape = (n, n, n)
        fast = median_time(lambda fm=fm, shape=shape: fm.resampling_field(shape, shift), repeat=3)
        one = median_time(lambda fm=fm, shape=shape: fm.resampling_field(shape, shift, threads=1),
                          repeat=3)
        row(f"{n}^3 kernel ({os.cpu_count()} threads)", fast)
        row(f"{n}^3 kernel (1 thread)", one)
        if n == 64 or not quick:
            start = time.perf_counter()
            fm._resampling_field_numpy(shape, shift)
            ref = time.perf_counter() - start
            row(f"{n}^3 kernel vs the numpy reference (before)", fast, ref, "numpy")
        try:
            peer = sitk_peer(fm)
        except ImportError:
            continue
        other = median_time(peer, repeat=1 if n > 64 else 3)
        row(f"{n}^3 kernel vs SimpleITK InvertDisplacementField", fast, other, "sitk")


if __name__ == "__main__":
    main(quick="--quick" in sys.argv[1:])
