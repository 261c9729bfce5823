"""numba kernel of the resampling field's inverse (see :meth:`.export.ForwardMap.resampling_field`).

Imported lazily: numba costs about 0.3 s to import and the kernel is cached on
disk (``cache=True``; ``NUMBA_CACHE_DIR`` when the package is read-only).

The kernel runs the same damped Newton iteration as the vectorised reference
(:meth:`.export.ForwardMap._invert_chunk`), one output voxel at a time, with the
cubic B-spline evaluated locally (the 4x4x4 control points of the voxel's
region). Along an output row each voxel starts from its neighbour's solution
plus the first-order step ``J^-1 e_x`` (the map is smooth: two or three
iterations instead of about six); a voxel whose warm start fails is solved
again from the reference's start (the identity's parameters), so every voxel
the reference solves is solved. It releases the GIL: the caller splits the
output's z slices over threads.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: status codes (as :meth:`.export.ForwardMap.invert_index`)
FOUND, NO_INVERSE, FOLDED = 0, 1, 2


@njit(cache=True, nogil=True, inline="always")
def _basis(t, w, dw, axis):
    """The cubic B-spline weights ``w[axis]`` and their derivatives ``dw[axis]`` at ``t``.

    ``w``, ``dw``: (3, 4) arrays, a row per axis (x, y, z).
    """
    u = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    w[axis, 0] = u * u * u / 6.0
    w[axis, 1] = (4.0 - 6.0 * t2 + 3.0 * t3) / 6.0
    w[axis, 2] = (1.0 + 3.0 * t + 3.0 * t2 - 3.0 * t3) / 6.0
    w[axis, 3] = t3 / 6.0
    dw[axis, 0] = -0.5 * u * u
    dw[axis, 1] = (-12.0 * t + 9.0 * t2) / 6.0
    dw[axis, 2] = (3.0 + 6.0 * t - 9.0 * t2) / 6.0
    dw[axis, 3] = 0.5 * t2


@njit(cache=True, nogil=True, inline="always")
def _cell(s, regions):
    """The region of parameter s, clipped to [0, regions - 1] (the reference's a)."""
    f = math.floor(s)
    if f < 0.0:
        return 0
    if f > regions - 1:
        return regions - 1
    return int(f)


@njit(cache=True, nogil=True, inline="always")
def _add3(w, q0, q1, q2, a0, a1, a2):
    """``a + w q`` of 3-vectors held as scalars.

    (Array ones would be stored to memory on every term.)
    """
    return a0 + w * q0, a1 + w * q1, a2 + w * q2


@njit(cache=True, nogil=True, inline="always")
def _spline(dq, s, regions, val, jac, w, dw):
    """val[m] = sum B dq[..., m] at parameters s; jac[m, axis] = d val[m] / d s[axis].

    ``w``, ``dw``: (3, 4) scratch for the weights (:func:`_basis`).
    """
    a0 = _cell(s[0], regions[0])
    a1 = _cell(s[1], regions[1])
    a2 = _cell(s[2], regions[2])
    _basis(s[0] - a0, w, dw, 0)
    _basis(s[1] - a1, w, dw, 1)
    _basis(s[2] - a2, w, dw, 2)
    # the value and its derivatives along x, y, z: jac's columns
    v0 = v1 = v2 = 0.0
    j00 = j10 = j20 = j01 = j11 = j21 = j02 = j12 = j22 = 0.0
    for k in range(4):
        for j in range(4):
            ax0 = ax1 = ax2 = 0.0  # the row's value and its x derivative
            dx0 = dx1 = dx2 = 0.0
            for i in range(4):
                q0 = dq[a2 + k, a1 + j, a0 + i, 0]
                q1 = dq[a2 + k, a1 + j, a0 + i, 1]
                q2 = dq[a2 + k, a1 + j, a0 + i, 2]
                ax0, ax1, ax2 = _add3(w[0, i], q0, q1, q2, ax0, ax1, ax2)
                dx0, dx1, dx2 = _add3(dw[0, i], q0, q1, q2, dx0, dx1, dx2)
            wyz = w[1, j] * w[2, k]
            v0, v1, v2 = _add3(wyz, ax0, ax1, ax2, v0, v1, v2)
            j00, j10, j20 = _add3(wyz, dx0, dx1, dx2, j00, j10, j20)
            j01, j11, j21 = _add3(dw[1, j] * w[2, k], ax0, ax1, ax2, j01, j11, j21)
            j02, j12, j22 = _add3(w[1, j] * dw[2, k], ax0, ax1, ax2, j02, j12, j22)
    val[0], val[1], val[2] = v0, v1, v2
    jac[0, 0], jac[0, 1], jac[0, 2] = j00, j01, j02
    jac[1, 0], jac[1, 1], jac[1, 2] = j10, j11, j12
    jac[2, 0], jac[2, 1], jac[2, 2] = j20, j21, j22


@njit(cache=True, nogil=True, inline="always")
def _det3(J):
    return (J[0, 0] * (J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1])
            - J[0, 1] * (J[1, 0] * J[2, 2] - J[1, 2] * J[2, 0])
            + J[0, 2] * (J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]))


