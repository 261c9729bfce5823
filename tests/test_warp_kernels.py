"""The compiled warp kernels (volwarp_cli/bspline/_warpkernels.c) against independent references.

- the box pushforward of a small random deformation against a brute-force
  evaluation of its definition (face-centre box, overlaps, Jacobian mass);
- a voxel's contributions do not depend on the block it is scattered in;
- the trilinear gather against scipy.ndimage.map_coordinates;
- finalize against its formula;
- wrong buffers are errors, not crashes.
"""

from __future__ import annotations

import sys
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from volwarp_cli import parallel
from volwarp_cli.box import Box
from volwarp_cli.bspline import _warpkernels as K
from volwarp_cli.bspline import pushforward
from volwarp_cli.bspline.pushforward import COVERED_HI, COVERED_LO, GROW_BELOW, QUANTUM
from volwarp_cli.bspline.reach import TargetBlock


def random_offsets(shape_zyx, rng, amplitude=0.6):
    """Planar float32 offsets [3, z+2, y+2, x+2] (smooth random field, margin extrapolated)."""
    nz, ny, nx = shape_zyx
    u = np.zeros((3, nz + 2, ny + 2, nx + 2), np.float32)
    view = np.moveaxis(u, 0, -1)
    coarse = rng.normal(0, amplitude, (3, 3, 3, 3))
    for c in range(3):
        zoom = [(n + 2) / 3 for n in (nz, ny, nx)]
        view[..., c] = ndimage.zoom(coarse[c], zoom, order=1)[:nz + 2, :ny + 2, :nx + 2]
    pushforward.fill_halo(view)
    return u


def grown_box(lo, hi, jac, det, near_lo, near_hi, stats=None):
    """A box of less than GROW_BELOW of its voxel's image volume ``det``, grown to it.

    Each side from the face centres' box towards the 8 corners' box (side: the sum of
    |d component / d axis|), one fraction k for the three: the root of the volume's
    tangent at 0, then two Newton steps (the volume then within 0.1% over the share,
    checked here), about the box's middle, within [near_lo, near_hi] (``stats["clamped"]``
    counts the boxes that bound cut).
    """
    side = hi - lo
    more = np.maximum(np.abs(jac).sum(axis=0) - side, 0.0)
    want = GROW_BELOW * det
    k = 1.0
    if np.prod(side + more) > want:
        k = min(1.0, (want / np.prod(side) - 1.0) / np.sum(more / side))
        for _ in range(2):
            a = side + k * more
            k -= (np.prod(a) - want) / (more[0] * a[1] * a[2] + a[0] * more[1] * a[2]
                                        + a[0] * a[1] * more[2])
        assert (1 - 1e-12) * want <= np.prod(side + k * more) <= 1.001 * want
    mid, grown = 0.5 * (lo + hi), side + k * more
    if stats is not None and (np.any(mid - 0.5 * grown < near_lo)
                              or np.any(mid + 0.5 * grown > near_hi)):
        stats["clamped"] = stats.get("clamped", 0) + 1
    return np.maximum(mid - 0.5 * grown, near_lo), np.minimum(mid + 0.5 * grown, near_hi)


def brute_force_box(u, values, off, scale, tshape_zyx, vmax, stats=None):
    """Weights and weighted values of the box pushforward, straight from the definition."""
    w = np.zeros(tshape_zyx)
    v = np.zeros(tshape_zyx)
    _, nzb, nyb, nxb = u.shape
    s = np.asarray(scale, float)
    for g in range(nzb - 2):
        for f in range(nyb - 2):
            for e in range(nxb - 2):
                U = u[:, g + 1, f + 1, e + 1].astype(float)
                base = np.asarray(off, float) + s * (e, f, g)
                # neighbours' offsets along x, y, z (axis order of u is c, z, y, x)
                nb = {}
                for axis, (dz, dy, dx) in enumerate(((0, 0, 1), (0, 1, 0), (1, 0, 0))):
                    nb[axis, -1] = u[:, g + 1 - dz, f + 1 - dy, e + 1 - dx].astype(float)
                    nb[axis, 1] = u[:, g + 1 + dz, f + 1 + dy, e + 1 + dx].astype(float)
                lo = np.empty(3)
                hi = np.empty(3)
                for c in range(3):  # component c: the 6 face centres' coordinate c
                    faces = []
                    for axis in range(3):
                        for side in (-1, 1):
                            shift = side * 0.5 * s[c] if axis == c else 0.0
                            faces.append(0.5 * (U[c] + nb[axis, side][c]) + shift)
                    lo[c], hi[c] = min(faces) + base[c], max(faces) + base[c]
                jac = np.array([[s[c] * (axis == c) + 0.5 * (nb[axis, 1][c] - nb[axis, -1][c])
                                 for c in range(3)] for axis in range(3)])
                det = abs(np.linalg.det(jac))
                if np.prod(hi - lo) < GROW_BELOW * det:  # a thin box grows
                    offs = [U] + list(nb.values())
                    lo, hi = grown_box(lo, hi, jac, det, base + np.min(offs, axis=0) - 0.5 * s,
                                       base + np.max(offs, axis=0) + 0.5 * s, stats)
                mass = det / np.prod(hi - lo)
                val = float(values[g, f, e]) / vmax
                for z in range(tshape_zyx[0]):
                    oz = min(hi[2], z + 0.5) - max(lo[2], z - 0.5)
                    if oz <= 0:
                        continue
                    for y in range(tshape_zyx[1]):
                        oy = min(hi[1], y + 0.5) - max(lo[1], y - 0.5)
                        if oy <= 0:
                            continue
                        for x in range(tshape_zyx[2]):
                            ox = min(hi[0], x + 0.5) - max(lo[0], x - 0.5)
                            if ox <= 0:
                                continue
                            w[z, y, x] += oz * oy * ox * mass
                            v[z, y, x] += oz * oy * ox * mass * val
    return w, v


