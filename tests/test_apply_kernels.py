"""`volwarp apply`'s sampling: cubic B-splines on tiny axes, and the memory a block counts."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from volwarp_cli.apply import plan_resample
from volwarp_cli.box import Box
from volwarp_cli.execute import compute_whole
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
    op.compute(Box((0, 0, 0), (2, 2, 2)), threads=threads)  # (scipy imported, kernels loaded)
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