@njit(cache=True, nogil=True, inline="always")
def _map_jacobian(jac, h, J):
    """``J`` = the map's Jacobian d(org + h s + val(s)) / ds = ``jac + diag(h)``; its det."""
    for m in range(3):
        for d in range(3):
            J[m, d] = jac[m, d]
        J[m, m] += h[m]
    return _det3(J)


@njit(cache=True, nogil=True, inline="always")
def _clip(v, regions):
    """A parameter clipped to the extrapolation box ``[-0.5, regions + 0.5]``."""
    if v < -0.5:
        return -0.5
    if v > regions + 0.5:
        return regions + 0.5
    return v


@njit(cache=True, nogil=True, inline="always")
def _solve3(J, det, r, out):
    """``out`` = J^-1 r (Cramer's rule; ``det`` = det J, nonzero)."""
    inv = 1.0 / det
    out[0] = inv * (r[0] * (J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1])
                    - J[0, 1] * (r[1] * J[2, 2] - J[1, 2] * r[2])
                    + J[0, 2] * (r[1] * J[2, 1] - J[1, 1] * r[2]))
    out[1] = inv * (J[0, 0] * (r[1] * J[2, 2] - J[1, 2] * r[2])
                    - r[0] * (J[1, 0] * J[2, 2] - J[1, 2] * J[2, 0])
                    + J[0, 2] * (J[1, 0] * r[2] - r[1] * J[2, 0]))
    out[2] = inv * (J[0, 0] * (J[1, 1] * r[2] - r[1] * J[2, 1])
                    - J[0, 1] * (J[1, 0] * r[2] - r[1] * J[2, 0])
                    + r[0] * (J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]))


@njit(cache=True, nogil=True, inline="always")
def _newton(dq, org, h, regions, y, s, iterations, tol, val, jac, J, r, step, new, w, dw):
    """Damped Newton for W(s) = org + h s + val(s) = y from ``s`` (updated in place).

    It is the reference's iteration step for step. Returns the residual (inf when
    singular or held at the extrapolation box's edge) and whether ``val`` and ``jac``
    are those at the returned ``s`` (converged: the last evaluation was at ``s``).
    """
    res = math.inf
    for _ in range(iterations):
        _spline(dq, s, regions, val, jac, w, dw)
        res = 0.0
        for m in range(3):
            r[m] = org[m] + h[m] * s[m] + val[m] - y[m]
            if abs(r[m]) > res:
                res = abs(r[m])
        if res < tol:
            return res, True
        det = _map_jacobian(jac, h, J)
        if not abs(det) > 1e-12:
            return math.inf, False
        _solve3(J, det, r, step)
        big = max(abs(step[0]), abs(step[1]), abs(step[2]))
        scale = 1.0 if big <= 1.0 else 1.0 / big
        moved = 0.0
        for d in range(3):
            v = _clip(s[d] - step[d] * scale, regions[d])
            if abs(v - s[d]) > moved:
                moved = abs(v - s[d])
            new[d] = v
        for d in range(3):
            s[d] = new[d]
        if not moved > 1e-13:
            return math.inf, False
    return res, False


