"""What importing a large library adds to the process, counted before it loads.

An explicit memory limit (``--memory-limit``, ``VOLWARP_MEMORY_LIMIT``) is a
ceiling on the whole process's peak (DESIGN.md). The work's estimates count
its arrays, and where the budget is tight a command loads its kernels before
its last check (:func:`.memory.ensure_fits_once_loaded`), but the loading
itself could cross the ceiling before that check: a sub-voxel distance of a
16^3 volume under ``--memory-limit 100M`` held 146 MiB (numba and LLVM) and
was refused only then. :func:`install` (the command line's entry point calls
it) puts a finder first on ``sys.meta_path`` that, at the first import of a
library of :data:`LIBRARY_BYTES` under an explicit limit, refuses it where
what it adds would not fit what is left: an OutOfMemoryError naming the
library and the limit, before any of it loads. Without an explicit limit the
machine's figures are the system's to enforce, and nothing is checked.
"""

from __future__ import annotations

import sys

#: What each library adds to a command's resident memory when first imported, numpy
#: loaded (measured on the project's machine, ``process_rss`` before and after, steady to
#: 0.2 MiB over runs, then rounded up by 2-3 MiB: a count a little over what a library
#: takes refuses a run at most that near its limit; tests/test_library_memory.py checks
#: every entry against a fresh process). numba's includes what its first compiled
#: kernels, loaded from the cache, bring: LLVM's set-up (116.7 MiB in all, with the
#: command's BLAS probe deferred by :mod:`.numba_blas`). A library that imports another
#: of them counts only its own part, the other checked as it loads: highdicom's is
#: beyond pydicom's, dask.array's beyond dask's; vtkmodules' is what the mesh's filters
#: import.
LIBRARY_BYTES = {
    "numba": 120 << 20,
    "scipy.interpolate": 54 << 20,
    "vtkmodules": 51 << 20,
    "nibabel": 50 << 20,
    "pydicom": 45 << 20,
    "scipy.spatial": 40 << 20,
    "OpenImageIO": 34 << 20,
    "distributed": 34 << 20,
    "scipy.ndimage": 29 << 20,
    "dask.array": 28 << 20,
    "highdicom": 23 << 20,
    "zarr": 21 << 20,
    "dask": 16 << 20,
}


class _CountedImports:
    """Refuses a costly library's first import where the limit cannot hold it.

    (A meta path finder needs only ``find_spec``; it finds nothing itself.)
    """

    def find_spec(self, name, path, target=None):
        nbytes = LIBRARY_BYTES.get(name)
        if nbytes is not None and name not in sys.modules:
            from . import memory

            if memory.explicit_limit() is not None:
                memory.ensure_fits_in_memory(nbytes, f"loading {name} (its code and "
                                                     "libraries)")
        return None


def install() -> None:
    """Count the libraries' imports against an explicit limit in this process (once)."""
    if not any(isinstance(f, _CountedImports) for f in sys.meta_path):
        sys.meta_path.insert(0, _CountedImports())
