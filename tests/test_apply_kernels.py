"""`volwarp apply`'s sampling: cubic B-splines on tiny axes, the memory a block counts, and
the C kernels (their checks, a reference, no numba on the command's path)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.apply import plan_resample
from volwarp_cli.box import Box
from volwarp_cli.execute import compute_whole
from volwarp_cli.transforms import _applykernels as K
from volwarp_cli.transforms.model import Affine, Chain
from volwarp_cli.volume import Volume

sitk = pytest.importorskip("SimpleITK")


def _fine_grid(shape, step=0.23):
    """A grid of ``step`` voxels over the input's buffer ``[-0.5, n - 0.5)``, and its indices."""
    n = np.array(shape[::-1])
    size = [int(v) for v in np.floor((n - 0.02) / step)]
    ref = Volume(np.zeros(size[::-1], np.uint8), spacing=(step,) * 3, origin=(-0.49,) * 3)
    z, y, x = np.mgrid[:size[2], :size[1], :size[0]] * step - 0.49
    return ref, (x, y, z)


@pytest.mark.parametrize("shape", [(5, 2, 6), (6, 5, 2), (2, 5, 6), (2, 2, 2), (1, 4, 5),
                                   (3, 1, 2)])
def test_cubic_on_tiny_axes(shape):
    """Cubic B-spline interpolation on axes of 1 and 2 samples, against two references.

    scipy's ``map_coordinates(order=3, mode="mirror")`` is the exact spline of
    the mirror-extended samples: volwarp's within 1e-7 everywhere. SimpleITK's
    ``BSplineInterpolateImageFunction`` equals it too, except at continuous
    indices in ``[1, 1.5)`` on an axis of 2 samples: there ITK's support
    reaches index 3, which its one reflection (``2 (n - 1) - i``) sends to
    -1, outside the coefficient line (the previous line's last coefficient,
    or memory before the image; see the next test). volwarp mirrors again
    (index 1), as the prefilter's own boundary assumes.
    """
    from scipy.ndimage import map_coordinates

    rng = np.random.default_rng(sum(shape))
    data = rng.normal(0, 1, shape)
    ref, (x, y, z) = _fine_grid(shape)
    op = plan_resample(Volume(data).header, data, Chain(), ref, interpolation="bspline",
                       background=0.0, values="intensity")
    ours = compute_whole(op)["resampled"]
    exact = map_coordinates(data, [z, y, x], order=3, mode="mirror")
    span = float(np.ptp(data))
    assert np.abs(ours - exact).max() <= 1e-7 * span
    theirs = sitk.GetArrayFromImage(sitk.Resample(sitk.GetImageFromArray(data), _sitk_grid(ref),
                                                  sitk.Transform(), sitk.sitkBSpline, 0.0,
                                                  sitk.sitkFloat64))
    band = np.zeros(ours.shape, bool)
    for idx, n in zip((x, y, z), shape[::-1], strict=True):
        if n == 2:
            band |= (idx >= 1) & (idx < 1.5)
    assert np.abs(ours - theirs)[~band].max() <= 1e-7 * span
    assert band.any() == (2 in shape)


def _sitk_grid(ref: Volume):
    img = sitk.Image([int(v) for v in ref.data.shape[::-1]], sitk.sitkFloat64)
    img.SetSpacing([float(v) for v in ref.spacing])
    img.SetOrigin([float(v) for v in ref.origin])
    return img


