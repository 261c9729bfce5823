"""Signed distance of a smooth (non-binary) volume's iso-surface, to sub-voxel accuracy.

A binary shape only tells on which side of the surface each voxel centre
lies, so its exact field (:mod:`.exact`) is stair-cased by half a voxel. A
smooth input (a scan, a blurred mask, a sampled implicit function) also tells
*where* the surface crosses between two samples. This module uses that:

1. **Crossings.** Along every grid line the surface is where the samples, taken
   as linear between neighbours, cross the iso level ``V``. A voxel with a
   crossing on its way to a neighbour is a *seed*. Per axis, keep the nearest
   crossing, at world distance ``a_x`` (``a_y``, ``a_z``) and on side ``s``.
2. **Local plane.** The plane through the (up to three) nearest crossings is
   the first-order surface. Its distance from the voxel centre is
   ``d = 1 / sqrt(sum 1 / a_i^2)`` and its foot point ``c = p + d^2 s_i / a_i``
   (per axis); for a plane surface this is exact.
3. **Propagation.** Every other voxel takes the foot point of its nearest seed
   (an exact Euclidean *feature transform* over the seed voxels, computed with
   the separable lower-envelope algorithm of :mod:`.exact` while carrying the
   winning seed), and is then improved by comparing with the foot points that
   its six neighbours chose. Its distance is its world distance to that foot
   point, signed by the side its own sample is on.

Accuracy (measured by ``tests/test_distance_subvoxel.py``): on smooth analytic
balls of radius 9.3 to 25 voxels (samples ``R - r`` and a logistic density,
centre off the lattice, isotropic and 1.5 x 1.0 x 0.8 spacing) the error
within two voxels of the surface is at most 0.075 voxel (mean 0.004-0.03), and
at most 0.26 voxel anywhere on the grid; a tilted plane is reproduced to 0.01
voxel near the surface. Thick slices cost accuracy, because each seed's
disc takes the largest spacing (:data:`DISC_RADIUS`): a cylinder along z at
0.5 mm in plane was within 0.006 mm near its surface with 0.5 mm slices but
0.10 mm (0.21 in-plane voxel) with 3 or 5 mm slices, and a sphere of 8.2 mm
on a 0.5 x 0.5 x 3 mm grid was off by up to 0.59 mm (measured in session 37;
the sign is always right). The field is not stair-cased: morph frames and meshes
from it are smooth. Where the surface leaves the grid it is not extrapolated:
distances are to the part of the surface the samples show.

Departure from the paper: Dinh & Carvalho (§0.5) only handle binary shapes
(they threshold first). This is the standard "closest point" initialisation of
level-set methods, followed by closest-point propagation.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .. import parallel
from ..errors import VolwarpError


@nb.njit(cache=True, nogil=True, inline="always")
def new_envelope(n):
    """The arrays of a lower envelope of up to ``n`` parabolas: sites, heights, breakpoints."""
    return np.empty(n, np.int64), np.empty(n, np.float64), np.empty(n + 1, np.float64)


@nb.njit(cache=True, nogil=True, inline="always")
def add_parabola(k, q, gq, h2, v, g, zb):
    """Add the parabola ``h2 (p - q)^2 + gq`` to a lower envelope; return its new last index.

    The envelope's parabolas ``0..k`` (``k = -1``: none yet) have their sites in
    ``v``, their heights in ``g`` and the breakpoints between them in ``zb``
    (``zb[j]`` to ``zb[j + 1]`` is where parabola ``j`` is lowest; the arrays of
    :func:`new_envelope`); sites come in increasing order (Felzenszwalb &
    Huttenlocher 2012, algorithm DT(f)). The exact field's passes
    (``_edtkernels.c``) hold the same function in C.
    """
    if k < 0:
        v[0] = q
        g[0] = gq
        zb[0] = -np.inf
        zb[1] = np.inf
        return 0
    s = 0.0
    while True:
        r = v[k]
        s = ((gq + h2 * q * q) - (g[k] + h2 * r * r)) / (2.0 * h2 * (q - r))
        if s <= zb[k]:
            k -= 1
            if k < 0:
                break
        else:
            break
    k += 1
    v[k] = q
    g[k] = gq
    zb[k] = -np.inf if k == 0 else s
    zb[k + 1] = np.inf
    return k


@nb.njit(cache=True, nogil=True, inline="always")
def column(plane, other, c, f, fo):
    """Copy column ``c`` of an (n, m) plane to ``f`` and that of ``other`` to ``fo``."""
    for i in range(f.shape[0]):
        f[i] = plane[i, c]
        fo[i] = other[i, c]


#: Jacobi steps of closest-point propagation after the feature transform.
REFINE_STEPS = 2
#: Radius of the surface disc each seed stands for, in units of the coarsest spacing.
DISC_RADIUS = 0.7


@nb.njit(cache=True, nogil=True, inline="always")
def _is_in(v, iso, above):
    return (v >= iso) if above else (v < iso)


@nb.njit(cache=True, nogil=True, inline="always")
def _neighbour(k, z, y, x, nz, ny, nx):
    # The k-th face neighbour (k = 0..5: x - 1, x + 1, y - 1, y + 1, z - 1, z + 1) of
    # (z, y, x): whether it is on the grid, and its index.
    step = 2 * (k & 1) - 1
    qz, qy, qx = z, y, x
    if k < 2:
        qx += step
        on = 0 <= qx < nx
    elif k < 4:
        qy += step
        on = 0 <= qy < ny
    else:
        qz += step
        on = 0 <= qz < nz
    return on, qz, qy, qx


@nb.njit(cache=True, nogil=True, inline="always")
def _crossings(vals, z, y, x, iso, above, hs, best, side):
    # Nearest iso crossing per axis (world distance) and its side; False if none.
    nz, ny, nx = vals.shape
    u = vals[z, y, x] - iso
    ins = (u >= 0) if above else (u < 0)
    found = False
    for ax in range(3):
        best[ax] = np.inf
        side[ax] = 0.0
    for nbi in range(6):
        on, qz, qy, qx = _neighbour(nbi, z, y, x, nz, ny, nx)
        if not on:
            continue
        ax = nbi // 2
        sgn = 2 * (nbi % 2) - 1
        w = vals[qz, qy, qx] - iso
        insq = (w >= 0) if above else (w < 0)
        if insq == ins:
            continue
        den = u - w
        t = 0.5
        if den != 0 and np.isfinite(den):
            t = u / den
        if not (t >= 0.0):
            t = 0.0
        if t > 1.0:
            t = 1.0
        a = t * hs[ax]
        found = True
        if a < best[ax]:
            best[ax] = a
            side[ax] = sgn
    return found

@nb.njit(cache=True, nogil=True, inline="always")
def _foot(vals, z, y, x, hs, best, side, c, origin):
    # Foot point (index coordinates of the whole grid: ``origin`` is vals[0, 0, 0]'s) of
    # the local surface plane: normal from central differences, through the crossing
    # on the grid line most nearly normal to the surface; planes through the three
    # crossings when the gradient vanishes.
    nz, ny, nx = vals.shape
    n = np.zeros(3)
    size = (nx, ny, nz)
    for ax in range(3):
        lo_x, lo_y, lo_z, hi_x, hi_y, hi_z = x, y, z, x, y, z
        if ax == 0:
            lo_x = max(x - 1, 0)
            hi_x = min(x + 1, size[0] - 1)
        elif ax == 1:
            lo_y = max(y - 1, 0)
            hi_y = min(y + 1, size[1] - 1)
        else:
            lo_z = max(z - 1, 0)
            hi_z = min(z + 1, size[2] - 1)
        span = (hi_x - lo_x) + (hi_y - lo_y) + (hi_z - lo_z)
        if span > 0:
            n[ax] = (vals[hi_z, hi_y, hi_x] - vals[lo_z, lo_y, lo_x]) / (span * hs[ax])
    g = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    c[0] = x + origin[2]
    c[1] = y + origin[1]
    c[2] = z + origin[0]
    c[3] = 0.0
    c[4] = 0.0
    c[5] = 0.0
    if g > 0 and np.isfinite(g):
        for ax in range(3):
            n[ax] /= g
            c[3 + ax] = n[ax]
        pick = -1
        for ax in range(3):
            if best[ax] < np.inf and (pick < 0 or abs(n[ax]) > abs(n[pick])):
                pick = ax
        # p - crossing = -side * a along axis `pick`
        dn = -side[pick] * best[pick] * n[pick]
        for ax in range(3):
            c[ax] -= dn * n[ax] / hs[ax]
        return
    if best[0] > 0.0 and best[1] > 0.0 and best[2] > 0.0:
        inv = 0.0
        for ax in range(3):
            if best[ax] < np.inf:
                inv += 1.0 / (best[ax] * best[ax])
        d2 = 1.0 / inv
        for ax in range(3):
            if best[ax] < np.inf:
                c[ax] += side[ax] * d2 / best[ax] / hs[ax]
                c[3 + ax] = side[ax] * np.sqrt(d2) / best[ax]

# The kernels below do a range of z slices (or of y planes), without the GIL;
# :func:`subvoxel_field` runs ranges over the threads. Every slice is computed on
# its own, so the field does not depend on the split.
@nb.njit(cache=True, nogil=True)
def _seeds(vals, iso, above, hs, offsets, fill, ids, cps, origin, z0, z1):
    # Count (fill=False) or fill (fill=True) the seeds of z slices [z0, z1).
    nz, ny, nx = vals.shape
    for z in range(z0, z1):
        best = np.empty(3)
        side = np.empty(3)
        k = offsets[z]
        cnt = 0
        for y in range(ny):
            for x in range(nx):
                # quick test first: most voxels have all six neighbours on their side
                ins = _is_in(vals[z, y, x], iso, above)
                if ((x == 0 or _is_in(vals[z, y, x - 1], iso, above) == ins)
                        and (x == nx - 1 or _is_in(vals[z, y, x + 1], iso, above) == ins)
                        and (y == 0 or _is_in(vals[z, y - 1, x], iso, above) == ins)
                        and (y == ny - 1 or _is_in(vals[z, y + 1, x], iso, above) == ins)
                        and (z == 0 or _is_in(vals[z - 1, y, x], iso, above) == ins)
                        and (z == nz - 1 or _is_in(vals[z + 1, y, x], iso, above) == ins)):
                    continue
                if not _crossings(vals, z, y, x, iso, above, hs, best, side):
                    continue
                if fill:
                    _foot(vals, z, y, x, hs, best, side, cps[k + cnt], origin)
                    ids[z, y, x] = k + cnt
                cnt += 1
        if not fill:
            offsets[z] = cnt

@nb.njit(cache=True, nogil=True, inline="always")
def _envelope_idx(f, fi, n, h2, v, g, zb, plane, pids, c):
    # The lower envelope of the parabolas h2 (p - q)^2 + f[q] (an infinite f[q]: no
    # seed there): its value and the seed id fi of its lowest parabola at every p, into
    # column c of plane and pids.
    k = -1
    for q in range(n):
        if f[q] != np.inf:
            k = add_parabola(k, q, f[q], h2, v, g, zb)
    if k < 0:
        for p in range(n):
            plane[p, c] = np.inf
            pids[p, c] = -1
        return
    j = 0
    for p in range(n):
        while zb[j + 1] < p:
            j += 1
        r = v[j]
        best = h2 * (p - r) * (p - r) + g[j]
        bi = fi[r]
        # at a breakpoint the neighbouring parabolas can tie with this one, and which one
        # the rounding of the breakpoint picks depends on where the line starts (a block's
        # line, the whole's): among equal distances the smaller seed id wins, whatever
        # the block (the distances themselves depend only on p - r)
        for jj in (j - 1, j + 1):
            if 0 <= jj <= k:
                r2 = v[jj]
                d2 = h2 * (p - r2) * (p - r2) + g[jj]
                if d2 < best or (d2 == best and fi[r2] < bi):
                    best = d2
                    bi = fi[r2]
        plane[p, c] = best
        pids[p, c] = bi


@nb.njit(cache=True, nogil=True)
def _feature_x(ids, hx, dist, z0, z1):
    # Pass 1 of the feature transform, z slices [z0, z1): in place, ids (seed id or -1)
    # becomes the id of the nearest seed along x, dist its squared distance.
    nz, ny, nx = ids.shape
    hx2 = hx * hx
    for z in range(z0, z1):
        for y in range(ny):
            last = -1
            lid = -1
            for x in range(nx):
                if ids[z, y, x] >= 0:
                    last = x
                    lid = ids[z, y, x]
                if last >= 0:
                    dist[z, y, x] = hx2 * (x - last) * (x - last)
                    ids[z, y, x] = lid
                else:
                    dist[z, y, x] = np.inf
            last = -1
            lid = -1
            for x in range(nx - 1, -1, -1):
                if dist[z, y, x] == 0.0:
                    last = x
                    lid = ids[z, y, x]
                if last >= 0:
                    d = hx2 * (last - x) * (last - x)
                    if d < dist[z, y, x]:
                        dist[z, y, x] = d
                        ids[z, y, x] = lid


@nb.njit(cache=True, nogil=True)
def _feature_y(ids, hy, dist, z0, z1):
    # Pass 2 (y), z slices [z0, z1).
    nz, ny, nx = ids.shape
    for z in range(z0, z1):
        _feature_plane(dist[z], ids[z], nx, ny, hy * hy)


@nb.njit(cache=True, nogil=True)
def _feature_z(ids, hz, dist, y0, y1):
    # Pass 3 (z), the (z, x) planes of y in [y0, y1).
    nz, ny, nx = ids.shape
    plane = np.empty((nz, nx), np.float32)
    pids = np.empty((nz, nx), ids.dtype)
    for y in range(y0, y1):
        for z in range(nz):
            for x in range(nx):
                plane[z, x] = dist[z, y, x]
                pids[z, x] = ids[z, y, x]
        _feature_plane(plane, pids, nx, nz, hz * hz)
        for z in range(nz):
            for x in range(nx):
                dist[z, y, x] = plane[z, x]
                ids[z, y, x] = pids[z, x]


@nb.njit(cache=True, nogil=True, inline="always")
def _feature_plane(plane, pids, m, n, h2):
    # nearest-seed envelope along axis 0 of an (n, m) plane, column by column, in place
    f = np.empty(n, np.float64)
    fi = np.empty(n, np.int64)
    v, g, zb = new_envelope(n)
    for c in range(m):
        column(plane, pids, c, f, fi)
        _envelope_idx(f, fi, n, h2, v, g, zb, plane, pids, c)


@nb.njit(cache=True, nogil=True, inline="always")
def _disc_d2(x, y, z, s, cps, hs, r0):
    # squared distance from voxel (x, y, z) to seed s's surface disc
    dx = (x - cps[s, 0]) * hs[0]
    dy = (y - cps[s, 1]) * hs[1]
    dz = (z - cps[s, 2]) * hs[2]
    d2 = dx * dx + dy * dy + dz * dz
    dn = dx * cps[s, 3] + dy * cps[s, 4] + dz * cps[s, 5]
    t = np.sqrt(max(d2 - dn * dn, 0.0)) - r0
    if t < 0.0:
        t = 0.0
    return dn * dn + t * t


@nb.njit(cache=True, nogil=True)
def _finish(vals, iso, above, hs, r0, eps, ids, new_ids, cps, out, origin, z0, z1):
    # Each seed stands for a small disc of the surface (foot point, unit
    # normal, radius r0). Each voxel keeps the nearest of the discs chosen
    # by itself and its 6 neighbours (one Jacobi step of closest-feature
    # propagation) and gets its signed distance to it. Far from the surface
    # neighbours mostly chose the same seed: only different ones are tried.
    nz, ny, nx = vals.shape
    oz, oy, ox = origin[0], origin[1], origin[2]
    for z in range(z0, z1):
        for y in range(ny):
            for x in range(nx):
                bid = ids[z, y, x]
                best = np.inf
                if bid >= 0:
                    best = _disc_d2(x + ox, y + oy, z + oz, bid, cps, hs, r0)
                own = bid
                for k in range(6):
                    on, qz, qy, qx = _neighbour(k, z, y, x, nz, ny, nx)
                    if not on:
                        continue
                    s = ids[qz, qy, qx]
                    if s < 0 or s == own or s == bid:
                        continue
                    d2 = _disc_d2(x + ox, y + oy, z + oz, s, cps, hs, r0)
                    if d2 < best or (d2 == best and s < bid):
                        best = d2
                        bid = s
                new_ids[z, y, x] = bid
                u = vals[z, y, x] - iso
                ins = (u >= 0) if above else (u < 0)
                d = np.sqrt(best)
                out[z, y, x] = -max(d, eps) if ins else d


def subvoxel_signed_distance(values: np.ndarray, iso: float, *, inside: str = "above",
                             spacing_zyx=(1.0, 1.0, 1.0)) -> np.ndarray:
    """Signed distance (negative inside, world units) to the iso-surface of smooth samples.

    Parameters
    ----------
    values : (Z, Y, X) array
        The samples; NaN counts as outside.
    iso : float
        The level ``V`` whose crossing is the surface.
    inside : {"above", "below"}
        The shape is where samples are at or above (below) ``V``.
    spacing_zyx : 3 floats
        Sample spacing along the array axes.

    Returns
    -------
    (Z, Y, X) float32 array

    Raises
    ------
    VolwarpError
        When the samples never cross ``V`` (no surface).
    """
    if inside not in ("above", "below"):
        raise VolwarpError(f"inside must be 'above' or 'below', got {inside!r}")
    vals = np.ascontiguousarray(values)
    if vals.dtype.kind not in "f":
        vals = vals.astype(np.float32)
    dist = subvoxel_field(vals, iso, inside == "above", spacing_zyx)
    if dist is None:
        raise VolwarpError(f"the samples never cross the iso level {iso:g}: there is no surface")
    return dist


def subvoxel_field(vals: np.ndarray, iso: float, above: bool, spacing_zyx,
                   threads: int | None = None, origin=(0, 0, 0)) -> np.ndarray | None:
    """The sub-voxel field of float samples ``vals``; None where they never cross ``iso``.

    Each kernel's slices run over ``threads`` (default :func:`.parallel.threads`;
    1 for an out-of-core block task, in a thread of its own): the same numbers
    for any count. ``origin``: the index (z, y, x) of ``vals[0, 0, 0]`` in the
    whole grid, where ``vals`` is a block's region: the foot points are kept
    in the whole grid's coordinates, so that a block's arithmetic is the
    whole's (in a block's own coordinates they round differently, and a
    voxel between two nearly equidistant discs could pick the other one).
    """
    n = parallel.threads() if threads is None else max(1, int(threads))
    origin = np.array([int(v) for v in origin], np.int64)
    nz, ny = vals.shape[0], vals.shape[1]

    def over(kernel, length, *args):
        parallel.run_ranges(lambda a, b: kernel(*args, a, b), length, n)

    hz, hy, hx = (float(s) for s in spacing_zyx)
    hs = np.array([hx, hy, hz])
    counts = np.zeros(nz, np.int64)
    idtype = np.int32 if vals.size < 2**31 else np.int64
    over(_seeds, nz, vals, float(iso), above, hs, counts, False, np.empty((1, 1, 1), idtype),
         np.empty((1, 6)), origin)
    total = int(counts.sum())
    if total == 0:
        return None
    offsets = np.zeros(nz, np.int64)
    offsets[1:] = np.cumsum(counts)[:-1]
    ids = np.full(vals.shape, -1, idtype)
    cps = np.empty((total, 6), np.float64)
    over(_seeds, nz, vals, float(iso), above, hs, offsets, True, ids, cps, origin)
    dist = np.empty(vals.shape, np.float32)
    over(_feature_x, nz, ids, hx, dist)
    over(_feature_y, nz, ids, hy, dist)
    over(_feature_z, ny, ids, hz, dist)
    r0 = DISC_RADIUS * float(max(hs))
    other = np.empty_like(ids)
    for _ in range(REFINE_STEPS):
        over(_finish, nz, vals, float(iso), above, hs, r0, 1e-6 * float(min(hs)), ids, other,
             cps, dist, origin)
        ids, other = other, ids
    return dist
