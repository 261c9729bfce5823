"""`volwarp batch` on a 2-worker LocalCluster against `make -j2` of the same chain.

    .venv/bin/python benchmarks/bench_batch.py [--scans 200] [--scheduler local|pool]

Makes N small scans (16^3 NRRD), a manifest (convert, then a signed distance
field of the result) and a Makefile with one rule per output calling the same
volwarp commands, then times, from a clean output folder each time:

- ``volwarp batch manifest.yaml --scheduler local --workers 2 -q`` (cluster
  start-up included), and
- ``make -j2`` of the Makefile,

alternated ``--pairs`` times, and prints the medians and the median of the
pair-by-pair ratios (target: at most 1.10); on a shared machine the pairs
show how much the load drifted. Both run the
same 2N volwarp processes, so the difference is the batch's own cost: the
cluster, the up-to-date checks, the scheduling, the record of commands.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

MANIFEST = """version: 1
inputs: {glob: "scans/*.nrrd"}
output_dir: out
steps:
  - {name: conv, run: convert, output: "{stem}.nrrd"}
  - {name: sdf, run: distance, input: conv, output: "{stem}_sdf.nrrd", options: ["--iso", "50"]}
"""


def make_tree(root: Path, count: int) -> None:
    import numpy as np

    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    (root / "scans").mkdir()
    n = 16
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32)
    for i in range(count):
        r = np.sqrt((x - 7.5) ** 2 + (y - 7.5) ** 2 + (z - 7.5) ** 2)
        data = np.clip(100 - 12 * (r - 3 - (i % 5) * 0.3), 0, 100).astype(np.int16)
        write_volume(Volume(data, spacing=(1.0, 1.0, 1.0)), root / "scans" / f"s{i:04d}.nrrd")
    (root / "manifest.yaml").write_text(MANIFEST)
    vw = f"{sys.executable} -m volwarp_cli"
    stems = [f"s{i:04d}" for i in range(count)]
    rules = ["all: " + " ".join(f"out/{s}_sdf.nrrd" for s in stems), ""]
    for s in stems:
        rules += [f"out/{s}.nrrd: scans/{s}.nrrd", "\t@mkdir -p out",
                  f"\t@VOLWARP_THREADS=1 {vw} convert $< -o $@ -q",
                  f"out/{s}_sdf.nrrd: out/{s}.nrrd",
                  f"\t@VOLWARP_THREADS=1 {vw} distance $< --iso 50 -o $@ -q", ""]
    (root / "Makefile").write_text("\n".join(rules) + "\n")


def timed(argv: list[str], cwd: Path) -> float:
    shutil.rmtree(cwd / "out", ignore_errors=True)
    start = time.perf_counter()
    subprocess.run(argv, cwd=cwd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", type=int, default=200)
    parser.add_argument("--scheduler", default="local", choices=["local", "pool"])
    parser.add_argument("--pairs", type=int, default=3, help="batch/make runs, alternated")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        make_tree(root, args.scans)
        batch = [sys.executable, "-m", "volwarp_cli", "batch", "manifest.yaml", "-q"]
        batch += (["--scheduler", "local", "--workers", "2"] if args.scheduler == "local"
                  else ["-j", "2"])
        ours, make = [], []
        for _ in range(args.pairs):  # alternated: the pair-by-pair ratio survives drift
            ours.append(timed(batch, root))
            make.append(timed(["make", "-s", "-j2"], root))
        ratio = statistics.median(a / b for a, b in zip(ours, make, strict=True))
        print(f"{args.scans} scans x 2 steps: volwarp batch --scheduler {args.scheduler} "
              f"(2 workers) {statistics.median(ours):.1f} s, make -j2 "
              f"{statistics.median(make):.1f} s, ratio {ratio:.3f} "
              f"(overhead {100 * (ratio - 1):+.1f}%, target <= +10%; pairs: "
              + ", ".join(f"{a:.1f}/{b:.1f}" for a, b in zip(ours, make, strict=True)) + ")")


if __name__ == "__main__":
    main()