def test_itk_reads_outside_a_two_sample_line():
    """Why SimpleITK differs on a 2-sample axis: index 3 is reflected once, to -1.

    On an x axis of 2 samples, at x in ``[1, 1.5)``, ITK weighs coefficient
    (-1, y, z): in its buffer, the last coefficient of the line before. Its
    value is reproduced exactly by reading that one (rows after the first:
    the first's is before the image). When ITK mirrors twice, this test
    fails and the band above can be compared too.
    """
    from scipy.ndimage import spline_filter

    rng = np.random.default_rng(3)
    data = rng.normal(0, 1, (1, 6, 2))
    flat = spline_filter(data, 3, mode="mirror")[0].ravel()  # (ITK's coefficients, exact)

    def weights(t):
        s = 1 - t
        return [s ** 3 / 6, (3 * t ** 3 - 6 * t ** 2 + 4) / 6,
                (-3 * t ** 3 + 3 * t ** 2 + 3 * t + 1) / 6, t ** 3 / 6]

    def itk_index(i, n):  # ITK's ApplyMirrorBoundaryConditions: one reflection each side
        i = -i if i < 0 else i
        return 2 * (n - 1) - i if i >= n - 1 else i

    for x, y in ((1.2, 2.0), (1.4, 3.3), (1.1, 2.7)):
        ref = sitk.Image([1, 1, 1], sitk.sitkFloat64)
        tr = sitk.TranslationTransform(3, [x, y, 0.0])
        theirs = sitk.GetArrayFromImage(sitk.Resample(sitk.GetImageFromArray(data), ref, tr,
                                                      sitk.sitkBSpline, 0.0,
                                                      sitk.sitkFloat64))[0, 0, 0]
        bx, by = int(np.floor(x)) - 1, int(np.floor(y)) - 1
        wx, wy = weights(x - bx - 1), weights(y - by - 1)
        emulated = sum(wx[m] * wy[j] * flat[itk_index(by + j, 6) * 2 + itk_index(bx + m, 2)]
                       for j in range(4) for m in range(4))
        assert itk_index(bx + 3, 2) == -1
        assert abs(theirs - emulated) < 1e-12


class _Reads:
    """A lazy source: every read a new array, as a file's reader gives."""

    def __init__(self, data):
        self.data, self.dtype, self.shape = data, data.dtype, data.shape

    def __getitem__(self, key):
        return np.array(self.data[key])


@pytest.mark.parametrize("dtype", [np.int16, np.float64])
def test_cubic_block_memory_counts_what_it_allocates(monkeypatch, dtype):
    """A cubic block's counted bytes hold what it allocates at its peak (tracemalloc).

    The prefilter's two float64 arrays of the grown region and the padded
    coefficients, the output, the parts' mapped points over the threads.
    scipy's line buffers are malloc'd (tracemalloc does not see them): their
    count is left out here. Blocks of every kind: whole, inside, at a corner,
    one voxel, thin.
    """
    from volwarp_cli import apply, parallel

    monkeypatch.setattr(apply, "_LINE_BUFFER_DOUBLES", 0, raising=False)
    monkeypatch.setattr(apply, "PART_POINTS", 2048)  # (several parts on the threads)
    rng = np.random.default_rng(1)
    data = rng.normal(0, 100, (40, 44, 50)).astype(dtype)
    chain = Chain([Affine(np.array([[1.0, 0.05, 0.0], [0.0, 0.98, 0.02], [0.01, 0.0, 1.03]]),
                          np.array([0.4, -0.3, 0.8]))])
    op = plan_resample(Volume(data).header, _Reads(data), chain, interpolation="bspline",
                       background=0.0, values="intensity")
    threads = parallel.threads()
    op.load()
    op.compute(Box((0, 0, 0), (2, 2, 2)), threads=threads)  # (scipy's filters imported)
    for box in (Box((0, 0, 0), (40, 44, 50)), Box((10, 10, 10), (30, 34, 40)),
                Box((0, 0, 0), (8, 8, 8)), Box((20, 20, 20), (21, 21, 21)),
                Box((0, 0, 0), (1, 44, 50)), Box((0, 0, 0), (40, 1, 1))):
        tracemalloc.start()
        try:
            op.compute(box, threads=threads)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert op.memory(box) >= peak, box


def test_a_nearest_block_s_counted_bytes_hold_a_background_the_input_type_cannot():
    """A background the uint8 input cannot hold is sampled in the output's type: the region is
    copied into it (the background kept, not clipped), and the count holds that copy: what
    the block allocates beyond a background that fits is what the count adds (it added
    nothing)."""
    from volwarp_cli import parallel

    rng = np.random.default_rng(2)
    data = rng.integers(0, 255, (40, 44, 50)).astype(np.uint8)
    chain = Chain([Affine(np.eye(3), np.array([6.0, 0.0, 0.0]))])
    box = Box((0, 0, 0), (40, 44, 50))
    threads = parallel.threads()
    counted, peaks = [], []
    for background in (0.0, -1000.0):
        op = plan_resample(Volume(data).header, _Reads(data), chain, interpolation="nearest",
                           background=background, values="intensity", dtype="float64")
        op.compute(Box((0, 0, 0), (2, 2, 2)), threads=threads)
        tracemalloc.start()
        try:
            out = op.compute(box, threads=threads)[op.KEY]
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
        counted.append(op.memory(box))
        assert counted[-1] >= peaks[-1]
        assert (out == background).sum() > 1000  # (the shifted-in columns)
    extra = peaks[1] - peaks[0]  # (the float64 copy of the region, less its uint8 read)
    assert extra > 0.5 * data.size * 8
    assert counted[1] - counted[0] >= extra


