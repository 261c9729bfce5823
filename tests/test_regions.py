"""Each operation's input-region rule against the dependence it claims.

For every rule: the whole computation's output block equals the block computed
from exactly the input region the rule gives; and, where the rule is tight, a
region one voxel smaller on any side gives a different block.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from scipy import ndimage
from scipy.spatial import cKDTree

from volwarp_cli.box import Box
from volwarp_cli.bspline import pushforward
from volwarp_cli.bspline.lattice import Lattice
from volwarp_cli.bspline.pushforward import HeldPlanes
from volwarp_cli.bspline.scene import Scene
from volwarp_cli.distance.exact import signed_edt
from volwarp_cli.distance.field import finish_field
from volwarp_cli.distance.minnorm import minnorm_signed, propagate
from volwarp_cli.distance.subvoxel import subvoxel_signed_distance
from volwarp_cli.geometry import Geometry
from volwarp_cli.regions import (
    distance_band_input,
    distance_pass_input,
    mesh_cells,
    mesh_input,
    sweep_input,
    warp_input,
)
from volwarp_cli.surface.isosurface import isosurface
from volwarp_cli.volume import xyz_to_zyx


def smaller(box: Box) -> list[tuple[int, int, Box]]:
    """``(axis, side, box)``: the box one voxel smaller on each of its six sides."""
    out = []
    for axis in range(3):
        for side in (0, 1):
            lo, hi = list(box.lo), list(box.hi)
            if side == 0:
                lo[axis] += 1
            else:
                hi[axis] -= 1
            out.append((axis, side, Box(lo, hi)))
    return out


def smooth_field(shape, seed, sigma=2.0):
    f = ndimage.gaussian_filter(np.random.default_rng(seed).normal(size=shape), sigma)
    return f / f.std()


# -- mesh -------------------------------------------------------------------------------
_C, _S = np.cos(0.4), np.sin(0.4)
MESH_GEOM = Geometry((20, 22, 24), spacing=(0.9, 1.1, 1.3), origin=(5.0, -3.0, 2.0),
                     direction=[[_C, -_S, 0], [_S, _C, 0], [0, 0, 1]])
MESH_DATA = smooth_field(MESH_GEOM.shape, 3)
MESH_ISO = 0.1234  # equals no sample: the level is not shifted (a whole-volume decision)


def cell_triangles(region: Box, cells: Box, normals: bool):
    """The triangles (T, 3, 3 world) and vertex normals of the isosurface of the samples
    ``region``, computed alone on its own geometry, that lie in ``cells``."""
    vol = MESH_GEOM.sub(region).volume(np.ascontiguousarray(MESH_DATA[region.slices]))
    mesh = isosurface(vol, MESH_ISO, normals=normals)
    tri = mesh.vertices[mesh.faces]
    # a triangle's vertices lie on its cell's edges: its centroid is inside the cell
    ijk = MESH_GEOM.world_to_index(tri.reshape(-1, 3)).reshape(tri.shape)
    cell = np.floor(ijk.mean(axis=1)).astype(int)[:, ::-1]  # (z, y, x)
    keep = np.all((cell >= cells.lo) & (cell < cells.hi), axis=1)
    return tri[keep], None if mesh.normals is None else mesh.normals[mesh.faces][keep]


def same_triangles(a, b, tol=1e-4) -> tuple[bool, bool]:
    """``(same triangles, same normals)``, matching triangles up to a rotation of their
    corners (float32 index points: a block's differ from the whole's in the last bits)."""
    (ta, na), (tb, nb) = a, b
    if len(ta) != len(tb):
        return False, False
    tree = cKDTree(tb.reshape(len(tb), 9))
    used, normals_ok = set(), True
    for i, tri in enumerate(ta):
        for r in range(3):
            d, j = tree.query(np.roll(tri, r, axis=0).ravel())
            if d < tol:
                used.add(int(j))
                if na is not None:
                    normals_ok &= bool(np.allclose(np.roll(na[i], r, axis=0), nb[j], atol=1e-4))
                break
        else:
            return False, False
    return len(used) == len(tb), normals_ok


@pytest.mark.parametrize("normals", [False, True])
@pytest.mark.parametrize("cells", [Box((5, 6, 7), (12, 14, 15)), Box((0, 0, 0), (6, 21, 9)),
                                   Box((13, 15, 16), (19, 21, 23))])
def test_mesh_block_from_its_region(cells, normals):
    shape = MESH_DATA.shape
    ref = cell_triangles(Box.from_shape(shape), cells, normals)
    assert len(ref[0]) > 20
    region = mesh_input(cells, shape, normals=normals)
    assert region == (Box(cells.lo, np.add(cells.hi, 1)).grow(1, within=Box.from_shape(shape))
                      if normals else Box(cells.lo, np.add(cells.hi, 1)))
    assert same_triangles(cell_triangles(region, cells, normals), ref) == (True, True)
    if cells != Box((5, 6, 7), (12, 14, 15)):
        return
    for _axis, _side, less in smaller(region):  # every side matters here
        tris, norms = same_triangles(cell_triangles(less, cells, normals), ref)
        if normals:  # all cells' samples are still there: the triangles, not the normals
            assert tris and not norms
        else:
            assert not tris


def test_mesh_rule_edges():
    shape = (4, 5, 6)
    assert mesh_cells(shape) == Box.from_shape((3, 4, 5))
    assert mesh_input(mesh_cells(shape), shape) == Box.from_shape(shape)
    assert mesh_input(mesh_cells(shape), shape, normals=True) == Box.from_shape(shape)
    assert mesh_input(Box((1, 1, 1), (1, 3, 3)), shape).empty
    with pytest.raises(ValueError, match="outside"):
        mesh_input(Box((0, 0, 0), (4, 1, 1)), shape)  # there are only 3 cells along z


# -- sweep ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sweep_spec(tmp_path_factory):
    from volwarp_cli.io.images import write_image
    from volwarp_cli.spec.loader import load_schema, parse_spec_text, validate
    from volwarp_cli.sweep.model import parse_sweep_spec

    tmp = tmp_path_factory.mktemp("sweep")
    c = (np.arange(64) + 0.5) / 64
    write_image(tmp / "ramp.png", (4 * np.outer(c, 1 - c)).astype(np.float32)[:, :, None])
    body = {"version": 1, "grid": {"origin": [-5, -5, -2.5], "spacing": 0.5, "shape": [20, 20, 10]},
            "fields": {"opacity": 1, "density": {"image": "ramp.png"}},
            "trajectory": [{"arc": {"center": [0.11, -0.07, 0], "radius": 3.1,
                                    "axis": [0, 0, 1]}}],
            "up": [0, 0, 1], "scale": [1.7, 2.3]}
    path = tmp / "spec.yaml"
    path.write_text(yaml.safe_dump(body, sort_keys=False))
    doc = parse_spec_text(path.read_text(), str(path), tmp)
    validate(doc, load_schema("sweep"))
    return parse_sweep_spec(doc)


@pytest.mark.parametrize("method", ["voxelize", "direct"])
def test_sweep_block_needs_only_its_geometry(sweep_spec, method):
    from volwarp_cli.sweep import evaluate

    # dyadic origin and spacing: a block's voxel centres origin + s lo + s i are the
    # whole's origin + s (lo + i) to the last bit
    geom = Geometry.from_xyz((20, 20, 10), spacing=0.5, origin=(-5, -5, -2.5))

    def fields(g):
        return evaluate(sweep_spec, g, method=method)

    whole = fields(geom)
    assert whole["density"].max() > 0.5
    for box in [Box((2, 3, 4), (7, 12, 15)), Box((5, 0, 13), (10, 9, 20)),
                Box((0, 10, 10), (10, 11, 20))]:
        assert sweep_input(box).empty
        block = fields(geom.sub(box))
        assert whole["opacity"][box.slices].sum() > 0
        for name in whole:
            assert np.array_equal(block[name], whole[name][box.slices])


# -- distance ---------------------------------------------------------------------------
DIST_SHAPE = (22, 24, 26)
DIST_SPACING = (1.0, 0.8, 1.25)  # (x, y, z)
DIST_ZYX = xyz_to_zyx(DIST_SPACING)
BAND = 2.7  # not a whole number of voxels on any axis: the halo is tight
OUT = Box((7, 8, 9), (14, 15, 17))

VOXEL_FIELDS = {
    "euclidean": lambda mask: signed_edt(mask, DIST_ZYX),
    "minnorm": lambda mask: minnorm_signed(mask, DIST_ZYX)[0],
}


def banded(field_fn, data, region, out, band=BAND):
    """The clipped field of ``data[region]`` computed alone, at the block ``out``."""
    field = finish_field(field_fn(np.ascontiguousarray(data[region.slices])), max_distance=band)
    return field[out.relative_to(region).slices]


@pytest.mark.parametrize("metric", list(VOXEL_FIELDS))
def test_banded_distance_block_from_its_halo(metric):
    fn = VOXEL_FIELDS[metric]
    whole = Box.from_shape(DIST_SHAPE)
    region = distance_band_input(OUT, DIST_SHAPE, DIST_SPACING, BAND)
    # floor(D / h) voxels per axis: z 2.7 / 1.25, y 2.7 / 0.8, x 2.7 / 1.0
    assert region == OUT.grow((2, 3, 2))
    mask = smooth_field(DIST_SHAPE, 5, 2.5) > 0.8
    assert 0 < mask[region.slices].sum() < region.size
    for out in (OUT, Box((0, 0, 0), (4, 24, 5)), Box((20, 3, 24), (22, 9, 26))):
        reg = distance_band_input(out, DIST_SHAPE, DIST_SPACING, BAND)
        assert np.array_equal(banded(fn, mask, reg, out), banded(fn, mask, whole, out))
    # tight: one site just inside the halo on each side; without it the block differs
    for axis, side, less in smaller(region):
        site = [(a + b) // 2 for a, b in zip(OUT.lo, OUT.hi, strict=True)]
        site[axis] = region.lo[axis] if side == 0 else region.hi[axis] - 1
        lonely = np.zeros(DIST_SHAPE, bool)
        lonely[tuple(site)] = True
        ref = banded(fn, lonely, whole, OUT)
        assert np.array_equal(banded(fn, lonely, region, OUT), ref)
        assert not np.array_equal(banded(fn, lonely, less, OUT), ref), (axis, side)


def _subvoxel_field(v):
    return subvoxel_signed_distance(v, 0.0, spacing_zyx=DIST_ZYX)


SUBVOXEL_SHAPE = (40, 40, 40)
SUBVOXEL_OUT = (Box((16, 15, 17), (24, 25, 23)), Box((0, 30, 0), (6, 40, 12)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_subvoxel_band_is_a_bound(seed):
    values = smooth_field(SUBVOXEL_SHAPE, seed, 3.0).astype(np.float32)
    band = 1.5
    whole = Box.from_shape(SUBVOXEL_SHAPE)
    for out in SUBVOXEL_OUT:
        region = distance_band_input(out, SUBVOXEL_SHAPE, DIST_SPACING, band, surface="subvoxel")
        assert not region.contains(whole)
        ref = banded(_subvoxel_field, values, whole, out, band)
        assert np.abs(ref).min() < 0.5 * band  # the surface passes through the block
        assert np.array_equal(banded(_subvoxel_field, values, region, out, band), ref)
        # the block does depend on samples around it: a one-voxel halo is not enough (on
        # these data 3 voxels are; the rule's bound takes 8 to 12)
        near = out.grow(1, within=whole)
        assert not np.array_equal(banded(_subvoxel_field, values, near, out, band), ref)


@pytest.mark.parametrize("seed", [4, 7, 11])  # the fields where blocks differed (by 0.19,
def test_subvoxel_band_is_exact_at_seed_ties(seed):  # 0.047 and 0.001) before ties went by id
    """Equidistant seeds: the nearest-seed transform's breakpoints round differently in a
    block's lines and the whole's; ties go to the smaller seed id, so a block equals the
    whole there too."""
    values = smooth_field(SUBVOXEL_SHAPE, seed, 3.0).astype(np.float32)
    whole = Box.from_shape(SUBVOXEL_SHAPE)
    for out in SUBVOXEL_OUT:
        region = distance_band_input(out, SUBVOXEL_SHAPE, DIST_SPACING, 1.5, surface="subvoxel")
        assert np.array_equal(banded(_subvoxel_field, values, region, out, 1.5),
                              banded(_subvoxel_field, values, whole, out, 1.5))


def test_distance_rule_edges():
    whole = Box.from_shape(DIST_SHAPE)
    assert distance_band_input(OUT, DIST_SHAPE, DIST_SPACING, None) == whole
    # ties count: D = 3 h (0.3 / 0.1 is 2.9999999999999996 in floats) takes 3 voxels
    assert distance_band_input(OUT, DIST_SHAPE, (0.1, 0.1, 0.1), 0.3) == OUT.grow(3)
    with pytest.raises(ValueError):
        distance_band_input(OUT, DIST_SHAPE, DIST_SPACING, 0.0)
    with pytest.raises(ValueError):
        distance_band_input(OUT, DIST_SHAPE, DIST_SPACING, 1.0, surface="other")
    # the unclipped exact transform's three passes in turn: the whole volume
    box = OUT
    for axis in (2, 1, 0):
        box = distance_pass_input(box, DIST_SHAPE, axis)
    assert box == whole


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_distance_pass_needs_whole_lines(axis):
    shape = DIST_SHAPE
    rng = np.random.default_rng(axis)
    field = np.where(rng.random(shape) < 0.02, rng.random(shape) * 3, np.inf).astype(np.float32)

    def one_pass(f, region):
        f = np.array(f[region.slices])
        propagate(f, DIST_ZYX, axes=(axis,))
        return f[OUT.relative_to(region).slices]

    region = distance_pass_input(OUT, shape, axis)
    assert region.shape[axis] == shape[axis]
    whole = Box.from_shape(shape)
    ref = one_pass(field, whole)
    assert np.array_equal(one_pass(field, region), ref)
    # a site at each end of the block's lines: a line one voxel shorter misses it
    for side in (0, 1):
        lonely = np.full(shape, np.inf, np.float32)
        end = [slice(a, b) for a, b in zip(OUT.lo, OUT.hi, strict=True)]
        end[axis] = 0 if side == 0 else shape[axis] - 1
        lonely[tuple(end)] = 0.0
        less = [b for a, s, b in smaller(region) if a == axis and s == side][0]
        ref = one_pass(lonely, whole)
        assert np.array_equal(one_pass(lonely, region), ref)
        assert not np.array_equal(one_pass(lonely, less), ref)


# -- warp -------------------------------------------------------------------------------
PAD = 2


def warp_setup(oversample, seed=0, shape=(12, 10, 14), lattice=(6, 6, 7)):
    grid = Lattice.create(shape, lattice, oversample)
    rng = np.random.default_rng(seed)
    domain = rng.random(grid.domain_shape[::-1]).astype(np.float32)
    return grid, domain


def warp_block(domain, grid, dq, region: Box, out: Box, method="box"):
    """Target block ``out`` rendered from the domain voxels ``region`` alone (the rest of
    the domain replaced by other values): the accumulators hold only the block's planes
    and a window of its rows and columns, as :meth:`Scene.set_lattice`'s rebuild does.
    Returns (values, weights) of the block."""
    other = np.random.default_rng(99).random(domain.shape).astype(np.float32)
    if not region.empty:
        other[region.slices] = domain[region.slices]
    scene = Scene(other, grid, dq, PAD, method=method, domain_range=(0.0, 1.0))
    (t0z, t0y, t0x), (t1z, t1y, t1x) = out.lo, out.hi
    tx, ty, _ = scene.target_shape
    acc = np.zeros((t1z - t0z, ty, tx, 2), np.int64)
    if not region.empty:
        scene.contribute([dq], region, 1, acc=acc, held=HeldPlanes(t0z, t1z),
                         window=((t0x, t1x), (t0y, t1y)))
    block = np.zeros(acc.shape[:3], np.float32)
    pushforward.finalize(acc, scene.vmax, Box((0, t0y, t0x), (t1z - t0z, t1y, t1x)), block)
    return block[:, t0y:t1y, t0x:t1x], acc[:, t0y:t1y, t0x:t1x, 0]


def whole_warp(domain, grid, dq, method="box"):
    return Scene(domain, grid, dq, PAD, method=method, domain_range=(0.0, 1.0)).compute()


def reaching_planes(domain, grid, dq, out: Box, method="box") -> Box:
    """The bounding box of the domain voxels that put weight into block ``out``, found
    plane by plane along each axis (the dependence itself, without the rule); empty
    when none does."""
    dshape = grid.domain_shape[::-1]
    lo, hi = [], []
    for axis in range(3):
        hit = []
        for g in range(dshape[axis]):
            a, b = [0, 0, 0], list(dshape)
            a[axis], b[axis] = g, g + 1
            if warp_block(domain, grid, dq, Box(a, b), out, method)[1].any():
                hit.append(g)
        if not hit:
            return Box((0, 0, 0), (0, 0, 0))
        lo.append(hit[0])
        hi.append(hit[-1] + 1)
    return Box(lo, hi)


@pytest.mark.parametrize("oversample", [2, 1.5])
def test_warp_rule_is_tight_for_a_translated_lattice(oversample):
    grid, domain = warp_setup(oversample)
    dq = np.zeros(grid.lattice[::-1] + (3,))
    dq[...] = (0.3, -0.4, 0.35)  # input voxels (x, y, z): boxes straddle target cells
    out = Box((4, 5, 6), (9, 10, 12))
    region = warp_input(out, dq, grid, PAD)
    ref = whole_warp(domain, grid, dq)[out.slices]
    assert np.array_equal(warp_block(domain, grid, dq, region, out)[0], ref)
    assert reaching_planes(domain, grid, dq, out) == region  # the dependence, exactly
    for axis, side, less in smaller(region):
        assert not np.array_equal(warp_block(domain, grid, dq, less, out)[0], ref), (axis, side)


@pytest.mark.parametrize("method", ["box", "nearest"])
@pytest.mark.parametrize("oversample", [2, 1.5])
def test_warp_block_from_its_region_with_a_deformed_lattice(oversample, method):
    grid, domain = warp_setup(oversample, seed=1, shape=(20, 18, 22), lattice=(10, 9, 11))
    rng = np.random.default_rng(2)
    dq = np.zeros(grid.lattice[::-1] + (3,))
    dq[4:7, 3:6, 4:7] = rng.normal(scale=0.7, size=(3, 3, 3, 3))  # the other regions still
    dq[5, 4, 5] = (1.5, -1.0, 1.2)
    scene = Scene(domain, grid, dq, PAD, method=method, domain_range=(0.0, 1.0))
    full = scene.compute()
    whole_domain = Box.from_shape(domain.shape)
    target = Box.from_shape(full.shape)
    for out in (Box((8, 7, 9), (14, 12, 15)), Box((2, 2, 2), (6, 6, 6)),
                Box((15, 3, 16), (22, 9, 24)), Box((0, 0, 0), (26, 22, 24)),
                Box((25, 21, 23), (26, 22, 24))):
        assert target.contains(out)
        region = warp_input(out, dq, grid, PAD)
        assert whole_domain.contains(region)
        assert np.array_equal(warp_block(domain, grid, dq, region, out, method)[0],
                              full[out.slices])
        if out.size > 1000:
            continue
        # a bound: the voxels that do reach the block lie inside it (loose by the hull's
        # spread where control points moved), and inside the scene's own z window from
        # one hull of the whole lattice
        assert region.contains(reaching_planes(domain, grid, dq, out, method))
        z0, z1 = scene.reach.domain_z_window(dq, out.lo[0], out.hi[0])
        assert z0 <= region.lo[0] and region.hi[0] <= z1


def test_warp_rule_edges():
    grid, domain = warp_setup(2)
    dq = np.zeros(grid.lattice[::-1] + (3,))
    assert warp_input(Box((3, 3, 3), (3, 5, 5)), dq, grid, PAD).empty
    # a block of the padding around the unmoved model: nothing reaches it
    assert warp_input(Box((0, 0, 0), (1, 14, 16)), dq, grid, PAD).empty
    # unmoved on a subdivision grid: each input voxel is its k^3 domain voxels (+ the
    # float32 slack's neighbours on each side)
    out = Box((5, 5, 5), (8, 9, 10))
    region = warp_input(out, dq, grid, PAD)
    exact = Box(np.multiply(np.subtract(out.lo, PAD), 2), np.multiply(np.subtract(out.hi, PAD), 2))
    assert region.contains(exact) and exact.grow(1).contains(region)
    assert np.array_equal(warp_block(domain, grid, dq, region, out)[0],
                          whole_warp(domain, grid, dq)[out.slices])
