"""Pushforward of the domain density into the target (paper §5–§6, thesis §5.4).

Each domain voxel ``(e, f, g)`` is sent to ``T = A(e, f, g) + U[g, f, e]``
(affine base map plus the deformation offsets, target voxel indices), then:

- ``nearest``: map and round (the papers' Figure 4/6 baseline): weight 1 to
  the target voxel holding ``T`` (ties round down, see ``ROUND``).
- ``box``: the papers' antialiasing: the six face centres are averages of
  neighbouring entries of the deformation array (paper §6), their bounding
  box stands in for the transformed voxel, and its overlap volume with each
  target voxel (as a fraction of the target voxel) is the weight.

Weights and weighted values are accumulated per target voxel; the result is
``v`` where the total weight is below 1 and ``v / w`` otherwise (paper §6).

Departures:

- The accumulators are int64 fixed point (weights and normalised weighted
  values in units of 2**-40), so adding and later *subtracting* a region's
  contribution is exact: the incremental updates of :mod:`.scene` equal a
  full recomputation bit for bit, instead of the papers' "write zeros".
- At the domain's outer faces the missing neighbour is extrapolated linearly
  (``1.5 U[e] - 0.5 U[e+1]``) so border voxels get a box too.
"""

from __future__ import annotations

import numpy as np

#: Rounding offset of the nearest modes: round half *down*, with a 1e-6 voxel
#: tolerance, the same in pullback and pushforward, so that a point on a tie
#: computed two slightly different ways still lands in the same voxel.
ROUND = 0.5 - 1e-6

#: Shift making coordinates positive so that truncation is floor.
SHIFT = 1048576.0
ISHIFT = 1048576

#: Fixed-point unit of the accumulators (2**40 per unit weight).
QUANTUM = float(2 ** 40)
METHODS = ("box", "nearest")