# -- the C kernels -----------------------------------------------------------------------
def _sample_args(n=5, points=4):
    """A whole image of ``n``^3 float64 samples and arguments sampling it at ``points``."""
    img = np.arange(float(n ** 3)).reshape(n, n, n)
    idx = np.full((points, 3), 1.25)
    return img, idx, np.zeros(3, np.int64), np.full(3, n, np.int64)


def _field_args(points=4):
    vec = np.zeros((4, 4, 4, 3))
    p = np.full((points, 3), 1.5)
    return vec, p, np.eye(3), np.zeros(3), np.zeros(3, np.int64), np.full(3, 4, np.int64)


def _wrong_calls():
    img, idx, lo, n = _sample_args()
    vec, p, inv, origin, offset, size = _field_args()
    out = np.empty(4)
    yield "float16 image", TypeError, K.sample_linear, (img.astype(np.float16), idx, lo, n,
                                                         0.0, out)
    yield "2-D image", ValueError, K.sample_linear, (img[0], idx, lo, n, 0.0, out)
    yield "strided image", ValueError, K.sample_linear, (img[:, :, ::2], idx, lo, n, 0.0, out)
    yield "(N, 2) indices", ValueError, K.sample_linear, (img, idx[:, :2].copy(), lo, n, 0.0,
                                                          out)
    yield "float32 indices", TypeError, K.sample_linear, (img, idx.astype(np.float32), lo, n,
                                                          0.0, out)
    yield "lo of 2", ValueError, K.sample_linear, (img, idx, lo[:2], n, 0.0, out)
    yield "lo beyond any grid", ValueError, K.sample_linear, (img, idx, np.array([-2 ** 63, 0, 0]),
                                                              n, 0.0, out)
    yield "int32 sizes", TypeError, K.sample_linear, (img, idx, lo, n.astype(np.int32), 0.0, out)
    yield "read-only out", ValueError, K.sample_linear, (img, idx, lo, n, 0.0, _read_only(4))
    yield "region short of the points", IndexError, K.sample_linear, (img[:1], idx, lo, n, 0.0,
                                                                      out)
    yield "region after the points", IndexError, K.sample_nearest, (img, idx, lo + 2, n + 2,
                                                                    img[0, 0, 0], out)
    yield "nearest out of another type", TypeError, K.sample_nearest, (
        img, idx, lo, n, img[0, 0, 0], np.empty(4, np.float32))
    yield "nearest background of another type", TypeError, K.sample_nearest, (
        img.astype(np.int16), idx, lo, n, np.float64(0), np.empty(4, np.int16))
    yield "cubic of int16", TypeError, K.sample_cubic, (img.astype(np.int16), idx, lo, n, 0.0,
                                                        out)
    yield "cubic support beyond the coefficients", IndexError, K.sample_cubic, (
        img[:3, :3, :3].copy(), idx, lo, n, 0.0, out)
    yield "field of 2 components", ValueError, K.field_map, (vec[..., :2], p, inv, origin,
                                                             offset, size, np.empty((4, 3)))
    yield "empty window", ValueError, K.field_map, (vec[:0], p, inv, origin, offset, size,
                                                    np.empty((4, 3)))
    yield "int field", TypeError, K.field_map, (vec.astype(np.int32), p, inv, origin, offset,
                                                size, np.empty((4, 3)))
    yield "inverse of 2x3", ValueError, K.field_map, (vec, p, inv[:2], origin, offset, size,
                                                    np.empty((4, 3)))
    yield "tiles of another count", ValueError, K.tile_range, (vec, 2, np.empty((1, 2, 2, 3)),
                                                               np.empty((2, 2, 2, 3)))
    yield "tile 0", ValueError, K.tile_range, (vec, 0, np.empty((2, 2, 2, 3)),
                                               np.empty((2, 2, 2, 3)))
    yield "planes of two types", ValueError, K.interleave, (
        img, img, img.astype(np.float32), np.empty(img.shape + (3,)))
    yield "B-spline of 2 components", ValueError, K.bspline_cubic, (
        vec[..., :2].copy(), p, np.empty((4, 3)))
    yield "affine 3x2", ValueError, K.affine, (p, inv[:, :2], origin, np.empty((4, 3)))


