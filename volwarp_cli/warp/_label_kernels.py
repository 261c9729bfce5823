"""numba kernels of the one-pass label warp (see :mod:`.labels`).

Imported lazily: numba costs about 0.3 s to import and the kernels are cached on
disk (``cache=True``; ``NUMBA_CACHE_DIR`` when the package is read-only).

:func:`scatter_labels` pushes every domain voxel of a block forward once, as
the box (or nearest) pushforward of ``_warpkernels.c`` does, and adds each of
its fixed-point contributions to the target voxel's total weight and to the
weight of the voxel's own label there. Its numbers are that kernel's, operation
for operation: the same doubles in the target's coordinates (the C scatter's
box sides, spans, overlaps and Jacobian mass, its still regions' shortcut
with the same result), products in the same order, the same rounding to
2**-40 (the C build contracts no multiply-add, ``-ffp-contract=off``, and
numba none without ``fastmath``; a division by zero gives an infinity, as in
C, with ``error_model="numpy"``). So each contribution is the integer a
label's own pass of the C scatter adds, and integer sums do not depend on
their order: every label's weights, in one pass. (The constants ``MAGIC``,
``SHIFT`` and ``ISHIFT`` are those of ``_warpkernels.c``, which does not
export them.)

The per-label weights of a target voxel live in ``slots`` (label code, weight)
pairs beside it, and in a chain of blocks of as many pairs from a shared pool
when more labels reach it (a junction of many labels; a noisy map): nothing
is ever dropped. :func:`resolve_planes` reads finished planes: the winner of
each voxel (largest weight, ties to the smaller id, the background competing
with the weight the label passes gave it), each label's total and voxel of
largest weight, and clears the planes (and returns their chains to the pool)
for the ring's next turn.

Label codes: 0 is the background (its voxels add to the total weight only),
1..n the other labels in increasing id order, so comparing codes compares ids;
``below``: the codes under it are the labels whose ids lie below the
background's.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..bspline.pushforward import QUANTUM, ROUND

#: 1.5 * 2**52: x + MAGIC - MAGIC rounds x to the nearest integer, ties to even (the
#: C kernel's quantize2, exact for |x| < 2**51)
MAGIC = 6755399441055744.0
#: makes box sides positive so that truncation is floor (the C kernel's SHIFT)
SHIFT = 1048576.0
ISHIFT = 1048576
#: int64 weight of a full target voxel (2**40)
IQUANTUM = 1 << 40
_LOW = (1 << 32) - 1


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _min(a, b):
    return a if a < b else b  # (the C macro: b when equal, whatever the zeros' signs)


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _max(a, b):
    return a if a > b else b


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _quantize(x):
    return np.int64((x + MAGIC) - MAGIC)


@njit(cache=True, nogil=True, error_model="numpy")
def _chain_add(t, code, q, slots, head_next, pool, state):
    """Add ``q`` to label ``code`` of voxel ``t`` in its chain (its own slots are full).

    ``pool``: the chains' blocks, each ``(next, codes..., weights...)`` (``2 *
    slots + 1`` int64s); ``state``: (free list, blocks used, blocks ever
    taken, blocks free). A new block comes from the free list, else from the
    unused end: :func:`scatter_labels` makes sure before each row that the
    pool has room for all its row can take.
    """
    stride = 2 * slots + 1
    c = head_next[t]
    prev = -1
    while c >= 0:
        b = c * stride
        for s in range(slots):
            lab = pool[b + 1 + s]
            if lab == code:
                pool[b + 1 + slots + s] += q
                return
            if lab == 0:
                pool[b + 1 + s] = code
                pool[b + 1 + slots + s] = q
                return
        prev = c
        c = pool[b]
    if state[0] >= 0:
        blk = state[0]
        state[0] = pool[blk * stride]
        state[3] -= 1
    else:
        blk = state[1]
        state[1] += 1
    state[2] += 1
    b = blk * stride
    pool[b] = -1
    for s in range(slots):
        pool[b + 1 + s] = 0
    pool[b + 1] = code
    pool[b + 1 + slots] = q
    if prev < 0:
        head_next[t] = blk
    else:
        pool[prev * stride] = blk


@njit(cache=True, nogil=True, error_model="numpy")
def _row_boxes(n, e0, bx, by, bz, sx, sy, sz, xr, xym, xyp, xzm, xzp, yr, yym, yyp, yzm, yzp,
               zr, zym, zyp, zzm, zzp, xlo, xhi, ylo, yhi, zlo, zhi, mass):
    """The boxes and mass of a row of ``n`` voxels from ``e0`` (row_boxes of the C kernel).

    Per component (x, y, z): its offsets along the row with one voxel either
    side (``xr``: voxel i at ``xr[i + 1]``) and along the rows and planes
    before and after (``xym``, ``xyp``, ``xzm``, ``xzp``: voxel i at ``[i]``).
    A loop of no scattered stores: vectorised.
    """
    hx = 0.5 * sx
    hy = 0.5 * sy
    hz = 0.5 * sz
    for i in range(n):
        x_c = np.float64(xr[i + 1])
        x_xm = np.float64(xr[i])
        x_xp = np.float64(xr[i + 2])
        x_ym = np.float64(xym[i])
        x_yp = np.float64(xyp[i])
        x_zm = np.float64(xzm[i])
        x_zp = np.float64(xzp[i])
        y_c = np.float64(yr[i + 1])
        y_xm = np.float64(yr[i])
        y_xp = np.float64(yr[i + 2])
        y_ym = np.float64(yym[i])
        y_yp = np.float64(yyp[i])
        y_zm = np.float64(yzm[i])
        y_zp = np.float64(yzp[i])
        z_c = np.float64(zr[i + 1])
        z_xm = np.float64(zr[i])
        z_xp = np.float64(zr[i + 2])
        z_ym = np.float64(zym[i])
        z_yp = np.float64(zyp[i])
        z_zm = np.float64(zzm[i])
        z_zp = np.float64(zzp[i])
        base = bx + sx * np.float64(e0 + i)
        # BOX_SIDE: the faces across the component's own axis offset by the half
        # voxel, the four others only need the extreme neighbour
        a0 = 0.5 * (x_c + x_xm) - hx
        a1 = 0.5 * (x_c + x_xp) + hx
        n0 = _min(_min(x_ym, x_yp), _min(x_zm, x_zp))
        n1 = _max(_max(x_ym, x_yp), _max(x_zm, x_zp))
        x0 = _min(_min(a0, a1), 0.5 * (x_c + n0)) + base
        x1 = _max(_max(a0, a1), 0.5 * (x_c + n1)) + base
        a0 = 0.5 * (y_c + y_ym) - hy
        a1 = 0.5 * (y_c + y_yp) + hy
        n0 = _min(_min(y_xm, y_xp), _min(y_zm, y_zp))
        n1 = _max(_max(y_xm, y_xp), _max(y_zm, y_zp))
        y0 = _min(_min(a0, a1), 0.5 * (y_c + n0)) + by
        y1 = _max(_max(a0, a1), 0.5 * (y_c + n1)) + by
        a0 = 0.5 * (z_c + z_zm) - hz
        a1 = 0.5 * (z_c + z_zp) + hz
        n0 = _min(_min(z_xm, z_xp), _min(z_ym, z_yp))
        n1 = _max(_max(z_xm, z_xp), _max(z_ym, z_yp))
        z0 = _min(_min(a0, a1), 0.5 * (z_c + n0)) + bz
        z1 = _max(_max(a0, a1), 0.5 * (z_c + n1)) + bz
        dxx = sx + 0.5 * (x_xp - x_xm)
        dxy = 0.5 * (y_xp - y_xm)
        dxz = 0.5 * (z_xp - z_xm)
        dyx = 0.5 * (x_yp - x_ym)
        dyy = sy + 0.5 * (y_yp - y_ym)
        dyz = 0.5 * (z_yp - z_ym)
        dzx = 0.5 * (x_zp - x_zm)
        dzy = 0.5 * (y_zp - y_zm)
        dzz = sz + 0.5 * (z_zp - z_zm)
        det = (dxx * (dyy * dzz - dyz * dzy) - dxy * (dyx * dzz - dyz * dzx)
               + dxz * (dyx * dzy - dyy * dzx))
        # (a degenerate box gets inf or NaN here; its spans are empty)
        mass[i] = abs(det) / ((x1 - x0) * (y1 - y0) * (z1 - z0))
        xlo[i] = x0
        xhi[i] = x1
        ylo[i] = y0
        yhi[i] = y1
        zlo[i] = z0
        zhi[i] = z1


@njit(cache=True, nogil=True, error_model="numpy")
def _row_spans(n, lo, hi, first, last, v0, v1, a0, a1):
    """The target voxels ``[v0, v1]`` of box sides ``[lo, hi]`` within [first, last] (row_spans).

    ``a0``, ``a1``: the overlaps with the first and the last of them; a
    degenerate side (not hi > lo) gets ``v1 < v0``. Vectorised.
    """
    f2 = first - 2.0
    l2 = last + 2.0
    for i in range(n):
        lo_i = lo[i]
        hi_i = hi[i]
        c0 = _min(_max(lo_i, f2), l2)
        c1 = _min(_max(hi_i, f2), l2)
        p = _max(np.int64(c0 - 0.5 + SHIFT) - ISHIFT + 1, first)
        q = _min(ISHIFT - np.int64(SHIFT - c1 - 0.5) - 1, last)
        v0[i] = p
        v1[i] = q if hi_i > lo_i else p - 1
        a0[i] = _min(c1, p + 0.5) - _max(c0, p - 0.5)
        a1[i] = _min(c1, q + 0.5) - _max(c0, q - 0.5)


@njit(cache=True, nogil=True, error_model="numpy")
def _still_row(n, use, fast, xs_a, xs_b, trow, nrow, sq0, sq1, row_codes, xi, slots, wall,
               head_l, head_w, head_next, pool, state):
    """Add the contributions of a row's (``use``) still voxels of at most two target voxels along x.

    ``trow``: the ``nrow`` target rows they reach (ring indices less the
    window's first column); ``sq0``, ``sq1``: per row and column, the
    contributions to its first and second x voxel (:func:`scatter_labels`).
    """
    for i in range(n):
        a = xs_a[i]
        b = xs_b[i]
        if not use[i] or not fast[i] or b < a or b - a > 1:
            continue
        code = row_codes[xi[i]]
        for r in range(nrow):
            t = trow[r] + a
            q = sq0[r, i]
            wall[t] += q
            if code != 0 and q != 0 and not _head_add(t, code, q, slots, head_l, head_w):
                _chain_add(t, code, q, slots, head_next, pool, state)
            if b > a:
                q = sq1[r, i]
                wall[t + 1] += q
                if code != 0 and q != 0 and not _head_add(t + 1, code, q, slots, head_l,
                                                          head_w):
                    _chain_add(t + 1, code, q, slots, head_next, pool, state)


@njit(cache=True, nogil=True, error_model="numpy")
def scatter_labels(u, org, codes, code_org, k, lead, off, scale, block, box, inv_vmax, still,
                   gran, domain, clip, ring, win_lo, win_shape, wall, head_l, head_w, head_next,
                   pool, state, slots, need, tile, start):
    """Push the domain voxels ``block`` forward into the ring of target planes.

    ``u``: float32 ``[3, z, y, x]``, the deformation offsets with a one-voxel
    margin, domain voxel (e, f, g) at ``u[:, g - oz + 1, f - oy + 1, e - ox + 1]``,
    ``org = (ox, oy, oz)`` (as the C scatter's). ``codes``: int32 label codes,
    ``[z, y, x]``, of the input voxels from ``code_org`` (x y z) on; domain
    voxel (e, f, g) lies in input voxel ``((e, f, g) - lead) // k``. ``off``, ``scale``:
    the affine base map (x y z); ``block``: domain voxels ``(e0, e1, f0, f1, g0,
    g1)``; ``box``: the box pushforward (else nearest); ``inv_vmax``: the
    scene's; ``still``: uint8 ``[Rz, Ry, Rx]`` (the still regions, or an empty
    array), ``gran`` the lattice's granularity (x y z), ``domain`` its size (x y
    z); ``clip``: target voxels kept ``(x0, x1, y0, y1, z0, z1)``, at most ``ring`` planes.

    The ring: target plane z in slot ``z % ring``, ``win_lo = (y0, x0)`` and
    ``win_shape = (ny, nx)`` the rows and columns it holds; ``wall``: total
    weight ``[ring * ny * nx]``; ``head_l``, ``head_w``: ``slots`` (code,
    weight) pairs a voxel; ``head_next``: its chain (-1: none); ``pool``:
    the chains' blocks and ``state`` its bookkeeping (:func:`_chain_add`).

    ``need``: uint8, per tile of ``tile`` input voxels a side (z y x, from
    input voxel 0): whether its voxels are pushed at all; those of the other
    tiles can reach no target voxel where a label lands (:func:`.labels.needed_tiles`).

    Rows in y order, each through the block's planes, from ``start`` ``(f, g)``
    on. Returns ``(-1, -1)`` when done, or the row ``(f, g)`` it stopped
    before, untouched, when the pool might not hold all that row can chain:
    grow the pool (a larger copy) and call again from there.
    """
    ox, oy, oz = org
    cx, cy, cz = code_org
    lead_x, lead_y, lead_z = lead
    bx, by_, bz_ = off
    sx, sy, sz = scale
    e0, e1, f0, f1, g0, g1 = block
    gx, gy, gz = gran
    dvx, dvy, dvz = domain
    tx0, tx1, ty0, ty1, tz0, tz1 = clip
    wy0, wx0 = win_lo
    ny, nx = win_shape
    hx = 0.5 * sx
    hy = 0.5 * sy
    hz = 0.5 * sz
    n = e1 - e0
    has_still = box and still.size > 0
    det_still = sx * (sy * sz)
    same = inv_vmax == 1.0  # (kq * inv_vmax is then kq: one rounding a contribution)
    # plane z in slot z % ring, found without a division: the clip's planes are fewer than
    # the ring's, so z - ring_base lies in [0, 2 ring)
    ring_base = tz0 - tz0 % ring
    q_one = _quantize(QUANTUM * 1.0)  # (nearest: weight 1)
    q_one_v = _quantize((QUANTUM * inv_vmax) * 1.0)
    # per column: the input column, the x regions of its neighbours, and the still
    # voxels' x sides (base -/+ half a voxel), spans and overlaps, found once
    xi = np.empty(n, np.int64)
    fast_a = np.empty(n, np.int64)
    fast_b = np.empty(n, np.int64)
    xs_lo = np.empty(n, np.float64)
    xs_hi = np.empty(n, np.float64)
    xt = np.empty(n, np.int64)
    use = np.zeros(n, np.uint8)
    for i in range(n):
        e = e0 + i
        xi[i] = (e - lead_x) // k - cx
        xt[i] = (xi[i] + cx) // tile
        fast_a[i] = _max(e - 1, 0) // gx
        fast_b[i] = _min(e + 1, dvx - 1) // gx
        base = bx + sx * np.float64(e)
        xs_lo[i] = -hx + base
        xs_hi[i] = hx + base
    xs_a = np.empty(n, np.int64)
    xs_b = np.empty(n, np.int64)
    xs_w0 = np.empty(n, np.float64)
    xs_w1 = np.empty(n, np.float64)
    _row_spans(n, xs_lo, xs_hi, tx0, tx1 - 1, xs_a, xs_b, xs_w0, xs_w1)
    # a row's general voxels: boxes and mass (phase 1), spans and overlaps
    lo = np.empty((3, n), np.float64)
    hi = np.empty((3, n), np.float64)
    mass = np.empty(n, np.float64)
    sa = np.empty((3, n), np.int64)
    sb = np.empty((3, n), np.int64)
    w0 = np.empty((3, n), np.float64)
    w1 = np.empty((3, n), np.float64)
    fast = np.zeros(n, np.uint8)
    rx = still.shape[2] if has_still else 0
    reg = np.zeros(max(rx, 1), np.uint8)
    known = np.full(4, -1, np.int64)
    nfast = 0
    ys_span = np.empty(2, np.int64)
    ys_w = np.empty(2, np.float64)
    one_lo = np.empty(1, np.float64)
    one_hi = np.empty(1, np.float64)
    # a still row's contributions (splat_narrow's, at most 2 x 2 target rows): the target
    # rows, their weights, and per column each row's quantised contributions to its first
    # and second x voxel, kept while the rows' weights stay the same (their numbers are
    # then the same: with an exact oversample, for every row of a still region)
    trow = np.zeros(4, np.int64)
    wrow = np.zeros(4, np.float64)
    known_w = np.full(6, np.nan)
    sq0 = np.zeros((4, n), np.int64)
    sq1 = np.zeros((4, n), np.int64)
    blocks = pool.shape[0] // (2 * slots + 1)
    # per plane: the still voxels' z sides, span and overlaps
    nzp = g1 - g0
    zs_lo = np.empty(nzp, np.float64)
    zs_hi = np.empty(nzp, np.float64)
    for g in range(g0, g1):
        bz = bz_ + sz * g
        zs_lo[g - g0] = -hz + bz
        zs_hi[g - g0] = hz + bz
    zs_a = np.empty(nzp, np.int64)
    zs_b = np.empty(nzp, np.int64)
    zs_w0 = np.empty(nzp, np.float64)
    zs_w1 = np.empty(nzp, np.float64)
    _row_spans(nzp, zs_lo, zs_hi, tz0, tz1 - 1, zs_a, zs_b, zs_w0, zs_w1)
    # rows in y order, then planes: the rows of one y reach the same few target rows,
    # which stay in the cache while those of the next y (the oversample's) reach them too
    for f in range(start[0], f1):
        by = by_ + sy * f
        yi = (f - lead_y) // k - cy
        fu = f - oy + 1
        # the still voxels' y span
        ys_lo = -hy + by
        ys_hi = hy + by
        one_lo[0] = ys_lo
        one_hi[0] = ys_hi
        _row_spans(1, one_lo, one_hi, ty0, ty1 - 1, ys_span[0:1], ys_span[1:2], ys_w[0:1],
                   ys_w[1:2])
        for g in range(start[1] if f == start[0] else g0, g1):
            bz = bz_ + sz * g
            zi = (g - lead_z) // k - cz
            gu = g - oz + 1
            p_ = g - g0
            row_need = need[(zi + cz) // tile, (yi + cy) // tile]
            nuse = 0
            for i in range(n):
                use[i] = row_need[xt[i]]
                nuse += use[i]
            if nuse == 0:
                continue  # (no voxel of the row can reach where a label lands)
            row_codes = codes[zi, yi]
            if has_still:  # the voxels whose 3x3x3 neighbourhoods' regions are all still
                c0 = _max(g - 1, 0) // gz
                c1 = _min(g + 1, dvz - 1) // gz
                b0 = _max(f - 1, 0) // gy
                b1 = _min(f + 1, dvy - 1) // gy
                if c0 != known[0] or c1 != known[1] or b0 != known[2] or b1 != known[3]:
                    for a in range(rx):
                        allv = 1
                        for c in range(c0, c1 + 1):
                            for b in range(b0, b1 + 1):
                                allv &= still[c, b, a]
                        reg[a] = allv
                    nfast = 0
                    for i in range(n):
                        fast[i] = reg[fast_a[i]] & reg[fast_b[i]]
                        nfast += fast[i]
                    known[0] = c0
                    known[1] = c1
                    known[2] = b0
                    known[3] = b1
            if not box:  # nearest: map and round (ties down), weight 1
                if n > blocks - state[1] + state[3]:
                    return f, g  # (the pool might fill: grown, then from this row)
                for i in range(n):
                    if not use[i]:
                        continue
                    e = e0 + i
                    eu = e - ox + 1
                    x = (bx + sx * np.float64(e)) + np.float64(u[0, gu, fu, eu]) + ROUND
                    y = (by + np.float64(u[1, gu, fu, eu])) + ROUND
                    z = (bz + np.float64(u[2, gu, fu, eu])) + ROUND
                    ix = np.int64(x)
                    ix -= x < np.float64(ix)
                    iy = np.int64(y)
                    iy -= y < np.float64(iy)
                    iz = np.int64(z)
                    iz -= z < np.float64(iz)
                    if ix < tx0 or iy < ty0 or iz < tz0 or ix >= tx1 or iy >= ty1 or iz >= tz1:
                        continue
                    slot_z = iz - ring_base
                    if slot_z >= ring:
                        slot_z -= ring
                    t = (slot_z * ny + (iy - wy0)) * nx + (ix - wx0)
                    code = row_codes[xi[i]]
                    wall[t] += q_one
                    if code != 0 and q_one_v != 0 and not _head_add(t, code, q_one_v, slots,
                                                                   head_l, head_w):
                        _chain_add(t, code, q_one_v, slots, head_next, pool, state)
                continue
            yzw = (ys_hi - ys_lo, zs_hi[p_] - zs_lo[p_])
            nrow = 0
            if (nfast and same and ys_span[1] >= ys_span[0] and zs_b[p_] >= zs_a[p_]
                    and ys_span[1] - ys_span[0] <= 1 and zs_b[p_] - zs_a[p_] <= 1):
                for dz in range(zs_b[p_] - zs_a[p_] + 1):
                    slot_z = zs_a[p_] + dz - ring_base
                    if slot_z >= ring:
                        slot_z -= ring
                    for dy in range(ys_span[1] - ys_span[0] + 1):
                        trow[nrow] = (slot_z * ny + ys_span[0] + dy - wy0) * nx - wx0
                        wrow[nrow] = (zs_w1[p_] if dz else zs_w0[p_]) * (
                            ys_w[1] if dy else ys_w[0])
                        nrow += 1
                changed = nrow != known_w[4] or yzw[0] * yzw[1] != known_w[5]
                for r in range(nrow):
                    changed |= wrow[r] != known_w[r]
                if changed:
                    for i in range(n):
                        kq = QUANTUM * (det_still / ((xs_hi[i] - xs_lo[i]) * yzw[0] * yzw[1]))
                        for r in range(nrow):
                            sq0[r, i] = _quantize(kq * (wrow[r] * xs_w0[i]))
                            sq1[r, i] = _quantize(kq * (wrow[r] * xs_w1[i]))
                    for r in range(nrow):
                        known_w[r] = wrow[r]
                    known_w[4] = nrow
                    known_w[5] = yzw[0] * yzw[1]
            # phase 1: the general voxels' boxes (of each run of the row's voxels in needed
            # tiles, those between its first and last general one)
            i = 0
            while i < n:
                if not use[i]:
                    i += 1
                    continue
                i0 = i
                while i < n and use[i]:
                    i += 1
                i1 = i
                if nfast:
                    while i0 < i1 and fast[i0]:
                        i0 += 1
                    while i1 > i0 and fast[i1 - 1]:
                        i1 -= 1
                if i1 <= i0:
                    continue
                m = i1 - i0
                p = e0 + i0 - ox + 1  # (u's column of voxel i0)
                _row_boxes(m, e0 + i0, bx, by, bz, sx, sy, sz,
                           u[0, gu, fu, p - 1:p + m + 1], u[0, gu, fu - 1, p:p + m],
                           u[0, gu, fu + 1, p:p + m], u[0, gu - 1, fu, p:p + m],
                           u[0, gu + 1, fu, p:p + m],
                           u[1, gu, fu, p - 1:p + m + 1], u[1, gu, fu - 1, p:p + m],
                           u[1, gu, fu + 1, p:p + m], u[1, gu - 1, fu, p:p + m],
                           u[1, gu + 1, fu, p:p + m],
                           u[2, gu, fu, p - 1:p + m + 1], u[2, gu, fu - 1, p:p + m],
                           u[2, gu, fu + 1, p:p + m], u[2, gu - 1, fu, p:p + m],
                           u[2, gu + 1, fu, p:p + m],
                           lo[0, i0:i1], hi[0, i0:i1], lo[1, i0:i1], hi[1, i0:i1],
                           lo[2, i0:i1], hi[2, i0:i1], mass[i0:i1])
                for c, first, last in ((0, tx0, tx1 - 1), (1, ty0, ty1 - 1), (2, tz0, tz1 - 1)):
                    _row_spans(m, lo[c, i0:i1], hi[c, i0:i1], first, last, sa[c, i0:i1],
                               sb[c, i0:i1], w0[c, i0:i1], w1[c, i0:i1])
            # room in the pool for a new block per contribution of a label
            room = 0
            for i in range(n):
                if not use[i] or row_codes[xi[i]] == 0:
                    continue
                if nfast and fast[i]:
                    nx_ = xs_b[i] - xs_a[i] + 1
                    ny_ = ys_span[1] - ys_span[0] + 1
                    nz_ = zs_b[p_] - zs_a[p_] + 1
                else:
                    nx_ = sb[0, i] - sa[0, i] + 1
                    ny_ = sb[1, i] - sa[1, i] + 1
                    nz_ = sb[2, i] - sa[2, i] + 1
                room += _max(nx_, 0) * _max(ny_, 0) * _max(nz_, 0)
            if room > blocks - state[1] + state[3]:
                return f, g  # (the pool might fill: grown, then from this row)
            # phase 2: the overlaps with the target voxels, accumulated (narrow spans, of at
            # most two voxels, take the overlaps found above; wider ones compute them from
            # the box's sides: the same numbers)
            if nrow:  # the still voxels in the common case: their contributions found above
                _still_row(n, use, fast, xs_a, xs_b, trow, nrow, sq0, sq1, row_codes, xi,
                           slots, wall, head_l, head_w, head_next, pool, state)
            for i in range(n):
                if not use[i] or (nrow and fast[i] and xs_b[i] - xs_a[i] <= 1
                                  and xs_b[i] >= xs_a[i]):
                    continue  # (not needed, or done)
                if nfast and fast[i]:  # a still voxel: its box the affine image (no u read)
                    xa = xs_a[i]
                    xb = xs_b[i]
                    ya = ys_span[0]
                    yb = ys_span[1]
                    za = zs_a[p_]
                    zb = zs_b[p_]
                    if xb < xa or yb < ya or zb < za:
                        continue
                    ax0 = xs_w0[i]
                    ax1 = xs_w1[i]
                    ay0 = ys_w[0]
                    ay1 = ys_w[1]
                    az0 = zs_w0[p_]
                    az1 = zs_w1[p_]
                    kq = QUANTUM * (det_still / ((xs_hi[i] - xs_lo[i]) * yzw[0] * yzw[1]))
                else:
                    xa = sa[0, i]
                    xb = sb[0, i]
                    ya = sa[1, i]
                    yb = sb[1, i]
                    za = sa[2, i]
                    zb = sb[2, i]
                    if xb < xa or yb < ya or zb < za:
                        continue
                    ax0 = w0[0, i]
                    ax1 = w1[0, i]
                    ay0 = w0[1, i]
                    ay1 = w1[1, i]
                    az0 = w0[2, i]
                    az1 = w1[2, i]
                    kq = QUANTUM * mass[i]
                code = row_codes[xi[i]]
                kqv = kq * inv_vmax
                if zb - za <= 1 and yb - ya <= 1 and xb - xa <= 1:
                    # the common case (splat_narrow): at most two voxels along each axis
                    two_x = xb > xa
                    for dz in range(zb - za + 1):
                        wz = az1 if dz else az0
                        slot_z = za + dz - ring_base
                        if slot_z >= ring:
                            slot_z -= ring
                        for dy in range(yb - ya + 1):
                            wzy = wz * (ay1 if dy else ay0)
                            t = (slot_z * ny + ya + dy - wy0) * nx + xa - wx0
                            w = wzy * ax0
                            q0 = _quantize(kq * w)
                            wall[t] += q0
                            if two_x:
                                w_b = wzy * ax1
                                q0_b = _quantize(kq * w_b)
                                wall[t + 1] += q0_b
                            if code == 0:
                                continue
                            q1 = q0 if same else _quantize(kqv * w)
                            if q1 != 0 and not _head_add(t, code, q1, slots, head_l, head_w):
                                _chain_add(t, code, q1, slots, head_next, pool, state)
                            if two_x:
                                q1 = q0_b if same else _quantize(kqv * w_b)
                                if q1 != 0 and not _head_add(t + 1, code, q1, slots, head_l,
                                                             head_w):
                                    _chain_add(t + 1, code, q1, slots, head_next, pool, state)
                    continue
                # a wide box (splat): overlaps as they go, from the box's sides
                if nfast and fast[i]:
                    xlo = xs_lo[i]
                    xhi = xs_hi[i]
                    ylo = ys_lo
                    yhi = ys_hi
                    zlo = zs_lo[p_]
                    zhi = zs_hi[p_]
                else:
                    xlo = lo[0, i]
                    xhi = hi[0, i]
                    ylo = lo[1, i]
                    yhi = hi[1, i]
                    zlo = lo[2, i]
                    zhi = hi[2, i]
                for tz in range(za, zb + 1):
                    wz = _min(zhi, tz + 0.5) - _max(zlo, tz - 0.5)
                    slot_z = tz - ring_base
                    if slot_z >= ring:
                        slot_z -= ring
                    for ty in range(ya, yb + 1):
                        wzy = wz * (_min(yhi, ty + 0.5) - _max(ylo, ty - 0.5))
                        row = (slot_z * ny + ty - wy0) * nx - wx0
                        for tx in range(xa, xb + 1):
                            w = wzy * (_min(xhi, tx + 0.5) - _max(xlo, tx - 0.5))
                            q0 = _quantize(kq * w)
                            t = row + tx
                            wall[t] += q0
                            if code == 0:
                                continue
                            q1 = q0 if same else _quantize(kqv * w)
                            if q1 != 0 and not _head_add(t, code, q1, slots, head_l, head_w):
                                _chain_add(t, code, q1, slots, head_next, pool, state)
    return -1, -1


@njit(cache=True, nogil=True, inline="always", error_model="numpy")
def _head_add(t, code, q, slots, head_l, head_w):
    """Add ``q`` to label ``code`` among voxel ``t``'s own slots; False when they are full."""
    b = t * slots
    for s in range(slots):
        lab = head_l[b + s]
        if lab == code:
            head_w[b + s] += q
            return True
        if lab == 0:
            head_l[b + s] = code
            head_w[b + s] = q
            return True
    return False


