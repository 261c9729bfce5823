"""Benchmark `volwarp morph`: frames interpolate, distance fields are computed once.

    python benchmarks/bench_morph.py [--quick]

A ball -> torus morph on a 128^3 grid (64^3 with --quick), 32 frames written as
NRRD by the command (a new process, I/O included). Per frame: the difference
between a 32-frame and a 2-frame run, divided by 30. Rows: time per frame vs one
volwarp distance computation, and vs the naive peer that recomputes a distance
field per frame with scipy (distance_transform_edt, both sides); the whole
morph vs the same 32 scipy recomputations.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))

from common import median_time, row, volwarp_argv  # noqa: E402


def main(quick: bool = False) -> None:
    import subprocess

    from scipy import ndimage as ndi

    from volwarp_cli.distance.field import signed_distance

    n = 64 if quick else 128
    frames = 32
    sys.path.insert(0, str(ROOT / "examples" / "morph-topology"))
    import make_shapes

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        make_shapes.main([str(tmp), "--size", str(n)])
        from volwarp_cli.io import read_volume

        ball = read_volume(tmp / "ball.nrrd").data
        one = median_time(lambda: signed_distance(ball, (1, 1, 1), iso=0.5), repeat=3)
        mask = ball > 0.5
        peer = median_time(lambda: ndi.distance_transform_edt(~mask)
                           - ndi.distance_transform_edt(mask), repeat=3)
        def command(count):
            return volwarp_argv("morph", str(tmp / "ball.nrrd"), str(tmp / "torus.nrrd"),
                                "--iso", "0.5", "--frames", str(count),
                                "-o", str(tmp / f"f{count}_{{i:02d}}.nrrd"))

        def timed(count):
            runs = []
            for _ in range(3):
                t = time.perf_counter()
                subprocess.run(command(count), check=True)
                runs.append(time.perf_counter() - t)
            return float(np.median(runs))

        subprocess.run(command(2), check=True)  # warm the numba cache
        short = timed(2)
        total = timed(frames)
        nbytes = sum(f.stat().st_size for f in tmp.glob(f"f{frames}_*.nrrd"))
    # the difference of a 32- and a 2-frame run is 30 frames' work (start-up,
    # reading and both distance fields cancel out)
    per_frame = (total - short) / (frames - 2)
    print(f"  {frames} frames of {n}^3 written as NRRD ({nbytes / 2**20:.0f} MiB); the two "
          "fields computed once")
    row(f"morph per frame {n}^3 (vs one volwarp distance)", per_frame, one, "distance")
    row(f"morph per frame {n}^3 (vs scipy recomputation)", per_frame, peer, "scipy")
    row(f"whole morph command, {frames} frames", total, frames * peer, f"{frames}x scipy")


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
