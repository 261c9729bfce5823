"""Benchmark `volwarp distance` against scipy, SimpleITK and edt (same run).

    python benchmarks/bench_distance.py [--quick]

A 256^3 shape (two overlapping ellipsoids; 128^3 with --quick). Rows:

* the in-process signed Euclidean core vs scipy.ndimage.distance_transform_edt
  (both sides), SimpleITK SignedMaurerDistanceMap and edt.sdf;
* the whole ``volwarp distance`` command (a new process, NRRD in and out) vs
  the scipy reference; its input is the same binary mask (uint8, unit
  spacing), so it takes the exact voxel-centre path and computes the same
  signed field as the core row and every peer;
* the same command against SimpleITK's whole job as a process (read the NRRD,
  SignedMaurerDistanceMap, write a float32 NRRD), alternated, like for like;
* the banded field of the smooth input (``--max-distance 4``, sub-voxel) as a
  whole command by blocks (``--chunked``) vs in memory: one operation, the
  in-memory run its one-block case, the same bytes (paired runs);
* the sub-voxel field of a smooth input, and the paper's min-norm scheme
  (time and pass count; reference: scipy distance_transform_cdt taxicab, both
  sides); the distance update of a moved field vs a full min-norm recomputation.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".numba-cache"))

from common import command_time, median_time, paired_times, row, volwarp_argv  # noqa: E402


def shape(n: int):
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32) / n
    a = ((x - 0.5) / 0.35) ** 2 + ((y - 0.47) / 0.3) ** 2 + ((z - 0.5) / 0.33) ** 2
    b = ((x - 0.25) / 0.15) ** 2 + ((y - 0.25) / 0.15) ** 2 + ((z - 0.25) / 0.12) ** 2
    smooth = 1.0 - np.minimum(a, b)  # > 0 inside, smooth
    return smooth > 0, smooth


#: SimpleITK's whole job as a process: read, signed Maurer distance (negative inside), write
SITK_JOB = """
import sys, SimpleITK as sitk
img = sitk.ReadImage(sys.argv[1])
d = sitk.SignedMaurerDistanceMap(img, insideIsPositive=False, squaredDistance=False,
                                 useImageSpacing=True)
sitk.WriteImage(sitk.Cast(d, sitk.sitkFloat32), sys.argv[2])
"""


def main(quick: bool = False) -> None:
    import edt
    import SimpleITK as sitk
    from scipy import ndimage as ndi

    from volwarp_cli.distance.exact import signed_edt
    from volwarp_cli.distance.minnorm import minnorm_signed
    from volwarp_cli.distance.subvoxel import subvoxel_signed_distance
    from volwarp_cli.distance.update import update_distance
    from volwarp_cli.io import write_volume
    from volwarp_cli.morph.align import affine_from_params
    from volwarp_cli.volume import Volume

    n = 128 if quick else 256
    rep = 3
    mask, smooth = shape(n)
    print(f"  shape {n}^3, {mask.mean():.1%} inside; 2 cores shared, medians of {rep}")
    ours = median_time(lambda: signed_edt(mask), repeat=rep)

    def scipy_signed():
        return ndi.distance_transform_edt(~mask) - ndi.distance_transform_edt(mask)

    sp = median_time(scipy_signed, repeat=1 if not quick else rep, warmup=0)
    img = sitk.GetImageFromArray(mask.astype(np.uint8))
    sk = median_time(lambda: sitk.SignedMaurerDistanceMap(
        img, insideIsPositive=False, squaredDistance=False, useImageSpacing=True), repeat=rep)
    ed = median_time(lambda: edt.sdf(mask, parallel=2), repeat=rep)
    row(f"signed euclidean {n}^3 (core)", ours, sp, "scipy")
    row(f"signed euclidean {n}^3 (core)", ours, sk, "SimpleITK")
    row(f"signed euclidean {n}^3 (core)", ours, ed, "edt.sdf")
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "shape.nrrd"
        write_volume(Volume(mask.astype(np.uint8)), src)
        ours_argv = volwarp_argv("distance", str(src), "-o", str(Path(tmp) / "d.nrrd"),
                                 "--iso", "0.5")
        cmd = command_time(ours_argv, repeat=rep)
        peer_argv = [sys.executable, "-c", SITK_JOB, str(src), str(Path(tmp) / "s.nrrd")]
        job, peer_job, job_ratio = paired_times(
            lambda: subprocess.run(ours_argv, check=True),
            lambda: subprocess.run(peer_argv, check=True), max(rep, 5))
        write_volume(Volume(smooth), Path(tmp) / "smooth.nrrd")
        band = ("distance", str(Path(tmp) / "smooth.nrrd"), "--iso", "0", "--max-distance", "4")
        out = [str(Path(tmp) / "m.nrrd"), str(Path(tmp) / "b.nrrd")]
        blocks, whole, ratio = paired_times(
            lambda: subprocess.run(volwarp_argv(*band, "-o", out[1], "--chunked"), check=True),
            lambda: subprocess.run(volwarp_argv(*band, "-o", out[0]), check=True), rep)
        assert Path(out[0]).read_bytes() == Path(out[1]).read_bytes()
    row(f"volwarp distance command {n}^3 (I/O incl.)", cmd, sp, "scipy")
    row(f"volwarp distance command {n}^3 (I/O incl.)", job, peer_job,
        "SimpleITK's whole job (process)", job_ratio)
    row(f"sub-voxel band command {n}^3 by blocks (D = 4)", blocks, whole, "in memory", ratio)
    sub = median_time(lambda: subvoxel_signed_distance(smooth, 0.0), repeat=rep)
    row(f"sub-voxel euclidean {n}^3 (smooth input)", sub, sp, "scipy")
    passes = {}

    def mn():
        passes["n"] = minnorm_signed(mask)[1]

    mnt = median_time(mn, repeat=rep)
    cdt = median_time(lambda: (ndi.distance_transform_cdt(~mask, metric="taxicab")
                               - ndi.distance_transform_cdt(mask, metric="taxicab")),
                      repeat=rep, warmup=0)
    row(f"min-norm {n}^3 ({passes['n']} passes)", mnt, cdt, "scipy cdt")
    field, _ = minnorm_signed(mask)
    move = affine_from_params({"translate": [6.0, 0.0, 3.0]})
    upd = median_time(lambda: update_distance(field, np.eye(4), move, (1, 1, 1),
                                              metric="minnorm"), repeat=rep)
    row(f"min-norm update after a 6-voxel move {n}^3", upd, mnt, "full min-norm")
    print("  paper (2004 software): 17.45 s for a 256^3 distance field, 7.75 s per update")


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
