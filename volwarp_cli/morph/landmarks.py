"""Landmark warps: thin-plate and Gaussian radial basis functions through point pairs.

Dinh & Carvalho (2004), §0.4: "users can define a thin-plate warping function
by specifying corresponding feature points between source and target shapes,
as described in [Cohen-Or et al. 1998]"; the paper's timing table also names
Gaussian warps. A warp ``W`` with ``W(p_i) = q_i`` for the pairs ``(p_i, q_i)``
is written as the identity plus a displacement::

    W(x) = x + sum_i w_i phi(|x - p_i|) + a + B x

``phi(r) = r`` for ``thin-plate`` (the biharmonic spline of 3-D space, the
thin-plate spline's 3-D form) and ``phi(r) = exp(-r^2 / (2 sigma^2))`` for
``gaussian``. The weights solve the interpolation conditions exactly, with
the side conditions ``sum w_i = 0`` and ``sum w_i p_i = 0`` (the affine part
is then the least-bending one). With fewer than four landmarks, or all of them
in one plane, the affine part cannot be determined and is reduced to a
translation (``B = 0``): the warp still sends every ``p_i`` onto ``q_i``.

The system is solved and evaluated by :class:`scipy.interpolate.RBFInterpolator`
on the displacements ``q_i - p_i``. ``thin-plate`` is its ``linear`` kernel
(``-r``: the same interpolant, the weights change sign; not its
``thin_plate_spline``, ``r^2 log r``, which is the 2-D kernel and another
warp), ``gaussian`` its ``gaussian`` kernel ``exp(-(epsilon r)^2)`` with
``epsilon = 1 / (sigma sqrt 2)``; both with ``degree=1`` (the affine part) or
``degree=0`` (the translation of the fallback above). This module keeps the
argument checks, the fallback and the error wording.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import VolwarpError

KINDS = ("thin-plate", "gaussian")

#: RBFInterpolator's name for each kind
_KERNELS = {"thin-plate": "linear", "gaussian": "gaussian"}


def _epsilon(kind: str, sigma: float | None) -> float:
    """RBFInterpolator's shape parameter: ``exp(-(eps r)^2) = exp(-r^2 / (2 sigma^2))``."""
    if kind == "gaussian":
        return 1.0 / (float(sigma) * np.sqrt(2.0))
    return 1.0  # the linear kernel is scale-free: epsilon only rescales the weights


def _degree(p: np.ndarray) -> int:
    """1 (affine part) with four or more landmarks not in one plane, else 0 (translation)."""
    n = len(p)
    if n < 4:
        return 0
    return 1 if np.linalg.matrix_rank(p - p.mean(axis=0)) == 3 else 0


@dataclass
class LandmarkWarp:
    """A fitted warp; call it on (N, 3) world points."""

    centers: np.ndarray  # (N, 3) the source landmarks p_i
    kind: str
    sigma: float | None
    degree: int  # 1: affine part, 0: translation only
    interpolator: object = field(repr=False)  # a scipy.interpolate.RBFInterpolator

    @classmethod
    def fit(cls, source, target, *, kind: str = "thin-plate", sigma: float | None = None
            ) -> LandmarkWarp:
        """Fit ``W`` with ``W(source[i]) = target[i]`` exactly."""
        p = np.asarray(source, dtype=np.float64)
        q = np.asarray(target, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or q.ndim != 2 or q.shape[1] != 3:
            raise VolwarpError("landmarks must be lists of (x, y, z) points")
        if len(p) != len(q):
            raise VolwarpError(f"landmark lists differ in length: {len(p)} source points, "
                               f"{len(q)} target points")
        if len(p) == 0:
            raise VolwarpError("a landmark warp needs at least one pair of points")
        if kind not in KINDS:
            raise VolwarpError(f"unknown warp kind {kind!r} (known: {', '.join(KINDS)})")
        if kind == "gaussian" and not (sigma and sigma > 0):
            raise VolwarpError("a gaussian warp needs sigma > 0")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise VolwarpError("landmarks must be finite")
        n = len(p)
        if n > 1:
            dist = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
            if np.min(dist[~np.eye(n, dtype=bool)]) < 1e-9:
                raise VolwarpError("two source landmarks coincide")
        degree = _degree(p)
        try:
            from scipy.interpolate import RBFInterpolator  # (0.15 s: only for a warp)

            interp = RBFInterpolator(p, q - p, kernel=_KERNELS[kind],
                                     epsilon=_epsilon(kind, sigma), degree=degree)
        except (np.linalg.LinAlgError, ValueError):
            raise VolwarpError("the landmark system is singular (landmarks too close or "
                               "degenerate)") from None
        return cls(p, kind, sigma, degree, interp)

    def displacement(self, points) -> np.ndarray:
        """``W(x) - x`` for (..., 3) world points."""
        x = np.asarray(points, dtype=np.float64)
        flat = x.reshape(-1, 3)
        if flat.shape[0] == 0:
            return np.zeros(x.shape)
        return self.interpolator(flat).reshape(x.shape)

    def __call__(self, points) -> np.ndarray:
        """``W(x)`` for (..., 3) world points."""
        x = np.asarray(points, dtype=np.float64)
        return x + self.displacement(x)
