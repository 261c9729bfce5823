"""The isosurface by blocks is the whole volume's, bit for bit and in its order.

The whole volume is the one-block case (:func:`volwarp_cli.surface.isosurface.isosurface`);
any blocks weld to the same arrays (vertices, faces, normals), and ``volwarp mesh``
writes the same PLY bytes in memory and by blocks, for every option that runs by
blocks (clean-ups, labels, a named scheduler).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from volwarp_cli.box import Box
from volwarp_cli.errors import VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import write_volume
from volwarp_cli.regions import mesh_cells
from volwarp_cli.surface import chunked
from volwarp_cli.surface.chunked import (
    MeshPart,
    edge_ids,
    edge_of,
    isosurface_blocks,
    weld,
)
from volwarp_cli.surface.isosurface import crossing_edges, isosurface
from volwarp_cli.volume import Volume

_C, _S = np.cos(0.7), np.sin(0.7)
ROTATED = [[_C, -_S, 0.0], [_S, _C, 0.0], [0.0, 0.0, 1.0]]
FLIPPED = [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]  # det < 0, axes swapped
SHAPE = (29, 41, 37)  # (z, y, x): odd sizes


def sphere(shape, radius):
    k, j, i = np.indices(shape, dtype=np.float64)
    c = [(n - 1) / 2 for n in shape]
    return (radius - np.sqrt((k - c[0]) ** 2 + (j - c[1]) ** 2 + (i - c[2]) ** 2)).astype(
        np.float32)


def blobs(shape, seed):
    """Smooth random blobs, several components, none touching the border at level 0.5."""
    rng = np.random.default_rng(seed)
    f = ndimage.gaussian_filter(rng.normal(size=shape), 2.5)
    f = (f - f.mean()) / f.std()
    border = np.zeros(shape, bool)
    border[2:-2, 2:-2, 2:-2] = True
    return np.where(border, f, -1.0).astype(np.float32)


def geometry(shape, direction):
    return Geometry(shape, spacing=(0.8, 1.1, 1.7), origin=(-4.0, 12.5, 3.25),
                    direction=np.eye(3) if direction is None else direction)


def assert_bitwise(a, b):
    assert a.shape == b.shape and a.dtype == b.dtype
    assert np.array_equal(a.view(np.uint8), b.view(np.uint8))


def assert_same_as_whole(data, geom, level, block_shape, *, normals=False, inside="above",
                         cap=False, threads=1):
    """Blocks of ``block_shape`` give the whole volume's arrays, in its order."""
    ref = isosurface(geom.volume(data), level, inside=inside, cap=cap, normals=normals)
    assert ref.n_faces > 0
    blocked = isosurface_blocks(data, geom, level, block_shape=block_shape, inside=inside,
                                cap=cap, normals=normals, threads=threads)
    assert_bitwise(blocked.vertices, ref.vertices)
    assert_bitwise(blocked.faces, ref.faces)
    if normals:
        assert_bitwise(blocked.normals, ref.normals)
    else:
        assert blocked.normals is None and ref.normals is None
    return blocked


