"""numba kernels of the volume ray caster (see :mod:`.raycast`).

Each kernel does a range of planes, block rows or pixel rows, without the GIL;
the wrappers run those ranges over volwarp's threads
(:func:`~volwarp_cli.parallel.run_blocks`). Every plane, block and pixel is
computed on its own, so the picture does not depend on the thread count.
Plain ``nogil`` kernels, not ``prange`` ones: they compile several times
faster (a cold numba cache made a first render wait ~17 s) and use the
thread count volwarp sets, not numba's pool.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .. import parallel

#: pixel rows per task of the march (rows differ in cost: many small tasks balance)
MARCH_ROWS = 8


def _over_threads(task, n: int, per: int = 1) -> None:
    """``task(a, b)`` over ranges covering [0, n), ``per`` items or more each, on the threads."""
    parallel.run_ranges(task, n, parts=max(1, min(n // max(per, 1), 4 * parallel.threads())))


@njit(cache=True, nogil=True)
def _gradient_planes(v, zoff, nzg, g, a, b):
    nz, ny, nx = v.shape
    for zl in range(a, b):
        z = zl + zoff
        z0 = z - 1 if z > 0 else 0
        z1 = z + 1 if z < nzg - 1 else nzg - 1
        if z0 < zoff:
            z0 = zoff
        if z1 > zoff + nz - 1:
            z1 = zoff + nz - 1
        for y in range(ny):
            y0 = y - 1 if y > 0 else 0
            y1 = y + 1 if y < ny - 1 else ny - 1
            for x in range(nx):
                x0 = x - 1 if x > 0 else 0
                x1 = x + 1 if x < nx - 1 else nx - 1
                g[zl, y, x, 0] = (v[zl, y, x1] - v[zl, y, x0]) / max(x1 - x0, 1)
                g[zl, y, x, 1] = (v[zl, y1, x] - v[zl, y0, x]) / max(y1 - y0, 1)
                g[zl, y, x, 2] = (v[z1 - zoff, y, x] - v[z0 - zoff, y, x]) / max(z1 - z0, 1)


def gradient_slab(v, zoff, nzg):
    """Central-difference gradient (x, y, z components) of the planes ``v`` holds.

    ``v[z, y, x]`` holds the planes ``zoff .. zoff + len(v) - 1`` of a volume of
    ``nzg`` planes: the one-sided differences are taken at the volume's real
    ends (planes 0 and ``nzg - 1``). A plane whose central difference needs a
    plane ``v`` does not hold (the first or last one held, not at the volume's
    end) gets a one-sided difference within ``v``: a halo plane, not to be used.
    """
    g = np.empty(v.shape + (3,), dtype=np.float32)
    _over_threads(lambda a, b: _gradient_planes(v, zoff, nzg, g, a, b), v.shape[0])
    return g


@njit(cache=True, nogil=True)
def _block_max_rows(v, b, zoff, nzg, k0, out, a, c):
    nz, ny, nx = v.shape
    by = out.shape[1]
    bx = out.shape[2]
    for kk in range(a, c):
        k = kk + k0
        for j in range(by):
            for i in range(bx):
                m = np.float32(0.0)
                for z in range(k * b, min(k * b + b + 1, nzg)):
                    for y in range(j * b, min(j * b + b + 1, ny)):
                        for x in range(i * b, min(i * b + b + 1, nx)):
                            if v[z - zoff, y, x] > m:
                                m = v[z - zoff, y, x]
                out[kk, j, i] = m


def block_max_slab(v, b, zoff, nzg, k0, k1):
    """The maximum of ``v`` over each block's voxels [k b, k b + b] (one voxel of overlap).

    For the block rows ``k0 .. k1 - 1`` (along z), from the planes ``v`` holds:
    ``v`` holds the planes ``zoff ..`` of a volume of ``nzg`` planes, at least
    ``k0 b .. min(k1 b + 1, nzg) - 1`` (a block's planes and the next block's first).
    """
    _, ny, nx = v.shape
    out = np.empty((k1 - k0, (ny + b - 1) // b, (nx + b - 1) // b), dtype=np.float32)
    _over_threads(lambda a, c: _block_max_rows(v, b, zoff, nzg, k0, out, a, c), k1 - k0)
    return out


@njit(cache=True, inline="always")
def _unit(v):
    if v > 1.0:
        return 1.0
    if v >= 0.0:
        return v
    return 0.0  # negative or NaN


@njit(cache=True, inline="always")
def _cell(p, n):
    if p < 0.0:
        p = 0.0
    elif p > n - 1:
        p = n - 1.0
    i0 = int(p)
    if i0 >= n - 1:
        i0 = n - 2 if n > 1 else 0
    f = p - i0
    i1 = i0 + 1 if n > 1 else 0
    return i0, i1, f


@njit(cache=True, inline="always")
def _clip_to_slab(p, d, n, t0, t1):
    """The part ``[t0, t1]`` of the ray ``p + t d`` (one axis) between samples 0 and n - 1."""
    if abs(d) < 1e-12:
        if p < 0.0 or p > n - 1:
            t1 = -1.0
    else:
        ta = (0.0 - p) / d
        tb = (n - 1 - p) / d
        if ta > tb:
            ta, tb = tb, ta
        if ta > t0:
            t0 = ta
        if tb < t1:
            t1 = tb
    return t0, t1


@njit(cache=True, inline="always")
def _block_exit(p, d, bi, B, te):
    """The lesser of ``te`` and where the ray ``p + t d`` (one axis) leaves block ``bi``."""
    if d > 1e-12:
        tt = ((bi + 1) * B - p) / d
    elif d < -1e-12:
        tt = (bi * B - p) / d
    else:
        tt = 1e300
    return tt if tt < te else te


@njit(cache=True)
def _march_row(row, op, cr_, cg_, cb_, const_col, grad, zoff, nz, ny, nx, zs, ze, first, bmax, B,
               spacing, centre, fwd, right, up, half_w, half_h, pix, radius, hstep, step, light,
               halfway, shading, state):
    w = state.shape[1]
    dx = fwd[0] / spacing[0]
    dy = fwd[1] / spacing[1]
    dz = fwd[2] / spacing[2]
    for c in range(w):
        a = -half_w + (c + 0.5) * pix
        bb = half_h - (row + 0.5) * pix
        ox = centre[0] + a * right[0] + bb * up[0] - 1.5 * radius * fwd[0]
        oy = centre[1] + a * right[1] + bb * up[1] - 1.5 * radius * fwd[1]
        oz = centre[2] + a * right[2] + bb * up[2] - 1.5 * radius * fwd[2]
        px = ox / spacing[0]
        py = oy / spacing[1]
        pz = oz / spacing[2]
        # slab intersection with the box of voxel centres
        t0, t1 = _clip_to_slab(px, dx, nx, 0.0, 3.0 * radius)
        t0, t1 = _clip_to_slab(py, dy, ny, t0, t1)
        t0, t1 = _clip_to_slab(pz, dz, nz, t0, t1)
        if first:
            cr = 0.0
            cg = 0.0
            cb = 0.0
            A = 0.0
            # a fixed per-pixel offset of the first sample (a hash of the pixel) turns the
            # rings of regular sampling into fine noise; renders stay deterministic
            hsh = ((row * 73856093) ^ (c * 19349663)) & 1023
            t = t0 + hstep * (hsh / 1024.0)
        else:
            t = state[row, c, 0]
            cr = state[row, c, 1]
            cg = state[row, c, 2]
            cb = state[row, c, 3]
            A = state[row, c, 4]
        while t <= t1 and A < 0.995:
            x = px + t * dx
            y = py + t * dy
            z = pz + t * dz
            # the sample belongs to the slab of its cell's first plane (z0): another
            # slab's, met later along every ray (z is monotonic in t), stops it here
            z0, z1, fz = _cell(z, nz)
            if z0 < zs or z0 >= ze:
                break
            bxi = min(max(int(x) // B, 0), bmax.shape[2] - 1)
            byi = min(max(int(y) // B, 0), bmax.shape[1] - 1)
            bzi = min(max(int(z) // B, 0), bmax.shape[0] - 1)
            if bmax[bzi, byi, bxi] <= 0.0:
                # skip to where the ray leaves this block
                te = _block_exit(x, dx, bxi, B, 1e300)
                te = _block_exit(y, dy, byi, B, te)
                te = _block_exit(z, dz, bzi, B, te)
                k = math.ceil((te + 1e-6) / hstep)
                if k < 1:
                    k = 1
                t += k * hstep
                continue
            x0, x1, fx = _cell(x, nx)
            y0, y1, fy = _cell(y, ny)
            z0 -= zoff
            z1 -= zoff
            w000 = (1 - fx) * (1 - fy) * (1 - fz)
            w100 = fx * (1 - fy) * (1 - fz)
            w010 = (1 - fx) * fy * (1 - fz)
            w110 = fx * fy * (1 - fz)
            w001 = (1 - fx) * (1 - fy) * fz
            w101 = fx * (1 - fy) * fz
            w011 = (1 - fx) * fy * fz
            w111 = fx * fy * fz
            o = (op[z0, y0, x0] * w000 + op[z0, y0, x1] * w100 + op[z0, y1, x0] * w010
                 + op[z0, y1, x1] * w110 + op[z1, y0, x0] * w001 + op[z1, y0, x1] * w101
                 + op[z1, y1, x0] * w011 + op[z1, y1, x1] * w111)
            if o > 1e-4:
                alpha = 1.0 - (1.0 - min(o, 1.0)) ** step
                if const_col:
                    r = cr_[0, 0, 0]
                    g = cg_[0, 0, 0]
                    b = cb_[0, 0, 0]
                else:
                    r = (cr_[z0, y0, x0] * w000 + cr_[z0, y0, x1] * w100
                         + cr_[z0, y1, x0] * w010 + cr_[z0, y1, x1] * w110
                         + cr_[z1, y0, x0] * w001 + cr_[z1, y0, x1] * w101
                         + cr_[z1, y1, x0] * w011 + cr_[z1, y1, x1] * w111)
                    g = (cg_[z0, y0, x0] * w000 + cg_[z0, y0, x1] * w100
                         + cg_[z0, y1, x0] * w010 + cg_[z0, y1, x1] * w110
                         + cg_[z1, y0, x0] * w001 + cg_[z1, y0, x1] * w101
                         + cg_[z1, y1, x0] * w011 + cg_[z1, y1, x1] * w111)
                    b = (cb_[z0, y0, x0] * w000 + cb_[z0, y0, x1] * w100
                         + cb_[z0, y1, x0] * w010 + cb_[z0, y1, x1] * w110
                         + cb_[z1, y0, x0] * w001 + cb_[z1, y0, x1] * w101
                         + cb_[z1, y1, x0] * w011 + cb_[z1, y1, x1] * w111)
                r = _unit(r)
                g = _unit(g)
                b = _unit(b)
                shade = 1.0
                spec = 0.0
                if shading:
                    gx = 0.0
                    gy = 0.0
                    gz = 0.0
                    for ch in range(3):
                        v = (grad[z0, y0, x0, ch] * w000 + grad[z0, y0, x1, ch] * w100
                             + grad[z0, y1, x0, ch] * w010 + grad[z0, y1, x1, ch] * w110
                             + grad[z1, y0, x0, ch] * w001 + grad[z1, y0, x1, ch] * w101
                             + grad[z1, y1, x0, ch] * w011 + grad[z1, y1, x1, ch] * w111)
                        if ch == 0:
                            gx = v / spacing[0]
                        elif ch == 1:
                            gy = v / spacing[1]
                        else:
                            gz = v / spacing[2]
                    gn = math.sqrt(gx * gx + gy * gy + gz * gz)
                    if gn > 1e-3 / min(spacing[0], min(spacing[1], spacing[2])):
                        nx_ = -gx / gn
                        ny_ = -gy / gn
                        nz_ = -gz / gn
                        ndl = abs(nx_ * light[0] + ny_ * light[1] + nz_ * light[2])
                        ndh = abs(nx_ * halfway[0] + ny_ * halfway[1] + nz_ * halfway[2])
                        shade = 0.3 + 0.7 * ndl
                        spec = 0.25 * ndh ** 24
                k = (1.0 - A) * alpha
                cr += k * (r * shade + spec)
                cg += k * (g * shade + spec)
                cb += k * (b * shade + spec)
                A += k
            t += hstep
        state[row, c, 0] = t
        state[row, c, 1] = cr
        state[row, c, 2] = cg
        state[row, c, 3] = cb
        state[row, c, 4] = A


@njit(cache=True, nogil=True)
def _march_rows(r0, r1, op, cr_, cg_, cb_, const_col, grad, zoff, nz, ny, nx, zs, ze, first,
                bmax, B, spacing, centre, fwd, right, up, half_w, half_h, pix, radius, hstep,
                step, light, halfway, shading, state):
    for row in range(r0, r1):
        _march_row(row, op, cr_, cg_, cb_, const_col, grad, zoff, nz, ny, nx, zs, ze, first, bmax,
                   B, spacing, centre, fwd, right, up, half_w, half_h, pix, radius, hstep, step,
                   light, halfway, shading, state)


def march_slab(op, cr_, cg_, cb_, const_col, grad, zoff, nz, ny, nx, zs, ze, first, bmax, B,
               spacing, centre, fwd, right, up, half_w, half_h, pix, radius, hstep, step, light,
               halfway, shading, state):
    """March every pixel's ray through the samples whose cell starts at a plane in [zs, ze).

    ``op``, ``cr_``/``cg_``/``cb_`` (or 1x1x1 with ``const_col``) and ``grad``
    hold the planes ``zoff ..`` of a volume of ``(nz, ny, nx)`` samples (the
    planes ``zs .. ze`` at least); ``bmax`` is the whole volume's
    :func:`block_max_slab`. ``state[row, col]`` = (t, red, green, blue, A), set on
    the ``first`` slab and carried from slab to slab (then :func:`finish`): the
    slabs in the rays' z order make, sample for sample, the one-slab march.
    """
    def rows(r0, r1):
        _march_rows(r0, r1, op, cr_, cg_, cb_, const_col, grad, zoff, nz, ny, nx, zs, ze, first,
                    bmax, B, spacing, centre, fwd, right, up, half_w, half_h, pix, radius, hstep,
                    step, light, halfway, shading, state)

    _over_threads(rows, state.shape[0], MARCH_ROWS)


@njit(cache=True, nogil=True)
def finish(state, background, img):
    """The picture of the marched rays: their colour over ``background`` (what is left of A)."""
    for row in range(state.shape[0]):
        for c in range(state.shape[1]):
            A = state[row, c, 4]
            img[row, c, 0] = state[row, c, 1] + (1.0 - A) * background[0]
            img[row, c, 1] = state[row, c, 2] + (1.0 - A) * background[1]
            img[row, c, 2] = state[row, c, 3] + (1.0 - A) * background[2]
