"""B-spline warp core: evaluators, capture map, identity, affine precision, local control,
incremental == full, handles (least norm)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volwarp_cli.box import Box
from volwarp_cli.bspline import basis
from volwarp_cli.bspline.capture import capture_volume
from volwarp_cli.bspline.evaluate import LatticeSpline
from volwarp_cli.bspline.handles import map_params, solve
from volwarp_cli.bspline.lattice import Lattice, affected_regions, capture_offsets, window_reduce
from volwarp_cli.bspline.pullback import capture_coordinates
from volwarp_cli.bspline.scene import Scene
from volwarp_cli.errors import VolwarpError
from volwarp_cli.volume import Volume


def smooth_blob(shape_zyx, sigma_frac=0.18):
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape_zyx], indexing="ij")
    r2 = (x / 0.9) ** 2 + (y / 0.7) ** 2 + (z / 0.8) ** 2
    return (100.0 * np.exp(-r2 / (2 * sigma_frac))).astype(np.float32)


def test_basis_partition_of_unity_and_table():
    t = np.linspace(0, 1, 11)
    assert np.allclose(basis.basis(t).sum(-1), 1.0)
    assert np.allclose(basis.basis_derivative(t).sum(-1), 0.0)
    # the table is the tensor product of the per-axis weights (eq. 3/4)
    tab = basis.coefficient_table(3, 4, 5)
    wx, wy, wz = basis.region_weights(3), basis.region_weights(4), basis.region_weights(5)
    assert np.allclose(tab[2, 1, 3], np.einsum("i,j,k->ijk", wx[2], wy[1], wz[3]))


def test_table_equals_separable_and_blocks_are_bit_identical():
    grid = Lattice.create((30, 20, 25), (9, 7, 8), 2)
    rng = np.random.default_rng(1)
    dq = rng.normal(scale=3.0, size=grid.lattice[::-1] + (3,))
    shape = grid.domain_shape[::-1] + (3,)
    sep = basis.evaluate_separable(dq, grid, np.zeros(shape, np.float32))
    tab = basis.evaluate_table(dq, grid, np.zeros(shape, np.float32))
    assert np.max(np.abs(sep - tab)) < 1e-5
    # a block evaluates to exactly the same values as the full array
    part = np.full(shape, np.nan, np.float32)
    basis.evaluate_separable(dq, grid, part, (1, 0, 2), (4, 3, 5))
    inside = ~np.isnan(part)
    assert inside.sum() == (3 * 10) * (3 * 10) * (3 * 10) * 3
    assert np.array_equal(part[inside], sep[inside])
    # and equals a direct evaluation of eq. 2 at a voxel centre
    e, f, g = 17, 5, 33
    prm = [(e + 0.5) / 10, (f + 0.5) / 10, (g + 0.5) / 10]
    val = LatticeSpline(dq, grid.regions).offsets([prm])[0]
    assert np.allclose(val, sep[g, f, e], atol=1e-5)


def test_the_scattered_evaluator_is_the_papers_tensor_product():
    """Offsets at scattered parameters are sum B_i(s) B_j(t) B_k(u) dq_kji over the 4^3
    control points of the region (the paper's eq. 2 with its blending functions), the
    Jacobian is that sum's derivative (central differences), the weights' rows are those
    products (64 a point, summing to 1) and give the offsets as weights @ dq."""
    grid = Lattice.create((40, 30, 20), (8, 7, 6), 1)
    rng = np.random.default_rng(5)
    dq = rng.normal(scale=2.0, size=grid.lattice[::-1] + (3,))
    regions = np.array(grid.regions)
    params = rng.uniform(0, 1, (40, 3)) * regions
    params[0] = regions  # the far corner: the last region's polynomial
    spline = LatticeSpline(dq, grid.regions)
    want = np.empty((len(params), 3))
    for n, s in enumerate(params):
        a = np.clip(np.floor(s), 0, regions - 1).astype(int)
        w = [basis.basis(np.array([s[d] - a[d]]))[0] for d in range(3)]
        block = dq[a[2]:a[2] + 4, a[1]:a[1] + 4, a[0]:a[0] + 4]
        want[n] = np.einsum("k,j,i,kjim->m", w[2], w[1], w[0], block)
    assert np.allclose(spline.offsets(params), want, atol=1e-12)
    eps = 1e-6
    jac = spline.jacobian(params[1:])
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = eps
        fd = (spline.offsets(params[1:] + step) - spline.offsets(params[1:] - step)) / (2 * eps)
        assert np.allclose(jac[:, :, axis], fd, atol=1e-6)
    rows = spline.weights(params)
    assert np.all(np.count_nonzero(rows, axis=1) <= 64) and np.allclose(rows.sum(axis=1), 1)
    assert np.allclose(rows @ dq.reshape(-1, 3), want, atol=1e-12)


@pytest.mark.parametrize("placement", ["uniform", "tripled"])
def test_capture_image_is_the_voxel_box(placement):
    """The model's part of the domain maps onto the input's voxel box [-0.5, I - 0.5]:
    with the uniform placement at an integer oversample k (a subdivision grid) the
    domain voxels [lead, lead + k I), each 1/k of an input voxel; with the tripled
    placement (a spanning grid) the whole domain box [0, D]."""
    grid = Lattice.create((30, 17, 11), (9, 6, 7), 2, placement)
    assert grid.subdivision == (2 if placement == "uniform" else 0)
    coords = capture_coordinates(grid, placement)
    dq = capture_offsets(grid, placement)
    for axis, c in enumerate(coords):
        n = grid.input_shape[axis]
        g = grid.granularity[axis]
        assert np.all(np.diff(c) > 0)
        ends = np.zeros((2, 3))
        ends[0, axis] = grid.data_lo[axis] / g
        ends[1, axis] = grid.data_hi[axis] / g
        mapped = map_params(dq, grid, ends)
        assert mapped[0, axis] == pytest.approx(-0.5, abs=1e-12)
        assert mapped[1, axis] == pytest.approx(n - 0.5, abs=1e-12)
    if placement == "uniform":
        for c, n, d, a in zip(coords, grid.input_shape, grid.domain_shape, grid.lead,
                              strict=True):
            assert d >= 2 * n and a == (d - 2 * n) // 2  # centred on the input
            # voxel centres half an input voxel apart: two in each input voxel
            assert np.allclose(c, -0.5 + (np.arange(d) - a + 0.5) / 2, atol=1e-12)
        assert grid.domain_shape == (30 * 2, 17 * 2 + 2, 11 * 2 + 2)  # G = 10, 12, 6
    else:
        for c, n in zip(coords, grid.input_shape, strict=True):
            assert c[0] > -0.5 and c[-1] < n - 0.5


def test_capture_of_a_subdivision_grid_is_the_box_model():
    """At an integer oversample every domain voxel takes its input voxel's value exactly
    (either sampling); a non-integer oversample keeps the spanning grid and trilinear
    samples."""
    rng = np.random.default_rng(4)
    data = rng.integers(0, 1000, size=(7, 9, 11)).astype(np.int16)
    for k in (1, 2, 3):
        for sampling in ("linear", "nearest"):
            cap = capture_volume(Volume(data), lattice=(6, 5, 7), oversample=k,
                                 sampling=sampling)
            grid = cap.grid
            assert grid.subdivision == k
            (x0, y0, z0), (x1, y1, z1) = grid.data_lo, grid.data_hi
            inside = cap.domain[z0:z1, y0:y1, x0:x1]
            want = np.repeat(np.repeat(np.repeat(data, k, 0), k, 1), k, 2)
            assert np.array_equal(inside, want.astype(np.float32))
    assert capture_volume(Volume(data), lattice=5, oversample=1.5).grid.subdivision == 0
    assert Lattice.create((7, 9, 11), (5, 5, 5), 2, "tripled").subdivision == 0


@pytest.mark.parametrize("size", [30, 31, 23])
def test_identity_exact_with_nearest_at_oversample_1(size):
    rng = np.random.default_rng(size)
    data = rng.integers(0, 255, size=(size, size - 3, size + 2)).astype(np.uint8)
    cap = capture_volume(Volume(data), lattice=(9, 8, 7), oversample=1, sampling="nearest")
    scene = Scene(cap.domain, cap.grid, cap.dq, 0, method="nearest")
    out = np.rint(scene.compute()).astype(np.uint8)
    assert np.array_equal(out, data)


def test_identity_default_settings_smooth_model():
    data = smooth_blob((64, 64, 64))
    cap = capture_volume(Volume(data))  # 9^3, uniform, oversample 2, linear
    scene = Scene(cap.domain, cap.grid, cap.dq, 3)  # box
    out = scene.compute()[3:-3, 3:-3, 3:-3]
    err = out - data
    rng_ = data.max() - data.min()
    assert np.sqrt(np.mean(err ** 2)) < 0.01 * rng_
    assert np.max(np.abs(err)) < 0.05 * rng_
    assert np.all(scene.compute()[:3] == 0)


@pytest.mark.parametrize("degrees", [12.0, 33.0])
def test_affine_precision_against_scipy(degrees):
    from scipy.ndimage import affine_transform

    n = 40
    data = smooth_blob((n, n, n), 0.12)
    cap = capture_volume(Volume(data), lattice=(7, 7, 7), oversample=2)
    ang = np.deg2rad(degrees)
    rot = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    m = rot @ np.diag([1.1, 0.9, 1.05])
    c = np.array([19.5, 19.5, 19.5])
    shift = np.array([1.5, -1.0, 0.5])
    pts = cap.grid.uniform_positions() + cap.dq
    moved = (pts - c) @ m.T + c + shift
    pad = 12
    scene = Scene(cap.domain, cap.grid, moved - cap.grid.uniform_positions(), pad)
    out = scene.compute()
    # reference: out(p) = data(M^-1 (p - pad - c - shift) + c), in (x, y, z) then [z, y, x]
    minv = np.linalg.inv(m)
    mat_xyz = minv
    off_xyz = -minv @ (c + shift + pad) + c
    perm = [2, 1, 0]
    ref = affine_transform(data, mat_xyz[np.ix_(perm, perm)], offset=off_xyz[perm],
                           output_shape=out.shape, order=1, mode="constant", cval=0.0)
    err = out - ref
    assert np.sqrt(np.mean(err ** 2)) < 0.002 * data.max()
    assert np.max(np.abs(err)) < 0.03 * data.max()
    # Totals: the papers' proxy alone (bounding box of the six face centres)
    # covers cos^2 of a rotated voxel, and "v where w < 1" left the rest at
    # zero: totals 4% low at 12 degrees, 30% at 33. Scaled to each voxel's
    # Jacobian volume, the rotated model keeps its total.
    ratio = out.sum() / ref.sum()
    assert abs(ratio - 1.0) < 0.005


def _moved_scene(method="box"):
    data = smooth_blob((26, 30, 34))
    cap = capture_volume(Volume(data), lattice=(8, 9, 10), oversample=1.5)
    return cap, Scene(cap.domain, cap.grid, cap.dq, 4, method=method)


@pytest.mark.parametrize("method", ["box", "nearest"])
def test_local_control_bit_identical_outside(method, local_updates):
    cap, scene = _moved_scene(method)
    before = scene.compute().copy()
    i, j, k = 4, 3, 5
    dq = scene.dq.copy()
    dq[k, j, i] += [2.0, -1.5, 1.0]
    old_img = _region_image(scene, i, j, k)
    scene.set_lattice(dq)
    new_img = _region_image(scene, i, j, k)
    lo = np.floor(np.minimum(old_img[0], new_img[0])).astype(int) - 1
    hi = np.ceil(np.maximum(old_img[1], new_img[1])).astype(int) + 2
    after = scene.out
    mask = np.ones(after.shape, bool)
    mask[max(lo[2], 0):hi[2], max(lo[1], 0):hi[1], max(lo[0], 0):hi[0]] = False
    assert mask.sum() > 0.3 * mask.size
    assert np.array_equal(after[mask], before[mask])
    assert not np.array_equal(after, before)


def _region_image(scene, i, j, k):
    """Bounding box (target index) of the image of the 64 regions of control point (i, j, k)."""
    grid = scene.grid
    lo = np.clip(np.array([i, j, k]) - 3, 0, np.array(grid.regions) - 1)
    hi = np.clip(np.array([i, j, k]), 0, np.array(grid.regions) - 1) + 1
    axes = [np.linspace(a, b, (b - a) * g + 1) for a, b, g in zip(lo, hi, grid.granularity, strict=False)]
    prm = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    pts = scene.map_points(prm)
    return pts.min(0), pts.max(0)


@settings(max_examples=20, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(moves=st.lists(st.tuples(st.integers(0, 6), st.integers(0, 5), st.integers(0, 4),
                                st.floats(-2.5, 2.5), st.floats(-2.5, 2.5),
                                st.floats(-2.5, 2.5)), min_size=1, max_size=4),
       method=st.sampled_from(["box", "nearest"]))
@pytest.mark.parametrize("oversample", [1.5, 1])  # a spanning grid; a subdivision grid
def test_incremental_equals_full(moves, method, oversample, local_updates):
    data = smooth_blob((14, 16, 18))
    cap = capture_volume(Volume(data), lattice=(7, 6, 5), oversample=oversample)
    scene = Scene(cap.domain, cap.grid, cap.dq, 4, method=method, update=local_updates)
    scene.compute()
    dq = cap.dq.copy()
    for i, j, k, dx, dy, dz in moves:
        dq = dq.copy()
        dq[k, j, i] += [dx, dy, dz]
        scene.set_lattice(dq)
    full = Scene(cap.domain, cap.grid, dq, 4, method=method, update=local_updates).compute()
    # fixed-point accumulators: exact, not merely within 1e-4 of the range
    assert np.array_equal(scene.out, full)


@settings(max_examples=30, deadline=None)
@given(shape=st.tuples(st.integers(6, 9), st.integers(6, 9), st.integers(6, 9)),
       width=st.integers(1, 6), seed=st.integers(0, 2 ** 16))
def test_window_reduce_is_a_sliding_window_min(shape, width, seed):
    from numpy.lib.stride_tricks import sliding_window_view

    a = np.random.default_rng(seed).normal(size=shape + (3,))
    want = sliding_window_view(a, (width,) * 3, axis=(0, 1, 2)).min(axis=(-3, -2, -1))
    assert np.array_equal(window_reduce(a, width, np.minimum), want)


def test_rebuild_block_covers_what_an_update_touches():
    """The target block a rebuild recomputes contains every target voxel the old and new
    contributions of the moved voxels reach (the subtracting update's tracked box), and
    its domain block contains the moved voxels."""
    data = smooth_blob((20, 22, 24))
    cap = capture_volume(Volume(data), lattice=(8, 7, 9), oversample=1.5)
    rng = np.random.default_rng(2)
    scene = Scene(cap.domain, cap.grid, cap.dq, 3, update="subtract")
    scene.compute()
    dq = cap.dq.copy()
    for point in [(2, 3, 1), (4, 0, 6), (5, 5, 5), (0, 6, 7), (3, 3, 3)]:
        dq = dq.copy()
        dq[point] += rng.normal(scale=2.0, size=3)
        rlo, rhi = affected_regions(np.array([point[::-1]]), cap.grid)
        g = np.array(cap.grid.granularity)
        voxels = Box.from_xyz(np.maximum(rlo * g - 1, 0).tolist(),
                              np.minimum(rhi * g + 1, np.array(cap.grid.domain_shape)).tolist())
        block = scene.reach.rebuild_block(scene._offset_bounds(scene.dq),
                                          scene._offset_bounds(dq), voxels)
        scene.set_lattice(dq)
        assert not scene.last_touched.empty
        assert block.target.contains(scene.last_touched)
        assert block.domain.contains(voxels)


def test_handles_reach_targets_with_least_norm():
    grid = Lattice.create((30, 24, 20), (9, 8, 7), 2)
    dq = capture_offsets(grid, "uniform")
    src = np.array([[10.0, 12.0, 9.0], [20.0, 5.0, 12.0], [3.0, 20.0, 4.0]])
    dst = src + np.array([[2.0, -1.0, 0.5], [0.0, 1.5, -2.0], [-1.0, 0.0, 1.0]])
    delta, params, residual = solve(dq, grid, src, dst)
    assert residual < 1e-9
    assert np.allclose(map_params(dq, grid, params), src, atol=1e-8)
    after = map_params(dq + delta, grid, params)
    assert np.max(np.abs(after - dst)) < 1e-3
    # least norm: delta lies in the row space of the weight matrix, so adding any
    # null-space change keeps the targets but makes the change larger
    rows = LatticeSpline(dq, grid.regions).weights(params)
    flat_delta = delta.reshape(-1, 3)
    coef, *_ = np.linalg.lstsq(rows.T, flat_delta, rcond=None)
    assert np.allclose(rows.T @ coef, flat_delta, atol=1e-10)
    rng = np.random.default_rng(0)
    for _ in range(5):
        v = rng.normal(size=flat_delta.shape)
        v -= rows.T @ np.linalg.lstsq(rows.T, v, rcond=None)[0]  # project to null space
        other = flat_delta + v
        assert np.allclose(rows @ other, rows @ flat_delta, atol=1e-9)
        assert np.linalg.norm(other) > np.linalg.norm(flat_delta)


def test_handles_pulling_against_each_other_stay_bounded():
    """Two handles 0.05 voxel apart dragged in opposite directions: the exact
    solution would move control points by hundreds of voxels; the solve keeps
    them within reach of the handles' moves and reports the miss."""
    grid = Lattice.create((30, 30, 30), (9, 9, 9), 2)
    dq = capture_offsets(grid, "uniform")
    src = np.array([[15.0, 15.0, 15.0], [15.05, 15.0, 15.0]])
    dst = src + np.array([[0.0, 0.0, 3.0], [0.0, 0.0, -3.0]])
    exact = np.linalg.lstsq(_weight_rows(grid, src, dq), dst - src, rcond=None)[0]
    assert np.abs(exact).max() > 100.0  # the trap
    delta, _, residual = solve(dq, grid, src, dst)
    assert np.abs(delta).max() <= 16.0 * 3.0 + 1.0  # handles.MOVE_BOUND
    assert 2.0 < residual < 3.5  # the compromise: both end near the middle
    # handles that agree are still met exactly, however close
    dst = src + np.array([[0.0, 0.0, 3.0], [0.0, 0.0, 3.0]])
    delta, params, residual = solve(dq, grid, src, dst)
    assert residual < 1e-9
    assert np.max(np.abs(map_params(dq + delta, grid, params) - dst)) < 1e-3


def _weight_rows(grid, points, dq):
    from volwarp_cli.bspline.handles import locate

    return LatticeSpline(dq, grid.regions).weights(locate(dq, grid, points))


def test_handle_on_warped_map_and_radius():
    grid = Lattice.create((30, 30, 30), (9, 9, 9), 2)
    dq = capture_offsets(grid, "uniform").copy()
    dq[4, 4, 4] += [3.0, -2.0, 1.0]  # a non-affine current map
    src = np.array([[15.0, 14.0, 16.0]])
    dst = np.array([[17.0, 14.0, 13.0]])
    free = np.zeros(grid.lattice[::-1], bool)
    free[3:6, 3:6, 3:6] = True
    delta, params, residual = solve(dq, grid, src, dst, free)
    assert residual < 1e-9
    assert np.all(delta[~free] == 0)
    assert np.allclose(map_params(dq, grid, params), src, atol=1e-8)
    assert np.max(np.abs(map_params(dq + delta, grid, params) - dst)) < 1e-3


def test_handle_outside_model_is_an_error():
    from volwarp_cli.bspline.handles import HandleError

    grid = Lattice.create((20, 20, 20), (7, 7, 7), 1)
    dq = capture_offsets(grid, "uniform")
    with pytest.raises(HandleError, match="outside"):
        solve(dq, grid, [[10.0, 10.0, 10.0], [40.0, 10.0, 10.0]], [[0, 0, 0], [0, 0, 0]])


def test_small_deformation_chunks_change_nothing(monkeypatch, local_updates):
    """Small z chunks of the deformation change nothing (the thread counts and block
    sizes, with the threads seen to run, are in test_threads_warp.py)."""
    from volwarp_cli.bspline import scene as scene_mod

    data = smooth_blob((20, 22, 24))
    rng = np.random.default_rng(5)
    moves = [((i, j, k), rng.normal(scale=1.5, size=3))
             for i, j, k in [(2, 3, 1), (4, 1, 3), (3, 3, 3), (0, 5, 0)]]

    def run_all():
        cap = capture_volume(Volume(data), lattice=(7, 8, 6), oversample=1.5)
        sc = Scene(cap.domain, cap.grid, cap.dq, 4, update=local_updates)
        sc.compute()
        dq = cap.dq.copy()
        outs = []
        for (i, j, k), d in moves:
            dq = dq.copy()
            dq[k, j, i] += d
            sc.set_lattice(dq)
            outs.append(sc.out.copy())
        return cap.domain.copy(), outs, sc.acc.copy()

    serial = run_all()
    monkeypatch.setattr(scene_mod, "CHUNK_BYTES", 1)  # 4-slab chunks
    chunked = run_all()
    for a, b in zip(serial[1], chunked[1], strict=True):
        assert np.array_equal(a, b)
    assert np.array_equal(serial[2], chunked[2])


def test_update_touching_most_of_the_lattice_recomputes_in_full(caplog):
    """Where subtracting and adding would cost more than a full pass, the scene recomputes:
    the same sums, so the same target bit for bit."""
    data = smooth_blob((20, 22, 24))
    cap = capture_volume(Volume(data), lattice=(7, 6, 5), oversample=1)
    scene = Scene(cap.domain, cap.grid, cap.dq, 4)
    scene.compute()
    dq = cap.dq.copy()
    dq[2, 2, 3] += [1.5, -1.0, 0.5]  # its 4^3 regions cover the whole 4 x 3 x 2 lattice
    with caplog.at_level("DEBUG", logger="volwarp"):
        scene.set_lattice(dq)
    assert "by full" in caplog.text
    with pytest.raises(VolwarpError, match="unknown update"):  # the papers' approximation
        Scene(cap.domain, cap.grid, cap.dq, 4, update="zero")  # is not one of the ways
    assert scene.last_touched == Box.from_xyz((0, 0, 0), scene.target_shape)
    assert np.array_equal(scene.out, Scene(cap.domain, cap.grid, dq, 4).compute())


def test_samples_far_above_the_rest_are_refused_before_they_wipe_it_out():
    """The box pushforward's exact sums are fixed point scaled by the largest |value|:
    a no-data marker (-3.4e38) or a spike 1e12 times the rest would leave the rest
    no precision (the warp came out 0 everywhere else). Those are refused; ordinary
    wide ranges (a probability map with tiny tails, one bright voxel in zeros) are not."""
    ball = np.zeros((16, 17, 18), np.float32)
    ball[4:12, 4:12, 4:12] = 100
    for marker in (-3.4e38, 1e12):
        data = ball.copy()
        data[0, 0, 0] = marker
        with pytest.raises(VolwarpError, match="clip or mask"):
            capture_volume(Volume(data), lattice=5, oversample=1)
    ok = ball.copy()
    ok[0, 0, 0] = 1e6  # 10^4 times the rest: sums still resolve 1e-6 of a unit
    cap = capture_volume(Volume(ok), lattice=5, oversample=1, sampling="nearest")
    scene = Scene(cap.domain, cap.grid, cap.dq, 0, method="nearest",
                  domain_range=cap.stats[:2])
    assert np.abs(scene.compute()[4:12, 4:12, 4:12] - 100).max() < 1e-4
    spike = ball.copy()
    spike[0, 0, 0] = 1e10  # 10^8 times the rest: about 1e-4 of it lost, still accepted
    capture_volume(Volume(spike), lattice=5, oversample=1)
    tails = np.exp(-np.linspace(0, 60, 16 * 17 * 18)).reshape(16, 17, 18)  # down to 1e-26
    capture_volume(Volume(tails.astype(np.float32)), lattice=5, oversample=1)
    point = np.zeros((16, 17, 18), np.float32)
    point[8, 8, 8] = 1e30  # nothing else but zeros: nothing to lose
    capture_volume(Volume(point), lattice=5, oversample=1)
    # a sparse volume: a small object (under 1% of the samples) beside a marker. The
    # percentile of all the samples is 0, and the warp came out 0 everywhere (exit 0)
    sparse = np.zeros((16, 17, 18), np.float32)
    sparse[7:9, 7:9, 7:9] = 0.75
    sparse[0, 0, 0] = -3.4e38
    with pytest.raises(VolwarpError, match="non-zero ones have .* <= 0.75"):
        capture_volume(Volume(sparse), lattice=5, oversample=1)


def test_a_lattice_too_big_for_memory_is_refused_before_it_is_built(monkeypatch):
    """A lattice much finer than the input (1000^3 points on 20^3 voxels) needs tens of
    GiB for its own arrays: refused with the sizes before any is allocated."""
    from volwarp_cli.errors import OutOfMemoryError

    monkeypatch.setenv("VOLWARP_MEMORY_LIMIT", str(1 << 30))
    data = np.zeros((20, 20, 20), np.float32)
    with pytest.raises(OutOfMemoryError, match="1000x1000x1000 control lattice needs"):
        capture_volume(Volume(data), lattice=1000, oversample=1)
