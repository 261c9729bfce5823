"""A SEG or RTSTRUCT against an enhanced (multi-frame) CT: one file, one SOP Instance for every slice.

The reference is pydicom-data's ``eCT_Supplemental.dcm`` (Enhanced CT Image Storage,
two 512x512 frames 10 mm apart, stored in the opposite order to volwarp's z order:
frame 2 is slice 0). A label map on its grid is written as a BINARY and a LABELMAP
SEG (highdicom takes the one multi-frame data set and the frames in the file's
order) and as an RTSTRUCT (each contour's image reference names the frame,
ReferencedFrameNumber; the referenced series lists the image once, with both
frames), and reads back exactly. Independent checks: highdicom's own mapping of the
SEG's frames to the source frames (``get_pixels_by_source_frame``), and each
contour's points lying in the plane of the frame it references, by the frame's
PlanePositionSequence and the shared PlaneOrientationSequence read here with pydicom.
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

from pydicom.data import get_testdata_file  # noqa: E402

from volwarp_cli.io import read_volume, write_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom, read_reference  # noqa: E402


@pytest.fixture(scope="module")
def enhanced_ct():
    path = get_testdata_file("eCT_Supplemental.dcm", download=False)  # (no network in tests)
    if path is None:  # (pydicom-data, in the test extras, ships it)
        pytest.skip("pydicom-data's eCT_Supplemental.dcm is not installed")
    return path


def frame_planes(path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Frame number -> (ImagePositionPatient, slice normal), from the file's functional groups."""
    ds = pydicom.dcmread(path, stop_before_pixels=True)
    iop = np.array(ds.SharedFunctionalGroupsSequence[0].PlaneOrientationSequence[0]
                   .ImageOrientationPatient, float)
    normal = np.cross(iop[:3], iop[3:])
    return {n: (np.array(f.PlanePositionSequence[0].ImagePositionPatient, float), normal)
            for n, f in enumerate(ds.PerFrameFunctionalGroupsSequence, 1)}


def phantom(shape) -> np.ndarray:
    lab = np.zeros(shape, np.uint8)
    lab[0, 100:140, 200:260] = 3
    lab[0, 150:160, 150:170] = 3
    lab[0, 152:158, 155:165] = 0         # a hole
    lab[1, 300:310, 50:70] = 5
    lab[1, 10, 20] = 3                   # one voxel, near a corner
    return lab


@pytest.fixture
def case(enhanced_ct, tmp_path):
    grid = read_dicom(enhanced_ct)
    lab = phantom(grid.data.shape)
    src = tmp_path / "labels.nrrd"
    write_volume(grid.with_data(lab), src)
    return enhanced_ct, grid, lab, src


def test_the_reference_names_each_slice_s_frame(enhanced_ct):
    ref = read_reference(enhanced_ct)
    assert ref.multi_frame and len(set(ref.sop_uids)) == 1 and len(set(ref.files)) == 1
    # volwarp's slices go along the normal: frame 2 (further along it) is... checked by hand
    planes = frame_planes(enhanced_ct)
    along = {n: float(p @ normal) for n, (p, normal) in planes.items()}
    assert list(ref.frame_numbers) == sorted(along, key=along.get)
    for k, n in enumerate(ref.frame_numbers):
        np.testing.assert_allclose(ref.grid.index_to_world([0, 0, k]), planes[n][0], atol=1e-6)


@pytest.mark.parametrize("dicom_type", ["seg", "labelmap-seg"])
def test_a_seg_against_an_enhanced_ct_reads_back_and_names_the_right_frames(case, tmp_path, run,
                                                                        dicom_type):
    ct, grid, lab, src = case
    out = tmp_path / "seg.dcm"
    res = run("convert", src, "--reference", ct, "--dicom-type", dicom_type, "-o", out)
    assert res.code == 0, res.stderr
    # BINARY segments are numbered 1..K in label order; LABELMAP keeps the values
    want = np.searchsorted([0, 3, 5], lab).astype(np.uint8) if dicom_type == "seg" else lab
    back = tmp_path / "back.nrrd"
    assert run("convert", out, "--reference", ct, "-o", back).code == 0
    got = read_volume(back)
    np.testing.assert_array_equal(got.data, want)
    np.testing.assert_allclose(got.origin, grid.origin, atol=1e-9)
    # highdicom's own reading: the SEG's frames mapped to the source image's frames
    seg = hd.seg.segread(str(out))
    uid = str(pydicom.dcmread(ct, stop_before_pixels=True).SOPInstanceUID)
    ref = read_reference(ct)
    by_frame = seg.get_pixels_by_source_frame(uid, source_frame_numbers=[1, 2],
                                              combine_segments=True, relabel=False)
    for k, n in enumerate(ref.frame_numbers):
        np.testing.assert_array_equal(by_frame[n - 1], want[k])
    assert str(seg.SOPInstanceUID) != uid and str(seg.SeriesInstanceUID) != ref.series_uid


def test_an_rtstruct_against_an_enhanced_ct_references_frames(case, tmp_path, run):
    ct, grid, lab, src = case
    out = tmp_path / "rs.dcm"
    res = run("convert", src, "--reference", ct, "--dicom-type", "rtstruct", "-o", out)
    assert res.code == 0, res.stderr
    back = tmp_path / "back.nrrd"
    assert run("convert", out, "--reference", ct, "-o", back).code == 0
    np.testing.assert_array_equal(read_volume(back).data, lab)

    ds = pydicom.dcmread(out)
    uid = str(pydicom.dcmread(ct, stop_before_pixels=True).SOPInstanceUID)
    series = (ds.ReferencedFrameOfReferenceSequence[0].RTReferencedStudySequence[0]
              .RTReferencedSeriesSequence[0])
    (image,) = series.ContourImageSequence  # the one image, once, with both its frames
    assert image.ReferencedSOPInstanceUID == uid
    assert [int(n) for n in image.ReferencedFrameNumber] == [1, 2]
    planes = frame_planes(ct)
    seen = set()
    for roi in ds.ROIContourSequence:
        for c in roi.ContourSequence:
            (ref,) = c.ContourImageSequence
            assert ref.ReferencedSOPInstanceUID == uid
            n = int(ref.ReferencedFrameNumber)
            position, normal = planes[n]
            pts = np.asarray(c.ContourData, float).reshape(-1, 3)
            assert np.abs((pts - position) @ normal).max() < 1e-3  # in that frame's plane
            seen.add(n)
    assert seen == {1, 2}


def test_a_single_frame_series_references_no_frame_numbers(tmp_path, run):
    from test_dicom_seg import write_ct

    folder = tmp_path / "ct"
    write_ct(folder, (3, 6, 7))
    grid = read_dicom(folder)
    lab = np.zeros(grid.data.shape, np.uint8)
    lab[1, 2:4, 2:5] = 1
    src = tmp_path / "labels.nrrd"
    write_volume(grid.with_data(lab), src)
    out = tmp_path / "rs.dcm"
    assert run("convert", src, "--reference", folder, "--dicom-type", "rtstruct",
               "-o", out).code == 0
    ds = pydicom.dcmread(out)
    series = (ds.ReferencedFrameOfReferenceSequence[0].RTReferencedStudySequence[0]
              .RTReferencedSeriesSequence[0])
    assert len(series.ContourImageSequence) == 3
    assert len({i.ReferencedSOPInstanceUID for i in series.ContourImageSequence}) == 3
    items = [i for roi in ds.ROIContourSequence for c in roi.ContourSequence
             for i in c.ContourImageSequence] + list(series.ContourImageSequence)
    assert not any("ReferencedFrameNumber" in i for i in items)