def _read_only(n):
    a = np.empty(n)
    a.setflags(write=False)
    return a


@pytest.mark.parametrize("what, error, kernel, args", list(_wrong_calls()),
                         ids=[c[0] for c in _wrong_calls()])
def test_kernels_refuse_wrong_calls(what, error, kernel, args):
    """A call with a wrong type, shape, layout or region is an exception, not a stray access."""
    with pytest.raises(error):
        kernel(*args)


@pytest.mark.parametrize("kernel, args, out", [
    (K.sample_linear, lambda o: (*_sample_args(points=5), 0.0, o), (8,)),
    (K.sample_nearest, lambda o: (*_sample_args(points=5), np.float64(0), o), (8,)),
    (K.sample_cubic, lambda o: (*_sample_args(points=5), 0.0, o), (8,)),
    (K.field_map, lambda o: (*_field_args(points=5), o), (8, 3)),
    (K.affine, lambda o: (np.ones((5, 3)), np.eye(3), np.zeros(3), o), (8, 3)),
    (K.bspline_cubic, lambda o: (np.zeros((5, 5, 5, 3)), np.ones((5, 3)), o), (8, 3)),
    (K.grid_points, lambda o: (np.zeros(3, np.int64), np.array([5, 1, 1]), np.eye(3),
                               np.zeros(3), o), (8, 3)),
], ids=["linear", "nearest", "cubic", "field_map", "affine", "bspline", "grid_points"])
def test_kernels_refuse_a_short_output_and_write_nothing(kernel, args, out):
    """Five points into room for four: refused, and the memory past the four is untouched."""
    guard = np.full(out, 7.0)
    with pytest.raises(ValueError, match="5 points but room for 4"):
        kernel(*args(guard[:4]))
    assert np.all(guard == 7.0)


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.float32, np.float64])
def test_sample_linear_is_map_coordinates_inside_the_buffer(dtype):
    """Trilinear samples of a region against scipy's ``map_coordinates(order=1)`` of the whole.

    Inside the buffer ``[-0.5, n - 0.5)`` ITK clamps the neighbours beyond the edges, as
    scipy's ``mode="nearest"``; outside, the background.
    """
    from scipy.ndimage import map_coordinates

    rng = np.random.default_rng(5)
    whole = rng.integers(0, 200, (7, 6, 9)).astype(dtype)
    n = np.array(whole.shape[::-1], np.int64)
    idx = rng.uniform(-1.0, n, (4000, 3))
    idx[:20] = n - 0.5 - 1e-9  # (the last half voxel: clamped)
    idx[20:40] = -0.5
    idx = np.ascontiguousarray(idx[np.floor(idx[:, 1]) >= 1])  # (none reads the first row)
    got = np.empty(len(idx))
    K.sample_linear(np.ascontiguousarray(whole[:, 1:]), idx, np.array([0, 1, 0], np.int64), n,
                    -5.0, got)
    inside = np.all((idx >= -0.5) & (idx < n - 0.5), axis=1)
    expect = map_coordinates(whole.astype(float), idx[inside, ::-1].T, order=1, mode="nearest")
    assert inside.sum() > 1000 and (~inside).sum() > 100
    np.testing.assert_allclose(got[inside], expect, rtol=0, atol=1e-9)
    assert np.all(got[~inside] == -5.0)


