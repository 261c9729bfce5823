"""numba's import-time BLAS probe deferred by the command line (volwarp_cli/numba_blas.py).

Each check runs in a fresh interpreter: numba loads once per process.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume


def _python(code: str) -> str:
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    return res.stdout


def test_a_kernel_loads_without_importing_scipy_linalg():
    out = _python(
        "import sys\n"
        "from volwarp_cli import numba_blas\n"
        "numba_blas.install()\n"
        "import numba, numpy as np\n"
        "f = numba.njit(lambda x: x + 1)\n"
        "f(np.zeros(3))\n"
        "import numba.np.arraymath as a\n"
        "print('scipy.linalg' in sys.modules, a._HAVE_BLAS)\n")
    assert out.split() == ["False", "True"]


def test_a_kernel_using_blas_still_gets_it():
    """np.dot in nopython mode: numba's own ensure_blas imports scipy's BLAS then."""
    out = _python(
        "import sys\n"
        "from volwarp_cli import numba_blas\n"
        "numba_blas.install()\n"
        "import numba, numpy as np\n"
        "f = numba.njit(lambda a, b: np.dot(a, b))\n"
        "a = np.arange(12.0).reshape(3, 4); b = np.arange(8.0).reshape(4, 2)\n"
        "print(np.array_equal(f(a, b), a @ b), 'scipy.linalg' in sys.modules)\n")
    assert out.split() == ["True", "True"]


def test_the_command_line_runs_a_distance_without_scipy_linalg(tmp_path):
    z, y, x = np.mgrid[:16, :16, :16]
    ball = 5.0 - np.sqrt((x - 8) ** 2 + (y - 8) ** 2 + (z - 8) ** 2)  # (smooth: the sub-voxel
    write_volume(Volume(ball.astype(np.float32)), tmp_path / "m.nrrd")  # field, numba's)
    res = subprocess.run([sys.executable, "-X", "importtime", "-m", "volwarp_cli", "distance",
                          str(tmp_path / "m.nrrd"), "--iso", "0", "-o", str(tmp_path / "d.nrrd")],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    imported = {line.split("|")[-1].strip() for line in res.stderr.splitlines()
                if line.startswith("import time:")}
    assert "numba.np.arraymath" in imported  # (a kernel was loaded)
    assert "scipy.linalg" not in imported
