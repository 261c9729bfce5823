"""Each command's fixed cost: the whole process on a 16^3 input against ``import numpy``.

    python benchmarks/bench_fixed_cost.py [--quick] [--pairs N]

A batch of many small scans pays every command's fixed part (start-up,
imports, the spec's YAML and schema, the reader's and writer's set-up) once per
scan. Each row runs one command as a new process (``python -m volwarp_cli``) on
the warm-up's 16^3 inputs (:func:`volwarp_cli.warmup.write_inputs`), alternated
with ``python -c "import numpy"`` (the same interpreter) ``--pairs`` times, and
prints both medians and the median of the pair-by-pair ratios (issue 32's
target for the one-move warp: at most 1.6x; for the 729-move warp 1.8x).
Every command runs once untimed first (the kernels compiled or loaded into the
cache, the files in the page cache).

The reference runs with one BLAS thread, as every volwarp command does (its
entry point sets ``OPENBLAS_NUM_THREADS=1`` before numpy loads): on a busy
machine a plain ``import numpy`` also pays the start of OpenBLAS's thread pool
(65 ms either way on the quiet 2-core machine; 213 against 151 ms with a load
average of 6), and the ratio would flatter volwarp. The plain reference's
median is printed last, for comparison.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402
from common import row  # noqa: E402


def _moves_spec(path: Path) -> Path:
    """A registration result's spec: every point of a 9^3 lattice moved (729 moves)."""
    lines = ["version: 1", "units: voxel", "capture: {lattice: 9}", "steps:", "  - move:"]
    for k in range(9):
        for j in range(9):
            for i in range(9):
                by = [0.1 * ((i + 2 * j + 3 * k) % 5 - 2), 0.05 * (i - j), 0.02 * (k - 4)]
                lines.append(f"      - {{index: [{i}, {j}, {k}], by: [{by[0]:.3f}, "
                             f"{by[1]:.3f}, {by[2]:.3f}]}}")
    path.write_text("\n".join(lines) + "\n")
    return path


def commands(p: dict, out: Path) -> list[tuple[str, list[str]]]:
    """``(row name, volwarp arguments)`` of every command on the 16^3 inputs."""
    o = str(out)
    return [
        ("--help", ["--help"]),
        ("info", ["info", p["blob"]]),
        ("convert (NRRD -> NIfTI)", ["convert", p["blob"], "-o", f"{o}/c.nii"]),
        ("capture (5^3 lattice)", ["capture", p["blob"], "-o", f"{o}/c.vwc", "--lattice", "5"]),
        ("warp, one move", ["warp", p["blob"], "--spec", p["move"], "-o", f"{o}/w.nrrd"]),
        ("warp, 729 moves (9^3 lattice)", ["warp", p["blob"], "--spec", p["moves729"],
                                           "-o", f"{o}/w729.nrrd"]),
        ("distance (exact, binary mask)", ["distance", p["mask"], "--iso", "100",
                                           "-o", f"{o}/d.nrrd"]),
        ("mesh (PLY)", ["mesh", p["blob"], "--iso", "50", "-o", f"{o}/m.ply"]),
        ("sweep (3 fields, Bezier)", ["sweep", p["bezier"], "-o", f"{o}/s_{{field}}.nrrd",
                                      "--spacing", "1"]),
        ("morph (3 frames)", ["morph", "--spec", p["morph_minnorm"], "-o",
                              f"{o}/f_{{i:02d}}.nrrd"]),
    ]


def main(quick: bool = False, pairs: int | None = None) -> None:
    from volwarp_cli.warmup import write_inputs

    pairs = pairs or (3 if quick else 9)
    one_blas = dict(os.environ, OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    numpy = common.process([sys.executable, "-c", "import numpy"], env=one_blas)
    plain = common.process([sys.executable, "-c", "import numpy"])
    with tempfile.TemporaryDirectory(prefix="volwarp-bench-fixed-") as tmp:
        p = write_inputs(tmp)
        p["moves729"] = str(_moves_spec(Path(tmp) / "moves729.yaml"))
        out = Path(tmp) / "out"
        out.mkdir()
        rows = [(name, common.process(common.volwarp_argv(*args))) for name, args in commands(p, out)]
        for _, run in rows:  # untimed: kernels compiled or loaded, files cached
            run()
        numpy()
        print(f"  whole processes on 16^3, against `python -c \"import numpy\"` "
              f"({pairs} alternated pairs each)", flush=True)
        for name, run in rows:
            ours, ref, ratio = common.paired_times(run, numpy, pairs)
            row(f"volwarp {name}", ours, ref, "import numpy", ratio=ratio)
        one, many, ratio = common.paired_times(numpy, plain, pairs)
        print(f"  (import numpy: one BLAS thread {one:.3f} s, plain {many:.3f} s, ratio "
              f"{ratio:.3f} (paired))", flush=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 pairs per row")
    parser.add_argument("--pairs", type=int, default=None, help="pairs per row (default 9)")
    args = parser.parse_args()
    main(quick=args.quick, pairs=args.pairs)
