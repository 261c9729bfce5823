"""The one-shot render (the whole target as one block) and the voxel-range evaluators give
exactly the full results."""

from __future__ import annotations

import numpy as np
import pytest
from one_shot import one_shot

from volwarp_cli.bspline import basis
from volwarp_cli.bspline.capture import capture_volume
from volwarp_cli.bspline.lattice import Lattice
from volwarp_cli.bspline.scene import Scene
from volwarp_cli.volume import Volume
from volwarp_cli.warp import blocks as blocks_module


def _blob(shape_zyx):
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape_zyx], indexing="ij")
    return (100.0 * np.exp(-(x * x + y * y + z * z) / 0.3)).astype(np.float32)


@pytest.mark.parametrize("method", ["box", "nearest"])
@pytest.mark.parametrize("shift", [(0.0, 0.0, 0.0), (2.0, -1.0, 9.0), (-3.0, 2.5, -14.0)])
@pytest.mark.parametrize("stream_planes", [1, 8])
def test_one_shot_equals_render(method, shift, stream_planes, monkeypatch):
    # tall in z so that the block's stream wraps its ring of planes (many times with 1
    # plane per step); large z moves stretch and fold the map along the streamed axis
    monkeypatch.setattr(blocks_module, "STREAM_PLANES", stream_planes)
    cap = capture_volume(Volume(_blob((90, 20, 24))), lattice=(6, 6, 12), oversample=1.5)
    dq = cap.dq.copy()
    dq[5, 2, 3] += shift
    dq[6, 3, 2] -= np.array(shift) * 0.5
    full = Scene(cap.domain, cap.grid, dq, 16, method=method).compute()
    once = one_shot(Scene(cap.domain, cap.grid, dq, 16, method=method))
    assert np.array_equal(once, full)
    # a deferred capture: boxes gathered chunk by chunk as the stream needs them, the
    # whole domain never
    lazy = capture_volume(Volume(_blob((90, 20, 24))), lattice=(6, 6, 12), oversample=1.5,
                          defer=True)
    assert lazy.domain is None
    value_range = (float(cap.domain.min()), float(cap.domain.max()))
    scene = Scene(lazy.voxmap, lazy.grid, dq, 16, method=method, domain_range=value_range)
    assert np.array_equal(one_shot(scene), full)
    assert scene.sampler is not None  # still not gathered whole
    assert np.array_equal(scene.compute(), full)  # gathers it whole
    assert np.array_equal(scene.domain, cap.domain) and scene.sampler is None


@pytest.mark.parametrize("method", ["box", "nearest"])
def test_subdivision_grid_paths_agree(method, local_updates, monkeypatch):
    """On a subdivision grid with domain voxels outside the input on every axis (lead 1,
    1, 1 at oversample 2), the one-shot render (whole or deferred capture), the full
    render and local updates give the same target bit for bit, and an unmoved lattice
    gives back the input."""
    monkeypatch.setattr(blocks_module, "STREAM_PLANES", 4)
    data = _blob((65, 20, 23))
    cap = capture_volume(Volume(data), lattice=(6, 6, 10), oversample=2)
    assert cap.grid.lead == (1, 1, 1) and cap.grid.data_hi == (47, 41, 131)
    ident = one_shot(Scene(cap.domain, cap.grid, cap.dq, 2, method=method,
                           update=local_updates))
    assert np.max(np.abs(ident[2:-2, 2:-2, 2:-2] - data)) <= 8 * 2.0 ** -39 * data.max()
    assert np.all(ident[:2] == 0) and np.all(ident[:, :, -2:] == 0)
    scene = Scene(cap.domain, cap.grid, cap.dq, 6, method=method, update=local_updates)
    scene.compute()
    dq = cap.dq.copy()
    for point, move in (((0, 2, 1), (1.5, -2.0, 3.0)), ((3, 5, 9), (-2.5, 1.0, -4.0)),
                        ((2, 2, 5), (0.5, 0.5, 6.0))):
        dq = dq.copy()
        dq[point[::-1]] += move
        scene.set_lattice(dq)
    full = Scene(cap.domain, cap.grid, dq, 6, method=method, update=local_updates).compute()
    assert np.array_equal(scene.out, full)
    once = one_shot(Scene(cap.domain, cap.grid, dq, 6, method=method, update=local_updates))
    assert np.array_equal(once, full)
    lazy = capture_volume(Volume(data), lattice=(6, 6, 10), oversample=2, defer=True)
    deferred = one_shot(Scene(lazy.voxmap, lazy.grid, dq, 6, method=method,
                              domain_range=lazy.stats[:2], update=local_updates))
    assert np.array_equal(deferred, full)


