"""RTSTRUCT ContourData parsed from the file's bytes: the numbers pydicom decodes, the same errors.

volwarp splits ContourData's DS bytes itself (pydicom's one ``DSfloat`` per number
was two thirds of reading a large RTSTRUCT). Checked against pydicom's own decoding
of the same file, on every spelling a DS value may take (signs, leading zeros,
exponents, padding, ``-0``); bad values are one error line naming the ROI and the
contour, nothing written: a word, a count that is not a multiple of 3, NaN, and a
single number (which used to end in an internal error).
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")

from test_dicom_seg import write_ct  # noqa: E402
from test_rtstruct import square, world, write_rtstruct  # noqa: E402

from volwarp_cli.io import read_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402
from volwarp_cli.io.rtstruct import _contour_data  # noqa: E402

SHAPE = (3, 9, 10)
#: valid DS spellings (PS3.5 6.2: up to 16 characters, sign, decimals, exponent, spaces)
SPELLINGS = ["{:+.4f}", "{:012.5f}", "{:.6e}", " {:.3f}", "{:.5E}", "{:.9g} "]


@pytest.fixture
def ct(tmp_path):
    folder = tmp_path / "ct"
    paths = write_ct(folder, SHAPE, spacing=(0.9, 0.7, 2.0), origin=(0.0, 0.0, 0.0),
                     orientation=(1, 0, 0, 0, 1, 0))
    return folder, paths, read_dicom(folder)


def with_contour_strings(path, strings_by_contour) -> None:
    """Rewrite ``path``'s contours' ContourData with the given DS strings."""
    ds = pydicom.dcmread(path)
    contours = [c for roi in ds.ROIContourSequence for c in roi.ContourSequence]
    for c, strings in zip(contours, strings_by_contour, strict=True):
        c.ContourData = strings
        c.NumberOfContourPoints = len(strings) // 3
    ds.save_as(path, enforce_file_format=True)


def test_contour_data_is_read_as_pydicom_decodes_it(ct, tmp_path, run):
    folder, paths, vol = ct
    pts = [world(vol, 1, square(2, 2, 6, 5)), world(vol, 2, [(0.0, 0.0), (3.0, 0.0)])]
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        5: ("box", [("CLOSED_PLANAR", pts[0])]), 6: ("bar", [("OPEN_PLANAR", pts[1])])})
    strings = [[SPELLINGS[n % len(SPELLINGS)].format(v) for n, v in enumerate(p.ravel())]
               for p in pts]
    strings[1][0] = "-0"  # (x of the bar's first point is 0: a negative zero)
    with_contour_strings(rs, strings)
    ds = pydicom.dcmread(rs)
    for roi in ds.ROIContourSequence:
        for c in roi.ContourSequence:
            ours = [float(v) for v in _contour_data(c)]  # (c not yet decoded: its bytes)
            theirs = [float(v) for v in pydicom.dcmread(rs).ROIContourSequence[
                int(roi.ReferencedROINumber) - 5].ContourSequence[0].ContourData]
            assert ours == theirs  # the same doubles
            assert [np.signbit(v) for v in ours] == [np.signbit(v) for v in theirs]
    out = tmp_path / "labels.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 0, res.stderr
    want = np.zeros(SHAPE, np.uint8)
    want[1, 2:6, 2:7] = 5
    want[2, 0, 0:4] = 6
    np.testing.assert_array_equal(read_volume(out).data, want)


@pytest.mark.parametrize("values, message", [
    (["1.5", "2.5", "abc"], "contour 1: ContourData is not numeric"),
    (["1.5", "2.5", "3.5", "4.5"], "ContourData must be finite x y z triples, got 4 values"),
    (["1.5", "nan", "3.5"], "ContourData must be finite x y z triples, got 3 values"),
    (["1.5"], "ContourData must be finite x y z triples, got 1 values"),
    (["1.5", "", "3.5"], "contour 1: ContourData is not numeric"),
], ids=["word", "four-values", "nan", "one-value", "empty-value"])
def test_bad_contour_data_is_one_error(ct, tmp_path, run, values, message):
    folder, paths, vol = ct
    rs = write_rtstruct(tmp_path / "rs.dcm", paths,
                        {5: ("box", [("CLOSED_PLANAR", world(vol, 1, square(2, 2, 6, 5)))])})
    # the bytes written as they are (pydicom would refuse these values when writing)
    ds = pydicom.dcmread(rs)
    c = ds.ROIContourSequence[0].ContourSequence[0]
    marker = "9" * 15
    c.ContourData = [marker] * len(values)
    ds.save_as(rs, enforce_file_format=True)
    raw = rs.read_bytes()
    text = "\\".join(values).encode()
    old = "\\".join([marker] * len(values)).encode()
    text += b" " * (len(old) - len(text))  # (same length: the element's length is kept)
    assert raw.count(old) == 1
    rs.write_bytes(raw.replace(old, text))
    out = tmp_path / "labels.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 1, res.stderr
    assert res.stderr.count("\n") == 1 and "internal error" not in res.stderr
    assert "ROI 5 'box'" in res.stderr and message in res.stderr
    assert not out.exists()
