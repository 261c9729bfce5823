"""Run every benchmark (benchmarks/bench_*.py) and print volwarp vs peer timings as ratios.

    python benchmarks/run.py            # all, full size
    python benchmarks/run.py --quick    # reduced sizes (a smoke run)
    python benchmarks/run.py warp mesh  # only these areas
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

HERE = Path(__file__).parent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("areas", nargs="*", help="bench_<area>.py to run (default: all)")
    parser.add_argument("--quick", action="store_true", help="reduced sizes")
    args = parser.parse_args()
    files = sorted(HERE.glob("bench_*.py"))
    if args.areas:
        files = [f for f in files if f.stem.removeprefix("bench_") in args.areas]
    failed = []
    for f in files:
        print(f"== {f.stem.removeprefix('bench_')} ==", flush=True)
        spec = importlib.util.spec_from_file_location(f.stem, f)
        module = importlib.util.module_from_spec(spec)
        sys.modules[f.stem] = module
        start = time.perf_counter()
        try:
            spec.loader.exec_module(module)
            module.main(quick=args.quick)
        except Exception as exc:  # keep going: one broken benchmark must not hide the others
            print(f"!! {f.stem} failed: {type(exc).__name__}: {exc}", flush=True)
            failed.append(f.stem)
        print(f"   ({time.perf_counter() - start:.1f} s)\n", flush=True)
    if failed:
        print("failed:", " ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
