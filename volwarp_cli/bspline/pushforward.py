"""Pushforward of the domain density into the target (paper §5–§6, thesis §5.4).

Each domain voxel ``(e, f, g)`` is sent to ``T = A(e, f, g) + U[g, f, e]``
(affine base map plus the deformation offsets, target voxel indices), then:

- ``nearest``: map and round (the papers' Figure 4/6 baseline): weight 1 to
  the target voxel holding ``T`` (ties round down, see ``ROUND``).
- ``box``: the papers' antialiasing: the six face centres are averages of
  neighbouring entries of the deformation array (paper §6), their bounding
  box stands in for the transformed voxel, and its overlap volume with each
  target voxel (as a fraction of the target voxel) is the weight.

Weights and weighted values are accumulated per target voxel; the papers'
result is ``v`` where the total weight is below 1 and ``v / w`` otherwise
(paper §6): a voxel partly covered by the model keeps the partial sum, i.e.
is blended with the (zero) space around it.

Departures:

- The accumulators are int64 fixed point (weights and normalised weighted
  values in units of 2**-40), so adding and later *subtracting* a region's
  contribution is exact: the incremental updates of :mod:`.scene` equal a
  full recomputation bit for bit, instead of the papers' "write zeros".
- The box's overlaps are scaled by (Jacobian volume of the voxel's image) /
  (box volume). The papers' proxy box of a voxel rotated by theta covers only
  about cos^2(theta) of it (2-D), so rotated parts of a model came out that
  much darker (about 30% at 33 degrees) under "v where w < 1"; with the
  scale every voxel carries its true volume and the inside of a rotated
  region sums to w = 1 on average. Axis-aligned stretches, and shears of
  less than one voxel per voxel, are unchanged.
- Per target voxel, box weights still scatter around 1 inside a rotated or
  strongly deformed region (down to about 0.83 at 45 degrees, oversample 1),
  and the papers' "v where w < 1" darkened those voxels (or, with a non-zero
  ``background``, pulled them towards it). volwarp normalises (``v / w``)
  wherever ``w >= COVERED_HI`` and blends with the background (``v + b (1 -
  w)``) only where ``w <= COVERED_LO``, the model's silhouette, with a linear
  ramp between.
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

#: Weights from which a target voxel counts as inside the model (normalised)
#: and up to which it counts as on its silhouette (blended with the background).
COVERED_HI = 0.8
COVERED_LO = 0.6

#: Fixed-point unit of the accumulators (2**40 per unit weight).
QUANTUM = float(2 ** 40)
METHODS = ("box", "nearest")


def _kernels():
    from numba import njit

    @njit(cache=True, nogil=True)
    def scatter(uha, uhb, npass, org, values, off, scale, lo, hi, sign, inv_vmax, box, acc,
                tzo):  # pragma: no cover - jit
        # uha (and uhb) hold deformation offsets around the block, with a one-voxel
        # margin: domain voxel (g, f, e) is uh[g - oz + 1, f - oy + 1, e - ox + 1].
        # Pass 0 adds sign * uha's contributions; with npass 2, pass 1 adds
        # -sign * uhb's, voxel by voxel (an update: old and new boxes hit the
        # same, cache-hot, target voxels).
        # acc holds target z planes [tzo, tzo + nz): target voxel z is acc[z - tzo].
        nz, ty, tx, _ = acc.shape
        tz0 = tzo
        tz1 = tzo + nz
        q = 1099511627776.0  # 2**40
        iq = np.int64(1) << 40
        bx0 = by0 = bz0 = np.int64(1) << 40
        bx1 = by1 = bz1 = np.int64(-1)
        nmax = max(tx, max(ty, nz)) + 2
        ovx = np.empty(nmax)
        ovy = np.empty(nmax)
        ovz = np.empty(nmax)
        # scalars in locals: the stores into acc could alias the small arrays,
        # which would make the compiler reload them in the inner loop
        sx = scale[0]
        sy = scale[1]
        sz = scale[2]
        fx = off[0]
        fy = off[1]
        fz = off[2]
        ex = 1 - org[0]
        ey = 1 - org[1]
        ez = 1 - org[2]
        e0 = lo[0]
        e1 = hi[0]
        f0 = lo[1]
        f1 = hi[1]
        g0 = lo[2]
        g1 = hi[2]
        hx = 0.5 * sx
        hy = 0.5 * sy
        hz = 0.5 * sz
        for g in range(g0, g1):
            bz = fz + sz * g
            for f in range(f0, f1):
                by = fy + sy * f
                for e in range(e0, e1):
                    bxx = fx + sx * e
                    val = values[g, f, e] * inv_vmax
                    G = g + ez
                    F = f + ey
                    E = e + ex
                    for p in range(npass):
                        uh = uha if p == 0 else uhb
                        sgn = sign if p == 0 else -sign
                        ux = uh[G, F, E, 0]
                        uy = uh[G, F, E, 1]
                        uz = uh[G, F, E, 2]
                        if not box:
                            x = np.int64(np.floor(bxx + ux + ROUND))
                            y = np.int64(np.floor(by + uy + ROUND))
                            z = np.int64(np.floor(bz + uz + ROUND))
                            if x < 0 or y < 0 or z < tz0 or x >= tx or y >= ty or z >= tz1:
                                continue
                            acc[z - tzo, y, x, 0] += sgn * iq
                            acc[z - tzo, y, x, 1] += sgn * np.int64(np.floor(val * q + 0.5))
                            bx0 = min(bx0, x)
                            by0 = min(by0, y)
                            bz0 = min(bz0, z)
                            bx1 = max(bx1, x)
                            by1 = max(by1, y)
                            bz1 = max(bz1, z)
                            continue
                        # six face centres: averages with the neighbours' entries (paper 6).
                        # Per component, the two faces across its own axis are offset by
                        # the half voxel; the four others only need the extreme neighbour
                        # (rounding is monotone: min(fl(u + a), fl(u + b)) = fl(u + min(a, b)))
                        n0 = min(min(uh[G, F - 1, E, 0], uh[G, F + 1, E, 0]),
                                 min(uh[G - 1, F, E, 0], uh[G + 1, F, E, 0]))
                        n1 = max(max(uh[G, F - 1, E, 0], uh[G, F + 1, E, 0]),
                                 max(uh[G - 1, F, E, 0], uh[G + 1, F, E, 0]))
                        a0 = 0.5 * (ux + uh[G, F, E - 1, 0]) - hx
                        a1 = 0.5 * (ux + uh[G, F, E + 1, 0]) + hx
                        xmin = min(min(a0, a1), 0.5 * (ux + n0))
                        xmax = max(max(a0, a1), 0.5 * (ux + n1))
                        n0 = min(min(uh[G, F, E - 1, 1], uh[G, F, E + 1, 1]),
                                 min(uh[G - 1, F, E, 1], uh[G + 1, F, E, 1]))
                        n1 = max(max(uh[G, F, E - 1, 1], uh[G, F, E + 1, 1]),
                                 max(uh[G - 1, F, E, 1], uh[G + 1, F, E, 1]))
                        a0 = 0.5 * (uy + uh[G, F - 1, E, 1]) - hy
                        a1 = 0.5 * (uy + uh[G, F + 1, E, 1]) + hy
                        ymin = min(min(a0, a1), 0.5 * (uy + n0))
                        ymax = max(max(a0, a1), 0.5 * (uy + n1))
                        n0 = min(min(uh[G, F, E - 1, 2], uh[G, F, E + 1, 2]),
                                 min(uh[G, F - 1, E, 2], uh[G, F + 1, E, 2]))
                        n1 = max(max(uh[G, F, E - 1, 2], uh[G, F, E + 1, 2]),
                                 max(uh[G, F - 1, E, 2], uh[G, F + 1, E, 2]))
                        a0 = 0.5 * (uz + uh[G - 1, F, E, 2]) - hz
                        a1 = 0.5 * (uz + uh[G + 1, F, E, 2]) + hz
                        zmin = min(min(a0, a1), 0.5 * (uz + n0))
                        zmax = max(max(a0, a1), 0.5 * (uz + n1))
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
                        z0 = max(np.int64(zmin - 0.5 + SHIFT) - ISHIFT + 1, tz0)
                        z1 = min(ISHIFT - np.int64(SHIFT - zmax - 0.5) - 1, tz1 - 1)
                        if x1 < x0 or y1 < y0 or z1 < z0:
                            continue
                        # Mass: the box stands for the voxel's image, whose volume is
                        # the Jacobian |det| of the face-centre differences. Scaling the
                        # overlaps by |det| / box volume gives each voxel its true
                        # volume, so a rotated region is covered once (w = 1) instead
                        # of cos^2 of it (the papers' proxy alone); an axis-aligned
                        # stretch or shear has |det| = box volume and is unchanged.
                        dxx = sx + 0.5 * (uh[G, F, E + 1, 0] - uh[G, F, E - 1, 0])
                        dxy = 0.5 * (uh[G, F, E + 1, 1] - uh[G, F, E - 1, 1])
                        dxz = 0.5 * (uh[G, F, E + 1, 2] - uh[G, F, E - 1, 2])
                        dyx = 0.5 * (uh[G, F + 1, E, 0] - uh[G, F - 1, E, 0])
                        dyy = sy + 0.5 * (uh[G, F + 1, E, 1] - uh[G, F - 1, E, 1])
                        dyz = 0.5 * (uh[G, F + 1, E, 2] - uh[G, F - 1, E, 2])
                        dzx = 0.5 * (uh[G + 1, F, E, 0] - uh[G - 1, F, E, 0])
                        dzy = 0.5 * (uh[G + 1, F, E, 1] - uh[G - 1, F, E, 1])
                        dzz = sz + 0.5 * (uh[G + 1, F, E, 2] - uh[G - 1, F, E, 2])
                        jac = abs(dxx * (dyy * dzz - dyz * dzy) - dxy * (dyx * dzz - dyz * dzx)
                                  + dxz * (dyx * dzy - dyy * dzx))
                        kq = q * (jac / ((xmax - xmin) * (ymax - ymin) * (zmax - zmin)))
                        wq = val * kq
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
                                        acc[z0 + dz - tzo, y0 + dy, x0 + dx, 0] += sgn * np.int64(
                                            w * kq + 0.5)
                                        acc[z0 + dz - tzo, y0 + dy, x0 + dx, 1] += sgn * np.int64(
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
                                        acc[z - tzo, y, x, 0] += sgn * np.int64(w * kq + 0.5)
                                        acc[z - tzo, y, x, 1] += sgn * np.int64(np.floor(w * wq + 0.5))
                        bx0 = min(bx0, x0)
                        by0 = min(by0, y0)
                        bz0 = min(bz0, z0)
                        bx1 = max(bx1, x1)
                        by1 = max(by1, y1)
                        bz1 = max(bz1, z1)
        return np.array([bx0, by0, bz0, bx1, by1, bz1], dtype=np.int64)

    @njit(cache=True, nogil=True)
    def finalize(acc, vmax, lo, hi, out, background):  # pragma: no cover - jit
        inv_q = 1.0 / 1099511627776.0
        for z in range(lo[2], hi[2]):
            for y in range(lo[1], hi[1]):
                for x in range(lo[0], hi[0]):
                    w = acc[z, y, x, 0] * inv_q
                    v = acc[z, y, x, 1] * inv_q * vmax
                    if w >= COVERED_HI:
                        out[z, y, x] = v / w
                    elif w <= COVERED_LO:
                        out[z, y, x] = v + background * (1.0 - w)
                    else:  # a continuous ramp between the two
                        t = (w - COVERED_LO) / (COVERED_HI - COVERED_LO)
                        out[z, y, x] = t * (v / w) + (1.0 - t) * (v + background * (1.0 - w))

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
            origin=(0, 0, 0), tzo=0, u_new=None):
    """Add (``sign`` +1) or remove (-1) the contributions of domain block [lo, hi) (x, y, z).

    With ``u_new`` (deformation offsets of another lattice, same layout as
    ``u``) the block's ``u_new`` contributions are added with ``-sign`` in the
    same pass: ``sign`` -1 replaces the old map's contributions by the new one's.

    ``u`` holds the deformation offsets with a one-voxel margin (see
    :func:`fill_halo`): domain voxel (e, f, g) is ``u[g - oz + 1, f - oy + 1,
    e - ox + 1]`` with ``origin = (ox, oy, oz)``; the margin and every
    neighbour of the block's voxels must be filled.
    ``acc`` holds the target z planes ``[tzo, tzo + len(acc))``; contributions
    to other planes are left out.
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

    def run(a, b):
        return kern(u, u if u_new is None else u_new, 1 if u_new is None else 2, org, values,
                    off, scale, a, b, np.int64(sign), inv, box, acc, np.int64(tzo))

    if split_z is None or not lo[2] < split_z[0] <= split_z[1] < hi[2]:
        boxes = [run(lo, hi)]
    else:
        from concurrent.futures import ThreadPoolExecutor

        z1, z2 = split_z
        hi_a, lo_b = hi.copy(), lo.copy()
        hi_a[2], lo_b[2] = z1, z2
        with ThreadPoolExecutor(2) as pool:
            fa = pool.submit(run, lo, hi_a)
            fb = pool.submit(run, lo_b, hi)
            boxes = [fa.result(), fb.result()]
        if z2 > z1:
            lo_m, hi_m = lo.copy(), hi.copy()
            lo_m[2], hi_m[2] = z1, z2
            boxes.append(run(lo_m, hi_m))
    boxes = [b for b in boxes if b[3] >= 0]
    if not boxes:
        return None
    return (np.min([b[:3] for b in boxes], axis=0),
            np.max([b[3:] for b in boxes], axis=0) + 1)


def finalize(acc, vmax, lo, hi, out, parallel=True, background=0.0):
    """``out = v / w`` inside the model, ``v + b (1 - w)`` on its silhouette, on [lo, hi).

    (x, y, z) block; see the module notes for the two weight levels.

    ``acc[z, y, x, 0]`` is the fixed-point weight, ``acc[..., 1]`` the weighted value;
    ``parallel`` lets large blocks use two threads. ``background`` ``b`` is the
    value of the space around the model (the papers': 0): a partly covered
    voxel is blended with it and an uncovered one gets it, exactly what
    pushing ``data - b`` and adding ``b`` would give.
    """
    from .basis import run_split

    _, kern = kernels()
    lo = np.asarray(lo, np.int64)
    hi = np.asarray(hi, np.int64)

    def args(z0, z1):
        a, b = lo.copy(), hi.copy()
        a[2], b[2] = z0, z1
        return acc, float(vmax), a, b, out, float(background)

    run_split(kern, args, int(lo[2]), int(hi[2]), int(np.prod(hi - lo)) if parallel else 0)
    return out
