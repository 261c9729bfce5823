"""Isosurfaces against analytic spheres and against scikit-image's marching cubes."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.surface.isosurface import isosurface
from volwarp_cli.surface.stats import enclosed_volume, is_closed, mesh_stats, surface_area
from volwarp_cli.volume import Volume


def sphere_volume(shape_xyz, radius, *, spacing=(1, 1, 1), origin=(0, 0, 0), direction=None,
                  center=None, inside_positive=True, dtype=np.float32) -> Volume:
    """Signed distance to a sphere sampled on a grid: positive inside when asked."""
    vol = Volume(np.zeros(tuple(reversed(shape_xyz)), dtype=dtype), spacing=spacing,
                 origin=origin, direction=np.eye(3) if direction is None else direction)
    k, j, i = np.indices(vol.data.shape)
    world = vol.index_to_world(np.stack([i, j, k], axis=-1).astype(np.float64))
    if center is None:
        lo, hi = vol.world_bounds()
        center = 0.5 * (lo + hi)
    dist = np.linalg.norm(world - np.asarray(center), axis=-1)
    f = radius - dist if inside_positive else dist - radius
    return vol.with_data(f.astype(dtype))


def outward_fraction(mesh, center) -> float:
    d = np.einsum("ij,ij->i", mesh.normals.astype(np.float64), mesh.vertices - center)
    return float(np.mean(d > 0))


def test_sphere_volume_area_closed_outward():
    r = 14.0
    vol = sphere_volume((40, 40, 40), r)
    mesh = isosurface(vol, 0.0)
    stats = mesh_stats(mesh)
    assert abs(stats["volume"] - 4 / 3 * np.pi * r**3) / (4 / 3 * np.pi * r**3) < 0.01
    assert abs(stats["area"] - 4 * np.pi * r**2) / (4 * np.pi * r**2) < 0.02
    assert stats["closed"] is True
    assert stats["components"] == 1
    assert outward_fraction(mesh, np.full(3, 19.5)) == 1.0
    # face normals agree with vertex normals (winding is outward too)
    fn = mesh.face_normals()
    centroids = mesh.vertices[mesh.faces].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", fn, centroids - 19.5) > 0)
    # vertices lie on the sphere (linear interpolation error of a distance field is tiny)
    radii = np.linalg.norm(mesh.vertices - 19.5, axis=1)
    assert np.max(np.abs(radii - r)) < 0.05


def test_anisotropic_spacing_and_origin_world_bbox():
    r = 9.0
    spacing = (0.5, 1.0, 2.0)
    origin = (10.0, -5.0, 3.0)
    # centre on a grid point so the extreme points are exact edge crossings
    center = np.array(origin) + np.array(spacing) * np.array([30, 15, 8])
    vol = sphere_volume((61, 31, 17), r, spacing=spacing, origin=origin, center=center)
    mesh = isosurface(vol, 0.0)
    st = mesh_stats(mesh)
    np.testing.assert_allclose(st["bbox_min"], center - r, atol=1e-4)
    np.testing.assert_allclose(st["bbox_max"], center + r, atol=1e-4)
    assert st["closed"] and st["components"] == 1
    assert abs(st["volume"] - 4 / 3 * np.pi * r**3) / (4 / 3 * np.pi * r**3) < 0.02
    assert outward_fraction(mesh, center) == 1.0


@pytest.mark.parametrize("direction", [
    np.diag([-1.0, 1.0, 1.0]),                                    # mirrored: det < 0
    np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),  # rotation: det > 0
    np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),          # the coronal test scan's
])
def test_direction_applied_and_winding_outward(direction):
    r = 7.0
    vol = sphere_volume((40, 36, 32), r, spacing=(0.5, 0.75, 1.0), origin=(5, 6, 7),
                        direction=direction)
    lo, hi = vol.world_bounds()
    center = 0.5 * (lo + hi)
    mesh = isosurface(vol, 0.0)
    assert enclosed_volume(mesh) > 0
    assert abs(enclosed_volume(mesh) - 4 / 3 * np.pi * r**3) / (4 / 3 * np.pi * r**3) < 0.03
    assert outward_fraction(mesh, center) == 1.0
    assert is_closed(mesh)
    radii = np.linalg.norm(mesh.vertices - center, axis=1)
    assert np.max(np.abs(radii - r)) < 0.05


@pytest.mark.parametrize("spacing", [1.0, 0.8])
@pytest.mark.parametrize("direction", [-np.eye(3), np.diag([-1.0, -1.0, 1.0])])
def test_normals_are_outward_in_a_frame_turned_about_with_isotropic_spacing(direction, spacing):
    """A NIfTI of RAS diag(1, 1, -1) is LPS direction -I: with isotropic spacing every
    normal pointed inward (the shortcut for a scaled identity took -I for one), while the
    winding and the volume were right; renders came out nearly black."""
    r = 7.0
    vol = sphere_volume((30, 30, 30), r, spacing=(spacing,) * 3, origin=(5, 6, 7),
                        direction=direction)
    lo, hi = vol.world_bounds()
    mesh = isosurface(vol, 0.0)
    assert enclosed_volume(mesh) > 0
    assert outward_fraction(mesh, 0.5 * (lo + hi)) == 1.0
    fn = mesh.face_normals()  # (vertex normals agree with the winding)
    assert np.mean(np.einsum("ij,ij->i", fn, mesh.normals[mesh.faces].mean(axis=1)) > 0) == 1.0


def test_inside_below_is_the_same_surface_wound_outwards():
    vol_pos = sphere_volume((24, 24, 24), 8.0)
    vol_neg = vol_pos.with_data(-vol_pos.data)
    a = isosurface(vol_pos, 0.0)
    b = isosurface(vol_neg, 0.0, inside="below")
    assert enclosed_volume(b) == pytest.approx(enclosed_volume(a), rel=1e-3)
    assert outward_fraction(b, np.full(3, 11.5)) == 1.0
    # the wrong side flips everything: a negative volume is the signature
    c = isosurface(vol_neg, 0.0, inside="above")
    assert enclosed_volume(c) < 0


def test_integer_samples_and_binary_mask():
    from conftest import ball

    data = ball(30, 9.0, dtype=np.uint8)
    mesh = isosurface(Volume(data), 0.5)
    st = mesh_stats(mesh)
    assert st["closed"] and st["components"] == 1
    # the staircase surface of a voxelised ball encloses about the voxel count
    assert abs(st["volume"] - data.sum()) / data.sum() < 0.05


def test_border_shape_is_open_without_cap_and_closed_with_it():
    data = np.zeros((10, 12, 14), dtype=np.float32)
    data[2:8, 3:9, 0:6] = 1.0   # a box touching the x = 0 face
    vol = Volume(data, spacing=(1.0, 1.0, 1.0))
    from volwarp_cli.box import Box
    from volwarp_cli.surface.chunked import volume_facts

    # the inside samples on the volume's faces: the box's 6 x 6 on the x = 0 face
    facts = volume_facts(data, 0.5, boxes=[Box.from_shape(data.shape)], count=True)
    assert facts.border == 36
    open_mesh = isosurface(vol, 0.5)
    assert not is_closed(open_mesh)
    capped = isosurface(vol, 0.5, cap=True)
    assert is_closed(capped)
    assert enclosed_volume(capped) > 0
    # the cap lies half a voxel beyond the border (the background pad's crossing)
    assert capped.vertices[:, 0].min() == pytest.approx(-0.5)
    # away from the border the two surfaces agree
    assert capped.vertices[:, 0].max() == pytest.approx(open_mesh.vertices[:, 0].max())


def test_cap_below_and_uint8_at_range_limit():
    data = np.full((8, 8, 8), 255, dtype=np.uint8)
    data[:, :, 4:] = 0
    vol = Volume(data)
    # inside below: the low half touches the border everywhere
    mesh = isosurface(vol, 128, inside="below", cap=True)
    assert is_closed(mesh) and enclosed_volume(mesh) > 0
    # a level at the top of uint8 with --cap still pads below it
    mesh2 = isosurface(vol, 255, cap=True)
    assert is_closed(mesh2)


def test_level_not_crossed_is_empty():
    vol = sphere_volume((10, 10, 10), 3.0)
    assert isosurface(vol, 100.0).is_empty
    assert mesh_stats(isosurface(vol, 100.0))["triangles"] == 0


def test_bad_arguments():
    vol = sphere_volume((10, 10, 10), 3.0)
    with pytest.raises(VolwarpError, match="inside"):
        isosurface(vol, 0.0, inside="outside")
    with pytest.raises(VolwarpError, match="finite"):
        isosurface(vol, float("nan"))
    bad = vol.data.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(VolwarpError, match="NaN"):
        isosurface(vol.with_data(bad), 0.0)


def test_agrees_with_skimage_marching_cubes():
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    rng = np.random.default_rng(3)
    # a lumpy smooth field: sum of a few Gaussian blobs, anisotropic spacing
    shape = (36, 30, 28)  # z, y, x
    z, y, x = np.indices(shape).astype(np.float64)
    f = np.zeros(shape)
    for _ in range(6):
        c = rng.uniform([6, 6, 6], np.array(shape) - 6)
        s = rng.uniform(3, 6)
        f += np.exp(-((z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2) / (2 * s * s))
    f = f.astype(np.float32)
    spacing = (0.8, 1.0, 1.3)  # x, y, z
    vol = Volume(f, spacing=spacing)
    mesh = isosurface(vol, 0.3)
    verts, faces, _, _ = marching_cubes(f, 0.3, spacing=tuple(reversed(spacing)))
    verts = verts[:, ::-1]  # (z, y, x) -> (x, y, z)
    assert abs(len(faces) - mesh.n_faces) / len(faces) < 0.10
    voxel = max(spacing)
    d1, _ = cKDTree(verts).query(mesh.vertices)
    d2, _ = cKDTree(mesh.vertices).query(verts)
    assert max(d1.max(), d2.max()) < voxel
    assert surface_area(mesh) == pytest.approx(
        float(np.linalg.norm(np.cross(verts[faces[:, 1]] - verts[faces[:, 0]],
                                      verts[faces[:, 2]] - verts[faces[:, 0]]),
                             axis=1).sum() / 2), rel=0.02)


def _ball(dtype):
    """A ball of 32-bit integers on whose falling edges VTK's ``s1 - s0`` wrapped.

    uint32: a Gaussian from 0 to 1000 (every falling edge wrapped); int32: a
    steep step from -2.1e9 to 2.1e9 (neighbours across it more than 2^31 apart).
    """
    z, y, x = np.mgrid[:24, :26, :28]
    r = np.sqrt((x - 13.3) ** 2 + (y - 12.6) ** 2 + (z - 11.2) ** 2)
    f = 1000 * np.exp(-r * r / 40) if dtype == "uint32" else 2.1e9 * np.tanh(3 * (7 - r))
    return np.round(f).astype(dtype)


@pytest.mark.parametrize("dtype,level", [("uint32", 100.5), ("int32", 0.5)])
def test_32_bit_integers_agree_with_skimage_marching_cubes(dtype, level):
    """Every vertex where the edge's linear interpolation equals the level, in memory and by
    blocks (the same bits), and scikit-image's area, volume and bounds."""
    from skimage.measure import marching_cubes

    from volwarp_cli.surface.chunked import isosurface_blocks
    from volwarp_cli.surface.isosurface import crossing_edges

    data = _ball(dtype)
    vol = Volume(data)  # index = world: the vertices are (i, j, k)
    mesh = isosurface(vol, level)
    blocked = isosurface_blocks(data, vol, level, block_shape=(7, 9, 5), normals=True,
                                threads=2)
    for a, b in ((mesh.vertices, blocked.vertices), (mesh.faces, blocked.faces),
                 (mesh.normals, blocked.normals)):
        assert a.dtype == b.dtype and np.array_equal(a.view(np.uint8), b.view(np.uint8))
    # the whole volume's vertices are its crossed edges', in order: each at the exact t
    lower, axis = crossing_edges(data, level)
    assert len(lower) == mesh.n_vertices
    rows = np.arange(len(lower))
    upper = lower.copy()
    upper[rows, axis] += 1
    s0 = data[lower[:, 2], lower[:, 1], lower[:, 0]].astype(np.float64)
    s1 = data[upper[:, 2], upper[:, 1], upper[:, 0]].astype(np.float64)
    exact = lower.astype(np.float64)
    exact[rows, axis] += (level - s0) / (s1 - s0)
    assert np.abs(mesh.vertices - exact).max() < 1e-5
    verts, faces, _, _ = marching_cubes(data.astype(np.float64), level)
    verts = verts[:, ::-1]  # (z, y, x) -> (x, y, z)
    tri = verts[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    inside = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    stats = mesh_stats(mesh)
    assert stats["closed"]
    assert stats["area"] == pytest.approx(area.sum() / 2, rel=1e-6)
    assert stats["volume"] == pytest.approx(abs(inside.sum()) / 6, rel=1e-6)
    assert np.allclose(mesh.vertices.min(axis=0), verts.min(axis=0), atol=1e-4)
    assert np.allclose(mesh.vertices.max(axis=0), verts.max(axis=0), atol=1e-4)