def test_sample_nearest_rounds_half_up_and_clamps_to_the_buffer():
    """ITK's nearest: ``k + 0.5`` samples ``k + 1``; ``[-0.5, 0)`` and ``[n - 1, n - 0.5)``
    the edge samples; ``n - 0.5`` and beyond, the background."""
    img = np.arange(4, dtype=np.int16).reshape(1, 1, 4) * 10
    x = np.array([-0.5, -0.2, 0.5, 1.5, 2.49, 2.5, 3.4, np.nextafter(3.5, 0), 3.5, -0.51])
    idx = np.ascontiguousarray(np.stack([x, np.zeros_like(x), np.zeros_like(x)], -1))
    out = np.empty(len(x), np.int16)
    K.sample_nearest(img, idx, np.zeros(3, np.int64), np.array([4, 1, 1]), np.int16(-1), out)
    assert out.tolist() == [0, 0, 10, 20, 20, 30, 30, 30, -1, -1]


def test_field_map_is_map_coordinates_and_windows_map_as_the_whole():
    """``p + u(p)`` against scipy per component, points outside unmoved, NaN reported; a window
    of the vectors maps its points as the whole field does (the same bits)."""
    from scipy.ndimage import map_coordinates

    rng = np.random.default_rng(6)
    vec = rng.normal(0, 2, (6, 7, 8, 3)).astype(np.float32)
    n = np.array([8, 7, 6], np.int64)
    mat = np.diag([1.5, 0.8, 1.2])
    origin = np.array([3.0, -2.0, 1.0])
    idx = rng.uniform(-1.5, n + 0.5, (3000, 3))
    p = np.ascontiguousarray(idx @ mat.T + origin)
    idx = (p - origin) @ np.linalg.inv(mat).T  # (the kernel's own indices, nearly)
    out = np.empty_like(p)
    args = (p, np.linalg.inv(mat), origin)
    assert K.field_map(vec, *args, np.zeros(3, np.int64), n, out) == -1
    inside = np.all((idx >= -0.5 + 1e-9) & (idx < n - 0.5 - 1e-9), axis=1)
    u = np.stack([map_coordinates(vec[..., c].astype(float), idx[inside, ::-1].T, order=1,
                                  mode="nearest") for c in range(3)], -1)
    np.testing.assert_allclose(out[inside] - p[inside], u, rtol=0, atol=1e-9)
    outside = np.all((idx < -0.5 - 1e-9) | (idx >= n - 0.5 + 1e-9), axis=1)
    assert outside.any() and np.array_equal(out[outside], p[outside])
    # a window covering the points of a box maps them as the whole
    box = np.all((idx >= 1.2) & (idx < [5.0, 4.0, 3.0]), axis=1)
    q = np.ascontiguousarray(p[box])
    win, whole = np.empty_like(q), np.empty_like(q)
    K.field_map(vec, q, *args[1:], np.zeros(3, np.int64), n, whole)
    K.field_map(vec[1:5, 1:6, 1:7], q, *args[1:], np.ones(3, np.int64), n, win)
    assert len(q) > 50 and np.array_equal(win.view(np.uint64), whole.view(np.uint64))
    vec[2, 3, 4] = np.nan  # (the points it neighbours: NaN, the first one reported)
    reach = np.flatnonzero(np.all(np.abs(idx - [4, 3, 2]) < 1, axis=1))
    assert K.field_map(vec, *args, np.zeros(3, np.int64), n, out) == reach[0]
    assert np.isnan(out[reach]).all() and np.isfinite(np.delete(out, reach, 0)).all()


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_field_map_near_a_node_takes_no_nan_from_beyond_it(axis):
    """A point within 1e-4 voxel of finite nodes takes no NaN from the nodes one voxel on.

    ``warp --grid grow`` exports NaN where a node has no preimage; the same grid read
    back from a NIfTI (float32 origin) lies about 3e-6 voxel off, and every point on the
    field's last finite face blended NaN with a weight of 3e-6: the background. Points
    further in than 1e-4 still take the NaN (and are reported).
    """
    rng = np.random.default_rng(8)
    vec = rng.normal(0, 2, (6, 7, 8, 3))
    n = np.array([8, 7, 6], np.int64)
    beyond = [slice(None)] * 3
    beyond[2 - axis] = slice(4, None)  # (nodes 4.. of the axis: no preimage)
    vec[tuple(beyond)] = np.nan
    idx = rng.uniform(0, n - 1, (500, 3))
    idx[:, axis] = 3.0
    out = np.empty_like(idx)
    zero, eye = np.zeros(3, np.int64), np.eye(3)
    exact = np.empty_like(idx)
    assert K.field_map(vec, np.ascontiguousarray(idx), eye, np.zeros(3), zero, n, exact) == -1
    for off in (3e-6, -3e-6, 9e-5):
        p = idx.copy()
        p[:, axis] += off
        assert K.field_map(vec, p, eye, np.zeros(3), zero, n, out) == -1, off
        # (the node's own displacement, as on the exact grid, to off times the gradient)
        np.testing.assert_allclose(out - p, exact - idx, rtol=0, atol=abs(off) * 20)
    p = idx.copy()
    p[:, axis] += 2e-4
    assert K.field_map(vec, p, eye, np.zeros(3), zero, n, out) == 0
    assert np.isnan(out).all(axis=1).all()


