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
#: loaded, with a quarter more: measured (``process_rss`` before and after) on a fresh
#: clone's install, CI's, where it is larger than on an install whose files have been in
#: the page cache a while (numba 158 against 117 MiB, VTK 70 against 48: the mapped
#: libraries' pages count, and their number varies with how they were read), and
#: numba's includes compiling its first kernels where the cache lacks them (LLVM's
#: set-up and the compiler: 158 MiB, with the command's BLAS probe deferred by
#: :mod:`.numba_blas`). tests/test_library_memory.py checks every entry against a fresh
#: process. So a run near its limit may be refused although its libraries would fit
#: (up to about 80 MiB early where numba's kernels are cached); never let through to
#: cross it. A library that imports another of them counts only its own part, the
#: other checked as it loads: highdicom's is beyond pydicom's, dask.array's beyond
#: dask's; vtkmodules' is what the mesh's filters import.
LIBRARY_BYTES = {
    "numba": 200 << 20,
    "vtkmodules": 88 << 20,
    "scipy.interpolate": 72 << 20,
    "nibabel": 64 << 20,
    "pydicom": 57 << 20,
    "scipy.spatial": 52 << 20,
    "OpenImageIO": 50 << 20,
    "distributed": 41 << 20,
    "scipy.ndimage": 37 << 20,
    "dask.array": 37 << 20,
    "highdicom": 26 << 20,
    "zarr": 26 << 20,
    "dask": 19 << 20,
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
