"""numba kernels: sampling images and vector grids at continuous indices, as ITK does.

Imported lazily (numba's import costs about 0.3 s; the kernels are cached on
disk). Plain ``nogil`` loops over points: the callers split the points over
volwarp's threads, and each point is computed on its own, so the result does
not depend on the split.

Indices are (x, y, z) continuous voxel indices. ITK's rules, checked against
SimpleITK: a point is inside an image's buffer when ``-0.5 <= i < n - 0.5``
on every axis; linear interpolation clamps the neighbours beyond the last
sample to it; cubic B-spline interpolation reads coefficients mirrored at
the edges (``-i``, ``2 (n - 1) - i``: the caller pads them); nearest rounds
half up. The trilinear and the cubic sums are one function each
(:func:`_trilinear`, :func:`_cubic_sum`) over a (z, y, x, components) array:
a scalar image is read as one component.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _inside(x, y, z, nx, ny, nz):
    return (x >= -0.5 and x < nx - 0.5 and y >= -0.5 and y < ny - 0.5
            and z >= -0.5 and z < nz - 0.5)


@njit(cache=True, nogil=True, inline="always")
def _axis(x, n):
    """The lower neighbour, the upper one (both clamped) and the upper's weight."""
    b = math.floor(x)
    d = x - b
    b0 = min(max(b, 0), n - 1)
    b1 = min(max(b + 1, 0), n - 1)
    return b0, b1, d


@njit(cache=True, nogil=True, inline="always")
def _cubic_weights(t, w):
    """The four cubic B-spline weights of fraction ``t`` into ``w``."""
    s = 1.0 - t
    w[0] = s * s * s / 6.0
    w[1] = (3.0 * t * t * t - 6.0 * t * t + 4.0) / 6.0
    w[2] = (-3.0 * t * t * t + 3.0 * t * t + 3.0 * t + 1.0) / 6.0
    w[3] = t * t * t / 6.0


@njit(cache=True, nogil=True, inline="always")
def _cubic_support(x, w):
    """The first of the four indices a cubic B-spline at ``x`` weighs; their weights into ``w``."""
    b = int(math.floor(x)) - 1
    _cubic_weights(x - b - 1, w)
    return b


@njit(cache=True, nogil=True, inline="always")
def _cubic_sum(a, c, bz, by, bx, wz, wy, wx):
    """Component ``c`` of ``a`` (z, y, x, components) weighed over the 4x4x4 indices from ``b``."""
    acc = 0.0
    for k in range(4):
        sy = 0.0
        for j in range(4):
            sx = 0.0
            for m in range(4):
                sx += wx[m] * a[bz + k, by + j, bx + m, c]
            sy += wy[j] * sx
        acc += wz[k] * sy
    return acc


@njit(cache=True, nogil=True, inline="always")
def _trilinear(a, c, z0, z1, y0, y1, x0, x1, fz, fy, fx):
    """Component ``c`` of ``a`` (z, y, x, components) between its eight neighbours."""
    lo = (a[z0, y0, x0, c] * (1 - fx) + a[z0, y0, x1, c] * fx) * (1 - fy) \
        + (a[z0, y1, x0, c] * (1 - fx) + a[z0, y1, x1, c] * fx) * fy
    hi = (a[z1, y0, x0, c] * (1 - fx) + a[z1, y0, x1, c] * fx) * (1 - fy) \
        + (a[z1, y1, x0, c] * (1 - fx) + a[z1, y1, x1, c] * fx) * fy
    return lo * (1 - fz) + hi * fz


@njit(cache=True, nogil=True)
def bspline_cubic(coef, idx, out):
    """ITK's BSplineTransform displacement: ``coef`` (z, y, x, 3) at grid indices ``idx``.

    Zero where a point's index is outside ``[1, n - 2)`` on some axis (ITK's valid region).
    """
    nz, ny, nx = coef.shape[0], coef.shape[1], coef.shape[2]
    wx, wy, wz = np.empty(4), np.empty(4), np.empty(4)
    for i in range(idx.shape[0]):
        x, y, z = idx[i, 0], idx[i, 1], idx[i, 2]
        out[i, 0] = 0.0
        out[i, 1] = 0.0
        out[i, 2] = 0.0
        if not (x >= 1.0 and x < nx - 2.0 and y >= 1.0 and y < ny - 2.0
                and z >= 1.0 and z < nz - 2.0):
            continue
        bx = _cubic_support(x, wx)
        by = _cubic_support(y, wy)
        bz = _cubic_support(z, wz)
        for c in range(3):
            out[i, c] = _cubic_sum(coef, c, bz, by, bx, wz, wy, wx)