@njit(cache=True, nogil=True, error_model="numpy")
def resolve_planes(z0, z1, ring, win_lo, win_shape, wall, head_l, head_w, head_next, pool,
                   state, slots, below, out, counts, total_hi, total_lo,
                   peak_w, peak_at):
    """Finish target planes ``[z0, z1)`` of the ring (``z1 - z0 <= ring``) and clear them.

    ``out[z - z0, y, x]``: the winning code of each voxel of the ring's rows and
    columns (``win_lo``, ``win_shape``); ``counts[code]``: voxels won; per
    label code, ``total_hi``/``total_lo``: its total weight in these planes,
    in two parts (``hi * 2**32 + lo``, exact for targets below 2**31 voxels);
    ``peak_w``/``peak_at``: its largest weight and the first voxel (z, y, x,
    in target indices) with it, updated. The background's weight is the label
    passes': ``max(w, 1) - w_fg`` (``w`` the voxel's total weight, ``w_fg`` its
    labels'). Ties go to the smaller id.
    """
    wy0, wx0 = win_lo
    ny, nx = win_shape
    stride = 2 * slots + 1
    for z in range(z0, z1):
        slot_z = z % ring
        for y in range(ny):
            row = (slot_z * ny + y) * nx
            for x in range(nx):
                t = row + x
                w_all = wall[t]
                wall[t] = 0
                w_fg = 0
                best_w = np.int64(-1)
                best = 0
                b = t * slots
                for s in range(slots):
                    c = head_l[b + s]
                    if c == 0:
                        break
                    head_l[b + s] = 0
                    w = head_w[b + s]
                    w_fg += w
                    total_lo[c] += w & _LOW
                    total_hi[c] += w >> 32
                    if w > peak_w[c]:
                        peak_w[c] = w
                        peak_at[c, 0] = z
                        peak_at[c, 1] = y + wy0
                        peak_at[c, 2] = x + wx0
                    if w > best_w or (w == best_w and c < best):
                        best_w = w
                        best = c
                blk = head_next[t]
                head_next[t] = -1
                while blk >= 0:
                    b = blk * stride
                    for s in range(slots):
                        c = pool[b + 1 + s]
                        if c == 0:
                            break
                        w = pool[b + 1 + slots + s]
                        w_fg += w
                        total_lo[c] += w & _LOW
                        total_hi[c] += w >> 32
                        if w > peak_w[c]:
                            peak_w[c] = w
                            peak_at[c, 0] = z
                            peak_at[c, 1] = y + wy0
                            peak_at[c, 2] = x + wx0
                        if w > best_w or (w == best_w and c < best):
                            best_w = w
                            best = c
                    nxt = pool[b]
                    pool[b] = state[0]  # (back to the free list)
                    state[0] = blk
                    state[3] += 1
                    blk = nxt
                w_b = _max(w_all, IQUANTUM) - w_fg
                if best != 0 and not (best_w > w_b or (best_w == w_b and best < below)):
                    best = 0
                out[z - z0, y, x] = best
                counts[best] += 1

