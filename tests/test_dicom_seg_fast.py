"""The fast SEG reader (pydicom's data set, no highdicom frame table) gives highdicom's label map.

``dicom_seg._fast_frames`` reads the common SEG (uncompressed, shared orientation
and pixel spacing, one plane position per frame); everything else goes through
highdicom's ``get_volume``. Both are run on the same files here: BINARY (frames
whose bits run on across bytes: 7x9 pixels; and of whole bytes), FRACTIONAL and LABELMAP SEGs of
random label maps with empty slices left out, one segment as a mask, overlapping
segments, and a compressed SEG (highdicom's path only).
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

from test_dicom_seg import OBLIQUE, make_seg, masks_of, write_ct  # noqa: E402

from volwarp_cli.errors import VolwarpError  # noqa: E402
from volwarp_cli.io import dicom_seg  # noqa: E402
from volwarp_cli.io.dicom_seg import open_seg, read_seg  # noqa: E402


def both(path, **kw):
    """``(fast, highdicom's)`` Volumes of the SEG at ``path`` (the fast one must be taken)."""
    ds = open_seg(path)
    assert dicom_seg._fast_frames(ds, str(path), kw.get("segment")) is not None
    fast = read_seg(path, **kw)
    saved = dicom_seg._fast_frames
    dicom_seg._fast_frames = lambda *a: None
    try:
        slow = read_seg(path, **kw)
    finally:
        dicom_seg._fast_frames = saved
    return fast, slow


def same(a, b) -> None:
    assert a.data.dtype == b.data.dtype
    np.testing.assert_array_equal(a.data, b.data)
    np.testing.assert_allclose(a.spacing, b.spacing, rtol=1e-9)
    np.testing.assert_allclose(a.origin, b.origin, atol=1e-6)
    np.testing.assert_allclose(a.direction, b.direction, atol=1e-9)
    assert a.meta == b.meta


def random_labels(rng, shape, n) -> np.ndarray:
    lab = rng.integers(0, n + 1, size=shape).astype(np.uint8)
    lab[rng.random(shape) < 0.5] = 0
    lab[0] = 0  # empty slices at the start and inside: left out of the SEG
    lab[shape[0] // 2] = 0
    return lab


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("kind", ["BINARY", "FRACTIONAL", "LABELMAP"])
def test_fast_reader_equals_highdicoms(tmp_path, kind, seed):
    rng = np.random.default_rng(seed)
    # 63 pixels a frame: a BINARY frame's bits run on into the next byte; 72: whole bytes
    shape = (6, 7, 9) if seed == 0 else (6, 8, 9)
    orientation = OBLIQUE if seed == 0 else (1.0, 0.0, 0.0, 0.0, 0.0, -1.0)
    paths = write_ct(tmp_path / "ct", shape, orientation=orientation, seed=seed)
    lab = random_labels(rng, shape, 3)
    pixels = lab if kind == "LABELMAP" else masks_of(lab)
    if kind == "FRACTIONAL":  # fractions around one half: the threshold is at half the maximum
        pixels = (pixels * rng.uniform(0.45, 1.0, size=pixels.shape)).astype(np.float32)
    seg = make_seg(paths, pixels, kind, tmp_path / "seg.dcm")
    fast, slow = both(seg)
    same(fast, slow)
    if kind != "FRACTIONAL":
        assert fast.data.shape[0] == shape[0] - 1  # (the first slice is left out)
        np.testing.assert_array_equal(fast.data, lab[1:])
    for n in (1, 3):
        same(*both(seg, segment=n))


def test_overlapping_segments_are_refused_both_ways(tmp_path):
    paths = write_ct(tmp_path / "ct", (3, 8, 8))
    masks = np.zeros((3, 8, 8, 2), bool)
    masks[1, 2:5, 2:5, 0] = True
    masks[1, 4:6, 4:6, 1] = True
    seg = make_seg(paths, masks, "BINARY", tmp_path / "seg.dcm")
    with pytest.raises(VolwarpError, match="--segment N"):
        read_seg(seg)
    saved = dicom_seg._fast_frames
    dicom_seg._fast_frames = lambda *a: None
    try:
        with pytest.raises(VolwarpError, match="--segment N"):
            read_seg(seg)
    finally:
        dicom_seg._fast_frames = saved
    same(*both(seg, segment=2))


def test_a_compressed_seg_is_read_by_highdicom(tmp_path):
    from pydicom.uid import RLELossless

    paths = write_ct(tmp_path / "ct", (4, 8, 8))
    lab = np.zeros((4, 8, 8), np.uint8)
    lab[1:3, 2:6, 1:4] = 2
    lab[2, 0, 0] = 1
    seg = make_seg(paths, lab, "LABELMAP", tmp_path / "seg.dcm", transfer_syntax_uid=RLELossless)
    assert dicom_seg._fast_frames(open_seg(seg), str(seg), None) is None
    np.testing.assert_array_equal(read_seg(seg).data, lab[1:3])
