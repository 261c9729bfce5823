"""Duplicates in a DICOM series folder: exact copies dropped, other duplicates by --duplicates.

A file copied within a series folder (``cp IM0002.dcm IM0002-copy.dcm``) has the
SOPInstanceUID and the pixels of its original: one image stored twice. It used to
count as a second image at its position, which split a series whose AcquisitionNumber
changes half way into two partial volumes (and --duplicates first did not help).
Several images at one position that are not copies are duplicates, which --duplicates
first|last resolves, whatever their AcquisitionNumber; only whole stacks at the same
positions (time points, repeated acquisitions) stay candidates of their own. The
series are written with pydicom by ``test_io_dicom.write_series``.
"""

from __future__ import annotations

import shutil

import numpy as np
import pydicom
import pytest
from pydicom.uid import RLELossless
from test_io_dicom import write_series, write_slice

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume
from volwarp_cli.io.dicom import read_dicom, scan_dicom
from volwarp_cli.io.dicom._read import open_dicom_lazy

WARNING = "exact duplicate file(s) dropped"


@pytest.fixture
def ramp():
    rng = np.random.default_rng(11)
    return rng.integers(-1000, 3000, size=(6, 5, 7)).astype(np.int16)


def two_acquisitions(folder, stored, **kw):
    """A series whose AcquisitionNumber is 1 for the lower three slices, 2 for the upper."""
    return write_series(folder, stored, shuffle=False,
                        per_slice=[{"AcquisitionNumber": 1 + k // 3} for k in range(6)], **kw)


def one_line_warning(stderr: str) -> None:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("volwarp: warning: "), stderr
    assert f"1 {WARNING}" in lines[0] and "IM0001-copy.dcm" in lines[0], stderr


def test_an_exact_copy_does_not_split_the_series(tmp_path, ramp):
    paths = two_acquisitions(tmp_path / "s", ramp)
    shutil.copy(paths[1], tmp_path / "s" / "IM0001-copy.dcm")
    cands = scan_dicom(tmp_path / "s")  # was: AcquisitionNumber 1 and 2, 3 slices each
    assert len(cands) == 1 and cands[0].shape_xyz == (7, 5, 6) and cands[0].n_files == 6
    np.testing.assert_array_equal(read_dicom(tmp_path / "s").data, ramp)
    template, lazy = open_dicom_lazy(tmp_path / "s")
    np.testing.assert_array_equal(np.asarray(lazy), ramp)
    assert template.shape_xyz == (7, 5, 6)


def test_info_and_convert_drop_the_copy_with_one_warning(run, tmp_path, ramp):
    paths = two_acquisitions(tmp_path / "s", ramp)
    shutil.copy(paths[1], tmp_path / "s" / "IM0001-copy.dcm")
    res = run("info", tmp_path / "s")
    assert res.code == 0, res
    assert "shape:     7 5 6" in res.stdout and "candidates: 1 volume" in res.stdout
    one_line_warning(res.stderr)
    for extra in ([], ["--duplicates", "first"]):
        out = tmp_path / f"o{len(extra)}.nrrd"
        res = run("convert", tmp_path / "s", "-o", out, *extra)
        assert res.code == 0, res
        one_line_warning(res.stderr)
        np.testing.assert_array_equal(read_volume(out).data, ramp)


def test_the_series_listing_counts_no_copy(run, tmp_path, ramp):
    import json

    write_series(tmp_path / "study" / "a", ramp, per_slice=[{"AcquisitionNumber": k + 1}
                                                            for k in range(6)])
    paths = write_series(tmp_path / "study" / "b", ramp[:3], series="1.2.826.0.1.3680043.8.498.2",
                         names=[f"B{k}.dcm" for k in range(3)])
    shutil.copy(paths[0], tmp_path / "study" / "b" / "IM0001-copy.dcm")
    # every slice its own AcquisitionNumber (as some scanners write) and a copy in series a
    shutil.copy(tmp_path / "study" / "a" / "IM0001.dcm", tmp_path / "study" / "a" /
                "IM0001-copy.dcm")
    res = run("info", tmp_path / "study", "--json")
    assert res.code == 0, res
    cands = json.loads(res.stdout)["candidates"]
    assert [(c["shape_xyz"], c["files"]) for c in cands] == [([7, 5, 6], 6), ([7, 5, 3], 3)]
    assert res.stderr.count("volwarp: warning: ") == 1 and f"2 {WARNING}" in res.stderr
    out = tmp_path / "a.nrrd"
    res = run("convert", tmp_path / "study", "--series", "0", "-o", out)
    assert res.code == 0, res
    np.testing.assert_array_equal(read_volume(out).data, ramp)


def test_a_compressed_copy_is_dropped_too(tmp_path, ramp):
    paths = write_series(tmp_path / "s", ramp, transfer_syntax=RLELossless,
                         per_slice=[{"AcquisitionNumber": 1 + k // 3} for k in range(6)])
    shutil.copy(paths[4], tmp_path / "s" / "copy.dcm")
    np.testing.assert_array_equal(read_dicom(tmp_path / "s").data, ramp)


def test_a_copy_of_a_multi_frame_file(tmp_path):
    from pydicom.data import get_testdata_file

    src = get_testdata_file("emri_small.dcm")
    (tmp_path / "m").mkdir()
    shutil.copy(src, tmp_path / "m" / "a.dcm")
    shutil.copy(src, tmp_path / "m" / "b.dcm")
    cands = scan_dicom(tmp_path / "m")
    assert len(cands) == 1 and cands[0].n_files == 1
    np.testing.assert_array_equal(read_dicom(tmp_path / "m").data, read_dicom(src).data)


def test_the_same_uid_with_other_pixels_is_a_duplicate_position(run, tmp_path, ramp):
    """Not a copy: neither image is dropped silently; --duplicates chooses."""
    paths = two_acquisitions(tmp_path / "s", ramp)
    ds = pydicom.dcmread(paths[1])
    ds.PixelData = (ramp[1] + 5).astype("<i2").tobytes()
    ds.save_as(tmp_path / "s" / "IM0001b.dcm")  # (after IM0001.dcm in file order)
    with pytest.raises(FormatError, match="IM0001.dcm and IM0001b.dcm"):
        read_dicom(tmp_path / "s")
    last = read_dicom(tmp_path / "s", duplicates="last").data
    np.testing.assert_array_equal(last[1], ramp[1] + 5)
    res = run("convert", tmp_path / "s", "-o", tmp_path / "o.nrrd")
    assert res.code == 1 and len(res.stderr.strip().splitlines()) == 1, res
    assert "--duplicates first|last" in res.stderr and not (tmp_path / "o.nrrd").exists()


@pytest.mark.parametrize("chunked", [False, True])
def test_a_reacquired_slice_is_governed_by_duplicates(run, tmp_path, ramp, chunked):
    """A slice acquired again (AcquisitionNumber 2) used to make a candidate of one slice."""
    write_series(tmp_path / "s", ramp, per_slice=[{"AcquisitionNumber": 1}] * 6)
    write_slice(tmp_path / "s" / "redo.dcm", ramp[3] + 9, position=(-10.0, 20.0, 37.5),
                extra={"AcquisitionNumber": 2})
    cands = scan_dicom(tmp_path / "s")
    assert len(cands) == 1 and cands[0].n_files == 7
    with pytest.raises(FormatError, match="share slice positions"):
        read_dicom(tmp_path / "s")
    first = read_dicom(tmp_path / "s", duplicates="first")
    np.testing.assert_array_equal(first.data, ramp)
    expected = ramp.copy()
    expected[3] += 9
    np.testing.assert_array_equal(read_dicom(tmp_path / "s", duplicates="last").data, expected)
    _, lazy = open_dicom_lazy(tmp_path / "s", duplicates="last")
    np.testing.assert_array_equal(np.asarray(lazy), expected)
    extra = ["--chunked", "--block", "3,3,3"] if chunked else []
    out = tmp_path / "d.nrrd"
    res = run("distance", tmp_path / "s", "--iso", "500", "--surface", "voxel", "-o", out,
              *extra)
    assert res.code == 1 and "--duplicates first|last" in res.stderr and not out.exists()
    res = run("distance", tmp_path / "s", "--iso", "500", "--surface", "voxel", "-o", out,
              "--duplicates", "last", *extra)
    assert res.code == 0, res
    ref = tmp_path / "ref.nrrd"
    assert run("distance", ref.parent / "s", "--iso", "500", "--surface", "voxel", "-o", ref,
               "--duplicates", "last").code == 0
    np.testing.assert_array_equal(read_volume(out).data, read_volume(ref).data)


def test_time_points_stay_candidates_of_their_own(tmp_path, ramp):
    """Whole stacks at the same positions are not duplicates (a copy among them is)."""
    paths = write_series(tmp_path / "s", ramp, per_slice=[{"TemporalPositionIdentifier": 1}] * 6)
    write_series(tmp_path / "s", ramp + 1, per_slice=[{"TemporalPositionIdentifier": 2}] * 6,
                 names=[f"T2_{k}.dcm" for k in range(6)])
    shutil.copy(paths[0], tmp_path / "s" / "copy.dcm")
    cands = scan_dicom(tmp_path / "s")
    assert [c.n_files for c in cands] == [6, 6]
    assert all("TemporalPositionIdentifier" in c.why for c in cands)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s", series=1).data, ramp + 1)


def test_first_and_last_follow_the_file_order_not_the_position(tmp_path, ramp):
    """Duplicates a few micrometres apart: --duplicates keeps the first/last file, as documented.

    The images sorted by position before the choice, so "first" took the lowest of them
    (here the last file) and "last" the highest (the first file).
    """
    write_series(tmp_path / "s", ramp)  # IM0000.dcm ... IM0005.dcm, slice 2 at z 35
    write_slice(tmp_path / "s" / "A-early.dcm", ramp[2] + 7, position=(-10.0, 20.0, 35.004))
    write_slice(tmp_path / "s" / "Z-late.dcm", ramp[2] + 9, position=(-10.0, 20.0, 34.996))
    for mode, added in (("first", 7), ("last", 9)):
        vol = read_dicom(tmp_path / "s", duplicates=mode)
        expected = ramp.copy()
        expected[2] += added
        np.testing.assert_array_equal(vol.data, expected)
        _, lazy = open_dicom_lazy(tmp_path / "s", duplicates=mode)
        np.testing.assert_array_equal(np.asarray(lazy), expected)
