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
def _basis(t, w, dw):
    u = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    w[0] = u * u * u / 6.0
    w[1] = (4.0 - 6.0 * t2 + 3.0 * t3) / 6.0
    w[2] = (1.0 + 3.0 * t + 3.0 * t2 - 3.0 * t3) / 6.0
    w[3] = t3 / 6.0
    dw[0] = -0.5 * u * u
    dw[1] = (-12.0 * t + 9.0 * t2) / 6.0
    dw[2] = (3.0 + 6.0 * t - 9.0 * t2) / 6.0
    dw[3] = 0.5 * t2


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
def _spline(dq, s, regions, val, jac, wx, wy, wz, dx, dy, dz):
    """val[m] = sum B dq[..., m] at parameters s; jac[m, axis] = d val[m] / d s[axis]."""
    a0 = _cell(s[0], regions[0])
    a1 = _cell(s[1], regions[1])
    a2 = _cell(s[2], regions[2])
    _basis(s[0] - a0, wx, dx)
    _basis(s[1] - a1, wy, dy)
    _basis(s[2] - a2, wz, dz)
    # scalar accumulators (array ones would be stored to memory on every term)
    v0 = 0.0
    v1 = 0.0
    v2 = 0.0
    j00 = 0.0
    j01 = 0.0
    j02 = 0.0
    j10 = 0.0
    j11 = 0.0
    j12 = 0.0
    j20 = 0.0
    j21 = 0.0
    j22 = 0.0
    for k in range(4):
        for j in range(4):
            ax0 = 0.0
            ax1 = 0.0
            ax2 = 0.0
            dx0 = 0.0
            dx1 = 0.0
            dx2 = 0.0
            for i in range(4):
                q0 = dq[a2 + k, a1 + j, a0 + i, 0]
                q1 = dq[a2 + k, a1 + j, a0 + i, 1]
                q2 = dq[a2 + k, a1 + j, a0 + i, 2]
                ax0 += wx[i] * q0
                ax1 += wx[i] * q1
                ax2 += wx[i] * q2
                dx0 += dx[i] * q0
                dx1 += dx[i] * q1
                dx2 += dx[i] * q2
            wyz = wy[j] * wz[k]
            dyz = dy[j] * wz[k]
            ydz = wy[j] * dz[k]
            v0 += wyz * ax0
            v1 += wyz * ax1
            v2 += wyz * ax2
            j00 += wyz * dx0
            j10 += wyz * dx1
            j20 += wyz * dx2
            j01 += dyz * ax0
            j11 += dyz * ax1
            j21 += dyz * ax2
            j02 += ydz * ax0
            j12 += ydz * ax1
            j22 += ydz * ax2
    val[0] = v0
    val[1] = v1
    val[2] = v2
    jac[0, 0] = j00
    jac[0, 1] = j01
    jac[0, 2] = j02
    jac[1, 0] = j10
    jac[1, 1] = j11
    jac[1, 2] = j12
    jac[2, 0] = j20
    jac[2, 1] = j21
    jac[2, 2] = j22