@njit(cache=True, nogil=True)
def invert_rows(dq, org, h, regions, shift, box_lo, box_hi, matrix, nx, ny, z0, z1,
                iterations, tol, accept, warm, out, status):
    """Fill ``out[z, y, x, 3]`` and ``status[z, y, x]`` for the output slices [z0, z1).

    ``out``: float32, world mm: M (F^-1(y) - y), NaN without one; ``status``: FOUND,
    NO_INVERSE, FOLDED.

    ``warm``: start each voxel from its row neighbour's solution (else every voxel
    starts from the identity's parameters, as the reference).
    """
    s = np.empty(3)
    start = np.empty(3)
    prev = np.empty(3)
    pred = np.empty(3)
    pred1 = np.empty(3)
    ex = np.zeros(3)
    ex[0] = 1.0
    yv = np.empty(3)
    val = np.empty(3)
    jac = np.empty((3, 3))
    J = np.empty((3, 3))
    r = np.empty(3)
    step = np.empty(3)
    new = np.empty(3)
    w = np.empty((3, 4))  # the B-spline weights along x, y, z, and their derivatives
    dw = np.empty((3, 4))
    eps = 1e-9
    nan = np.float32(np.nan)
    for iz in range(z0, z1):
        for iy in range(ny):
            have_prev = 0
            for ix in range(nx):
                yv[0] = ix + shift[0]
                yv[1] = iy + shift[1]
                yv[2] = iz + shift[2]
                st = NO_INVERSE
                near = True
                for d in range(3):
                    if not (yv[d] >= box_lo[d] and yv[d] <= box_hi[d]):
                        near = False
                if near:
                    # the reference's start: the identity's parameters, clipped
                    for d in range(3):
                        start[d] = _clip((yv[d] - org[d]) / h[d], regions[d])
                    tried_start = False
                    if warm and have_prev:
                        for d in range(3):
                            # s(y + 1) = s + s' + s''/2, s' = J^-1 e_x, s'' from the last two
                            v = prev[d] + pred[d]
                            if have_prev > 1:
                                v += 0.5 * (pred[d] - pred1[d])
                            s[d] = _clip(v, regions[d])
                    else:
                        for d in range(3):
                            s[d] = start[d]
                        tried_start = True
                    for _attempt in range(2):
                        res, fresh = _newton(dq, org, h, regions, yv, s, iterations, tol, val,
                                             jac, J, r, step, new, w, dw)
                        inside = True
                        for d in range(3):
                            if not (s[d] >= -eps and s[d] <= regions[d] + eps):
                                inside = False
                        if res < accept and inside:
                            st = FOUND
                            break
                        if tried_start:
                            break
                        for d in range(3):
                            s[d] = start[d]
                        tried_start = True
                if st == FOUND:
                    if not fresh:
                        _spline(dq, s, regions, val, jac, w, dw)
                    det = _map_jacobian(jac, h, J)
                    if det <= 0.0:
                        st = FOLDED
                        have_prev = 0
                    else:
                        # the next voxel (y + e_x) starts from here
                        for d in range(3):
                            pred1[d] = pred[d]
                        _solve3(J, det, ex, pred)
                        for d in range(3):
                            prev[d] = s[d]
                        have_prev += 1
                else:
                    have_prev = 0
                status[iz, iy, ix] = st
                if st == FOUND:
                    for m in range(3):
                        acc = 0.0
                        for d in range(3):
                            acc += matrix[m, d] * (org[d] + h[d] * s[d] - yv[d])
                        out[iz, iy, ix, m] = acc
                else:
                    for m in range(3):
                        out[iz, iy, ix, m] = nan


@njit(cache=True, nogil=True)
def jacobian_rows(dq, org, h, regions, nx, ny, z0, z1, out):
    """The det dF/dx (float32) of the input grid's slices [z0, z1) into ``out[z, y, x]``.

    These are the values of :meth:`.export.ForwardMap.jacobian`, row by row (the y and z
    weights of a row contracted once per control column).
    """
    cx = dq.shape[2]
    w = np.empty((3, 4))  # the B-spline weights along x, y, z, and their derivatives
    dw = np.empty((3, 4))
    col = np.empty((3, cx, 3))  # [weight combination, control column, component]
    for iz in range(z0, z1):
        sz = (iz - org[2]) / h[2]
        c = _cell(sz, regions[2])
        _basis(sz - c, w, dw, 2)
        for iy in range(ny):
            sy = (iy - org[1]) / h[1]
            b = _cell(sy, regions[1])
            _basis(sy - b, w, dw, 1)
            for i in range(cx):
                for m in range(3):
                    v = 0.0
                    vy = 0.0
                    vz = 0.0
                    for k in range(4):
                        for j in range(4):
                            q = dq[c + k, b + j, i, m]
                            v += w[1, j] * w[2, k] * q
                            vy += dw[1, j] * w[2, k] * q
                            vz += w[1, j] * dw[2, k] * q
                    col[0, i, m] = v
                    col[1, i, m] = vy / h[1]
                    col[2, i, m] = vz / h[2]
            for ix in range(nx):
                sx = (ix - org[0]) / h[0]
                a = _cell(sx, regions[0])
                _basis(sx - a, w, dw, 0)
                # dF/dx = I + d(dq)/dx, its columns along x, y, z
                j00, j10, j20 = 1.0, 0.0, 0.0
                j01, j11, j21 = 0.0, 1.0, 0.0
                j02, j12, j22 = 0.0, 0.0, 1.0
                for i in range(4):
                    ddx = dw[0, i] / h[0]
                    wi = w[0, i]
                    ai = a + i
                    j00, j10, j20 = _add3(ddx, col[0, ai, 0], col[0, ai, 1], col[0, ai, 2],
                                          j00, j10, j20)
                    j01, j11, j21 = _add3(wi, col[1, ai, 0], col[1, ai, 1], col[1, ai, 2],
                                          j01, j11, j21)
                    j02, j12, j22 = _add3(wi, col[2, ai, 0], col[2, ai, 1], col[2, ai, 2],
                                          j02, j12, j22)
                out[iz, iy, ix] = (j00 * (j11 * j22 - j12 * j21) - j01 * (j10 * j22 - j12 * j20)
                                   + j02 * (j10 * j21 - j11 * j20))