def _node_case(shape, shift, oblique, seed):
    """A field with 3 voxels of margin round an output grid ``shift`` voxels off its nodes."""
    from volwarp_cli.transforms.model import DisplacementField, GridFrame

    rng = np.random.default_rng(seed)
    size = tuple(n + 6 for n in shape[::-1])  # (x, y, z)
    vec = rng.normal(0, 2, size[::-1] + (3,)).astype(np.float32)
    if oblique:
        a, b = 0.3, -0.2
        rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
        direction, spacing, origin = rz @ rx, np.array([0.9375, 1.1, 0.7]), np.array([-91.3, 4.7, 12.1])
    else:  # (binary fractions: the kernel's own indices are whole, its sums exact)
        direction, spacing, origin = np.eye(3), np.array([1.0, 2.0, 0.5]), np.array([-8.0, 4.0, 1.5])
    frame = GridFrame(size, origin, spacing, direction)
    m = frame.matrix
    grid = Affine(m, origin + m @ (np.array(shift, float) + 3), "grid")
    return DisplacementField(frame, vec, "field"), grid


@settings(max_examples=60, deadline=None)
@given(shape=st.tuples(*[st.integers(1, 7)] * 3), shift=st.tuples(*[st.integers(-3, 3)] * 3),
       oblique=st.booleans(), seed=st.integers(0, 2 ** 16))
def test_a_field_on_the_output_grid_adds_the_vectors_its_kernel_interpolates(shape, shift,
                                                                             oblique, seed):
    """A field whose nodes are the output's voxels (ANTs' warp on its fixed grid): its vectors
    are added as they lie, what the interpolating kernel gives there (the same bits where its
    indices are whole; within 1e-9 mm where rounding puts them a hair off). A window of the
    field adds as the whole; a box across the field's edge adds its nodes on the field and
    leaves the rest, as the kernel does (an output's blocks across it: the whole's bytes); a
    grid off the nodes, or a box beyond the window, is left to the kernel (False, nothing
    added)."""
    field, grid = _node_case(shape, shift, oblique, seed)
    lo, hi = np.zeros(3, np.int64), np.array(shape[::-1], np.int64)
    p = np.empty((int(np.prod(shape)), 3))
    K.grid_points(lo, hi, grid.matrix, grid.offset, p)
    ref = field.map(p)
    q = p.copy()
    assert field.add_nodes(grid, lo, hi, q)
    if oblique:
        np.testing.assert_allclose(q, ref, rtol=0, atol=1e-9)
    else:
        assert np.array_equal(q.view(np.uint64), ref.view(np.uint64))
    # a window of the vectors: the box's nodes and one voxel more on each side
    from volwarp_cli.transforms.model import DisplacementField

    a = np.maximum(lo + np.array(shift) + 2, 0)
    b = np.minimum(hi + np.array(shift) + 4, field.frame.size)
    win = DisplacementField(field.frame, field.vectors[a[2]:b[2], a[1]:b[1], a[0]:b[0]],
                            "field", offset=tuple(int(v) for v in a))
    w = p.copy()
    assert win.add_nodes(grid, lo, hi, w) and np.array_equal(w, q)
    # half a voxel off the nodes, turned, or reaching past the window on the field: the kernel's
    half = Affine(grid.matrix, grid.offset + grid.matrix @ [0.5, 0, 0], "grid")
    turned = Affine(grid.matrix @ np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]), grid.offset,
                    "grid")
    across = np.empty((int(np.prod(hi - lo + 7)), 3))
    K.grid_points(lo - 7, hi, grid.matrix, grid.offset, across)
    ref = field.map(across)
    assert field.add_nodes(grid, lo - 7, hi, across)
    if oblique:
        np.testing.assert_allclose(across, ref, rtol=0, atol=1e-9)
    else:
        assert np.array_equal(across.view(np.uint64), ref.view(np.uint64))
    first = lo + np.array(shift) + 3  # (the box's first node: a window without it)
    cut = DisplacementField(field.frame, field.vectors[first[2] + 1:, first[1]:, first[0]:],
                            "field", offset=(int(first[0]), int(first[1]), int(first[2]) + 1))
    for g, box, f in ((half, (lo, hi), field), (turned, (lo, hi), field),
                      (grid, (lo, hi), cut)):
        r = np.empty((int(np.prod(box[1] - box[0])), 3))
        K.grid_points(box[0], box[1], g.matrix, g.offset, r)
        before = r.copy()
        assert not f.add_nodes(g, *box, r) and np.array_equal(r, before)