@pytest.mark.parametrize("evaluate", [basis.evaluate_separable, basis.evaluate_table])
def test_voxel_range_evaluation_is_bit_identical(evaluate):
    grid = Lattice.create((30, 20, 25), (9, 7, 8), 2)
    dq = np.random.default_rng(3).normal(scale=2.0, size=grid.lattice[::-1] + (3,))
    full = evaluate(dq, grid, np.zeros(grid.domain_shape[::-1] + (3,), np.float32))
    x, y, z = (7, 45), (3, 22), (11, 30)  # not aligned with the regions (G = 10)
    part = np.zeros((z[1] - z[0], y[1] - y[0], x[1] - x[0], 3), np.float32)
    evaluate(dq, grid, part, x=x, y=y, z=z, origin=(x[0], y[0], z[0]))
    assert np.array_equal(part, full[z[0]:z[1], y[0]:y[1], x[0]:x[1]])


@pytest.mark.parametrize("method", ["box", "nearest"])
def test_background_is_the_value_of_the_space_around_the_model(method, local_updates):
    """Warping with background b equals warping data - b with background 0, plus b
    (the pushforward is linear), in the full, one-shot and incremental paths; an
    uncovered voxel (in the padding) gets b exactly."""
    data = _blob((30, 20, 24)) - 40.0  # like a signed field: negative inside, positive around
    b = 37.5
    cap = capture_volume(Volume(data), lattice=7, oversample=1.5)
    shifted = capture_volume(Volume(data - b), lattice=7, oversample=1.5)
    dq = cap.dq.copy()
    dq[4, 3, 3] += [2.0, -1.5, 3.0]
    ref = Scene(shifted.domain, shifted.grid, dq, 5, method=method, update=local_updates).compute() + b
    full = Scene(cap.domain, cap.grid, dq, 5, method=method, background=b, update=local_updates).compute()
    once = one_shot(Scene(cap.domain, cap.grid, dq, 5, method=method, background=b,
                          update=local_updates))
    scene = Scene(cap.domain, cap.grid, cap.dq, 5, method=method, background=b, update=local_updates)
    scene.compute()
    scene.set_lattice(dq)
    for got in (full, once, scene.result()):
        np.testing.assert_allclose(got, ref, atol=1e-4)
    assert full[0, 0, 0] == b and full[-1, -1, -1] == b  # padding: nothing lands there


@pytest.mark.parametrize("background", [0.0, 100.0])
@pytest.mark.parametrize("degrees", [33.0, 45.0])
def test_rotated_constant_stays_constant_inside(background, degrees):
    """Inside a rotated model every target voxel is fully covered, however the box
    weights scatter: a constant stays that constant, not darkened (b = 0) or
    pulled towards the background (b = 100)."""
    n = 30
    cap = capture_volume(Volume(np.full((n, n, n), 50.0, np.float32)), lattice=7, oversample=1)
    a = np.deg2rad(degrees)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    c = np.full(3, (n - 1) / 2)
    pts = cap.grid.uniform_positions() + cap.dq
    dq = (pts - c) @ rot.T + c - cap.grid.uniform_positions()
    pad = 8
    out = one_shot(Scene(cap.domain, cap.grid, dq, pad, background=background))
    z, y, x = np.indices(out.shape)
    centre = c + pad
    inside = ((x - centre[0]) ** 2 + (y - centre[1]) ** 2 < 10 ** 2) & (abs(z - centre[2]) < 12)
    np.testing.assert_allclose(out[inside], 50.0, atol=1e-3)
    assert out[0, 0, 0] == background  # the padding
