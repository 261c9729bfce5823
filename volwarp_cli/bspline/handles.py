"""Handles: "move this point there" (paper §7, thesis §6; Hsu's direct manipulation).

For a handle ``from -> to``, Newton's method on the cubic write map finds the
domain parameter ``(s0, t0, u0)`` that the current map sends to ``from``.
Each handle gives one row of basis weights ``B`` over the control points;
all handles of a step are solved together for the least-norm change::

    delta P = B^+ (to - from)       (per coordinate; via the SVD of B)

so that afterwards the map sends each parameter exactly to its ``to`` point
when the system is solvable, unless that would move control points far more
than the handles move (handles closer together than the control points,
pulled apart): then the pseudoinverse is truncated (see
:func:`_bounded_least_norm`) and the handles are met as a compromise. An
optional ``radius`` (the spec's units: world mm, or voxels with ``units: voxel``)
limits the unknowns to control points within that distance of a handle's
``from`` point.

All positions here are input voxel indices (x, y, z); the caller converts
world coordinates.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError
from .evaluate import LatticeSpline
from .lattice import Lattice

#: Relative cut-offs tried for the handle system's singular values (see
#: :func:`_bounded_least_norm`), and the bound on control-point moves.
RCONDS = (1e-12, 1e-4, 1e-3, 1e-2, 3e-2, 0.1, 0.3)
MOVE_BOUND = 16.0  # times the largest handle move, plus one voxel


class HandleError(VolwarpError):
    """A handle that cannot be placed; ``index`` says which one."""

    def __init__(self, message: str, index: int):
        self.index = index
        super().__init__(message)


def _eval(spline: LatticeSpline, grid: Lattice, params, derivative: bool):
    """Positions (N, 3) of parameters ``params`` under ``spline``'s offsets, and d/ds (N, 3, 3)."""
    params = np.atleast_2d(np.asarray(params, dtype=np.float64))
    h = grid.spacing_h
    val = spline.offsets(params) + (grid.origin + h * params)
    if not derivative:
        return val, None
    return val, spline.jacobian(params) + np.diag(h)[None]


def map_params(dq, grid: Lattice, params) -> np.ndarray:
    """Positions (input voxels, x y z) of spline parameters (N, 3) under offsets ``dq``."""
    return _eval(LatticeSpline(dq, grid.regions), grid, params, False)[0]


def _newton(spline, grid, point, start, iters=60):
    s = start.copy()
    regions = np.array(grid.regions, dtype=np.float64)
    for _ in range(iters):
        val, jac = _eval(spline, grid, s[None], True)
        r = val[0] - point
        if np.max(np.abs(r)) < 1e-10:
            break
        try:
            step = np.linalg.solve(jac[0], r)
        except np.linalg.LinAlgError:
            return s, np.inf
        # damp steps that would jump far outside the parameter box
        s = np.clip(s - step, -0.5, regions + 0.5)
    val, _ = _eval(spline, grid, s[None], False)
    return s, float(np.max(np.abs(val[0] - point)))


def locate(dq, grid: Lattice, points) -> np.ndarray:
    """Parameters (N, 3) that the map sends to ``points`` (input voxels); Newton's method.

    Starts from the inverse of the affine base map, then from the nearest of
    a coarse grid of parameters. Raises :class:`HandleError` for a point the
    warped model does not cover.
    """
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    spline = LatticeSpline(dq, grid.regions)
    regions = np.array(grid.regions, dtype=np.float64)
    h = grid.spacing_h
    # the model's parameters: the domain voxels inside the input (all on a spanning grid)
    g = np.array(grid.granularity, dtype=np.float64)
    p_lo, p_hi = np.array(grid.data_lo) / g, np.array(grid.data_hi) / g
    coarse = None
    out = np.empty_like(points)
    for n, p in enumerate(points):
        starts = [np.clip((p - grid.origin) / h, 0, regions)]
        found = None
        for attempt in range(2):
            for st in starts:
                s, res = _newton(spline, grid, p, st)
                if res < 1e-6 and np.all(s >= p_lo - 1e-9) and np.all(s <= p_hi + 1e-9):
                    found = np.clip(s, p_lo, p_hi)
                    break
            if found is not None or attempt == 1:
                break
            if coarse is None:
                axes = [np.linspace(0, r, int(4 * r) + 1) for r in regions]
                cs = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
                coarse = (cs, _eval(spline, grid, cs, False)[0])
            d = np.linalg.norm(coarse[1] - p, axis=1)
            starts = [coarse[0][i] for i in np.argsort(d)[:4]]
        if found is None:
            raise HandleError(f"point {np.round(p, 4).tolist()} (input voxels x y z) is outside "
                              "the region the warped model covers", n)
        out[n] = found
    return out


