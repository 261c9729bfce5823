"""One grid geometry: :class:`Geometry`'s sizes, corners and comparisons, and the morph's
frame grids and the sweep's output grids made as Geometry."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from volwarp_cli.errors import VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.morph.grid import GridError, choose_grid, explicit_grid, union_geometry
from volwarp_cli.volume import Volume

ROT = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z


# -- Geometry ---------------------------------------------------------------------------
def test_size_is_the_exact_voxel_count():
    g = Geometry.from_xyz((5, 4, 3))
    assert g.size == 60 == g.box.size and isinstance(g.size, int)
    assert Geometry((0, 4, 3)).size == 0
    huge = Geometry((1 << 31,) * 3)  # beyond int64: numpy's product would wrap
    assert huge.size == 1 << 93


def test_identity_direction():
    assert Geometry((2, 3, 4)).identity_direction
    assert Geometry.from_xyz((4, 3, 2), spacing=0.5, origin=(1, 2, 3)).identity_direction
    assert Geometry((2, 3, 4), direction=np.eye(3) * -0.0 + np.eye(3)).identity_direction
    assert not Geometry((2, 3, 4), direction=ROT).identity_direction
    assert not Geometry((2, 3, 4), direction=np.diag([1.0, 1.0, -1.0])).identity_direction
    assert not Geometry((2, 3, 4), direction=np.eye(3) + 1e-12 * ROT).identity_direction


def test_corner_indices_order_and_world_corners():
    g = Geometry.from_xyz((4, 3, 2), spacing=(0.5, 2.0, 3.0), origin=(1, -2, 5), direction=ROT)
    c = g.corner_indices()
    assert c.shape == (8, 3) and c.dtype == np.float64
    want = [[x, y, z] for x in (0, 3) for y in (0, 2) for z in (0, 1)]
    np.testing.assert_array_equal(c, want)
    np.testing.assert_array_equal(g.corner_indices(voxel_boxes=True),
                                  [[x, y, z] for x in (-0.5, 3.5) for y in (-0.5, 2.5)
                                   for z in (-0.5, 1.5)])
    # homogeneous through the 4x4 matrix, or through index_to_world: the same points
    hom = np.hstack([c, np.ones((8, 1))]) @ g.index_to_world_matrix.T
    np.testing.assert_allclose(hom[:, :3], g.index_to_world(c), atol=1e-12)
    lo, hi = g.bounds_world()
    np.testing.assert_allclose(lo, hom[:, :3].min(axis=0))
    np.testing.assert_allclose(hi, hom[:, :3].max(axis=0))
    with pytest.raises(VolwarpError, match="no voxels"):
        Geometry((0, 2, 2)).corner_indices()


def test_same_grid_matches_volume_same_grid():
    kw = {"spacing": (1.0, 2.0, 1.5), "origin": (3.0, -1.0, 0.5), "direction": ROT}
    a = Volume(np.zeros((3, 4, 5), np.float32), **kw)
    g = Geometry.of(a)
    assert g.same_grid(g) and g.same_grid(a)  # a Volume is taken as its geometry
    for other, same in [
        (Volume(np.zeros((3, 4, 5)), **dict(kw, origin=(3.0, -1.0, 0.5 + 1e-8))), True),
        (Volume(np.zeros((3, 4, 5)), **dict(kw, origin=(3.0, -1.0, 0.6))), False),
        (Volume(np.zeros((3, 4, 6)), **kw), False),
        (Volume(np.zeros((3, 4, 5)), **dict(kw, spacing=(1.0, 2.0, 1.0))), False),
        (Volume(np.zeros((3, 4, 5)), **dict(kw, direction=np.eye(3))), False),
    ]:
        assert g.same_grid(Geometry.of(other)) is same is a.same_grid(other)


def test_geometry_is_frozen_and_exact():
    g = Geometry.from_xyz((4, 3, 2), spacing=0.1, origin=(0.3, 0.7, -1e-17))
    with pytest.raises(dataclasses.FrozenInstanceError):
        g.spacing = (1.0, 1.0, 1.0)
    assert g.origin == (0.3, 0.7, -1e-17) and g.spacing == (0.1, 0.1, 0.1)
    assert hash(g) == hash(Geometry.from_xyz((4, 3, 2), spacing=(0.1,) * 3,
                                             origin=np.array([0.3, 0.7, -1e-17])))


# -- the morph's frame grid -------------------------------------------------------------
def test_explicit_grid_is_a_geometry():
    g = explicit_grid({"origin": [4, 5, 6], "spacing": 2.0, "size": [16, 12, 8]})
    assert g == Geometry((8, 12, 16), spacing=2.0, origin=(4, 5, 6))
    g = explicit_grid({"origin": [0, 0, 0], "spacing": [1, 2, 3], "size": [2, 3, 4],
                       "direction": ROT.tolist()})
    assert g.shape_xyz == (2, 3, 4) and g.spacing == (1.0, 2.0, 3.0)
    np.testing.assert_array_equal(g.direction_array, ROT)
    with pytest.raises(GridError, match="singular") as err:
        explicit_grid({"origin": [0, 0, 0], "spacing": 1, "size": [2, 2, 2],
                       "direction": np.zeros((3, 3)).tolist()})
    assert err.value.key == ("grid", "direction")


def test_union_geometry_extends_the_source_lattice():
    source = Geometry.from_xyz((10, 8, 6), spacing=(1.0, 0.5, 2.0), origin=(1.0, 2.0, 3.0),
                               direction=ROT)
    target = Geometry.from_xyz((10, 8, 6), spacing=1.0, origin=(20.0, 0.0, 0.0))
    move = np.eye(4)
    move[:3, 3] = (0.5, 0.25, 0.0)
    u = union_geometry(source, target, np.eye(4), move, margin=1.5)
    assert isinstance(u, Geometry)
    assert u.spacing == source.spacing and u.direction == source.direction
    # the source's voxels are voxels of the union: integer indices
    idx = u.world_to_index(source.index_to_world(source.corner_indices()))
    np.testing.assert_allclose(idx, np.round(idx), atol=1e-9)
    # it covers both moved inputs with the margin (2 voxels: ceil(1.5)) to spare
    pts = np.vstack([source.index_to_world(source.corner_indices()),
                     target.index_to_world(target.corner_indices()) + move[:3, 3]])
    i = u.world_to_index(pts)
    last = np.array(u.shape_xyz) - 1
    assert np.all(i.min(axis=0) >= 2 - 1e-6) and np.all(i.min(axis=0) < 3)  # and no more
    assert np.all(i.max(axis=0) <= last - 2 + 1e-6) and np.all(i.max(axis=0) > last - 3)
    with pytest.raises(GridError, match="margin") as err:
        union_geometry(source, target, np.eye(4), move, margin=1e300)
    assert err.value.key == ("margin",)


def test_choose_grid_rules():
    a = Geometry.from_xyz((6, 6, 6), spacing=1.0)
    b = Geometry.from_xyz((6, 6, 6), spacing=1.0, origin=(1e-8, 0, 0))
    c = Geometry.from_xyz((6, 6, 6), spacing=2.0)
    eye = np.eye(4)
    assert choose_grid(None, a, b, eye, eye, moved=False) is a  # the same grid
    assert choose_grid("target", a, c, eye, eye, moved=False) is c
    assert choose_grid(None, a, c, eye, eye, moved=True) == union_geometry(a, c, eye, eye)
    with pytest.raises(GridError, match=r"different grids .*spacing \[1.0, 1.0, 1.0\]"):
        choose_grid(None, a, c, eye, eye, moved=False)


# -- the sweep's output grid ------------------------------------------------------------
@pytest.fixture
def line_sweep(tmp_path):
    from volwarp_cli.spec.loader import load_schema, parse_spec_text, validate
    from volwarp_cli.sweep.model import parse_sweep_spec

    body = {"version": 1, "grid": {"shape": [12, 10, 8]}, "fields": {"opacity": 1},
            "trajectory": [{"line": {"from": [0, 0, 0], "to": [10, 0, 0]}}],
            "up": [0, 0, 1], "scale": [4, 4]}
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(body, sort_keys=False))
    doc = parse_spec_text(path.read_text(), str(path), tmp_path)
    validate(doc, load_schema("sweep"))
    return parse_sweep_spec(doc)


def test_fit_grid_is_an_axis_aligned_geometry(line_sweep):
    from volwarp_cli.sweep.model import fit_grid, fit_grid_values, sweep_geometry

    lo, hi = line_sweep.bounds()
    g = fit_grid(line_sweep.grid, lo, hi)
    assert isinstance(g, Geometry) and g.identity_direction
    assert g.shape_xyz == (12, 10, 8) and g.shape == (8, 10, 12)
    shape, origin, spacing = fit_grid_values(line_sweep.grid, lo, hi)
    assert g == sweep_geometry(shape, origin, spacing)
    assert g.origin == tuple(origin) and g.spacing == tuple(spacing)  # exactly


@pytest.mark.parametrize("method", ["voxelize", "direct"])
def test_sweep_refuses_a_rotated_grid(line_sweep, method):
    from volwarp_cli.sweep import evaluate
    from volwarp_cli.sweep.model import fit_grid

    lo, hi = line_sweep.bounds()
    g = fit_grid(line_sweep.grid, lo, hi)
    f = evaluate(line_sweep, g, method=method)
    assert f["opacity"].shape == g.shape and f["opacity"].max() > 0.5
    turned = Geometry(g.shape, g.spacing, g.origin, ROT)
    with pytest.raises(VolwarpError, match="axis-aligned"):
        evaluate(line_sweep, turned, method=method)
