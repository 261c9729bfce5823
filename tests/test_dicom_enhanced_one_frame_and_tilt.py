"""DICOM series read against SimpleITK (GDCM) and pydicom: cases found by a hunt for silent errors."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
sitk = pytest.importorskip("SimpleITK")

from pydicom.data import get_testdata_file  # noqa: E402
from test_io_dicom import write_series  # noqa: E402

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


def _world_ramp(pts):
    return 1000 + 3 * pts[..., 0] - 2 * pts[..., 1] + 5 * pts[..., 2]


@pytest.mark.parametrize("labels", [False, True])
def test_tilted_slice_shifted_by_whole_pixels_keeps_its_edge(tmp_path, labels):
    """An oblique gantry-tilted stack whose last slice moves exactly 3 pixels along its rows:
    its positions, written to six decimals, put that shift 4e-7 pixel off, and the
    resampling took the field's edge column for outside: the volume's minimum, exit 0.
    Every voxel of the field (to 1e-3 pixel) keeps the world ramp the slices hold; a
    label map keeps its ids there."""
    c, s = math.cos(0.5), math.sin(0.5)
    orientation = (c, s, 0, -s * 0.6, c * 0.6, 0.8)
    row, col = np.array(orientation[:3]), np.array(orientation[3:])
    spacing, shape, n = (0.8, 0.7), (30, 26), 8
    positions = [np.array([5.0, -3.0, 7.0]) + k * (2.0 * np.cross(row, col) + 0.3 * row - 0.2 * col)
                 for k in range(n)]
    j, i = np.mgrid[0:shape[0], 0:shape[1]]
    stored = np.empty((n,) + shape, np.int16)
    for k, p in enumerate(positions):
        world = p + i[..., None] * spacing[1] * row + j[..., None] * spacing[0] * col
        stored[k] = np.rint(_world_ramp(world))
    if labels:
        # ids 0, 7, 55 in bands of the ramp (the resampling picks the nearest sample)
        lo, hi = np.percentile(stored, [40, 70])
        stored = np.select([stored < lo, stored < hi], [0, 7], 55).astype(np.int16)
    write_series(tmp_path / "t", stored, positions=positions, spacing=spacing,
                 orientation=orientation)
    vol = read_dicom(tmp_path / "t")
    ijk = np.indices(vol.shape_xyz).reshape(3, -1).T
    world = vol.index_to_world(ijk)
    got = vol.data[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    last = ijk[:, 2] == n - 1
    # where each voxel of the last plane lies in the last slice's pixels
    x = (world[last] - positions[-1]) @ row / spacing[1]
    y = (world[last] - positions[-1]) @ col / spacing[0]
    tol = 1e-3
    inside = (x > -tol) & (x < shape[1] - 1 + tol) & (y > -tol) & (y < shape[0] - 1 + tol)
    edge = inside & (np.abs(x) < tol)
    assert edge.sum() >= 20  # the column the slice's shift puts at the field's edge
    if labels:
        xi, yi = np.rint(x[inside]).astype(int), np.rint(y[inside]).astype(int)
        np.testing.assert_array_equal(got[last][inside], stored[-1][yi, xi])
    else:
        np.testing.assert_allclose(got[last][inside], _world_ramp(world[last][inside]), atol=0.51)


@pytest.mark.parametrize("orientation", [(1, 0, 0, 1e-5, 1, 0), (0.6, 0.8, 2e-5, 0, 3e-5, -1)])
def test_cosines_a_hair_off_a_right_angle_are_squared_as_simpleitk(tmp_path, run, orientation):
    """ImageOrientationPatient 1e-5 off orthogonal (cosines rounded by the scanner): the
    grid was kept sheared by that much, unlike SimpleITK's, and ``convert`` to NIfTI
    refused the series as a sheared grid (exit 1). The row cosine is made square to the
    column cosine as ITK does: SimpleITK's direction, and the NIfTI holds the same points."""
    rng = np.random.default_rng(11)
    stored = rng.integers(-1000, 3000, size=(5, 6, 7)).astype(np.int16)
    write_series(tmp_path / "s", stored, orientation=orientation)
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(tmp_path / "s")))
    img = reader.Execute()
    vol = read_dicom(tmp_path / "s")
    np.testing.assert_allclose(vol.direction, np.reshape(img.GetDirection(), (3, 3)), atol=1e-12)
    np.testing.assert_allclose(vol.origin, img.GetOrigin(), atol=1e-6)
    np.testing.assert_allclose(vol.spacing, img.GetSpacing(), atol=1e-6)
    out = tmp_path / "s.nii.gz"
    res = run("convert", tmp_path / "s", "-o", out)
    assert res.code == 0, res.stderr
    nii = sitk.ReadImage(str(out))
    np.testing.assert_allclose(np.reshape(nii.GetDirection(), (3, 3)),
                               np.reshape(img.GetDirection(), (3, 3)), atol=1e-6)
    np.testing.assert_allclose(nii.GetOrigin(), img.GetOrigin(), atol=1e-4)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(nii), sitk.GetArrayFromImage(img))


def test_a_series_without_pixel_spacing_says_the_1mm_it_assumes(tmp_path, caplog):
    """No PixelSpacing (nor ImagerPixelSpacing): 1 mm pixels, as SimpleITK takes them, but
    said (a warning) and recorded in DICOM_geometry, as the docs promise of what the files
    leave out; it was silent, and a distance or a mesh of it was off by the real size."""
    import pydicom as dicom

    stored = np.arange(3 * 4 * 5, dtype=np.int16).reshape(3, 4, 5)
    paths = write_series(tmp_path / "s", stored)
    for p in paths:
        ds = dicom.dcmread(p)
        del ds.PixelSpacing
        ds.save_as(p)
    with caplog.at_level("WARNING"):
        vol = read_dicom(tmp_path / "s")
    assert "no PixelSpacing" in caplog.text and "1 mm pixels assumed" in caplog.text
    assert "1 mm pixels (no PixelSpacing)" in vol.meta["DICOM_geometry"]
    ref = sitk.ImageSeriesReader()
    ref.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(tmp_path / "s")))
    img = ref.Execute()
    np.testing.assert_allclose(vol.spacing, img.GetSpacing(), atol=1e-6)
    assert np.array_equal(vol.data, sitk.GetArrayFromImage(img))