def test_box_pushforward_matches_its_definition():
    rng = np.random.default_rng(3)
    dz, dy, dx = 5, 6, 7
    u = random_offsets((dz, dy, dx), rng)
    values = rng.uniform(-3, 5, (dz, dy, dx)).astype(np.float32)
    off = (1.3, 0.7, 1.1)
    scale = (0.93, 1.07, 0.81)
    tshape = (9, 10, 11)
    vmax = float(np.abs(values).max())
    acc = np.zeros(tshape + (2,), np.int64)
    bb = pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, vmax, "box", acc)
    w, v = brute_force_box(u, values, off, scale, tshape, vmax)
    assert np.abs(acc[..., 0] / QUANTUM - w).max() < 1e-9
    assert np.abs(acc[..., 1] / QUANTUM - v).max() < 1e-9
    touched = np.argwhere(w > 0)
    assert bb == Box(tuple(touched.min(0).tolist()), tuple((touched.max(0) + 1).tolist()))


def rotated_offsets(shape_zyx, matrix, centre):
    """Planar float32 offsets [3, z+2, y+2, x+2] of the map g -> R (g - c) + c (halo included)."""
    nz, ny, nx = shape_zyx
    g = np.stack(np.meshgrid(np.arange(-1, nx + 1), np.arange(-1, ny + 1), np.arange(-1, nz + 1),
                             indexing="ij"), -1).astype(float)  # [x, y, z, 3]
    moved = (g - centre) @ np.asarray(matrix).T + centre - g
    return np.ascontiguousarray(np.moveaxis(moved, -1, 0).transpose(0, 3, 2, 1)).astype(np.float32)


def test_thin_boxes_of_an_oblique_rotation_grow_as_defined():
    """45 degrees about x, then z: the face centres' box holds 35% of each voxel's image; the
    kernel grows it as the definition says (brute_force_box's grown_box, scipy's root)."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("xz", [45, 45], degrees=True).as_matrix()
    dz, dy, dx = 5, 6, 7
    u = rotated_offsets((dz, dy, dx), rot, np.array([3.0, 2.5, 2.0]))
    values = np.random.default_rng(4).uniform(-3, 5, (dz, dy, dx)).astype(np.float32)
    off, scale, tshape = (2.0, 2.0, 2.0), (1.0, 1.0, 1.0), (10, 11, 12)
    vmax = float(np.abs(values).max())
    acc = np.zeros(tshape + (2,), np.int64)
    pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, vmax,
                        "box", acc)
    w, v = brute_force_box(u, values, off, scale, tshape, vmax)
    assert np.abs(acc[..., 0] / QUANTUM - w).max() < 1e-9
    assert np.abs(acc[..., 1] / QUANTUM - v).max() < 1e-9


def rough_rotated_offsets(seed, shape_zyx=(6, 7, 8)):
    """A smooth random field (cubic zoom of n^3 normal offsets) plus an oblique rotation."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    n, amplitude = int(rng.integers(3, 7)), rng.uniform(0.5, 4)
    u = np.zeros((3,) + tuple(m + 2 for m in shape_zyx))
    coarse = rng.normal(0, amplitude, (3, n, n, n))
    for c in range(3):
        zoomed = ndimage.zoom(coarse[c], [(m + 2) / n for m in shape_zyx], order=3)
        u[c] = zoomed[:shape_zyx[0] + 2, :shape_zyx[1] + 2, :shape_zyx[2] + 2]
    rot = Rotation.from_euler("xz", rng.uniform(20, 70, 2), degrees=True).as_matrix()
    g = np.stack(np.meshgrid(*[np.arange(-1, m + 1) for m in shape_zyx[::-1]], indexing="ij"),
                 -1).astype(float)
    u += np.moveaxis(g @ rot.T - g, -1, 0).transpose(0, 3, 2, 1)
    return u.astype(np.float32)


