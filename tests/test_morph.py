"""Implicit morph core: analytic spheres, endpoints, alignment, landmark warps, topology."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

from volwarp_cli.errors import VolwarpError
from volwarp_cli.morph.align import affine_from_params, euler_matrix
from volwarp_cli.morph.grid import GridError
from volwarp_cli.morph.interpolate import blend, density, frame_times
from volwarp_cli.morph.landmarks import LandmarkWarp
from volwarp_cli.morph.pipeline import prepare
from volwarp_cli.morph.spec import MorphJob, ShapeRef
from volwarp_cli.volume import Volume

N = 40


def radial(n=N, center=None, spacing=1.0):
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float64) * spacing
    c = np.full(3, (n - 1) / 2 * spacing) if center is None else np.asarray(center)
    return np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)


def smooth_ball(radius, n=N, center=None, **kw):
    """Samples R - r (smooth): the sub-voxel field reproduces the sphere."""
    return Volume((radius - radial(n, center)).astype(np.float32), **kw)


def job(times, **kw):
    return MorphJob(source=ShapeRef(Path("s"), 0.0), target=ShapeRef(Path("t"), 0.0),
                    times=times, **kw)


def iou(a, b):
    return np.count_nonzero(a & b) / np.count_nonzero(a | b)


@pytest.mark.parametrize("t", [0.0, 0.2, 0.5, 0.7, 1.0])
def test_concentric_spheres_give_interpolated_radius(t):
    r1, r2 = 6.3, 14.6
    prep = prepare(job([t]), smooth_ball(r1), smooth_ball(r2))
    f = prep.morph.field(t)
    r = radial()
    expected = (1 - t) * r1 + t * r2
    band = np.abs(r - expected) <= 2
    # the frame field is the distance to the sphere of the interpolated radius
    assert np.abs(f - (r - expected))[band].max() < 0.15
    # voxel-accurate: inside voxels are exactly those closer than the radius,
    # except within 0.15 voxel of the sphere
    clear = np.abs(r - expected) > 0.15
    np.testing.assert_array_equal((f < 0)[clear], (r < expected)[clear])


def test_endpoints_reproduce_source_and_target_binary():
    a = (radial(center=(15, 20, 19)) <= 9).astype(np.uint8)
    b = ((np.abs(np.mgrid[:N, :N, :N] - np.array([22, 18, 21])[:, None, None, None])
          <= np.array([6, 9, 12])[:, None, None, None]).all(axis=0)).astype(np.uint8)
    j = job([0.0, 0.5, 1.0])
    j.source.iso = j.target.iso = 0.5
    prep = prepare(j, Volume(a), Volume(b))
    assert iou(prep.morph.field(0.0) < 0, a > 0) >= 0.99
    assert iou(prep.morph.field(1.0) < 0, b > 0) >= 0.99
    np.testing.assert_array_equal(prep.morph.field(0.0) < 0, a > 0)  # exactly, on the same grid
    np.testing.assert_array_equal(prep.morph.field(1.0) < 0, b > 0)


def test_translation_alignment_moves_frame0_by_exactly_that_translation():
    spacing = (1.0, 1.0, 2.0)
    mask = (radial(center=(14, 20, 22)) <= 8).astype(np.uint8)
    src = Volume(mask, spacing=spacing, origin=(5.0, -3.0, 10.0))
    tgt = Volume(mask, spacing=spacing, origin=(5.0, -3.0, 10.0))
    j = job([0.0, 1.0], align_source={"translate": [6.0, -4.0, 8.0]})
    j.source.iso = j.target.iso = 0.5
    prep = prepare(j, src, tgt)
    frame0 = prep.morph.field(0.0) < 0
    g = prep.grid
    world0 = np.argwhere(frame0)[:, ::-1] @ g.matrix.T + g.origin_array
    world_src = np.argwhere(mask > 0)[:, ::-1] @ (src.direction * src.spacing).T + src.origin
    moved = world_src + [6.0, -4.0, 8.0]
    key = lambda p: set(map(tuple, np.round(p, 6)))  # noqa: E731
    assert key(world0) == key(moved)
    frame1 = prep.morph.field(1.0) < 0
    world1 = np.argwhere(frame1)[:, ::-1] @ g.matrix.T + g.origin_array
    assert key(world1) == key(world_src)


def test_rotation_and_scale_alignment_of_target():
    src = smooth_ball(8.0, n=48)
    tgt = Volume((1 - np.sqrt(((np.mgrid[:48, :48, :48][2] - 23.5) / 12) ** 2
                              + ((np.mgrid[:48, :48, :48][1] - 23.5) / 6) ** 2
                              + ((np.mgrid[:48, :48, :48][0] - 23.5) / 6) ** 2)).astype(np.float32))
    j = job([1.0], align_target={"rotate": [0, 0, 90], "scale": 0.5})
    prep = prepare(j, src, tgt)
    f = prep.morph.field(1.0)
    # the 12 x 6 x 6 ellipsoid, halved and turned: 3 along x, 6 along y
    c = np.array(prep.grid.shape) // 2
    row_x = f[c[0], c[1]]
    row_y = f[c[0], :, c[2]]
    assert 4 <= np.count_nonzero(row_x < 0) <= 7
    assert 10 <= np.count_nonzero(row_y < 0) <= 13


@pytest.mark.parametrize("kind,sigma", [("thin-plate", None), ("gaussian", 6.0)])
@pytest.mark.parametrize("n_points", [1, 2, 3, 5, 8])
def test_landmark_warp_interpolates_pairs(kind, sigma, n_points):
    rng = np.random.default_rng(n_points)
    p = rng.uniform(0, 40, (n_points, 3))
    q = p + rng.normal(0, 3, (n_points, 3))
    w = LandmarkWarp.fit(p, q, kind=kind, sigma=sigma)
    assert np.abs(w(p) - q).max() < 1e-6


def test_thin_plate_reproduces_affine_maps():
    rng = np.random.default_rng(7)
    p = rng.uniform(-10, 10, (9, 3))
    a = euler_matrix([10, -20, 30]) * 1.2
    q = p @ a.T + [1.0, 2.0, -3.0]
    w = LandmarkWarp.fit(p, q)
    x = rng.uniform(-20, 20, (50, 3))
    np.testing.assert_allclose(w(x), x @ a.T + [1.0, 2.0, -3.0], atol=1e-8)


def test_landmark_errors():
    with pytest.raises(VolwarpError, match="differ in length"):
        LandmarkWarp.fit(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(VolwarpError, match="sigma"):
        LandmarkWarp.fit(np.eye(3), np.eye(3), kind="gaussian")
    with pytest.raises(VolwarpError, match="coincide"):
        LandmarkWarp.fit([[0, 0, 0], [0, 0, 0]], [[1, 0, 0], [2, 0, 0]])


def test_static_warp_moves_the_source_onto_the_target_landmark():
    p, q = (12.0, 20.0, 20.0), (27.0, 20.0, 20.0)
    src = smooth_ball(5.0, center=p)
    tgt = smooth_ball(5.0, center=q)
    j = job([0.0, 0.5, 1.0], warp_source_points=np.array([p]), warp_target_points=np.array([q]),
            grid="source")
    prep = prepare(j, src, tgt)
    r_q = radial(center=q)
    # one pair: a pure translation; the warped source sits on the target already
    for t in (0.0, 0.5, 1.0):
        f = prep.morph.field(t)
        assert np.abs(f - (r_q - 5.0))[np.abs(r_q - 5) < 2].max() < 0.2


def test_progressive_warp_carries_the_shape_along():
    p, q = (11.0, 20.0, 20.0), (28.0, 20.0, 20.0)
    src = smooth_ball(5.0, center=p)
    tgt = smooth_ball(5.0, center=q)
    plain = prepare(job([0.5]), src, tgt, )
    assert np.count_nonzero(plain.morph.field(0.5) < 0) == 0  # no overlap: nothing halfway
    j = job([0.0, 0.5, 1.0], warp_mode="progressive",
            warp_source_points=np.array([p]), warp_target_points=np.array([q]), grid="source")
    prep = prepare(j, src, tgt)
    np.testing.assert_array_equal(prep.morph.field(0.0), plain.morph.source)
    np.testing.assert_array_equal(prep.morph.field(1.0), plain.morph.target)
    mid = prep.morph.field(0.5)
    r_mid = radial(center=(19.5, 20.0, 20.0))
    assert np.abs(mid - (r_mid - 5.0))[np.abs(r_mid - 5) < 2].max() < 0.2


def count_holes_2d(mask2d):
    _, n_bg = ndi.label(~mask2d)
    return n_bg - 1


def torus(n, big, small):
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float64) - (n - 1) / 2
    return (small - np.sqrt((np.sqrt(x ** 2 + y ** 2) - big) ** 2 + z ** 2)).astype(np.float32)


def test_ball_to_torus_changes_topology():
    n = 44
    src = smooth_ball(12.0, n=n)
    tgt = Volume(torus(n, 12.0, 5.0))
    times = frame_times(frames=9)
    prep = prepare(job(times), src, tgt)
    holes, comps = [], []
    for t in times:
        inside = prep.morph.field(t) < 0
        comps.append(ndi.label(inside)[1])
        holes.append(count_holes_2d(inside[n // 2]))
    assert comps == [1] * 9  # one piece throughout
    assert holes[0] == 0 and holes[-1] == 1  # the ball has no hole, the torus one
    k = holes.index(1)
    assert all(h == 0 for h in holes[:k]) and all(h == 1 for h in holes[k:])


def test_one_blob_to_two():
    n = 40
    src = smooth_ball(11.0, n=n)
    two = np.maximum(7.0 - radial(n, (10, 19.5, 19.5)), 7.0 - radial(n, (29, 19.5, 19.5)))
    prep = prepare(job(frame_times(frames=5)), src, Volume(two.astype(np.float32)))
    counts = [ndi.label(prep.morph.field(t) < 0)[1] for t in frame_times(frames=5)]
    assert counts[0] == 1 and counts[-1] == 2
    assert counts == sorted(counts)


def test_density_output_is_a_ramp_with_the_surface_at_half():
    f = np.linspace(-3, 3, 13, dtype=np.float32).reshape(1, 1, 13)
    occ = density(f, 2.0)
    assert occ[0, 0, 0] == 1.0 and occ[0, 0, -1] == 0.0 and occ[0, 0, 6] == 0.5
    assert np.all(np.diff(occ[0, 0]) <= 0)


def test_blend_is_exact_at_the_ends():
    a = np.random.default_rng(0).random((3, 4, 5)).astype(np.float32)
    b = a * 3 + 1
    np.testing.assert_array_equal(blend(a, b, 0.0), a)
    np.testing.assert_array_equal(blend(a, b, 1.0), b)
    np.testing.assert_allclose(blend(a, b, 0.25), 0.75 * a + 0.25 * b, rtol=1e-6)


def test_bad_inputs():
    with pytest.raises(GridError, match="different grids"):
        prepare(job([0.0]), smooth_ball(5.0), smooth_ball(5.0, spacing=(1, 1, 2)))
    with pytest.raises(VolwarpError, match="empty"):
        prepare(job([0.0]), smooth_ball(-1.0), smooth_ball(5.0))
    with pytest.raises(VolwarpError, match="outside"):
        frame_times(times=[0.0, 1.5])
    with pytest.raises(VolwarpError, match="at least 2"):
        frame_times(frames=1)


def test_affine_params():
    m = affine_from_params({"scale": 2.0, "center": [1, 1, 1]})
    np.testing.assert_allclose(m @ [1, 1, 1, 1], [1, 1, 1, 1])
    np.testing.assert_allclose(m @ [2, 1, 1, 1], [3, 1, 1, 1])
    m = affine_from_params({"rotate": [0, 0, 90], "translate": [1, 0, 0], "center": [0, 0, 0]})
    np.testing.assert_allclose(m @ [1, 0, 0, 1], [1, 1, 0, 1], atol=1e-12)
    with pytest.raises(VolwarpError, match="combined"):
        affine_from_params({"matrix": np.eye(4).tolist(), "scale": 2})
    with pytest.raises(VolwarpError, match="center"):
        affine_from_params({"rotate": [0, 0, 5]})


def test_explicit_grid_and_static_warp_of_attributes():
    src = smooth_ball(8.0)
    tgt = smooth_ball(8.0)
    grid = {"origin": [4.0, 4.0, 4.0], "spacing": 2.0, "size": [16, 16, 16]}
    attr = Volume(np.broadcast_to(np.arange(N, dtype=np.float32), (N, N, N)).copy())
    j = job([0.0, 1.0], grid=grid, warp_source_points=np.array([[19.5, 19.5, 19.5]]),
            warp_target_points=np.array([[23.5, 19.5, 19.5]]))
    prep = prepare(j, src, tgt, {"x": (attr, attr)})
    assert prep.grid.shape == (16, 16, 16)
    np.testing.assert_allclose(prep.grid.origin, 4.0)
    a0 = prep.morph.attribute(0.0, *prep.attributes["x"])
    a1 = prep.morph.attribute(1.0, *prep.attributes["x"])
    # the target attribute is the x coordinate sampled on the 2 mm grid
    np.testing.assert_allclose(a1[5, 5, 3:12], 4.0 + 2.0 * np.arange(3, 12), atol=1e-4)
    # the (static) warp moved the source 4 mm along +x: its attribute too
    np.testing.assert_allclose(a0[5, 5, 3:12], a1[5, 5, 3:12] - 4.0, atol=1e-3)


def test_attribute_file_names():
    from volwarp_cli.morph.outputs import attribute_name as _attribute_name

    assert _attribute_name("out/f_003.nrrd", "rgb") == "out/f_003_rgb.nrrd"
    assert _attribute_name("f_1.nii.gz", "grey") == "f_1_grey.nii.gz"


@pytest.mark.parametrize("inside", ["above", "below"])
@pytest.mark.parametrize("dtype", ["uint8", "int16", "float32"])
def test_source_range_keeps_the_side_of_every_voxel(inside, dtype):
    from volwarp_cli.morph.interpolate import occupancy_to_range

    occ = np.linspace(0, 1, 1001, dtype=np.float32).reshape(1, 1, -1)
    vals = occupancy_to_range(occ, 0.0, 100.0, 200.0, inside, dtype)
    assert vals.dtype == np.dtype(dtype)
    in_shape = vals >= 100 if inside == "above" else vals < 100
    np.testing.assert_array_equal(in_shape, occ > 0.5)
    ends = (vals.flat[0], vals.flat[-1])
    assert ends == ((0, 200) if inside == "above" else (200, 0))