def edge_count_closed(faces) -> bool:
    """Every undirected edge in exactly two faces, once in each direction (oriented)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed, counts = np.unique(e, axis=0, return_counts=True)
    if np.any(counts != 1):
        return False
    undirected, ucounts = np.unique(np.sort(e, axis=1), axis=0, return_counts=True)
    return bool(np.all(ucounts == 2))


@pytest.mark.parametrize("direction", [None, ROTATED, FLIPPED])
@pytest.mark.parametrize("normals", [False, True])
def test_sphere_bit_for_bit_and_closed(direction, normals):
    data = sphere(SHAPE, 11.3)
    mesh = assert_same_as_whole(data, geometry(SHAPE, direction), 0.0, (10, 7, 13),
                                normals=normals)
    assert edge_count_closed(mesh.faces)
    # outward: face normals point away from the centre
    geom = geometry(SHAPE, direction)
    centre = geom.index_to_world([(n - 1) / 2 for n in reversed(SHAPE)])
    fn = mesh.face_normals()
    cent = mesh.vertices[mesh.faces].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", fn, cent - centre) > 0)


@pytest.mark.parametrize("seed,block_shape", [(1, (10, 7, 13)), (2, (5, 11, 3)),
                                              (3, (28, 40, 36)), (4, (1, 40, 9))])
def test_blobs_several_components(seed, block_shape):
    data = blobs(SHAPE, seed)
    mesh = assert_same_as_whole(data, geometry(SHAPE, FLIPPED), 0.5, block_shape,
                                normals=True)
    assert edge_count_closed(mesh.faces)
    from volwarp_cli.surface.topology import connected_components

    assert connected_components(mesh)[0] > 1


def test_inside_below_cap_and_border():
    data = -sphere(SHAPE, 16.0)  # negative inside, cut by the border
    geom = geometry(SHAPE, ROTATED)
    assert_same_as_whole(data, geom, 0.0, (10, 7, 13), inside="below", normals=True)
    capped = assert_same_as_whole(data, geom, 0.0, (10, 7, 13), inside="below", cap=True,
                                  normals=True)
    assert edge_count_closed(capped.faces)


def test_integer_samples_equal_to_the_level():
    # uint8 mask at level 1: every "above" sample equals the level, which is shifted off
    # the samples by a whole-volume decision the blocks must share
    data = (sphere(SHAPE, 9.0) > 0).astype(np.uint8)
    for cap in (False, True):
        mesh = assert_same_as_whole(data, geometry(SHAPE, None), 1.0, (6, 9, 8), cap=cap,
                                    normals=True)
        assert edge_count_closed(mesh.faces)
        # the shifted level keeps every vertex off the samples: no zero-area triangle
        assert mesh.n_vertices == len(np.unique(mesh.vertices, axis=0))


def test_whole_volume_order_is_flying_edges_order_of_edges_and_cells():
    """What the weld rests on: VTK numbers the whole volume's vertices in edge-id order
    and makes its triangles cell by cell; so does every block (a box of rows)."""
    data = blobs(SHAPE, 8)
    from volwarp_cli.surface.isosurface import _flying_edges

    for box in (Box.from_shape(SHAPE), Box((3, 5, 7), (20, 33, 30))):
        part = data[box.slices]
        points, faces, _, _ = _flying_edges(part, 0.5, False)
        lower, axis = crossing_edges(part, 0.5)
        ids = edge_ids(lower, axis, part.shape)
        assert len(ids) == len(points) > 1000 and np.all(np.diff(ids) > 0)
        cell = lower[faces].min(axis=1)
        key = (cell[:, 2] * part.shape[1] + cell[:, 1]) * part.shape[2] + cell[:, 0]
        assert np.all(np.diff(key) >= 0)


def test_float_keys_would_not_do_and_ids_round_trip():
    # vertices so close to a sample that float32 (i + t) rounds to the sample itself:
    # the edge still comes back exactly (no position-based key could tell the edges)
    data = sphere(SHAPE, 11.0)
    data[14, 20, 18 + 11] = 1e-7  # x-edge crossings a hair away from this sample
    mesh = assert_same_as_whole(data, geometry(SHAPE, ROTATED), 0.0, (10, 7, 13))
    assert edge_count_closed(mesh.faces)
    shape = (5, 6, 7)
    lower = np.array([[0, 0, 0], [6, 5, 4], [3, 2, 1]])
    ids = edge_ids(lower, np.array([2, 0, 1]), shape)
    back, axis = edge_of(ids, shape)
    assert np.array_equal(back, lower) and axis.tolist() == [2, 0, 1]
    # ids sort by row (k, j), then axis, then i
    assert edge_ids(np.array([[6, 0, 0], [0, 0, 0]]), np.array([0, 1]), shape).tolist() == [
        6, 7]


def test_weld_refuses_blocks_that_disagree_on_a_shared_vertex():
    one = MeshPart(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32), None,
                   np.array([1, 2, 3]), np.array([0]))
    other = MeshPart(np.ones((3, 3), np.float32), np.array([[0, 1, 2]], np.int32), None,
                     np.array([3, 4, 5]), np.array([1]))
    with pytest.raises(VolwarpError, match="different vertices"):
        weld([one, other])
    other.points[0] = 0.0  # now they agree on edge 3: welded to 5 vertices, faces by cell
    welded = weld([other, one])
    assert len(welded.points) == 5
    assert welded.faces.tolist() == [[0, 1, 2], [2, 3, 4]]


def test_threads_and_blocks_same_mesh():
    data = blobs(SHAPE, 5)
    geom = geometry(SHAPE, ROTATED)
    from volwarp_cli import parallel

    with parallel.use_threads(1):
        one = isosurface(geom.volume(data), 0.5)
    with parallel.use_threads(2):
        two = isosurface(geom.volume(data), 0.5)
    for a, b in ((one.vertices, two.vertices), (one.faces, two.faces),
                 (one.normals, two.normals)):
        assert_bitwise(a, b)
    assert_same_as_whole(data, geom, 0.5, (9, 9, 9), normals=True, threads=2)
    assert_same_as_whole(data, geom, 0.5, (7, 30, 8), cap=True, threads=2)


SMALL = ndimage.gaussian_filter(np.random.default_rng(7).normal(size=(9, 12, 10)), 1.2)
SMALL = (SMALL / SMALL.std()).astype(np.float32)
SMALL_GEOM = geometry(SMALL.shape, FLIPPED)
SMALL_REF = {n: isosurface(SMALL_GEOM.volume(SMALL), 0.3, normals=bool(n)) for n in (0, 1)}


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.tuples(st.integers(1, 9), st.integers(1, 12), st.integers(1, 10)), st.booleans())
def test_property_any_block_shape(block_shape, normals):
    mesh = isosurface_blocks(SMALL, SMALL_GEOM, 0.3, block_shape=block_shape, normals=normals)
    ref = SMALL_REF[int(normals)]
    assert_bitwise(mesh.vertices, ref.vertices)
    assert_bitwise(mesh.faces, ref.faces)
    if normals:
        assert_bitwise(mesh.normals, ref.normals)


def test_refusals():
    data = blobs(SHAPE, 6)
    vol = geometry(SHAPE, ROTATED).volume(data)
    bad = data.copy()
    bad[3, 3, 3] = np.nan
    with pytest.raises(VolwarpError, match="NaN"):
        isosurface_blocks(bad, vol, 0.5, block_shape=(10, 7, 13))
    with pytest.raises(VolwarpError, match="inside must be"):
        isosurface_blocks(data, vol, 0.5, inside="out")
    assert isosurface_blocks(data, vol, 50.0, block_shape=(10, 7, 13)).is_empty


def test_in_memory_and_loop_paths_do_not_import_dask():
    code = ("import sys, numpy as np\n"
            "from volwarp_cli.volume import Volume\n"
            "from volwarp_cli.surface.isosurface import isosurface\n"
            "from volwarp_cli.surface.chunked import isosurface_blocks\n"
            "d = np.random.default_rng(0).normal(size=(8, 9, 10)).astype(np.float32)\n"
            "isosurface(Volume(d), 0.1)\n"
            "isosurface_blocks(d, Volume(d), 0.1, block_shape=4)\n"
            "assert 'dask' not in sys.modules, 'dask imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_blocks_run_vtk_on_one_thread(monkeypatch):
    seen = []
    real = chunked._flying_edges

    def spy(*args, **kwargs):
        from volwarp_cli import parallel

        seen.append(parallel.threads())
        return real(*args, **kwargs)

    monkeypatch.setattr(chunked, "_flying_edges", spy)
    isosurface_blocks(SMALL, SMALL_GEOM, 0.3, block_shape=5, threads=2)
    assert len(seen) > 1 and set(seen) == {1}


def _numpy_stats(samples, dtype, iso):
    """The block statistics by the plain numpy formulas: the reference of Stats.of."""
    a = np.asarray(samples).astype(dtype, copy=False)
    lo, hi = float(np.min(a)), float(np.max(a))
    if np.isnan(lo) or np.isnan(hi):
        return (True,)
    if iso is None:
        return (lo, hi)
    below = a[a < iso]
    return (lo, hi, bool(np.any(a == iso)), float(below.max()) if below.size else None)


@settings(max_examples=150, deadline=None)
@given(dtype=st.sampled_from(["u1", "i2", ">i2", "i4", "i8", "f2", "f4", "f8", "?"]),
       seed=st.integers(0, 2**31), iso=st.sampled_from([None, 0.5, 3.0, 3, 0.1, -2.0, 1e30]),
       nan=st.booleans(), cap=st.booleans())
def test_block_stats_equal_numpys(dtype, seed, iso, nan, cap):
    """Stats.of gives the plain formulas' range, hit and largest sample below the level, in
    the type flying edges runs on (float32 compares a level rounded to float32), on strided
    blocks, with NaNs found anywhere."""
    from volwarp_cli.surface.chunked import Stats
    from volwarp_cli.surface.isosurface import work_dtype

    rng = np.random.default_rng(seed)
    a = rng.integers(-5, 8, size=(3, 4, 5))
    a = (a > 1) if dtype == "?" else a.astype(dtype)
    if a.dtype.kind == "f":
        a = (a + rng.choice([0.0, 0.1, 0.5], size=a.shape)).astype(dtype)
        if nan:
            a[tuple(rng.integers(0, n) for n in a.shape)] = np.nan
    a = a[:, 1:, ::2]
    work = work_dtype(a.dtype, cap)
    s = Stats.of(a, work, iso)
    got = (True,) if s.nan else ((s.lo, s.hi) if iso is None
                                 else (s.lo, s.hi, s.hit, s.below_max))
    assert got == _numpy_stats(a, work, iso)


# -- the command: the same PLY bytes ------------------------------------------------------
@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A rotated float field, an integer mask (its level on the samples) and a label map."""
    folder = tmp_path_factory.mktemp("mesh-blocks")
    geom = dict(spacing=(0.8, 1.1, 1.7), origin=(-4.0, 12.5, 3.25), direction=ROTATED)
    write_volume(Volume(blobs(SHAPE, 11) + 0.4 * sphere(SHAPE, 12.0) / 12.0, **geom),
                 folder / "field.nrrd")
    write_volume(Volume((sphere(SHAPE, 9.0) > 0).astype(np.uint8) * 3, **geom),
                 folder / "mask.nrrd")
    z, y, x = np.indices(SHAPE)
    lab = np.zeros(SHAPE, np.int16)
    lab[(x - 12) ** 2 + (y - 14) ** 2 + (z - 15) ** 2 <= 64] = 7
    lab[5:25, 4:24, 26:] = 300  # on the border: capped
    lab[3:9, 30:38, 4:11] = -2
    write_volume(Volume(lab, **geom), folder / "seg.nrrd")
    for name, (dtype, _) in WIDE_INTEGERS.items():
        write_volume(Volume(wide_ball(dtype), **geom), folder / name)
    return folder


