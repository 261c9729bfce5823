"""A library's first import counted against an explicit memory limit, before it loads.

:data:`volwarp_cli.library_memory.LIBRARY_BYTES` must hold what each library really
adds (each entry against a fresh process's import); and a command whose libraries
cannot fit under its limit is refused before loading them, its peak within the
limit, where it used to load them and be refused above it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from volwarp_cli import memory
from volwarp_cli.library_memory import LIBRARY_BYTES

# A fresh process as a command is when it imports a library: numpy loaded, numba's
# cache and BLAS probe set up as the entry point sets them; then the library, and for
# numba the cached kernels of a distance (what its first kernels bring: LLVM's set-up),
# for vtkmodules the modules the mesh's filters import.
_IMPORT = """\
import importlib, os, sys
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
import numpy as np
from volwarp_cli.entry import configure_numba_cache
from volwarp_cli import numba_blas, memory
configure_numba_cache()
numba_blas.install()
name = sys.argv[1]
if name == "numba":
    from volwarp_cli.distance import field
if name == "dask.array":  # (counted beyond what they import first)
    import dask
if name == "highdicom":
    import pydicom
try:
    before = memory.process_rss()
    importlib.import_module(name)
    if name == "vtkmodules":  # (the package is tiny: counted for the mesh's modules)
        for sub in ("util.numpy_support", "vtkCommonCore", "vtkCommonDataModel",
                    "vtkFiltersCore"):
            importlib.import_module("vtkmodules." + sub)
    if name == "numba":
        field.warm_kernels("euclidean", "subvoxel", np.dtype(np.float32), 0.5, "above")
    print(memory.process_rss() - before)
except ImportError:
    print("missing")
"""


def _added(name: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != memory.MEMORY_ENV}
    proc = subprocess.run([sys.executable, "-c", _IMPORT, name], capture_output=True,
                          text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.split()[-1]


def test_each_librarys_count_holds_what_its_import_adds():
    """Every entry at least what the library adds in a fresh process (numba with its first
    kernels), so that a refusal's arithmetic is an upper bound; and a large one is not
    counted as a trifle (numba's 117-158 MiB measured: the test would see an import that
    no longer loads anything)."""
    names = sorted(LIBRARY_BYTES)
    with ThreadPoolExecutor(2) as pool:
        added = dict(zip(names, pool.map(_added, names), strict=True))
    checked = {n: int(v) for n, v in added.items() if v != "missing"}
    assert "numba" in checked and "scipy.ndimage" in checked, added
    over = {n: (v >> 20, LIBRARY_BYTES[n] >> 20) for n, v in checked.items()
            if v > LIBRARY_BYTES[n]}
    assert not over, f"imports adding more MiB than counted (added, counted): {over}"
    assert checked["numba"] > 64 << 20, checked["numba"]


def _distance(src, out, limit: str):
    """``volwarp distance`` (sub-voxel: numba's kernels) in a fresh process; its peak RSS."""
    from peaks import volwarp_peak

    return volwarp_peak("distance", src, "-o", out, "--iso", "5", "--memory-limit", limit,
                        timeout=120)


@pytest.fixture
def smooth16(tmp_path):
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    z, y, x = np.mgrid[:16, :16, :16]
    r = np.sqrt((x - 8.0) ** 2 + (y - 8.0) ** 2 + (z - 8.0) ** 2).astype(np.float32)
    path = tmp_path / "r.nrrd"
    write_volume(Volume(r), path)
    return path


def test_a_command_whose_libraries_cannot_fit_is_refused_before_loading_them(tmp_path,
                                                                              smooth16):
    """A 16^3 sub-voxel distance under 100M: its field is 100 KiB, but numba and LLVM take
    117-158 MiB. It loaded them (146 MiB held) and only then was refused; now the
    import is refused first, naming numba and the limit, the process within the limit
    and nothing written. With room for them (300M) the same command runs."""
    out = tmp_path / "d.nrrd"
    code, err, peak = _distance(smooth16, out, "100M")
    assert code == 1, err
    assert "loading numba" in err and "--memory-limit: 100.0 MiB" in err, err
    assert len(err.strip().splitlines()) == 1, err
    assert peak <= 100 << 20, peak >> 20
    assert not out.exists()
    code, err, peak = _distance(smooth16, out, "300M")
    assert code == 0, err
    assert out.exists() and peak <= 300 << 20
