"""Smoothing, decimation, components and the statistics, against analytic answers."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.surface import ops
from volwarp_cli.surface.isosurface import isosurface
from volwarp_cli.surface.mesh import Mesh, vertex_normals
from volwarp_cli.surface.stats import enclosed_volume, is_closed, mesh_stats, surface_area
from volwarp_cli.volume import Volume


def voxel_ball(n=40, r=13.0) -> Mesh:
    """The staircase isosurface of a binary ball (what a mask gives)."""
    c = (n - 1) / 2
    z, y, x = np.indices((n, n, n))
    data = (((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2) <= r * r).astype(np.uint8)
    return isosurface(Volume(data), 0.5)


def unit_cube() -> Mesh:
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=float)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return Mesh(v, f)


def test_stats_of_a_unit_cube_are_exact():
    cube = unit_cube()
    st = mesh_stats(cube)
    assert st["vertices"] == 8 and st["triangles"] == 12
    assert st["area"] == pytest.approx(6.0)
    assert st["volume"] == pytest.approx(1.0)
    assert st["bbox_min"] == [0, 0, 0] and st["bbox_max"] == [1, 1, 1]
    assert st["closed"] is True and st["components"] == 1
    # inverted winding: negative volume, still closed
    assert enclosed_volume(cube.flipped()) == pytest.approx(-1.0)
    # far from the origin the volume stays exact
    far = Mesh(cube.vertices * 2 + 1e6, cube.faces)
    assert enclosed_volume(far) == pytest.approx(8.0, rel=1e-9)


def test_closed_detects_holes_and_bad_winding():
    cube = unit_cube()
    assert not is_closed(Mesh(cube.vertices, cube.faces[:-1]))
    bad = cube.faces.copy()
    bad[0] = bad[0][::-1]
    assert not is_closed(Mesh(cube.vertices, bad))
    assert not is_closed(Mesh.empty())


def test_vertex_normals_of_cube_corners():
    cube = unit_cube()
    n = vertex_normals(cube.vertices, cube.faces)
    outward = cube.vertices - 0.5
    assert np.all(np.einsum("ij,ij->i", n, outward) > 0)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-6)


def test_smoothing_keeps_volume_and_approaches_the_sphere():
    r = 13.0
    mesh = voxel_ball(40, r)
    true_area = 4 * np.pi * r**2
    vol0 = enclosed_volume(mesh)
    smoothed = ops.smooth(mesh, 20)
    assert smoothed.n_faces == mesh.n_faces and is_closed(smoothed)
    # windowed sinc does not shrink: the volume is kept
    assert enclosed_volume(smoothed) == pytest.approx(vol0, rel=0.01)
    # the staircase's excess area (about 10% for a voxel ball) mostly goes away
    assert surface_area(mesh) / true_area > 1.08
    assert abs(surface_area(smoothed) / true_area - 1) < 0.03
    # the radii become even
    c = mesh.vertices.mean(axis=0)
    spread0 = np.std(np.linalg.norm(mesh.vertices - c, axis=1))
    spread1 = np.std(np.linalg.norm(smoothed.vertices - c, axis=1))
    assert spread1 < 0.6 * spread0
    # normals are recomputed and outward
    assert np.all(np.einsum("ij,ij->i", smoothed.normals, smoothed.vertices - c) > 0)


def test_decimation_reduces_and_keeps_shape():
    r = 14.0
    z, y, x = np.indices((40, 40, 40)).astype(np.float32)
    f = r - np.sqrt((x - 19.5) ** 2 + (y - 19.5) ** 2 + (z - 19.5) ** 2)
    mesh = isosurface(Volume(f), 0.0)
    dec = ops.decimate(mesh, 0.8)
    assert dec.n_faces == pytest.approx(0.2 * mesh.n_faces, rel=0.1)
    assert is_closed(dec)
    assert enclosed_volume(dec) == pytest.approx(4 / 3 * np.pi * r**3, rel=0.02)
    radii = np.linalg.norm(dec.vertices - 19.5, axis=1)
    assert np.max(np.abs(radii - r)) < 0.5
    assert dec.normals is not None and len(dec.normals) == dec.n_vertices
    assert np.all(np.einsum("ij,ij->i", dec.normals, dec.vertices - 19.5) > 0)


def test_components_and_largest():
    cube = unit_cube()
    small = Mesh(cube.vertices * 0.5 + 5, cube.faces)
    big = Mesh(cube.vertices * 2 - 7, cube.faces)
    both = Mesh(np.vstack([small.vertices, big.vertices]),
                np.vstack([small.faces, big.faces + 8]))
    count, labels = ops.connected_components(both)
    assert count == 2 and labels.tolist() == [0] * 12 + [1] * 12
    # equal triangle counts: the first one wins, deterministically
    kept = ops.largest_component(both)
    assert kept.n_faces == 12 and kept.n_vertices == 8
    np.testing.assert_allclose(kept.vertices, small.vertices)
    # with a real difference, the bigger piece (more triangles) is kept
    z, y, x = np.indices((30, 30, 40)).astype(np.float32)
    f = np.maximum(5 - np.sqrt((x - 8) ** 2 + (y - 15) ** 2 + (z - 15) ** 2),
                   9 - np.sqrt((x - 27) ** 2 + (y - 15) ** 2 + (z - 15) ** 2))
    mesh = isosurface(Volume(f), 0.0)
    assert mesh_stats(mesh)["components"] == 2
    largest = ops.largest_component(mesh)
    assert mesh_stats(largest)["components"] == 1 and is_closed(largest)
    assert enclosed_volume(largest) == pytest.approx(4 / 3 * np.pi * 9**3, rel=0.02)
    assert largest.vertices[:, 0].min() > 15


def test_bad_parameters():
    cube = unit_cube()
    with pytest.raises(VolwarpError):
        ops.decimate(cube, 1.0)
    with pytest.raises(VolwarpError):
        ops.smooth(cube, -1)
    with pytest.raises(VolwarpError):
        ops.smooth(cube, 5, pass_band=3.0)
    with pytest.raises(VolwarpError, match="0 or at least 2"):  # (1 collapsed the mesh)
        ops.smooth(cube, 1)
    assert ops.smooth(cube, 0) is cube
    assert ops.decimate(cube, 0.0) is cube


def gyroid_mesh(n=40, period=20.0, cap=True) -> Mesh:
    """A high-genus surface: a gyroid cell block, capped so that it is closed."""
    s = 2 * np.pi / period
    z, y, x = (np.indices((n, n, n)) * s).astype(np.float32)
    f = np.sin(x) * np.cos(y) + np.sin(y) * np.cos(z) + np.sin(z) * np.cos(x)
    return isosurface(Volume(f.astype(np.float32)), 0.0, cap=cap)


def test_decimation_keeps_a_high_genus_surface_closed():
    mesh = gyroid_mesh()
    st0 = mesh_stats(mesh)
    assert st0["closed"]
    # Euler characteristic V - E + F (E = 3F/2 for a closed surface) is kept:
    # edge collapses under the link condition do not change the topology
    euler0 = st0["vertices"] - st0["triangles"] // 2
    for reduction in (0.5, 0.9):
        dec = ops.decimate(mesh, reduction)
        st = mesh_stats(dec)
        assert st["closed"] is True
        assert st["components"] == st0["components"]
        assert st["vertices"] - st["triangles"] // 2 == euler0
        assert st["triangles"] <= (1 - reduction) * mesh.n_faces * 1.05
        assert st["volume"] == pytest.approx(st0["volume"], rel=0.01)
        # no vertex strays from the original surface by more than a voxel
        from scipy.spatial import cKDTree

        d, _ = cKDTree(mesh.vertices).query(dec.vertices)
        assert d.max() < 1.0


def test_decimation_keeps_an_open_border_in_place():
    mesh = gyroid_mesh(cap=False)
    assert not is_closed(mesh)
    dec = ops.decimate(mesh, 0.7)
    assert dec.n_faces < 0.4 * mesh.n_faces
    # the border (edges used once) is made of original vertices, unmoved
    def border_points(m):
        f = m.faces
        a, b = f.reshape(-1), np.roll(f, -1, axis=1).reshape(-1)
        key = np.minimum(a, b) * m.n_vertices + np.maximum(a, b)
        uniq, count = np.unique(key, return_counts=True)
        once = uniq[count == 1]
        idx = np.unique(np.concatenate([once // m.n_vertices, once % m.n_vertices]))
        return {tuple(np.round(m.vertices[i], 9)) for i in idx}
    assert border_points(dec) == border_points(mesh)



def test_a_nan_vertex_leaves_its_neighbours_normals_as_their_other_triangles_make_them():
    """``apply`` writes a vertex it could not move as NaN: its triangles add nothing, so the
    normals of the finite vertices beside it are those of their other triangles (they were
    all NaN, 102 of a 30x30 grid's in a review)."""
    from volwarp_cli.surface.mesh import vertex_normals

    n = 6
    y, x = np.mgrid[:n, :n].astype(float)
    z = 0.1 * np.sin(x) * np.cos(y)
    verts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(n * n).reshape(n, n)
    faces = np.concatenate([np.column_stack([idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(),
                                             idx[1:, 1:].ravel()]),
                            np.column_stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(),
                                             idx[1:, :-1].ravel()])])
    lost = idx[2, 3]
    holed = verts.copy()
    holed[lost] = np.nan
    got = vertex_normals(holed, faces)
    kept = faces[~(faces == lost).any(axis=1)]
    want = vertex_normals(verts, kept)
    finite = np.arange(n * n) != lost
    assert np.isfinite(got).all()
    np.testing.assert_array_equal(got[finite], want[finite])
    assert (got[lost] == 0).all()