#: 32-bit integer volumes and their levels: VTK's s1 - s0 wrapped in these types (uint32
#: on every falling edge; int32 where neighbours differ by more than 2^31)
WIDE_INTEGERS = {"u32.nrrd": ("uint32", 100.5), "i32.nrrd": ("int32", 0.5)}


def wide_ball(dtype):
    """A ball on :data:`SHAPE`: uint32 a Gaussian from 0 to 1000, int32 a step of 4.2e9."""
    k, j, i = np.indices(SHAPE, dtype=np.float64)
    r = np.sqrt((i - 17.3) ** 2 + (j - 19.6) ** 2 + (k - 13.2) ** 2)
    f = 1000 * np.exp(-r * r / 60) if dtype == "uint32" else 2.1e9 * np.tanh(3 * (9 - r))
    return np.round(f).astype(dtype)


CASES = {
    "plain": ("field.nrrd", ["--iso", "0.2"]),
    "default-level": ("field.nrrd", []),
    "cap-below": ("field.nrrd", ["--iso", "0.2", "--inside", "below", "--cap"]),
    "largest-component": ("field.nrrd", ["--iso", "0.2", "--largest-component"]),
    "smooth": ("field.nrrd", ["--iso", "0.2", "--smooth", "8"]),
    "decimate": ("field.nrrd", ["--iso", "0.2", "--decimate", "0.6"]),
    "integer-level": ("mask.nrrd", ["--iso", "3", "--cap"]),
    "label": ("seg.nrrd", ["--label", "300"]),
}