@njit(cache=True, nogil=True, inline="always")
def _det3(J):
    return (J[0, 0] * (J[1, 1] * J[2, 2] - J[1, 2] * J[2, 1])
            - J[0, 1] * (J[1, 0] * J[2, 2] - J[1, 2] * J[2, 0])
            + J[0, 2] * (J[1, 0] * J[2, 1] - J[1, 1] * J[2, 0]))


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
def _newton(dq, org, h, regions, y, s, iterations, tol, val, jac, J, r, step, new,
            wx, wy, wz, dx, dy, dz):
    """Damped Newton for W(s) = org + h s + val(s) = y from ``s`` (updated in place).

    It is the reference's iteration step for step. Returns the residual (inf when
    singular or held at the extrapolation box's edge) and whether ``val`` and ``jac``
    are those at the returned ``s`` (converged: the last evaluation was at ``s``).
    """
    res = math.inf
    for _ in range(iterations):
        _spline(dq, s, regions, val, jac, wx, wy, wz, dx, dy, dz)
        res = 0.0
        for m in range(3):
            r[m] = org[m] + h[m] * s[m] + val[m] - y[m]
            if abs(r[m]) > res:
                res = abs(r[m])
        if res < tol:
            return res, True
        for m in range(3):
            for d in range(3):
                J[m, d] = jac[m, d]
            J[m, m] += h[m]
        det = _det3(J)
        if not abs(det) > 1e-12:
            return math.inf, False
        _solve3(J, det, r, step)
        big = max(abs(step[0]), abs(step[1]), abs(step[2]))
        scale = 1.0 if big <= 1.0 else 1.0 / big
        moved = 0.0
        for d in range(3):
            v = s[d] - step[d] * scale
            if v < -0.5:
                v = -0.5
            elif v > regions[d] + 0.5:
                v = regions[d] + 0.5
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
    wx = np.empty(4)
    wy = np.empty(4)
    wz = np.empty(4)
    dx = np.empty(4)
    dy = np.empty(4)
    dz = np.empty(4)
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
                        v = (yv[d] - org[d]) / h[d]
                        if v < -0.5:
                            v = -0.5
                        elif v > regions[d] + 0.5:
                            v = regions[d] + 0.5
                        start[d] = v
                    tried_start = False
                    if warm and have_prev:
                        for d in range(3):
                            # s(y + 1) = s + s' + s''/2, s' = J^-1 e_x, s'' from the last two
                            v = prev[d] + pred[d]
                            if have_prev > 1:
                                v += 0.5 * (pred[d] - pred1[d])
                            if v < -0.5:
                                v = -0.5
                            elif v > regions[d] + 0.5:
                                v = regions[d] + 0.5
                            s[d] = v
                    else:
                        for d in range(3):
                            s[d] = start[d]
                        tried_start = True
                    for _attempt in range(2):
                        res, fresh = _newton(dq, org, h, regions, yv, s, iterations, tol, val, jac,
                                      J, r, step, new, wx, wy, wz, dx, dy, dz)
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
                        _spline(dq, s, regions, val, jac, wx, wy, wz, dx, dy, dz)
                    for m in range(3):
                        for d in range(3):
                            J[m, d] = jac[m, d]
                        J[m, m] += h[m]
                    det = _det3(J)
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
    wx = np.empty(4)
    wy = np.empty(4)
    wz = np.empty(4)
    dx = np.empty(4)
    dy = np.empty(4)
    dz = np.empty(4)
    col = np.empty((3, cx, 3))  # [weight combination, control column, component]
    for iz in range(z0, z1):
        sz = (iz - org[2]) / h[2]
        c = _cell(sz, regions[2])
        _basis(sz - c, wz, dz)
        for iy in range(ny):
            sy = (iy - org[1]) / h[1]
            b = _cell(sy, regions[1])
            _basis(sy - b, wy, dy)
            for i in range(cx):
                for m in range(3):
                    v = 0.0
                    vy = 0.0
                    vz = 0.0
                    for k in range(4):
                        for j in range(4):
                            q = dq[c + k, b + j, i, m]
                            v += wy[j] * wz[k] * q
                            vy += dy[j] * wz[k] * q
                            vz += wy[j] * dz[k] * q
                    col[0, i, m] = v
                    col[1, i, m] = vy / h[1]
                    col[2, i, m] = vz / h[2]
            for ix in range(nx):
                sx = (ix - org[0]) / h[0]
                a = _cell(sx, regions[0])
                _basis(sx - a, wx, dx)
                j00 = 1.0
                j11 = 1.0
                j22 = 1.0
                j01 = 0.0
                j02 = 0.0
                j10 = 0.0
                j12 = 0.0
                j20 = 0.0
                j21 = 0.0
                for i in range(4):
                    ddx = dx[i] / h[0]
                    w = wx[i]
                    j00 += ddx * col[0, a + i, 0]
                    j10 += ddx * col[0, a + i, 1]
                    j20 += ddx * col[0, a + i, 2]
                    j01 += w * col[1, a + i, 0]
                    j11 += w * col[1, a + i, 1]
                    j21 += w * col[1, a + i, 2]
                    j02 += w * col[2, a + i, 0]
                    j12 += w * col[2, a + i, 1]
                    j22 += w * col[2, a + i, 2]
                out[iz, iy, ix] = (j00 * (j11 * j22 - j12 * j21) - j01 * (j10 * j22 - j12 * j20)
                                   + j02 * (j10 * j21 - j11 * j20))