@pytest.mark.parametrize("seed", [9, 17, 178])
def test_a_grown_box_is_clamped_to_its_neighbours_reach_as_defined(seed):
    """Where a thin box's growth would pass its voxel's and neighbours' offsets widened by
    the half voxel (the reach bounds blocks and threads are planned by), it stops there:
    the kernel against the definition on fields chosen so that the clamp acts (no test
    reached it before: a kernel built without it passed the suite)."""
    u = rough_rotated_offsets(seed)
    dz, dy, dx = 6, 7, 8
    values = np.random.default_rng(seed).uniform(-3, 5, (dz, dy, dx)).astype(np.float32)
    g = np.stack(np.meshgrid(np.arange(dx), np.arange(dy), np.arange(dz), indexing="ij"), -1)
    pos = g.transpose(2, 1, 0, 3) + np.moveaxis(u[:, 1:-1, 1:-1, 1:-1], 0, -1)
    first = np.floor(pos.min(axis=(0, 1, 2))) - 3
    off = tuple(float(-v) for v in first)
    tshape = tuple(int(v) for v in (np.ceil(pos.max(axis=(0, 1, 2))) - first + 4)[::-1])
    vmax = float(np.abs(values).max())
    acc = np.zeros(tshape + (2,), np.int64)
    pushforward.scatter(u, values, off, (1.0, 1.0, 1.0), Box.from_xyz((0, 0, 0), (dx, dy, dz)),
                        1, vmax, "box", acc)
    stats = {}
    w, v = brute_force_box(u, values, off, (1.0, 1.0, 1.0), tshape, vmax, stats)
    assert stats.get("clamped", 0) >= 1  # (the case reaches the clamp)
    assert np.abs(acc[..., 0] / QUANTUM - w).max() < 1e-9
    assert np.abs(acc[..., 1] / QUANTUM - v).max() < 1e-9


@pytest.mark.parametrize("method", ["box", "nearest"])
def test_contributions_do_not_depend_on_the_block(method):
    """Integer sums: the same per-voxel contributions give the same accumulators in any split."""
    rng = np.random.default_rng(5)
    dz, dy, dx = 13, 11, 40
    u = random_offsets((dz, dy, dx), rng, amplitude=1.5)
    values = rng.uniform(0, 1, (dz, dy, dx))  # float64 domain
    # coordinates away from 0 and scales that round: a voxel position computed from
    # the block's start instead of its own index differs in the last bit and flips
    # the fixed-point rounding of some overlaps (seen: 21 accumulators differ)
    off = (100.3, 1.0 / 7.0, 0.3)
    scale = (256.0 / 258.0, 0.77, 1.0 / 3.0 + 0.5)
    tshape = (14, 15, 145)
    whole = np.zeros(tshape + (2,), np.int64)
    pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, 1.0, method, whole)
    parts = np.zeros_like(whole)
    cuts = [(0, 7, 23, 40), (0, 4, 11), (0, 6, 13)]  # x, y, z
    for x0, x1 in pairwise(cuts[0]):
        for y0, y1 in pairwise(cuts[1]):
            for z0, z1 in pairwise(cuts[2]):
                pushforward.scatter(u, values, off, scale, Box.from_xyz((x0, y0, z0), (x1, y1, z1)), 1, 1.0,
                                    method, parts)
    assert np.array_equal(whole, parts)
    assert whole[..., 0].sum() > 0
    # removing what was added leaves exactly nothing
    pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), -1, 1.0, method, parts)
    assert not parts.any()