def _kernels():
    from numba import njit

    @njit(cache=True, nogil=True)
    def scatter(uh, org, values, off, scale, lo, hi, sign, inv_vmax, box, acc):  # pragma: no cover
        # uh holds the deformation offsets around the block, with a one-voxel
        # margin: domain voxel (g, f, e) is uh[g - oz + 1, f - oy + 1, e - ox + 1].
        tz, ty, tx, _ = acc.shape
        q = 1099511627776.0  # 2**40
        iq = np.int64(1) << 40
        bx0 = by0 = bz0 = np.int64(1) << 40
        bx1 = by1 = bz1 = np.int64(-1)
        nmax = max(tx, max(ty, tz)) + 2
        ovx = np.empty(nmax)
        ovy = np.empty(nmax)
        ovz = np.empty(nmax)
        hx = 0.5 * scale[0]
        hy = 0.5 * scale[1]
        hz = 0.5 * scale[2]
        for g in range(lo[2], hi[2]):
            bz = off[2] + scale[2] * g
            for f in range(lo[1], hi[1]):
                by = off[1] + scale[1] * f
                for e in range(lo[0], hi[0]):
                    bxx = off[0] + scale[0] * e
                    val = values[g, f, e] * inv_vmax
                    G = g + 1 - org[2]
                    F = f + 1 - org[1]
                    E = e + 1 - org[0]
                    ux = uh[G, F, E, 0]
                    uy = uh[G, F, E, 1]
                    uz = uh[G, F, E, 2]
                    if not box:
                        x = np.int64(np.floor(bxx + ux + ROUND))
                        y = np.int64(np.floor(by + uy + ROUND))
                        z = np.int64(np.floor(bz + uz + ROUND))
                        if x < 0 or y < 0 or z < 0 or x >= tx or y >= ty or z >= tz:
                            continue
                        acc[z, y, x, 0] += sign * iq
                        acc[z, y, x, 1] += sign * np.int64(np.floor(val * q + 0.5))
                        bx0 = min(bx0, x)
                        by0 = min(by0, y)
                        bz0 = min(bz0, z)
                        bx1 = max(bx1, x)
                        by1 = max(by1, y)
                        bz1 = max(bz1, z)
                        continue
                    # six face centres: averages with the neighbours' entries (paper 6)
                    # x faces
                    a0 = uh[G, F, E - 1, 0]
                    a1 = uh[G, F, E + 1, 0]
                    xmin = min(0.5 * (ux + a0) - hx, 0.5 * (ux + a1) + hx)
                    xmax = max(0.5 * (ux + a0) - hx, 0.5 * (ux + a1) + hx)
                    a0 = uh[G, F, E - 1, 1]
                    a1 = uh[G, F, E + 1, 1]
                    ymin = min(0.5 * (uy + a0), 0.5 * (uy + a1))
                    ymax = max(0.5 * (uy + a0), 0.5 * (uy + a1))
                    a0 = uh[G, F, E - 1, 2]
                    a1 = uh[G, F, E + 1, 2]
                    zmin = min(0.5 * (uz + a0), 0.5 * (uz + a1))
                    zmax = max(0.5 * (uz + a0), 0.5 * (uz + a1))
                    # y faces
                    a0 = 0.5 * (ux + uh[G, F - 1, E, 0])
                    a1 = 0.5 * (ux + uh[G, F + 1, E, 0])
                    xmin = min(xmin, min(a0, a1))
                    xmax = max(xmax, max(a0, a1))
                    a0 = 0.5 * (uy + uh[G, F - 1, E, 1]) - hy
                    a1 = 0.5 * (uy + uh[G, F + 1, E, 1]) + hy
                    ymin = min(ymin, min(a0, a1))
                    ymax = max(ymax, max(a0, a1))
                    a0 = 0.5 * (uz + uh[G, F - 1, E, 2])
                    a1 = 0.5 * (uz + uh[G, F + 1, E, 2])
                    zmin = min(zmin, min(a0, a1))
                    zmax = max(zmax, max(a0, a1))
                    # z faces
                    a0 = 0.5 * (ux + uh[G - 1, F, E, 0])
                    a1 = 0.5 * (ux + uh[G + 1, F, E, 0])
                    xmin = min(xmin, min(a0, a1))
                    xmax = max(xmax, max(a0, a1))
                    a0 = 0.5 * (uy + uh[G - 1, F, E, 1])
                    a1 = 0.5 * (uy + uh[G + 1, F, E, 1])
                    ymin = min(ymin, min(a0, a1))
                    ymax = max(ymax, max(a0, a1))
                    a0 = 0.5 * (uz + uh[G - 1, F, E, 2]) - hz
                    a1 = 0.5 * (uz + uh[G + 1, F, E, 2]) + hz
                    zmin = min(zmin, min(a0, a1))
                    zmax = max(zmax, max(a0, a1))
                    xmin += bxx
                    xmax += bxx
                    ymin += by
                    ymax += by
                    zmin += bz
                    zmax += bz
                    if not (xmax > xmin and ymax > ymin and zmax > zmin):
                        continue
                    # floor/ceil by truncation of shifted values (coordinates > -2**20)
                    x0 = max(np.int64(xmin - 0.5 + SHIFT) - ISHIFT + 1, 0)
                    x1 = min(ISHIFT - np.int64(SHIFT - xmax - 0.5) - 1, tx - 1)
                    y0 = max(np.int64(ymin - 0.5 + SHIFT) - ISHIFT + 1, 0)
                    y1 = min(ISHIFT - np.int64(SHIFT - ymax - 0.5) - 1, ty - 1)
                    z0 = max(np.int64(zmin - 0.5 + SHIFT) - ISHIFT + 1, 0)
                    z1 = min(ISHIFT - np.int64(SHIFT - zmax - 0.5) - 1, tz - 1)
                    if x1 < x0 or y1 < y0 or z1 < z0:
                        continue
                    wq = val * q
                    if x1 - x0 <= 1 and y1 - y0 <= 1 and z1 - z0 <= 1:
                        # the common case (at most 2 target voxels per axis), unrolled
                        ax0 = min(xmax, x0 + 0.5) - max(xmin, x0 - 0.5)
                        ax1 = min(xmax, x1 + 0.5) - max(xmin, x1 - 0.5) if x1 > x0 else 0.0
                        ay0 = min(ymax, y0 + 0.5) - max(ymin, y0 - 0.5)
                        ay1 = min(ymax, y1 + 0.5) - max(ymin, y1 - 0.5) if y1 > y0 else 0.0
                        az0 = min(zmax, z0 + 0.5) - max(zmin, z0 - 0.5)
                        az1 = min(zmax, z1 + 0.5) - max(zmin, z1 - 0.5) if z1 > z0 else 0.0
                        for dz in range(z1 - z0 + 1):
                            wz = az0 if dz == 0 else az1
                            for dy in range(y1 - y0 + 1):
                                wzy = wz * (ay0 if dy == 0 else ay1)
                                for dx in range(x1 - x0 + 1):
                                    w = wzy * (ax0 if dx == 0 else ax1)
                                    acc[z0 + dz, y0 + dy, x0 + dx, 0] += sign * np.int64(w * q + 0.5)
                                    acc[z0 + dz, y0 + dy, x0 + dx, 1] += sign * np.int64(
                                        np.floor(w * wq + 0.5))
                    else:
                        for v in range(x0, x1 + 1):
                            ovx[v - x0] = min(xmax, v + 0.5) - max(xmin, v - 0.5)
                        for v in range(y0, y1 + 1):
                            ovy[v - y0] = min(ymax, v + 0.5) - max(ymin, v - 0.5)
                        for v in range(z0, z1 + 1):
                            ovz[v - z0] = min(zmax, v + 0.5) - max(zmin, v - 0.5)
                        for z in range(z0, z1 + 1):
                            wz = ovz[z - z0]
                            for y in range(y0, y1 + 1):
                                wzy = wz * ovy[y - y0]
                                for x in range(x0, x1 + 1):
                                    w = wzy * ovx[x - x0]
                                    acc[z, y, x, 0] += sign * np.int64(w * q + 0.5)
                                    acc[z, y, x, 1] += sign * np.int64(np.floor(w * wq + 0.5))
                    bx0 = min(bx0, x0)
                    by0 = min(by0, y0)
                    bz0 = min(bz0, z0)
                    bx1 = max(bx1, x1)
                    by1 = max(by1, y1)
                    bz1 = max(bz1, z1)
        return np.array([bx0, by0, bz0, bx1, by1, bz1], dtype=np.int64)

    @njit(cache=True, nogil=True)
    def finalize(acc, vmax, lo, hi, out):  # pragma: no cover - jit
        inv_q = 1.0 / 1099511627776.0
        for z in range(lo[2], hi[2]):
            for y in range(lo[1], hi[1]):
                for x in range(lo[0], hi[0]):
                    w = acc[z, y, x, 0] * inv_q
                    v = acc[z, y, x, 1] * inv_q * vmax
                    out[z, y, x] = v if w < 1.0 else v / w

    return scatter, finalize