@njit(cache=True, nogil=True)
def sample_linear(img, idx, lo, n, background, out):
    """Trilinear samples of ``img`` (a region starting at global index ``lo``, x, y, z).

    ``img`` C-contiguous; ``idx`` global (x, y, z) indices, ``n`` the whole
    input's sizes (x, y, z): the inside test and the clamping are the whole
    input's; ``out`` float64.
    """
    a = img.reshape((img.shape[0], img.shape[1], img.shape[2], 1))
    nx, ny, nz = n[0], n[1], n[2]
    ox, oy, oz = lo[0], lo[1], lo[2]
    for i in range(idx.shape[0]):
        x, y, z = idx[i, 0], idx[i, 1], idx[i, 2]
        if not _inside(x, y, z, nx, ny, nz):
            out[i] = background
            continue
        x0, x1, fx = _axis(x, nx)
        y0, y1, fy = _axis(y, ny)
        z0, z1, fz = _axis(z, nz)
        out[i] = _trilinear(a, 0, z0 - oz, z1 - oz, y0 - oy, y1 - oy, x0 - ox, x1 - ox,
                            fz, fy, fx)


@njit(cache=True, nogil=True)
def sample_nearest(img, idx, lo, n, background, out):
    """Nearest samples of ``img`` (region at ``lo``), rounded half up; ``out`` of img's type."""
    nx, ny, nz = n[0], n[1], n[2]
    for i in range(idx.shape[0]):
        x, y, z = idx[i, 0], idx[i, 1], idx[i, 2]
        if not _inside(x, y, z, nx, ny, nz):
            out[i] = background
            continue
        ix = min(max(int(math.floor(x + 0.5)), 0), nx - 1) - lo[0]
        iy = min(max(int(math.floor(y + 0.5)), 0), ny - 1) - lo[1]
        iz = min(max(int(math.floor(z + 0.5)), 0), nz - 1) - lo[2]
        out[i] = img[iz, iy, ix]


@njit(cache=True, nogil=True)
def sample_cubic(coef, idx, lo, n, background, out):
    """Cubic B-spline samples from prefiltered coefficients ``coef`` (C-contiguous) at ``lo``.

    ``coef`` holds the coefficients of the indices from ``lo`` (x, y, z) on,
    mirrored beyond the input's edges where the points reach them (two
    indices: ``lo`` may be -2): every point's 4x4x4 support lies in it.
    """
    a = coef.reshape((coef.shape[0], coef.shape[1], coef.shape[2], 1))
    nx, ny, nz = n[0], n[1], n[2]
    wx, wy, wz = np.empty(4), np.empty(4), np.empty(4)
    for i in range(idx.shape[0]):
        x, y, z = idx[i, 0], idx[i, 1], idx[i, 2]
        if not _inside(x, y, z, nx, ny, nz):
            out[i] = background
            continue
        bx = _cubic_support(x, wx) - lo[0]
        by = _cubic_support(y, wy) - lo[1]
        bz = _cubic_support(z, wz) - lo[2]
        out[i] = _cubic_sum(a, 0, bz, by, bx, wz, wy, wx)


@njit(cache=True, nogil=True)
def affine(p, m, o, out):
    """``out = p @ m.T + o`` for points ``p`` (N, 3) (numpy's matmul is slow for 3x3)."""
    for i in range(p.shape[0]):
        x, y, z = p[i, 0], p[i, 1], p[i, 2]
        for r in range(3):
            out[i, r] = m[r, 0] * x + m[r, 1] * y + m[r, 2] * z + o[r]


@njit(cache=True, nogil=True)
def grid_points(lo, hi, m, o, out):
    """World points ``m @ (i, j, k) + o`` of the grid indices in ``[lo, hi)`` (x, y, z), x fastest."""
    n = 0
    for k in range(lo[2], hi[2]):
        for j in range(lo[1], hi[1]):
            for i in range(lo[0], hi[0]):
                for r in range(3):
                    out[n, r] = m[r, 0] * i + m[r, 1] * j + m[r, 2] * k + o[r]
                n += 1