@pytest.mark.parametrize("method", ["box", "nearest"])
def test_split_by_target_planes_gives_the_same_sums(method):
    """parts (TargetBlocks): one thread per part takes its target planes from its domain
    block; voxels whose boxes straddle a cut are done by both parts,
    each keeping its side. The sums equal one unsplit run's; a part whose domain range
    misses some straddling voxels loses their contributions."""
    rng = np.random.default_rng(8)
    dz, dy, dx = 24, 9, 10
    u = random_offsets((dz, dy, dx), rng, amplitude=1.5)
    values = rng.uniform(0, 1, (dz, dy, dx)).astype(np.float32)
    off, scale = (1.3, 0.7, 2.2), (1.0, 1.0, 0.9)
    tshape = (26, 12, 13)
    whole = np.zeros(tshape + (2,), np.int64)
    pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, 1.0, method, whole)
    # a box reaches at most r planes from its base position 2.2 + 0.9 g
    r = float(np.abs(u[2]).max()) + 1.0

    def window(t0, t1):  # the domain planes whose boxes can reach target planes [t0, t1)
        return (max(0, int(np.floor((t0 - 1 - r - 2.2) / 0.9))),
                min(dz, int(np.ceil((t1 + r - 2.2) / 0.9)) + 1))

    edges = [0, 8, 12, 19, tshape[0]]

    def part(t0, t1, g0, g1):
        return TargetBlock(Box((t0, 0, 0), (t1, tshape[1], tshape[2])),
                           Box((g0, 0, 0), (g1, dy, dx)))

    parts = [part(a, b, *window(a, b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    assert parts[1].domain.lo[0] < parts[0].domain.hi[0]  # straddling voxels in both ranges
    with parallel.use_threads(len(parts)):
        split = np.zeros_like(whole)
        pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1,
                            1.0, method, split, parts=parts)
        assert np.array_equal(whole, split)
        assert all(whole[p.target.lo[0]:p.target.hi[0], ..., 0].any() for p in parts)
        short = np.zeros_like(whole)  # the third part starting too late misses some
        third = parts[2]
        bad = parts[:2] + [part(third.target.lo[0], third.target.hi[0], parts[1].domain.hi[0],
                                third.domain.hi[0])] + parts[3:]
        pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, 1.0, method,
                            short, parts=bad)
        assert not np.array_equal(whole, short)


@pytest.mark.parametrize("method", ["box", "nearest"])
def test_window_keeps_exactly_the_contributions_inside_it(method):
    """A target window (columns, rows, planes) clips contributions and changes no sum in it:
    what a local rebuild of the accumulators relies on. Boxes straddle the window's edges
    and lie beyond them (large offsets)."""
    rng = np.random.default_rng(11)
    dz, dy, dx = 9, 10, 12
    u = random_offsets((dz, dy, dx), rng, amplitude=3.0)
    values = rng.uniform(-1, 2, (dz, dy, dx)).astype(np.float32)
    off, scale = (2.2, 1.7, 2.4), (0.8, 0.9, 0.7)
    whole = np.zeros((12, 13, 14, 2), np.int64)
    pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, 2.0, method, whole)
    for (x0, x1), (y0, y1), (z0, z1) in [((3, 9), (2, 11), (4, 8)), ((0, 14), (5, 6), (0, 12)),
                                         ((7, 8), (0, 13), (8, 10))]:
        part = np.zeros_like(whole)
        pushforward.scatter(u, values, off, scale, Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, 2.0, method,
                            part[z0:z1], held=pushforward.HeldPlanes(z0),
                            window=((x0, x1), (y0, y1)))
        inside = np.zeros(whole.shape[:3], bool)
        inside[z0:z1, y0:y1, x0:x1] = True
        assert np.array_equal(part[inside], whole[inside])
        assert not part[~inside].any()
        assert part.any() and whole[~inside].any()


@pytest.mark.parametrize("offset", [0.0, 0.3])
@pytest.mark.parametrize("moved", [False, True])
def test_touched_box_is_what_the_scatter_added(offset, moved):
    """The box the scatter says it touched (what a local update refinishes) is exactly the
    extent of the accumulators it changed: still voxels one column each at consecutive
    columns (offset 0: a grid warped onto itself, added a stretch at a time) or two
    (offset 0.3), with and without a moved region among them, and a window cutting the
    rows short."""
    rng = np.random.default_rng(17)
    dz, dy, dx = 8, 12, 40  # (whole regions of 4 voxels)
    u = np.zeros((3, dz + 2, dy + 2, dx + 2), np.float32)
    if moved:  # (regions of 4 columns: x region 3 moves)
        u[:, :, :, 13:17] = rng.uniform(-0.6, 0.6, (3, dz + 2, dy + 2, 4))
    values = rng.uniform(1, 2, (dz, dy, dx)).astype(np.float32)
    still = np.ones((1, 2, 3, 10), np.uint8)
    if moved:
        still[0, :, :, 2:5] = 0
    for window in (None, ((5, 31), (0, 12))):
        acc = np.zeros((dz + 2, dy + 2, dx + 2, 2), np.int64)
        touched = pushforward.scatter(u, values, (offset, offset, offset), (1.0, 1.0, 1.0),
                                      Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, 2.0, "box", acc,
                                      still=still, granularity=(4, 4, 4), window=window)
        hit = np.argwhere(acc.any(axis=-1))
        assert touched is not None and hit.size
        assert touched.lo == tuple(hit.min(axis=0)) and touched.hi == tuple(hit.max(axis=0) + 1)
        general = np.zeros_like(acc)  # (and the sums are those of the general path)
        pushforward.scatter(u, values, (offset, offset, offset), (1.0, 1.0, 1.0),
                            Box.from_xyz((0, 0, 0), (dx, dy, dz)), 1, 2.0, "box", general,
                            window=window)
        assert np.array_equal(acc, general)


