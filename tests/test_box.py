"""The region type's algebra (hypothesis) and the grid geometry against SimpleITK."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.box import Box
from volwarp_cli.errors import VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.volume import Volume

coord = st.integers(-20, 20)


@st.composite
def boxes(draw, lo=-20, hi=20, max_side=12):
    a = [draw(st.integers(lo, hi)) for _ in range(3)]
    n = [draw(st.integers(0, max_side)) for _ in range(3)]
    return Box(a, [v + k for v, k in zip(a, n, strict=True)])


def voxels(box: Box) -> set:
    """The box's voxels as a set of (z, y, x) indices (the reference the algebra is
    checked against)."""
    return {(z, y, x) for z in range(box.lo[0], box.hi[0]) for y in range(box.lo[1], box.hi[1])
            for x in range(box.lo[2], box.hi[2])}


# -- validation and sizes -------------------------------------------------------------
def test_validation():
    with pytest.raises(ValueError, match="hi >= lo"):
        Box((0, 0, 0), (1, -1, 1))
    with pytest.raises(ValueError, match="3 values"):
        Box((0, 0), (1, 1))
    with pytest.raises(ValueError, match="below index 0"):
        _ = Box((-1, 0, 0), (2, 2, 2)).slices
    b = Box(np.array([1, 2, 3]), (4, 5, 6))  # numpy ints become ints
    assert b.lo == (1, 2, 3) and all(type(v) is int for v in b.lo)
    assert b.shape == (3, 3, 3) and b.size == 27 and not b.empty
    assert Box((1, 1, 1), (1, 5, 5)).empty
    assert Box.from_shape((4, 5, 6)) == Box((0, 0, 0), (4, 5, 6))
    assert hash(b) == hash(Box((1, 2, 3), (4, 5, 6)))


@given(boxes())
def test_shape_size_empty_match_the_voxels(b):
    assert b.size == len(voxels(b)) == int(np.prod(b.shape))
    assert b.empty == (len(voxels(b)) == 0)


# -- intersection -----------------------------------------------------------------------
@given(boxes(), boxes(), boxes())
def test_intersection_algebra(a, b, c):
    ab = a.intersect(b)
    assert voxels(ab) == voxels(a) & voxels(b)
    assert ab == b.intersect(a)  # commutative
    assert ab.intersect(c) == a.intersect(b.intersect(c))  # associative
    assert a.intersect(a) == a  # idempotent
    assert a.contains(ab) and b.contains(ab)  # inside both


@given(boxes(), boxes())
def test_union_hull_is_the_smallest_box_holding_both(a, b):
    h = a.union_hull(b)
    assert h.contains(a) and h.contains(b)
    assert h == b.union_hull(a)
    pts = voxels(a) | voxels(b)
    if pts:
        arr = np.array(sorted(pts))
        assert h == Box(arr.min(axis=0), arr.max(axis=0) + 1)
    else:
        assert h.empty


@given(boxes(), boxes())
def test_contains(a, b):
    assert a.contains(b) == (voxels(b) <= voxels(a))
    for p in list(voxels(a))[:5]:
        assert a.contains(p)
    assert not a.contains(a.hi)


# -- grow, shift ------------------------------------------------------------------------
@given(boxes(lo=0, hi=10), st.integers(0, 5), st.tuples(*[st.integers(-2, 4)] * 3))
def test_grow_and_clamp(b, n, per_axis):
    whole = Box.from_shape((12, 14, 16))
    b = b.intersect(whole)
    g = b.grow(n)
    assert g.shape == tuple(s + 2 * n for s in b.shape)
    # growing then intersecting with the whole is growing within it
    assert b.grow(n, within=whole) == g.intersect(whole)
    assert whole.contains(b.grow(n, within=whole))
    if not b.empty:
        assert b.grow(n, within=whole).contains(b)
        assert g.grow(-n) == b
    shrink_ok = all(s + 2 * k >= 0 for s, k in zip(b.shape, per_axis, strict=True))
    if shrink_ok:
        assert b.grow(per_axis).shape == tuple(s + 2 * k for s, k in
                                               zip(b.shape, per_axis, strict=True))
    else:
        with pytest.raises(ValueError):
            b.grow(per_axis)


@given(boxes(), st.tuples(coord, coord, coord))
def test_shift_moves_every_voxel(b, d):
    s = b.shift(d)
    assert voxels(s) == {tuple(p + k for p, k in zip(v, d, strict=True)) for v in voxels(b)}
    assert s.shift(tuple(-k for k in d)) == b
    assert s.relative_to(s).lo == (0, 0, 0)


# -- tilings ----------------------------------------------------------------------------
@given(boxes(max_side=9), st.integers(0, 2), st.integers(1, 12))
def test_split_tiles_the_box(b, axis, parts):
    pieces = b.split(axis, parts)
    assert len(pieces) == parts
    seen = [voxels(p) for p in pieces]
    assert set().union(*seen) == voxels(b)
    assert sum(len(v) for v in seen) == len(voxels(b))  # no overlap
    sizes = [p.shape[axis] for p in pieces]
    assert max(sizes) - min(sizes) <= 1
    assert all(p.hi[axis] == q.lo[axis] for p, q in zip(pieces[:-1], pieces[1:], strict=True))


@given(boxes(max_side=9), st.tuples(*[st.integers(1, 5)] * 3))
def test_blocks_tile_the_box_in_c_order(b, block):
    tiles = b.blocks(block)
    seen = [voxels(t) for t in tiles]
    assert set().union(*seen) == voxels(b)
    assert sum(len(v) for v in seen) == len(voxels(b))  # no overlap
    assert all(not t.empty and all(s <= k for s, k in zip(t.shape, block, strict=True))
               for t in tiles)
    assert [t.lo for t in tiles] == sorted(t.lo for t in tiles)  # C order: x fastest


def test_blocks_and_split_errors():
    b = Box.from_shape((4, 4, 4))
    with pytest.raises(ValueError):
        b.blocks((0, 2, 2))
    with pytest.raises(ValueError):
        b.split(3, 2)
    with pytest.raises(ValueError):
        b.split(0, 0)
    assert Box((1, 1, 1), (1, 2, 2)).blocks((2, 2, 2)) == []


# -- numpy and (x, y, z) ------------------------------------------------------------------
@settings(max_examples=50)
@given(boxes(lo=0, hi=8, max_side=6))
def test_slices_round_trip_with_numpy(b):
    shape = (14, 15, 16)
    data = np.arange(np.prod(shape)).reshape(shape)
    block = data[b.slices]
    whole = Box.from_shape(shape)
    assert block.shape == b.intersect(whole).shape
    # every element of the block is the voxel the box names
    idx = np.unravel_index(block.ravel(), shape)
    assert set(zip(*(i.tolist() for i in idx), strict=True)) == voxels(b.intersect(whole))
    # writing through the slices touches exactly the box
    mask = np.zeros(shape, bool)
    mask[b.slices] = True
    assert int(mask.sum()) == b.intersect(whole).size


@given(boxes())
def test_xyz_round_trip(b):
    lo, hi = b.xyz()
    assert lo == b.lo[::-1] and hi == b.hi[::-1]
    assert Box.from_xyz(lo, hi) == b
    assert Box.from_xyz(*Box.from_xyz(b.lo, b.hi).xyz()) == Box.from_xyz(b.lo, b.hi)


# -- geometry ---------------------------------------------------------------------------
def _rotation(ax, ay, az, mirror=False):
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    r = rz @ ry @ rx
    return r @ np.diag([1, 1, -1]) if mirror else r


GEOM = Geometry((7, 9, 11), spacing=(0.7, 1.3, 2.1), origin=(-12.5, 40.25, 3.0),
                direction=_rotation(0.3, -0.5, 1.1, mirror=True))


def _sitk_image(g: Geometry):
    import SimpleITK as sitk

    nz, ny, nx = g.shape
    image = sitk.Image(nx, ny, nz, sitk.sitkFloat32)
    image.SetSpacing(g.spacing)
    image.SetOrigin(g.origin)
    image.SetDirection(tuple(np.asarray(g.direction).ravel()))  # row-major, columns = axes
    return image


def test_geometry_points_match_simpleitk_and_volume():
    image = _sitk_image(GEOM)
    vol = GEOM.volume(np.zeros(GEOM.shape, np.float32))
    assert Geometry.of(vol) == GEOM
    for ijk in [(0, 0, 0), (10, 8, 6), (3, 7, 2), (2.5, -1.25, 4.75)]:
        ref = image.TransformContinuousIndexToPhysicalPoint([float(v) for v in ijk])
        assert np.allclose(GEOM.index_to_world(ijk), ref, atol=1e-12)
        assert np.allclose(vol.index_to_world(ijk), ref, atol=1e-12)
        assert np.allclose(GEOM.world_to_index(ref), ijk, atol=1e-12)
    pts = np.random.default_rng(0).normal(size=(20, 3)) * 10
    assert np.allclose(GEOM.index_to_world(GEOM.world_to_index(pts)), pts)
    lo, hi = GEOM.bounds_world()
    vlo, vhi = vol.world_bounds()
    assert np.allclose(lo, vlo) and np.allclose(hi, vhi)
    blo, bhi = GEOM.bounds_world(voxel_boxes=True)
    assert np.all(blo < lo) and np.all(bhi > hi)


@pytest.mark.parametrize("box", [Box((0, 0, 0), (7, 9, 11)), Box((2, 3, 4), (6, 8, 10)),
                                 Box((6, 8, 10), (7, 9, 11)), Box((1, 0, 5), (2, 9, 6))])
def test_sub_matches_simpleitk_region_of_interest(box):
    import SimpleITK as sitk

    image = _sitk_image(GEOM)
    (x0, y0, z0), (x1, y1, z1) = box.xyz()
    sliced = image[x0:x1, y0:y1, z0:z1]
    roi = sitk.RegionOfInterest(image, size=[x1 - x0, y1 - y0, z1 - z0], index=[x0, y0, z0])
    sub = GEOM.sub(box)
    assert sub.shape == box.shape and sub.shape_xyz == sliced.GetSize() == roi.GetSize()
    assert sub.spacing == GEOM.spacing and sub.direction == GEOM.direction
    for ref in (sliced, roi):
        assert np.allclose(sub.origin, ref.GetOrigin(), atol=1e-12)
        assert np.allclose(np.asarray(sub.direction).ravel(), ref.GetDirection())
        for ijk in [(0, 0, 0), (x1 - x0 - 1, y1 - y0 - 1, z1 - z0 - 1), (0, y1 - y0 - 1, 0)]:
            p = ref.TransformIndexToPhysicalPoint([int(v) for v in ijk])
            assert np.allclose(sub.index_to_world(ijk), p, atol=1e-12)
            # the block's voxel is the whole's voxel lo + ijk
            whole = np.add(ijk, (x0, y0, z0))
            assert np.allclose(GEOM.index_to_world(whole), p, atol=1e-12)
    # a halo beyond the grid continues its lattice
    assert np.allclose(GEOM.sub(box.grow(2)).index_to_world((2, 2, 2)), sub.origin)


def test_geometry_validation_and_xyz():
    with pytest.raises(VolwarpError, match="positive"):
        Geometry((2, 2, 2), spacing=(1, 0, 1))
    with pytest.raises(VolwarpError, match="singular"):
        Geometry((2, 2, 2), direction=np.zeros((3, 3)))
    with pytest.raises(VolwarpError, match="3 non-negative"):
        Geometry((2, 2))
    with pytest.raises(VolwarpError, match="do not fit"):
        GEOM.volume(np.zeros((2, 2, 2)))
    g = Geometry.from_xyz((11, 9, 7), spacing=2.0)
    assert g.shape == (7, 9, 11) and g.shape_xyz == (11, 9, 7) and g.spacing == (2.0, 2.0, 2.0)
    assert GEOM.spacing_zyx == (2.1, 1.3, 0.7)
    assert g.box == Box.from_shape((7, 9, 11))
    vol = Volume(np.zeros((3, 4, 5)), spacing=(1, 2, 3), origin=(4, 5, 6))
    assert Geometry.of(vol).shape == (3, 4, 5)
