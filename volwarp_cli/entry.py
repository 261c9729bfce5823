"""The ``volwarp`` command's entry point: the stop handling comes before any import.

Importing numpy, click and the command modules takes about 0.1 s; a SIGINT in
that time used to print a KeyboardInterrupt traceback and exit -2. The
handlers of :mod:`volwarp_cli.signals` (standard library only) are installed
first, so a stop at any moment exits 130 / 143 with one line.
"""

from __future__ import annotations

import os
import sys


def main() -> int:
    """Run the ``volwarp`` command line; its exit code."""
    # A command-line run, before numpy is imported: BLAS's own threads stay at one.
    # volwarp's kernels take the cores with their own threads (--threads) and make no
    # large dense products; OpenBLAS's threads, woken by the small products of the
    # spline bases, would only spin beside them (about 5% of a warp's CPU) or, inside a
    # cluster worker, oversubscribe it. A user's own setting wins. (Set here, for the
    # command's process only: importing volwarp as a library changes no environment.)
    for name in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")
    from . import signals

    signals.install()
    try:
        from .cli.main import main as run
    except signals.Interrupted as exc:  # stopped while the command line was imported
        sys.stderr.write(f"volwarp: error: {exc}\n")
        sys.stderr.flush()
        os._exit(128 + exc.signum)
    return run()