@pytest.mark.parametrize("method", ["box", "nearest"])
def test_values_may_hold_only_the_blocks_planes(method):
    """The scatter reads a block's samples from a buffer of just its planes (what a
    capture gathered plane by plane gives) exactly as from the whole domain."""
    rng = np.random.default_rng(12)
    dz, dy, dx = 12, 9, 10
    u = random_offsets((dz, dy, dx), rng, amplitude=1.0)
    values = rng.uniform(-1, 2, (dz, dy, dx)).astype(np.float32)
    still = np.zeros((1, 4, 3, 5), np.uint8)
    still[0, 1:3] = 1  # the still shortcut reads the samples too
    whole = np.zeros((14, 12, 13, 2), np.int64)
    parts = np.zeros_like(whole)
    for z0, z1 in [(0, 5), (5, 6), (6, 12)]:
        kw = dict(still=still if method == "box" else None, granularity=(2, 3, 3))
        pushforward.scatter(u, values, (1.2, 1.4, 1.1), (0.9, 1.1, 0.95),
                            Box.from_xyz((0, 0, z0), (dx, dy, z1)), 1, 2.0, method, whole, **kw)
        pushforward.scatter(u, values[z0:z1].copy(), (1.2, 1.4, 1.1), (0.9, 1.1, 0.95),
                            Box.from_xyz((0, 0, z0), (dx, dy, z1)), 1, 2.0, method, parts,
                            planes=(z0, dz),
                            **kw)
    assert np.array_equal(whole, parts) and whole.any()
    with pytest.raises(ValueError, match="outside"):  # a plane of the block not given
        pushforward.scatter(u, values[2:5].copy(), (1.2, 1.4, 1.1), (0.9, 1.1, 0.95),
                            Box.from_xyz((0, 0, 1), (dx, dy, 5)), 1, 2.0, method, parts,
                            planes=(2, dz))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_trilinear_gather_matches_scipy(dtype):
    rng = np.random.default_rng(7)
    data = rng.normal(size=(6, 7, 8)).astype(dtype)
    axes = [np.sort(rng.uniform(0, n - 1, m)) for n, m in ((8, 5), (7, 4), (6, 3))]  # x, y, z
    idx = []
    for c, n in zip(axes, (8, 7, 6), strict=True):
        i0 = np.floor(c).astype(np.int32)
        i1 = np.minimum(i0 + 1, n - 1).astype(np.int32)
        idx.append((i0, i1, c - i0))
    out = np.empty((3, 4, 5), dtype)
    (x0, x1, fx), (y0, y1, fy), (z0, z1, fz) = idx
    lo, hi = K.sample(data, x0, x1, fx, y0, y1, fy, z0, z1, fz, out, 0, 3)
    assert (lo, hi) == (float(out.min()), float(out.max()))
    zz, yy, xx = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    ref = ndimage.map_coordinates(data.astype(float), [zz, yy, xx], order=1)
    assert np.allclose(out, ref, rtol=0, atol=1e-5 if dtype == np.float32 else 1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("columns", ["consecutive", "clamped"])
def test_gather_with_zero_weights_is_a_copy(dtype, columns):
    """Every weight 0 (a capture at oversample 1): the samples at the lower indices plus 0.0,
    so -0.0 comes out +0.0, whether the columns run consecutively (copied as a row) or
    not (an edge's clamped indices, gathered one by one); the range is of the copy."""
    rng = np.random.default_rng(23)
    data = rng.normal(size=(6, 7, 40)).astype(dtype)
    data[rng.random(data.shape) < 0.2] = -0.0
    data[2, 3, 5:9] = 1e30 if dtype == np.float32 else 1e300  # (the range's high end)
    x0 = (np.arange(3, 37) if columns == "consecutive" else
          np.minimum(np.arange(10, 44), 39)).astype(np.int32)
    y0 = np.array([0, 3, 3, 6], np.int32)
    z0 = np.array([5, 2, 0], np.int32)
    out = np.full((3, 4, len(x0)), np.nan, dtype)
    zeros = [np.zeros(len(i)) for i in (x0, y0, z0)]
    lo, hi = K.sample(data, x0, x0, zeros[0], y0, y0, zeros[1], z0, z0, zeros[2], out, 0, 3)
    ref = data[z0][:, y0][:, :, x0] + dtype(0.0)
    assert np.array_equal(out, ref)
    assert not np.signbit(out[out == 0]).any() and (data[z0][:, y0][:, :, x0] == 0).any()
    assert np.signbit(data[z0][:, y0][:, :, x0][ref == 0]).any()  # (there were -0.0 to mend)
    assert (lo, hi) == (float(ref.min()), float(ref.max()))
    part = np.full_like(out, 7.0)  # planes [1, 3) only: plane 0 untouched
    K.sample(data, x0, x0, zeros[0], y0, y0, zeros[1], z0, z0, zeros[2], part, 1, 3)
    assert np.array_equal(part[1:], ref[1:]) and (part[0] == 7.0).all()
    none = np.zeros(0, np.int32)  # no column: nothing read, an empty range
    assert K.sample(data, none, none, np.zeros(0), y0, y0, zeros[1], z0, z0, zeros[2],
                    np.zeros((3, 4, 0), dtype), 0, 3) == (np.inf, -np.inf)


@pytest.mark.parametrize("heavy", [1.0, 4000.0])
def test_finalize_formula(heavy):
    """Sums of ordinary size, and sums beyond 2**51 (a region folded onto a few voxels):
    both conversions give the formula's values."""
    rng = np.random.default_rng(9)
    w = rng.uniform(0, 1.3, (4, 5, 6)) * heavy
    v = rng.uniform(-1, 1, (4, 5, 6))
    acc = np.stack([np.rint(w * QUANTUM), np.rint(v * QUANTUM)], -1).astype(np.int64)
    out = np.full((4, 5, 6), np.nan)
    vmax, b = 3.0, 7.5
    K.finalize(acc, vmax, (1, 0, 2), (6, 5, 4), out, b)
    w = acc[..., 0] / QUANTUM
    v = acc[..., 1] / QUANTUM * vmax
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip((w - COVERED_LO) / (COVERED_HI - COVERED_LO), 0, 1)
        ref = t * (v / w) + (1 - t) * (v + b * (1 - w))
    ref = np.where(w >= COVERED_HI, v / np.where(w > 0, w, 1), ref)
    ref = np.where(w <= COVERED_LO, v + b * (1 - w), ref)
    if heavy > 1:
        assert np.abs(acc).max() > 2 ** 51
    assert np.allclose(out[2:, :, 1:], ref[2:, :, 1:], rtol=1e-12, atol=1e-12)
    assert np.isnan(out[:2]).all() and np.isnan(out[:, :, 0]).all()  # outside the block
    # clear: the same samples, and the block's accumulators back to zero (only the block's)
    again = np.full_like(out, np.nan)
    before = acc.copy()
    K.finalize(acc, vmax, (1, 0, 2), (6, 5, 4), again, b, True)
    assert np.array_equal(again, out, equal_nan=True)
    assert not acc[2:, :, 1:].any()
    assert np.array_equal(acc[:2], before[:2]) and np.array_equal(acc[:, :, 0], before[:, :, 0])


def test_wrong_buffers_are_errors():
    acc = np.zeros((4, 4, 4, 2), np.int64)
    out = np.zeros((4, 4, 4), np.float32)
    with pytest.raises(TypeError, match="sample type"):
        K.finalize(acc.astype(np.int32), 1.0, (0, 0, 0), (4, 4, 4), out, 0.0)
    for swapped in (acc.astype(">i8"), out.astype(">f4")):  # another machine's byte order
        with pytest.raises(TypeError, match="sample type"):
            K.finalize(swapped if swapped.ndim == 4 else acc, 1.0, (0, 0, 0), (4, 4, 4),
                       swapped if swapped.ndim == 3 else out, 0.0)
    assert not out.any()
    with pytest.raises(ValueError, match="outside"):
        K.finalize(acc, 1.0, (0, 0, 0), (5, 4, 4), out, 0.0)
    with pytest.raises(ValueError, match="dimensions"):
        K.finalize(np.zeros((4, 4, 4), np.int64), 1.0, (0, 0, 0), (4, 4, 4), out, 0.0)
    with pytest.raises(ValueError, match="contiguous"):
        K.finalize(acc[::2], 1.0, (0, 0, 0), (4, 2, 2), out[::2], 0.0)
    with pytest.raises(ValueError, match="read-only"):
        out.flags.writeable = False
        K.finalize(acc, 1.0, (0, 0, 0), (4, 4, 4), out, 0.0)
    u = np.zeros((3, 4, 4, 4), np.float32)
    vals = np.zeros((2, 2, 2), np.float32)
    with pytest.raises(ValueError, match="block outside"):
        pushforward.scatter(u, vals, (0, 0, 0), (1, 1, 1), Box.from_xyz((0, 0, 0), (3, 2, 2)), 1, 1.0, "box",
                            acc)
    i = np.array([0, 9], np.int32)
    f = np.zeros(2)
    with pytest.raises(IndexError, match="outside the source"):
        K.sample(np.zeros((2, 2, 2), np.float32), i, i, f, i[:1], i[:1], f, i[:1], i[:1], f,
                 np.zeros((1, 1, 2), np.float32), 0, 1)


@pytest.mark.parametrize("oversample", [1.0, 1.5, 2.0])
def test_still_regions_take_a_shortcut_to_the_same_sums(monkeypatch, oversample):
    """Regions whose control points are unmoved skip the box computation, bit for bit
    (at oversample 2 the subdivision grid has domain voxels outside the input on every
    axis, which neither path scatters)."""
    from volwarp_cli.bspline.capture import capture_volume
    from volwarp_cli.bspline.scene import Scene
    from volwarp_cli.volume import Volume

    rng = np.random.default_rng(11)
    data = rng.uniform(0, 100, (23, 19, 29)).astype(np.float32)
    cap = capture_volume(Volume(data), lattice=(9, 8, 7), oversample=oversample)
    dq = cap.dq.copy()
    dq[3, 4, 5] += [1.7, -0.9, 0.6]
    still = pushforward.still_regions([dq])
    assert still is not None and 0 < still.mean() < 1
    masks = []  # the still masks the scatter was given
    scatter = pushforward.scatter

    def recording_scatter(*args, **kwargs):
        masks.append(kwargs.get("still"))
        return scatter(*args, **kwargs)

    monkeypatch.setattr(pushforward, "scatter", recording_scatter)
    fast = Scene(cap.domain, cap.grid, dq, 3)
    fast.compute()
    assert masks and all(m is not None for m in masks)
    masks.clear()
    monkeypatch.setattr(Scene, "_still", lambda self, dqs: None)  # no shortcut
    slow = Scene(cap.domain, cap.grid, dq, 3)
    slow.compute()
    assert masks and all(m is None for m in masks)
    assert np.array_equal(fast.acc, slow.acc)
    assert np.array_equal(fast.out, slow.out)


def _baseline_module(tmp_path):
    """The kernels compiled without the vector clones (what a machine without AVX2 runs)."""
    import importlib.machinery
    import importlib.util
    import shutil
    import subprocess
    import sysconfig

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:  # pragma: no cover - the install needs one
        pytest.skip("no C compiler")
    so = tmp_path / ("_warpkernels" + sysconfig.get_config_var("EXT_SUFFIX"))
    src = Path(K.__file__).with_name("_warpkernels.c")
    subprocess.run([cc, "-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math",
                    "-Wno-psabi", "-shared", "-fPIC", "-DVOLWARP_NO_CLONES",
                    f"-I{sysconfig.get_paths()['include']}", str(src), "-o", str(so)],
                   check=True)
    name = "volwarp_cli.bspline._warpkernels"
    installed = sys.modules[name]
    loader = importlib.machinery.ExtensionFileLoader(name, str(so))
    try:
        module = importlib.util.module_from_spec(importlib.util.spec_from_loader(name, loader))
        loader.exec_module(module)
    finally:  # (loading an extension puts it in sys.modules under its name: every later
        sys.modules[name] = installed  # test of this process would run the baseline build)
    return module


def test_vector_clones_give_the_baseline_results(tmp_path):
    """The installed kernels (AVX-512 or AVX2 clones where the CPU has them) and a build without clones
    agree bit for bit: gather, spline evaluation and scatter (general and still voxels)."""
    base = _baseline_module(tmp_path)
    rng = np.random.default_rng(13)
    data = rng.normal(size=(9, 10, 11)).astype(np.float32)
    idx = [np.sort(rng.integers(0, n - 1, m)).astype(np.int32) for n, m in ((11, 13), (10, 12),
                                                                        (9, 7))]
    args = []
    for i0 in idx:
        args += [i0, (i0 + 1).astype(np.int32), rng.uniform(0, 1, len(i0))]
    outs = [np.empty((7, 12, 13), np.float32) for _ in range(2)]
    ranges = [mod.sample(data, *args, out, 0, 7) for mod, out in zip((K, base), outs,
                                                                     strict=True)]
    assert ranges[0] == ranges[1] and np.array_equal(outs[0], outs[1])

    dq = rng.normal(size=(7, 8, 9, 3))
    w = [np.ascontiguousarray(rng.uniform(0, 1, (g, 4))) for g in (3, 4, 5)]
    evals = [np.zeros((20, 20, 18, 3), np.float32) for _ in range(2)]
    for mod, out in zip((K, base), evals, strict=True):
        mod.separable(dq, *w, 1, 17, 2, 19, 3, 20, out, 1, 2, 3)
    assert np.array_equal(evals[0], evals[1])

    u = random_offsets((13, 11, 17), rng, amplitude=1.2)
    u[:, :, :, :9] = 0  # a still part: regions of 3 voxels in x, the first 3 columns
    values = rng.uniform(-2, 5, (13, 11, 17)).astype(np.float32)
    still = np.zeros((1, 13, 11, 17 // 1), np.uint8)[:, :, :, :17]
    still[..., :3] = 1
    accs = [np.zeros((17, 16, 22, 2), np.int64) for _ in range(2)]
    for method in ("box", "nearest"):
        for mod, acc in zip((K, base), accs, strict=True):
            acc[:] = 0
            mod.scatter(u, u, 1, (0, 0, 0), values, (0, 13), (1.5, 2.25, 1.75), (0.93, 1.07, 0.81),
                        (0, 0, 0), (17, 11, 13), 1, 0.2, method == "box", acc,
                        (0, 22, 0, 16, 0, 17), False,
                        True, still if method == "box" else None, (1, 1, 1), (0, 0), (-1, -1),
                        (0, 0))
        assert np.array_equal(accs[0], accs[1]) and accs[0].any()

    for scale in (1.0, 4000.0):  # both conversions of finalize
        sums = (rng.uniform(-1, 1.3, (3, 4, 37, 2)) * scale * 2.0 ** 40).astype(np.int64)
        finals = [np.empty((3, 4, 37), np.float32) for _ in range(2)]
        for mod, out in zip((K, base), finals, strict=True):
            mod.finalize(sums, 2.5, (0, 0, 0), (37, 4, 3), out, 1.5)
        assert np.array_equal(finals[0], finals[1])


def test_kernel_jobs_refuse_misplaced_arguments():
    """The typed kernel calls: a triple in the wrong field, a wrong dtype or a missing field
    is a TypeError at construction, not a run on the wrong voxels."""
    from volwarp_cli.bspline.jobs import FinalizeJob, ScatterJob, SeparableJob

    u = np.zeros((3, 4, 4, 4), np.float32)
    values = np.zeros((2, 2, 2), np.float32)
    acc = np.zeros((4, 4, 4, 2), np.int64)
    good = dict(u=u, u_new=None, origin=(0, 0, 0), values=values, planes=(0, 2),
                offset=(1.0, 1.0, 1.0), scale=(1.0, 1.0, 1.0), block=Box((0, 0, 0), (2, 2, 2)),
                sign=1, inv_vmax=1.0, box=True, acc=acc, clip=(0, 4, 0, 4, 0, 4))
    ScatterJob(**good)
    for change in [{"block": ((0, 0, 0), (2, 2, 2))}, {"clip": (0, 4, 0, 4)},
                   {"offset": (1.0, 1.0)},
                   {"acc": acc.astype(np.int32)}, {"u": u[0]}, {"sign": 2},
                   {"box": "box"}, {"planes": (0, 2, 5)}]:
        with pytest.raises(TypeError):
            ScatterJob(**{**good, **change})
    with pytest.raises(TypeError):
        ScatterJob(u, None, (0, 0, 0))  # positional: keyword-only
    with pytest.raises(TypeError, match="block"):
        FinalizeJob(acc=acc, vmax=1.0, block=((0, 0, 0), (4, 4, 4)),
                    out=np.zeros((4, 4, 4), np.float32))
    with pytest.raises(TypeError, match="weights"):
        SeparableJob(dq=np.zeros((4, 4, 4, 3)), weights=(np.zeros((1, 4)),) * 2, x=(0, 1),
                     y=(0, 1), z=(0, 1), out=np.zeros((1, 1, 1, 3), np.float32),
                     origin=(0, 0, 0))


def test_the_baseline_build_leaves_the_installed_kernels_in_place(tmp_path):
    """Loading the baseline build for a comparison does not replace the module every later
    test of the process imports (a patched kernel was then never called)."""
    base = _baseline_module(tmp_path)
    from volwarp_cli.bspline._warpkernels import scatter_labels

    assert base is not K and sys.modules[K.__name__] is K and scatter_labels is K.scatter_labels