def _mesh_blocks_spied(monkeypatch):
    """The blocks flying edges ran on: whether each was the whole volume.

    (Not counting the kernels' warm-up on a small ball, which the budget's
    decision may run first so that it counts what they load.)
    """
    from volwarp_cli.surface.run import _WARM_SIZE

    seen = []
    real = chunked.mesh_block

    def spy(raw, region, cells, plan):
        if tuple(plan.shape) != (_WARM_SIZE,) * 3:
            seen.append(cells == mesh_cells(plan.shape))
        return real(raw, region, cells, plan)

    monkeypatch.setattr(chunked, "mesh_block", spy)
    return seen


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("threads", [1, 2])
def test_ply_by_blocks_is_the_in_memory_file(run, inputs, tmp_path, monkeypatch, name,
                                             threads):
    source, args = CASES[name]
    mem, blk = tmp_path / "m.ply", tmp_path / "b.ply"
    seen = _mesh_blocks_spied(monkeypatch)
    res = run("mesh", inputs / source, "-o", mem, *args, "--threads", threads)
    assert res.code == 0, res.stderr
    assert seen == [True]  # in memory: one block, the whole volume
    seen.clear()
    res = run("mesh", inputs / source, "-o", blk, *args, "--threads", threads, "--chunked",
              "--block", "7,9,5")
    assert res.code == 0, res.stderr
    assert len(seen) >= 8 and not any(seen)  # by blocks: many, none the whole
    data = mem.read_bytes()
    assert b"element face 0\n" not in data and len(data) > 20000
    assert blk.read_bytes() == data