_KERNELS = None


def kernels():
    global _KERNELS
    if _KERNELS is None:
        _KERNELS = _kernels()
    return _KERNELS


def fill_halo(uh, faces=None):
    """Extrapolate the one-voxel halo of a deformation array linearly (``2 U[0] - U[1]``).

    With it, a border voxel's outer face centre is ``1.5 U[0] - 0.5 U[1]``.
    ``faces``: (axis, side) pairs to refresh (axis 0 = z of the array, side 0 =
    low end); default all six.
    """
    if faces is None:
        faces = [(a, side) for a in range(3) for side in (0, 1)]
    for axis, side in faces:
        n = uh.shape[axis] - 2

        def sl(i, axis=axis):
            idx = [slice(None)] * 4
            idx[axis] = i
            return tuple(idx)

        if n == 1:
            uh[sl(0 if side == 0 else 2)] = uh[sl(1)]
        elif side == 0:
            uh[sl(0)] = 2 * uh[sl(1)] - uh[sl(2)]
        else:
            uh[sl(n + 1)] = 2 * uh[sl(n)] - uh[sl(n - 1)]


def scatter(u, values, off, scale, lo, hi, sign, vmax, method, acc, split_z=None,
            origin=(0, 0, 0)):
    """Add (``sign`` +1) or remove (-1) the contributions of domain block [lo, hi) (x, y, z).

    ``u`` holds the deformation offsets with a one-voxel margin (see
    :func:`fill_halo`): domain voxel (e, f, g) is ``u[g - oz + 1, f - oy + 1,
    e - ox + 1]`` with ``origin = (ox, oy, oz)``; the margin and every
    neighbour of the block's voxels must be filled.
    ``split_z``: domain z indices ``(z1, z2)`` such that [lo, z1) and [z2, hi)
    are known to write disjoint target z ranges; those halves then run on two
    threads, and the band [z1, z2) after them (integer sums: the result does
    not depend on the split).
    Returns the touched target bounding box ``(lo_xyz, hi_xyz)`` (hi
    exclusive), or None when nothing landed in the target.
    """
    kern, _ = kernels()
    inv = 1.0 / vmax if vmax > 0 else 0.0
    off = np.asarray(off, np.float64)
    scale = np.asarray(scale, np.float64)
    lo = np.asarray(lo, np.int64)
    hi = np.asarray(hi, np.int64)
    box = method == "box"
    org = np.asarray(origin, np.int64)
    if split_z is None or not lo[2] < split_z[0] <= split_z[1] < hi[2]:
        bb = kern(u, org, values, off, scale, lo, hi, np.int64(sign), inv, box, acc)
    else:
        from concurrent.futures import ThreadPoolExecutor

        z1, z2 = split_z
        hi_a = hi.copy()
        hi_a[2] = z1
        lo_b = lo.copy()
        lo_b[2] = z2
        lo_m, hi_m = lo.copy(), hi.copy()
        lo_m[2], hi_m[2] = z1, z2
        with ThreadPoolExecutor(2) as pool:
            fa = pool.submit(kern, u, org, values, off, scale, lo, hi_a, np.int64(sign), inv, box,
                             acc)
            fb = pool.submit(kern, u, org, values, off, scale, lo_b, hi, np.int64(sign), inv, box,
                             acc)
            boxes = [fa.result(), fb.result()]
        if z2 > z1:
            boxes.append(kern(u, org, values, off, scale, lo_m, hi_m, np.int64(sign), inv, box,
                              acc))
        boxes = [b for b in boxes if b[3] >= 0]
        if not boxes:
            bb = np.full(6, -1, np.int64)
        else:
            bb = np.concatenate([np.min([b[:3] for b in boxes], axis=0),
                                 np.max([b[3:] for b in boxes], axis=0)])
    if bb[3] < 0:
        return None
    return bb[:3].copy(), bb[3:] + 1


def finalize(acc, vmax, lo, hi, out):
    """``out = v if w < 1 else v / w`` on the target block [lo, hi) (x, y, z).

    ``acc[z, y, x, 0]`` is the fixed-point weight, ``acc[..., 1]`` the weighted value.
    """
    from .basis import run_split

    _, kern = kernels()
    lo = np.asarray(lo, np.int64)
    hi = np.asarray(hi, np.int64)

    def args(z0, z1):
        a, b = lo.copy(), hi.copy()
        a[2], b[2] = z0, z1
        return acc, float(vmax), a, b, out

    run_split(kern, args, int(lo[2]), int(hi[2]), int(np.prod(hi - lo)))
    return out
