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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import VolwarpError

KINDS = ("thin-plate", "gaussian")


def _phi(r: np.ndarray, kind: str, sigma: float | None) -> np.ndarray:
    if kind == "thin-plate":
        return r
    return np.exp(-(r * r) / (2.0 * sigma * sigma))


@dataclass
class LandmarkWarp:
    """A fitted warp; call it on (N, 3) world points."""

    centers: np.ndarray  # (N, 3) the source landmarks p_i
    weights: np.ndarray  # (N, 3)
    affine: np.ndarray   # (4, 3): rows 1, x, y, z -> displacement
    kind: str
    sigma: float | None

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
        dist = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
        if n > 1 and np.min(dist[~np.eye(n, dtype=bool)]) < 1e-9:
            raise VolwarpError("two source landmarks coincide")
        poly = np.hstack([np.ones((n, 1)), p])
        if n < 4 or np.linalg.matrix_rank(poly - poly.mean(axis=0) * [0, 1, 1, 1]) < 4:
            poly = poly[:, :1]  # translation only
        m = poly.shape[1]
        k = _phi(dist, kind, sigma)
        system = np.zeros((n + m, n + m))
        system[:n, :n] = k
        system[:n, n:] = poly
        system[n:, :n] = poly.T
        rhs = np.zeros((n + m, 3))
        rhs[:n] = q - p
        try:
            sol = np.linalg.solve(system, rhs)
        except np.linalg.LinAlgError:
            raise VolwarpError("the landmark system is singular (landmarks too close or "
                               "degenerate)") from None
        affine = np.zeros((4, 3))
        affine[:m] = sol[n:]
        return cls(p, sol[:n], affine, kind, sigma)

    def displacement(self, points) -> np.ndarray:
        """``W(x) - x`` for (..., 3) world points."""
        x = np.asarray(points, dtype=np.float64)
        shape = x.shape
        x = x.reshape(-1, 3)
        out = np.empty_like(x)
        chunk = max(1, 2_000_000 // max(len(self.centers), 1))
        for s in range(0, len(x), chunk):
            xs = x[s:s + chunk]
            r = np.sqrt(((xs[:, None, :] - self.centers[None, :, :]) ** 2).sum(-1))
            out[s:s + chunk] = (_phi(r, self.kind, self.sigma) @ self.weights
                                + self.affine[0] + xs @ self.affine[1:])
        return out.reshape(shape)

    def __call__(self, points) -> np.ndarray:
        x = np.asarray(points, dtype=np.float64)
        return x + self.displacement(x)
