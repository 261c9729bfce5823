"""DICOM series read against SimpleITK (GDCM) and pydicom: cases found by a hunt for silent errors."""

from __future__ import annotations

import copy

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
sitk = pytest.importorskip("SimpleITK")

from pydicom.data import get_testdata_file  # noqa: E402

from volwarp_cli.io.dicom import read_dicom  # noqa: E402

sitk.ProcessObject_SetGlobalWarningDisplay(False)

LEGACY_ENHANCED_MR = "1.2.840.10008.5.1.4.1.1.4.4"
LEGACY_ENHANCED_PET = "1.2.840.10008.5.1.4.1.1.128.1"


def one_frame_enhanced(path, sop, frame=0):
    """eCT_Supplemental's frame ``frame`` alone, as a file of SOP class ``sop``.

    Its position, orientation, pixel spacing and rescale (intercept -1024) are
    only in the functional groups.
    """
    ds = pydicom.dcmread(get_testdata_file("eCT_Supplemental.dcm"))
    assert "ImagePositionPatient" not in ds and "RescaleIntercept" not in ds
    one = copy.deepcopy(ds)
    one.SOPClassUID = one.file_meta.MediaStorageSOPClassUID = sop
    one.SOPInstanceUID = one.file_meta.MediaStorageSOPInstanceUID = pydicom.uid.generate_uid()
    one.NumberOfFrames = 1
    one.PerFrameFunctionalGroupsSequence = [ds.PerFrameFunctionalGroupsSequence[frame]]
    size = ds.Rows * ds.Columns * 2
    one.PixelData = ds.PixelData[frame * size:(frame + 1) * size]
    one.save_as(path)
    return one


@pytest.mark.parametrize("sop", [LEGACY_ENHANCED_MR, LEGACY_ENHANCED_PET])
def test_one_frame_file_with_functional_groups_takes_their_geometry_and_rescale(tmp_path, sop):
    """A one-frame file of an enhanced SOP class volwarp did not list (Legacy Converted
    Enhanced MR or PET) was read as if it had no geometry: origin 0, unit spacing,
    identity orientation, and its stored values without the intercept, exit 0."""
    path = tmp_path / "one.dcm"
    ds = one_frame_enhanced(path, sop)
    vol = read_dicom(path)
    img = sitk.ReadImage(str(path))
    assert vol.shape_xyz == img.GetSize()
    np.testing.assert_allclose(vol.origin, img.GetOrigin(), atol=1e-6)
    np.testing.assert_allclose(vol.spacing[:2], img.GetSpacing()[:2], atol=1e-9)
    np.testing.assert_allclose(vol.direction, np.reshape(img.GetDirection(), (3, 3)), atol=1e-9)
    pvt = ds.SharedFunctionalGroupsSequence[0].PixelValueTransformationSequence[0]
    expected = ds.pixel_array.astype(np.int64) * int(pvt.RescaleSlope) + int(pvt.RescaleIntercept)
    np.testing.assert_array_equal(vol.data[0], expected)
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(img))
    assert "DICOM_geometry" not in vol.meta


def test_series_of_one_frame_legacy_enhanced_files_is_one_stack(tmp_path):
    """One file per slice, each placed by its functional groups: one volume in position order."""
    folder = tmp_path / "s"
    folder.mkdir()
    files = [one_frame_enhanced(folder / f"f{k}.dcm", LEGACY_ENHANCED_MR, frame=k) for k in (0, 1)]
    vol = read_dicom(folder)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(folder)))
    img = reader.Execute()
    assert vol.shape_xyz == img.GetSize() == (512, 512, 2)
    # z of the frames: -159 (frame 1), -149 (frame 2); the normal row x column is -z
    z = [float(f.PerFrameFunctionalGroupsSequence[0].PlanePositionSequence[0]
               .ImagePositionPatient[2]) for f in files]
    assert z == [-159.0, -149.0]
    np.testing.assert_allclose(vol.origin, [99.5, -301.5, -149.0], atol=1e-6)
    np.testing.assert_allclose(vol.direction[:, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(vol.spacing, [0.388672, 0.388672, 10.0], atol=1e-6)
    for k, f in ((0, files[1]), (1, files[0])):
        np.testing.assert_array_equal(vol.data[k], f.pixel_array.astype(np.int32) - 1024)
    # SimpleITK's series (sorted the other way along z): the same values at the same points
    for k in range(2):
        point = vol.index_to_world(np.array([3, 5, k]))
        i, j, m = img.TransformPhysicalPointToIndex(tuple(point))
        assert sitk.GetArrayFromImage(img)[m, j, i] == vol.data[k, 5, 3]
