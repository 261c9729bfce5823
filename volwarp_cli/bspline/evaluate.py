"""The lattice's offsets at scattered parameters: the one evaluator of value, Jacobian, weights.

The write map's offsets are a tensor-product uniform cubic B-spline of the
control-point offsets (paper §3): knots at the integers, parameter
``(s, t, u)`` in ``[0, R]`` per axis (``R`` regions), the end regions'
polynomials extended outside. That is scipy's :class:`~scipy.interpolate.NdBSpline`
with knots ``-3 .. R + 3`` on each axis and ``extrapolate=True`` (it agrees
with the paper's sum over the 4^3 control points of a region to 5e-15 and
is 6x faster on 20,000 points); :meth:`LatticeSpline.weights` gives the 64
weights of a parameter point (a handle's row of the least-norm system). Handles, the moved points and the exported
fields all evaluate the map here; the volume's dense evaluation is the
separable or tabulated one of :mod:`.basis` (per voxel, in the kernels),
and the field inverse's inner loop is compiled (:mod:`volwarp_cli.warp._export_kernels`).

Parameters are ``(N, 3)`` x y z; the lattice is ``dq`` ``(Cz, Cy, Cx, 3)``,
so the spline's axes are taken z, y, x and the parameters reversed.
"""

from __future__ import annotations

import numpy as np

#: the B-spline's degree
DEGREE = 3


def knots(regions) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The knot vectors (z, y, x) of a lattice of ``regions`` (x, y, z) regions."""
    return tuple(np.arange(-3.0, int(r) + 4.0) for r in list(regions)[::-1])


class LatticeSpline:
    """The offsets ``dq`` ``(Cz, Cy, Cx, 3)`` of a lattice of ``regions`` (x y z) as a spline."""

    def __init__(self, dq, regions):
        from scipy.interpolate import NdBSpline  # (here: scipy.interpolate costs 0.25 s to import)

        self.t = knots(regions)
        self.spline = NdBSpline(self.t, np.asarray(dq, dtype=np.float64), DEGREE,
                                extrapolate=True)

    def offsets(self, params) -> np.ndarray:
        """The offsets (N, 3) at parameters ``params`` (N, 3; x y z)."""
        return self.spline(_zyx(params))

    def jacobian(self, params) -> np.ndarray:
        """The derivatives of the offsets by (s, t, u): (N, 3, 3), ``[n, component, axis]``."""
        zyx = _zyx(params)
        return np.stack([self.spline(zyx, nu=nu) for nu in ((0, 0, 1), (0, 1, 0), (1, 0, 0))],
                        axis=-1)

    def weights(self, params) -> np.ndarray:
        """The basis weights of each parameter point over the control points.

        ``(N, Cz * Cy * Cx)``, columns in the flat order of ``dq``'s first
        three axes; each row holds the point's 64 products of the blending
        functions (:func:`.basis.basis`) of its region. (scipy's
        ``NdBSpline.design_matrix`` gives the same inside the support but
        indexes past the last control point at its far end, s = R.)
        """
        from .basis import basis

        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        shape = [len(t) - DEGREE - 1 for t in self.t]  # control points, z y x
        regions = np.array(shape[::-1]) - DEGREE  # x y z
        a = np.clip(np.floor(params), 0, regions - 1).astype(np.intp)
        w = [basis(params[:, d] - a[:, d]) for d in range(3)]  # (N, 4) each, x y z
        products = np.einsum("nk,nj,ni->nkji", w[2], w[1], w[0]).reshape(len(params), -1)
        r = np.arange(4)
        flat = ((a[:, 2, None, None, None] + r[None, :, None, None]) * shape[1]
                + a[:, 1, None, None, None] + r[None, None, :, None]) * shape[2] \
            + a[:, 0, None, None, None] + r[None, None, None, :]
        rows = np.zeros((len(params), int(np.prod(shape))))
        np.put_along_axis(rows, flat.reshape(len(params), -1), products, axis=1)
        return rows


def _zyx(params) -> np.ndarray:
    """Parameters (N, 3) x y z as the spline's (z, y, x) points."""
    return np.ascontiguousarray(np.atleast_2d(np.asarray(params, dtype=np.float64))[:, ::-1])
