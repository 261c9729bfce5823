"""Out of core: a 1024^3 int16 volume by blocks under --memory-limit, against 512^3 in memory.

For warp (9^3 lattice, every control point moved), the exact distance, the mesh and a
morph (the volume into itself, both fields in a band of 8 mm, two frames):
the time and peak RSS (/usr/bin/time -v) of the command on a 1024^3 int16 volume
(generated here, 2 GiB, not shipped) with ``--chunked --memory-limit 4G``, and its
throughput per voxel against the in-memory command on 512^3. Targets (issue 19):
peak RSS within the limit plus 0.5 GB; throughput at least 0.7 of the in-memory one.

    python benchmarks/bench_scale.py            # 1024^3 against 512^3 (about 15 min)
    python benchmarks/bench_scale.py --quick    # 256^3 against 128^3, limit 256M
    python benchmarks/bench_scale.py --keep DIR # keep the generated volumes in DIR
    python benchmarks/bench_scale.py --only morph,distance
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))

from bench_threads import general_coefficients, general_spec  # noqa: E402
from common import volwarp_argv  # noqa: E402


def make_volume(path: Path, n: int) -> None:
    """An n^3 int16 NRRD of a few soft blobs, written plane by plane (never held whole)."""
    from volwarp_cli.io.nrrd import nrrd_header
    from volwarp_cli.volume import Header

    header = nrrd_header(Header((n, n, n), np.dtype(np.int16)), np.dtype(np.int16),
                         encoding="raw", byte_order="little")
    axis = np.linspace(-1.0, 1.0, n, dtype=np.float32)
    y, x = np.meshgrid(axis, axis, indexing="ij")
    centres = [(0.2, 0.0, 0.0, 0.25), (-0.4, 0.3, -0.2, 0.08), (0.0, -0.5, 0.4, 0.05)]
    with open(path, "wb") as fh:
        fh.write(header)
        for z in axis:
            plane = np.zeros((n, n), np.float32)
            for cx, cy, cz, w in centres:
                plane += 1000.0 * np.exp(-((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2) / w)
            fh.write(plane.astype("<i2").tobytes())


def timed(argv: list[str]) -> tuple[float, int, str]:
    """``(seconds, peak RSS bytes, stderr)`` of one command, by /usr/bin/time -v."""
    start = time.perf_counter()
    res = subprocess.run(["/usr/bin/time", "-v", *argv], capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} failed:\n{res.stderr[-2000:]}")
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", res.stderr).group(1))
    return seconds, rss * 1024, res.stderr


def main(quick: bool = False, keep: str | None = None, only=()) -> None:
    big, small, limit = (256, 128, "256M") if quick else (1024, 512, "4G")
    from volwarp_cli.memory import parse_size

    limit_bytes = parse_size(limit)
    with tempfile.TemporaryDirectory(dir=keep) as tmp:
        tmp = Path(keep) if keep else Path(tmp)
        vols = {}
        for n in (small, big):
            vols[n] = tmp / f"v{n}.nrrd"
            if not vols[n].exists():
                t = time.perf_counter()
                make_volume(vols[n], n)
                print(f"  generated {n}^3 int16 ({vols[n].stat().st_size / 2**30:.2f} GiB) in "
                      f"{time.perf_counter() - t:.1f} s", flush=True)
        spec = tmp / "general.yaml"
        general_spec(spec, general_coefficients(9, 2.0 * big / 256))
        jobs = {
            "warp (9^3 lattice, general)": lambda src, out: [
                "warp", str(src), "--spec", str(spec), "-o", str(out) + ".nrrd", "--crop"],
            "distance (exact)": lambda src, out: [
                "distance", str(src), "-o", str(out) + ".nrrd", "--iso", "300",
                "--surface", "voxel"],
            "mesh": lambda src, out: ["mesh", str(src), "-o", str(out) + ".ply", "--iso", "300"],
            # the volume into itself: both fields (a band, for smooth samples) and two frames
            "morph (2 frames, band 8)": lambda src, out: [
                "morph", str(src), str(src), "--iso", "300", "--frames", "2",
                "--max-distance", "8", "-o", str(out) + "_{i}.nrrd"],
        }
        if only:
            jobs = {k: v for k, v in jobs.items() if k.split()[0] in only}
        print(f"  {'':<30} {'in memory ' + str(small) + '^3':>24} "
              f"{'by blocks ' + str(big) + '^3, limit ' + limit:>34}  throughput  RSS target",
              flush=True)
        for name, args in jobs.items():
            out = tmp / "out"
            t_mem, rss_mem, _ = timed(volwarp_argv(*args(vols[small], out), "-q"))
            t_blk, rss_blk, _ = timed(volwarp_argv(*args(vols[big], out), "--chunked",
                                                   "--memory-limit", limit, "-q"))
            for f in tmp.glob("out[._]*"):
                f.unlink()
            per_mem = small ** 3 / t_mem
            per_blk = big ** 3 / t_blk
            ratio = per_blk / per_mem
            ok = rss_blk <= limit_bytes + 0.5 * 2 ** 30
            print(f"  {name:<30} {t_mem:8.1f} s {rss_mem / 2**30:6.2f} GiB      "
                  f"{t_blk:8.1f} s {rss_blk / 2**30:6.2f} GiB          "
                  f"{ratio:5.2f}x    {'within' if ok else 'OVER'}", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--keep", default=None, metavar="DIR")
    parser.add_argument("--only", default="", metavar="CMD,...",
                        help="only these commands (warp, distance, mesh, morph)")
    a = parser.parse_args()
    main(quick=a.quick, keep=a.keep, only=tuple(c for c in a.only.split(",") if c))