def test_apply_adds_the_nodes_of_a_field_on_its_grid_and_samples_as_through_the_kernel(
        monkeypatch):
    """A resampling whose field lies on the output grid never calls the interpolating kernel
    (it would raise here), and its output is the one the kernel gives (forced: the same
    bytes, the indices being whole)."""
    from volwarp_cli.transforms import model

    rng = np.random.default_rng(5)
    data = rng.normal(100, 30, (9, 10, 11)).astype(np.float32)
    vol = Volume(data, spacing=(1.0, 2.0, 0.5), origin=(-8.0, 4.0, 1.5))
    # (the field's frame: 3 voxels wider than the volume's grid on every side)
    frame = model.GridFrame((17, 16, 15), np.array([-11.0, -2.0, 0.0]), np.array([1.0, 2.0, 0.5]),
                            np.eye(3))
    field = model.DisplacementField(frame, rng.normal(0, 1.5, (15, 16, 17, 3)).astype(np.float32),
                                    "field")
    chain = Chain([field, Affine(np.diag([1.01, 0.99, 1.0]), np.array([0.3, -0.2, 0.1]))])

    op = plan_resample(vol.header, data, chain, interpolation="linear")  # (its coverage
    real = K.field_map                                                   # check maps points)
    monkeypatch.setattr(K, "field_map", lambda *a: (_ for _ in ()).throw(AssertionError("called")))
    nodes = compute_whole(op)["resampled"]
    monkeypatch.setattr(K, "field_map", real)
    monkeypatch.setattr(model.DisplacementField, "add_nodes", lambda *a: False)
    through = compute_whole(op)["resampled"]
    assert np.array_equal(nodes, through) and np.isfinite(nodes).all()
    assert np.count_nonzero(nodes != compute_whole(
        plan_resample(vol.header, data, Chain(chain.steps[1:]), interpolation="linear")
    )["resampled"]) > 0.5 * nodes.size  # (the field moves the samples)


def test_a_nan_node_of_a_field_on_the_output_grid_moves_its_point_to_nan():
    field, grid = _node_case((4, 5, 6), (1, 0, -1), False, 3)
    field.vectors[5, 4, 6] = np.nan  # (z, y, x): the node of the output's (x 2, y 1, z 3)
    lo, hi = np.zeros(3, np.int64), np.array([6, 5, 4], np.int64)
    p = np.empty((120, 3))
    K.grid_points(lo, hi, grid.matrix, grid.offset, p)
    assert field.add_nodes(grid, lo, hi, p)
    bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
    assert bad.tolist() == [(3 * 5 + 1) * 6 + 2]  # (its neighbours' points: not moved there)