@pytest.mark.parametrize("scheduler", [None, "processes"])
def test_label_plys_by_blocks_are_the_in_memory_files(run, inputs, tmp_path, scheduler):
    extra = ["--chunked", "--block", "8"] + (["--scheduler", scheduler] if scheduler else [])
    res = run("mesh", inputs / "seg.nrrd", "--labels", "-o", tmp_path / "m_{label}.ply")
    assert res.code == 0, res.stderr
    res = run("mesh", inputs / "seg.nrrd", "--labels", "-o", tmp_path / "b_{label}.ply", *extra)
    assert res.code == 0, res.stderr
    names = sorted(p.name for p in tmp_path.glob("*.ply"))
    assert names == sorted(f"{w}_{v}.ply" for w in "bm" for v in (-2, 7, 300))
    for label in (-2, 7, 300):
        data = (tmp_path / f"m_{label}.ply").read_bytes()
        assert f"volwarp_label={label}\n".encode() in data
        assert (tmp_path / f"b_{label}.ply").read_bytes() == data
    # one label's file says which too (it said iso=0.5 only: any label's, or the union's)
    res = run("mesh", inputs / "seg.nrrd", "--label", "-2", "-o", tmp_path / "one.ply")
    assert res.code == 0, res.stderr
    one = (tmp_path / "one.ply").read_bytes()
    assert b"volwarp_label=-2\n" in one and b"volwarp_iso" not in one


@pytest.mark.parametrize("source", list(WIDE_INTEGERS))
def test_32_bit_integers_by_blocks_are_the_in_memory_file_and_skimages(run, inputs, tmp_path,
                                                                       source):
    """The float64 working copy of 32-bit integers: the same PLY bytes in memory, by blocks
    on threads and on processes, and scikit-image's area and volume (the wrapped
    difference made them 6% off)."""
    import json

    from skimage.measure import marching_cubes

    dtype, level = WIDE_INTEGERS[source]
    outs = {"m": [], "t": ["--chunked", "--block", "7,9,5", "--threads", "2"],
            "p": ["--chunked", "--block", "9", "--scheduler", "processes"]}
    stats = {}
    for key, extra in outs.items():
        res = run("mesh", inputs / source, "--iso", level, "-o", tmp_path / f"{key}.ply",
                  "--json", *extra)
        assert res.code == 0, res.stderr
        stats[key] = json.loads(res.stdout)
    data = (tmp_path / "m.ply").read_bytes()
    assert all((tmp_path / f"{key}.ply").read_bytes() == data for key in "tp")
    spacing = (1.7, 1.1, 0.8)  # the inputs' (z, y, x); a rotation keeps areas and volumes
    verts, faces, _, _ = marching_cubes(wide_ball(dtype).astype(np.float64),
                                        level, spacing=spacing)
    tri = verts[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    inside = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    assert stats["m"]["closed"] and stats["m"]["vertices"] == len(verts)
    assert stats["m"]["area"] == pytest.approx(area.sum() / 2, rel=1e-6)
    assert stats["m"]["volume"] == pytest.approx(abs(inside.sum()) / 6, rel=1e-6)


def test_the_whole_not_fitting_runs_by_blocks_by_itself(run, inputs, tmp_path, monkeypatch):
    """Without --chunked the choice is the memory's arithmetic, before any sample is read:
    a whole that does not fit runs by blocks, and writes the in-memory bytes;
    --no-chunked refuses it instead, and writes nothing."""
    from volwarp_cli.surface.run import MeshOperation

    mem, blk = tmp_path / "m.ply", tmp_path / "b.ply"
    assert run("mesh", inputs / "field.nrrd", "-o", mem, "--iso", "0.2").code == 0
    real = MeshOperation.memory

    def memory(self, box):  # the whole volume needs a petabyte; its blocks what they need
        return 1 << 50 if box == Box.from_shape(self.shape) else real(self, box)

    monkeypatch.setattr(MeshOperation, "memory", memory)
    seen = _mesh_blocks_spied(monkeypatch)
    res = run("mesh", inputs / "field.nrrd", "-o", blk, "--iso", "0.2")
    assert res.code == 0, res.stderr
    assert seen and not any(seen)
    assert blk.read_bytes() == mem.read_bytes()
    refused = tmp_path / "r.ply"
    res = run("mesh", inputs / "field.nrrd", "-o", refused, "--iso", "0.2", "--no-chunked")
    assert res.code == 1 and "needs" in res.stderr and not refused.exists()