@njit(cache=True, nogil=True)
def interleave(a, b, c, out):
    """``out[..., 0], out[..., 1], out[..., 2] = a, b, c``: (z, y, x) planes, C-contiguous."""
    fa, fb, fc = a.ravel(), b.ravel(), c.ravel()
    o = out.reshape(-1)
    for i in range(fa.size):
        o[3 * i] = fa[i]
        o[3 * i + 1] = fb[i]
        o[3 * i + 2] = fc[i]


@njit(cache=True, nogil=True)
def tile_range(vec, tile, tmin, tmax):
    """Per-tile min and max of each component of ``vec`` (z, y, x, 3), NaN skipped, in one pass.

    ``tmin``/``tmax`` (tiles z, y, x, 3), float64, filled with NaN by the
    caller: a tile of NaN only stays NaN (as ``np.fmin``).
    """
    nz, ny, nx = vec.shape[0], vec.shape[1], vec.shape[2]
    for z in range(nz):
        tz = z // tile
        for y in range(ny):
            ty = y // tile
            for x in range(nx):
                tx = x // tile
                for c in range(3):
                    v = vec[z, y, x, c]
                    if v == v:
                        if not tmin[tz, ty, tx, c] <= v:
                            tmin[tz, ty, tx, c] = v
                        if not tmax[tz, ty, tx, c] >= v:
                            tmax[tz, ty, tx, c] = v


@njit(cache=True, nogil=True)
def field_map(vec, p, inv, origin, offset, n, out):
    """``out = p + u(p)``: the field on the grid of world-to-index ``inv (p - origin)``.

    ``vec`` (z, y, x, 3) holds the grid's vectors from index ``offset`` (x, y,
    z) on (a window); ``n``: the whole grid's sizes (x, y, z). The inside test
    and the clamping are the whole grid's, so a window maps as the whole; an
    index beyond the window (never, when it covers the points) is clamped to it.

    Returns the first point whose displacement is not finite (a NaN or
    infinite vector among its neighbours), or -1: the caller refuses it.
    """
    nx, ny, nz = n[0], n[1], n[2]
    wz, wy, wx = vec.shape[0], vec.shape[1], vec.shape[2]
    first = -1
    for i in range(p.shape[0]):
        dx, dy, dz = p[i, 0] - origin[0], p[i, 1] - origin[1], p[i, 2] - origin[2]
        x = inv[0, 0] * dx + inv[0, 1] * dy + inv[0, 2] * dz
        y = inv[1, 0] * dx + inv[1, 1] * dy + inv[1, 2] * dz
        z = inv[2, 0] * dx + inv[2, 1] * dy + inv[2, 2] * dz
        if not _inside(x, y, z, nx, ny, nz):
            out[i, 0] = p[i, 0]
            out[i, 1] = p[i, 1]
            out[i, 2] = p[i, 2]
            continue
        x0, x1, fx = _axis(x, nx)
        y0, y1, fy = _axis(y, ny)
        z0, z1, fz = _axis(z, nz)
        x0 = min(max(x0 - offset[0], 0), wx - 1)
        x1 = min(max(x1 - offset[0], 0), wx - 1)
        y0 = min(max(y0 - offset[1], 0), wy - 1)
        y1 = min(max(y1 - offset[1], 0), wy - 1)
        z0 = min(max(z0 - offset[2], 0), wz - 1)
        z1 = min(max(z1 - offset[2], 0), wz - 1)
        u0 = _trilinear(vec, 0, z0, z1, y0, y1, x0, x1, fz, fy, fx)
        u1 = _trilinear(vec, 1, z0, z1, y0, y1, x0, x1, fz, fy, fx)
        u2 = _trilinear(vec, 2, z0, z1, y0, y1, x0, x1, fz, fy, fx)
        out[i, 0] = p[i, 0] + u0
        out[i, 1] = p[i, 1] + u1
        out[i, 2] = p[i, 2] + u2
        if not abs(u0 + u1 + u2) < math.inf and first < 0:  # (a NaN or an infinity)
            first = i
    return first