def test_apply_imports_no_numba(tmp_path):
    """`volwarp apply` through an affine, a displacement field and a B-spline (each
    interpolation) loads no numba: its kernels are C (numba's start-up was half the run)."""
    from volwarp_cli.io import write_volume

    rng = np.random.default_rng(2)
    write_volume(Volume(rng.normal(100, 20, (12, 13, 14)).astype(np.float32)),
                 tmp_path / "in.nrrd")
    a = sitk.AffineTransform(3)
    a.SetMatrix([1.02, 0.05, 0.0, -0.03, 0.97, 0.04, 0.02, 0.0, 1.05])
    a.SetTranslation([0.5, -0.3, 0.2])
    sitk.WriteTransform(a, str(tmp_path / "a.tfm"))
    field = sitk.GetImageFromArray(rng.normal(0, 0.5, (12, 13, 14, 3)), isVector=True)
    sitk.WriteImage(sitk.Cast(field, sitk.sitkVectorFloat32), str(tmp_path / "f.nii.gz"))
    b = sitk.BSplineTransformInitializer(sitk.Image([14, 13, 12], sitk.sitkFloat32), [3, 3, 3])
    b.SetParameters(rng.normal(0, 0.3, len(b.GetParameters())).tolist())
    sitk.WriteTransform(b, str(tmp_path / "b.tfm"))
    code = textwrap.dedent("""
        import sys
        from volwarp_cli.cli.main import main
        for i in ("linear", "nearest", "bspline"):
            args = ["apply", "in.nrrd", "-o", f"out_{i}.nrrd", "-t", "f.nii.gz", "-t",
                    "a.tfm", "-t", "b.tfm", "--interpolation", i]
            assert main(args) == 0, i
        assert "numba" not in sys.modules
    """)
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert len(list(tmp_path.glob("out_*.nrrd"))) == 3


def _tile_range_reference(vec, tile):
    """Per-tile NaN-skipping extremes by numpy (NaN where a tile holds no number)."""
    tiles = [-(-n // tile) for n in vec.shape[:3]]
    tmin, tmax = np.full((*tiles, 3), np.nan), np.full((*tiles, 3), np.nan)
    for k in np.ndindex(*tiles):
        block = vec[tuple(slice(i * tile, (i + 1) * tile) for i in k)].reshape(-1, 3)
        numbers = ~np.isnan(block)
        for c in range(3):
            if numbers[:, c].any():
                values = block[numbers[:, c], c]
                tmin[k][c], tmax[k][c] = values.min(), values.max()
    return tmin, tmax


@settings(max_examples=120, deadline=None)
@given(shape=st.tuples(*[st.integers(1, 21)] * 3), tile=st.sampled_from([1, 2, 3, 5, 16, 2 ** 61]),
       dtype=st.sampled_from([np.float32, np.float64]), layout=st.sampled_from(
           ["contiguous", "x strided", "components reversed", "z reversed"]),
       holes=st.floats(0, 1), seed=st.integers(0, 2 ** 16))
def test_tile_range_is_numpys_per_tile_extremes(shape, tile, dtype, layout, holes, seed):
    """The tile kernel (rows of lanes where x runs contiguous; else sample by sample) against
    numpy, with NaN holes (whole tiles of them too), infinities and signed zeros."""
    rng = np.random.default_rng(seed)
    nz, ny, nx = shape
    whole = rng.normal(size=(nz, ny, 2 * nx, 3)) * 10.0 ** rng.integers(-3, 4)
    whole[rng.random(whole.shape) < holes] = np.nan
    whole[rng.random(whole.shape) < 0.02] = np.inf
    whole[rng.random(whole.shape) < 0.02] = -np.inf
    whole[rng.random(whole.shape) < 0.05] = -0.0
    whole = whole.astype(dtype)
    vec = {"contiguous": whole[:, :, :nx], "x strided": whole[:, :, ::2],
           "components reversed": whole[:, :, :nx, ::-1],
           "z reversed": whole[::-1, :, :nx]}[layout]
    want = _tile_range_reference(vec, tile)
    tiles = [-(-n // tile) for n in shape]
    got = np.full((*tiles, 3), np.nan), np.full((*tiles, 3), np.nan)
    K.tile_range(vec, tile, *got)
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g, w, equal_nan=True)
    # rows of tiles given in two calls (a field read slab by slab) come to the same
    if tiles[0] > 1:
        parts = np.full((*tiles, 3), np.nan), np.full((*tiles, 3), np.nan)
        K.tile_range(vec[:tile], tile, parts[0][:1], parts[1][:1])
        K.tile_range(vec[tile:], tile, parts[0][1:], parts[1][1:])
        for g, w in zip(parts, want, strict=True):
            assert np.array_equal(g, w, equal_nan=True)
