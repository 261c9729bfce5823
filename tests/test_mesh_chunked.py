"""The blocked isosurface equals the in-memory one bit for bit (after canonical ordering)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from volwarp_cli.errors import VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.surface import chunked
from volwarp_cli.surface.chunked import (
    canonical_mesh,
    edge_ids,
    edge_of,
    isosurface_blocks,
    isosurface_dask,
    isosurface_edge_ids,
    surface_mesh_blocks,
)
from volwarp_cli.surface.isosurface import isosurface
from volwarp_cli.surface.pipeline import Cleanup, surface_mesh

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


def canonical(mesh, ids):
    return canonical_mesh(mesh.vertices, mesh.faces, ids, mesh.normals)


def assert_bitwise(a, b):
    assert a.shape == b.shape and a.dtype == b.dtype
    assert np.array_equal(a.view(np.uint8), b.view(np.uint8))


def assert_same_as_memory(data, geom, level, block_shape, *, normals=False, inside="above",
                          cap=False, blocked=None):
    vol = geom.volume(data)
    ref = isosurface(vol, level, inside=inside, cap=cap, normals=normals)
    ids = isosurface_edge_ids(vol, level, inside=inside, cap=cap)
    assert len(ids) == ref.n_vertices and ref.n_faces > 0
    if blocked is None:
        blocked = isosurface_blocks(data, geom, level, block_shape=block_shape, inside=inside,
                                    cap=cap, normals=normals)
    assert (blocked.n_vertices, blocked.n_faces) == (ref.n_vertices, ref.n_faces)
    rv, rf, rn = canonical(ref, ids)
    # the blocked mesh is already canonical: vertices by edge id, faces sorted
    assert_bitwise(blocked.vertices, rv)
    assert_bitwise(blocked.faces, rf)
    if normals:
        assert_bitwise(blocked.normals, rn)
    else:
        assert blocked.normals is None
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
    mesh = assert_same_as_memory(data, geometry(SHAPE, direction), 0.0, (10, 7, 13),
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
    mesh = assert_same_as_memory(data, geometry(SHAPE, FLIPPED), 0.5, block_shape,
                                 normals=True)
    assert edge_count_closed(mesh.faces)
    from volwarp_cli.surface.topology import connected_components

    assert connected_components(mesh)[0] > 1


def test_inside_below_cap_and_border():
    data = -sphere(SHAPE, 16.0)  # negative inside, cut by the border
    geom = geometry(SHAPE, ROTATED)
    assert_same_as_memory(data, geom, 0.0, (10, 7, 13), inside="below", normals=True)
    capped = assert_same_as_memory(data, geom, 0.0, (10, 7, 13), inside="below", cap=True,
                                   normals=True)
    assert edge_count_closed(capped.faces)


def test_integer_samples_equal_to_the_level():
    # uint8 mask at level 1: every "above" sample equals the level, which is shifted off
    # the samples by a whole-volume decision the blocks must share
    data = (sphere(SHAPE, 9.0) > 0).astype(np.uint8)
    for cap in (False, True):
        mesh = assert_same_as_memory(data, geometry(SHAPE, None), 1.0, (6, 9, 8), cap=cap,
                                     normals=True)
        assert edge_count_closed(mesh.faces)


def test_float_keys_would_not_do_and_ids_round_trip():
    # vertices so close to a sample that float32 (i + t) rounds to the sample itself:
    # the edge still comes back exactly (no position-based key could tell the edges)
    data = sphere(SHAPE, 11.0)
    data[14, 20, 18 + 11] = 1e-7  # x-edge crossings a hair away from this sample
    mesh = assert_same_as_memory(data, geometry(SHAPE, ROTATED), 0.0, (10, 7, 13))
    assert edge_count_closed(mesh.faces)
    shape = (5, 6, 7)
    lower = np.array([[0, 0, 0], [6, 5, 4], [3, 2, 1]])
    ids = edge_ids(lower, np.array([2, 0, 1]), shape)
    back, axis = edge_of(ids, shape)
    assert np.array_equal(back, lower) and axis.tolist() == [2, 0, 1]


def test_dask_chunks_and_threads_same_mesh():
    da = pytest.importorskip("dask.array")
    data = blobs(SHAPE, 5)
    geom = geometry(SHAPE, ROTATED)
    darr = da.from_array(data, chunks=(11, 9, 14))  # do not divide 28 x 40 x 36 cells
    mesh = isosurface_dask(darr, geom, 0.5, normals=True, scheduler="threads", num_workers=2)
    assert_same_as_memory(data, geom, 0.5, None, normals=True, blocked=mesh)
    capped = isosurface_dask(darr, geom, 0.5, block_shape=(7, 30, 8), cap=True,
                             scheduler="sync")
    assert_same_as_memory(data, geom, 0.5, None, cap=True, blocked=capped)
    loop = isosurface_blocks(data, geom, 0.5, block_shape=(9, 9, 9), normals=True, threads=2)
    assert_same_as_memory(data, geom, 0.5, None, normals=True, blocked=loop)


SMALL = ndimage.gaussian_filter(np.random.default_rng(7).normal(size=(9, 12, 10)), 1.2)
SMALL = (SMALL / SMALL.std()).astype(np.float32)
SMALL_GEOM = geometry(SMALL.shape, FLIPPED)
SMALL_REF = {n: canonical(isosurface(SMALL_GEOM.volume(SMALL), 0.3, normals=n),
                          isosurface_edge_ids(SMALL_GEOM.volume(SMALL), 0.3)) for n in (0, 1)}


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.tuples(st.integers(1, 9), st.integers(1, 12), st.integers(1, 10)), st.booleans())
def test_property_any_block_shape(block_shape, normals):
    mesh = isosurface_blocks(SMALL, SMALL_GEOM, 0.3, block_shape=block_shape, normals=normals)
    rv, rf, rn = SMALL_REF[int(normals)]
    assert_bitwise(mesh.vertices, rv)
    assert_bitwise(mesh.faces, rf)
    if normals:
        assert_bitwise(mesh.normals, rn)


def test_surface_mesh_blocks_matches_the_chain_and_refusals():
    data = blobs(SHAPE, 6)
    vol = geometry(SHAPE, ROTATED).volume(data)
    for cleanup in (Cleanup(), Cleanup(largest_component=True)):
        ref, iso = surface_mesh(vol, 0.5, cleanup=cleanup)
        mesh, iso_b = surface_mesh_blocks(vol, None, 0.5, block_shape=(10, 7, 13),
                                          cleanup=cleanup)
        assert iso == iso_b and (mesh.n_vertices, mesh.n_faces) == (ref.n_vertices, ref.n_faces)
        assert np.allclose(np.sort(mesh.vertices, axis=0), np.sort(ref.vertices, axis=0),
                           rtol=0, atol=0)
    _, iso = surface_mesh_blocks(vol, None, None, block_shape=(10, 7, 13))
    assert iso == surface_mesh(vol)[1]
    with pytest.raises(VolwarpError, match="outside the data range"):
        surface_mesh_blocks(vol, None, 99.0)
    bad = data.copy()
    bad[3, 3, 3] = np.nan
    with pytest.raises(VolwarpError, match="NaN"):
        surface_mesh_blocks(bad, vol, 0.5)
    with pytest.raises(VolwarpError, match="NaN"):
        isosurface_blocks(bad, vol, 0.5)
    with pytest.raises(VolwarpError, match="inside must be"):
        isosurface_blocks(data, vol, 0.5, inside="out")
    assert isosurface_blocks(data, vol, 50.0).is_empty


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
    assert seen and set(seen) == {1}


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
