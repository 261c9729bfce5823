"""numba's BLAS probe deferred: scipy.linalg imported when a kernel needs BLAS, not before.

The first kernel numba compiles or loads from its cache in a process
imports ``numba.np.arraymath``, whose module-level ``_check_blas()`` calls
``numba.np.linalg.ensure_blas()``, which imports ``scipy.linalg`` to find
its BLAS (0.16-0.22 s on the project's machine, most of a 16^3 command's
fixed cost beyond its imports). None of volwarp's kernels calls BLAS.
:func:`install` (the command line's entry point calls it, before numba
loads) makes that one probe answer from whether scipy is installed,
without importing it; every other ``ensure_blas()`` call, by a kernel that
does use BLAS, is numba's own and imports scipy then. A library user's
process is left as it is.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys

_LINALG = "numba.np.linalg"


class _DeferProbe:
    """Finds ``numba.np.linalg`` once, wrapping its ``ensure_blas`` after it runs.

    (A meta path finder needs only ``find_spec``: no ``importlib.abc`` base,
    whose import brings importlib.resources, 4-8 ms of every command's start.)
    """

    def find_spec(self, name, path, target=None):
        if name != _LINALG:
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            real = getattr(module, "ensure_blas", None)
            if real is not None:
                module.ensure_blas = _deferring(real)

        spec.loader.exec_module = exec_module
        return spec


def _deferring(real):
    def ensure_blas():
        if sys._getframe(1).f_code.co_name == "_check_blas":  # arraymath's import-time probe
            if importlib.util.find_spec("scipy") is None:
                raise ImportError("scipy 0.16+ is required for linear algebra")
            return
        real()

    ensure_blas.__doc__ = real.__doc__
    return ensure_blas


def install() -> None:
    """Defer numba's BLAS probe in this process (nothing if numba's linalg is loaded)."""
    if _LINALG in sys.modules or any(isinstance(f, _DeferProbe) for f in sys.meta_path):
        return
    sys.meta_path.insert(0, _DeferProbe())