def solve(dq, grid: Lattice, sources, targets, free_mask=None):
    """Least-norm control-point change moving each source point to its target (bounded).

    Parameters
    ----------
    dq : (Cz, Cy, Cx, 3) current offsets.
    sources, targets : (H, 3) input voxel positions (x y z).
    free_mask : (Cz, Cy, Cx) bool, or None for all points.
        Control points allowed to move.

    Returns
    -------
    delta : (Cz, Cy, Cx, 3) float64
        The change, zero outside the free points.
    params : (H, 3)
        The located parameters of the sources.
    residual : float
        Largest remaining error (input voxels) of the solved system.
    """
    sources = np.atleast_2d(np.asarray(sources, dtype=np.float64))
    targets = np.atleast_2d(np.asarray(targets, dtype=np.float64))
    params = locate(dq, grid, sources)
    current = map_params(dq, grid, params)
    ncp = int(np.prod(grid.lattice))
    rows = LatticeSpline(dq, grid.regions).weights(params)  # 64 weights a handle
    if free_mask is not None:
        free = np.flatnonzero(np.asarray(free_mask).ravel())
    else:
        free = np.arange(ncp)
    sub = rows[:, free]
    for n in range(len(params)):
        if not np.any(sub[n] > 1e-12):
            raise HandleError("no control point that influences this handle is within the "
                              "radius", n)
    rhs = targets - current
    # Only control points that influence some handle can take part in the
    # least-norm solution (the others get 0): solve for those alone, a few
    # hundred columns instead of the whole lattice.
    active = np.flatnonzero(np.any(sub > 0.0, axis=0))
    sol = _bounded_least_norm(sub[:, active], rhs)
    delta = np.zeros((ncp, 3))
    delta[free[active]] = sol
    residual = float(np.max(np.abs(sub[:, active] @ sol - rhs))) if len(rhs) else 0.0
    return delta.reshape(dq.shape), params, residual


def _bounded_least_norm(a: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Least-norm solution of ``a x = rhs``, truncated only as far as needed.

    Handles much closer together than the control points, dragged apart,
    make the system nearly singular: its exact solution moves control points
    by hundreds or millions of voxels and folds the volume. The exact
    (least-norm) solution is kept when no control point moves more than
    ``MOVE_BOUND`` times the largest handle move; otherwise the smallest
    singular values are dropped, cut-off by cut-off (``RCONDS``), until it
    does, and the handles are met as a compromise (the caller reports the
    miss); if even the most truncated solution moves too far, it is scaled
    down to the bound.
    """
    if a.size == 0:
        return np.zeros((a.shape[1], rhs.shape[1]))
    u, sv, vt = np.linalg.svd(a, full_matrices=False)
    bound = MOVE_BOUND * float(np.max(np.abs(rhs))) + 1.0
    proj = u.T @ rhs
    for rcond in RCONDS:
        keep = sv > rcond * sv[0]
        sol = vt[keep].T @ (proj[keep] / sv[keep, None])
        largest = float(np.max(np.abs(sol)))
        if largest <= bound:
            return sol
    return sol * (bound / largest)
