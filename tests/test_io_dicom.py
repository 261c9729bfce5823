"""DICOM input: against SimpleITK on pydicom's sample files, and on series written here."""

from __future__ import annotations

import logging
import os
import random
from pathlib import Path

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
sitk = pytest.importorskip("SimpleITK")

from pydicom.data import get_testdata_file  # noqa: E402
from pydicom.dataset import Dataset, FileMetaDataset  # noqa: E402
from pydicom.uid import (  # noqa: E402
    CTImageStorage,
    ExplicitVRLittleEndian,
    RLELossless,
    RTDoseStorage,
    generate_uid,
)

from volwarp_cli.errors import FormatError, VolwarpError  # noqa: E402
from volwarp_cli.io import read_volume  # noqa: E402
from volwarp_cli.io.dicom import (  # noqa: E402
    DicomSeriesChoiceError,
    is_dicom_path,
    read_dicom,
    scan_dicom,
)
from volwarp_cli.io.dicom._read import read_reference  # noqa: E402

sitk.ProcessObject_SetGlobalWarningDisplay(False)
ATOL = 1e-4


# -- helpers ------------------------------------------------------------------

def sitk_series(folder, orthogonal=True):
    reader = sitk.ImageSeriesReader()
    reader.SetForceOrthogonalDirection(orthogonal)
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(folder)))
    return reader.Execute()


def sitk_direction(img):
    return np.array(img.GetDirection()).reshape(3, 3)


def assert_same_geometry(vol, img, atol=ATOL):
    assert vol.shape_xyz == tuple(img.GetSize())
    np.testing.assert_allclose(vol.spacing, img.GetSpacing(), rtol=0, atol=atol)
    np.testing.assert_allclose(vol.origin, img.GetOrigin(), rtol=0, atol=atol)
    np.testing.assert_allclose(vol.direction, sitk_direction(img), rtol=0, atol=atol)
    assert vol.space == "left-posterior-superior"


def assert_same_world(vol, img, values=None):
    """Same samples at the same world points, whatever the index order of each."""
    ours = vol.direction * vol.spacing[None, :]
    theirs = sitk_direction(img) * np.array(img.GetSpacing())[None, :]
    m = np.linalg.solve(theirs, ours)  # our index step -> their index step
    perm = np.rint(m)
    np.testing.assert_allclose(m, perm, atol=1e-6)
    assert sorted(np.abs(perm).sum(axis=0)) == [1, 1, 1]
    arr = sitk.GetArrayFromImage(img) if values is None else values
    n = np.array(vol.shape_xyz)
    corners = np.array([[a, b, c] for a in (0, n[0] - 1) for b in (0, n[1] - 1)
                        for c in (0, n[2] - 1)])
    their_corners = np.rint(np.array([img.TransformPhysicalPointToContinuousIndex(
        tuple(vol.index_to_world(c))) for c in corners]))
    assert their_corners.min() >= 0 and np.all(their_corners.max(axis=0) < img.GetSize())
    ijk = np.indices(vol.shape_xyz).reshape(3, -1).T
    theirs_ijk = (ijk @ perm.T + their_corners[0]).astype(int)
    mine = vol.data[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    other = arr[theirs_ijk[:, 2], theirs_ijk[:, 1], theirs_ijk[:, 0]]
    np.testing.assert_array_equal(mine, other)


def write_slice(path, pixels, *, position, orientation=(1, 0, 0, 0, 1, 0), spacing=(0.8, 0.7),
                series="1.2.826.0.1.3680043.8.498.1", slope=None, intercept=None,
                signed=True, bits_stored=16, instance=1, modality="CT", extra=None,
                transfer_syntax=ExplicitVRLittleEndian):
    """Write one CT slice (pixels: [rows, columns] of stored values)."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = CTImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = CTImageStorage
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = modality
    ds.PatientName = "Doe^Jane"
    ds.PatientID = "ID-12345"
    ds.PatientBirthDate = "19700101"
    ds.StudyInstanceUID = "1.2.826.0.1.3680043.8.498.9"
    ds.SeriesInstanceUID = series
    ds.SeriesDescription = f"series {series[-1]}"
    ds.SeriesNumber = int(series[-1])
    ds.FrameOfReferenceUID = "1.2.826.0.1.3680043.8.498.7"
    ds.InstanceNumber = instance
    ds.ImagePositionPatient = [f"{v:.6f}" for v in position]
    ds.ImageOrientationPatient = [f"{v:.8f}" for v in orientation]
    ds.PixelSpacing = list(spacing)
    ds.SliceThickness = 9.5  # deliberately wrong: the spacing comes from the positions
    ds.Rows, ds.Columns = pixels.shape
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = 16
    ds.BitsStored = bits_stored
    ds.HighBit = bits_stored - 1
    ds.PixelRepresentation = 1 if signed else 0
    if slope is not None:
        ds.RescaleSlope = slope
    if intercept is not None:
        ds.RescaleIntercept = intercept
    for k, v in (extra or {}).items():
        setattr(ds, k, v)
    ds.PixelData = pixels.astype("<i2" if signed else "<u2").tobytes()
    if transfer_syntax != ExplicitVRLittleEndian:
        ds.compress(transfer_syntax)
    ds.save_as(path, enforce_file_format=True)


def write_series(folder, stored, *, positions=None, spacing_z=2.5, orientation=(1, 0, 0, 0, 1, 0),
                 origin=(-10.0, 20.0, 30.0), shuffle=True, names=None, per_slice=None, **kw):
    """Write stored[z, y, x] as one file per slice; wrong InstanceNumbers, shuffled names."""
    folder.mkdir(parents=True, exist_ok=True)
    row, col = np.array(orientation[:3], float), np.array(orientation[3:], float)
    normal = np.cross(row, col)
    if positions is None:
        positions = [np.array(origin) + k * spacing_z * normal for k in range(len(stored))]
    order = list(range(len(stored)))
    rng = random.Random(7)
    if shuffle:
        rng.shuffle(order)
    paths = []
    for rank, k in enumerate(order):
        name = names[k] if names else f"IM{rank:04d}.dcm"
        extra = dict(per_slice[k]) if per_slice else {}  # DICOM keywords
        write_slice(folder / name, stored[k], position=positions[k], orientation=orientation,
                    instance=(k * 7) % len(stored) + 1, extra=extra, **kw)
        paths.append(folder / name)
    return paths


@pytest.fixture
def ramp():
    rng = np.random.default_rng(3)
    return rng.integers(-1000, 3000, size=(6, 5, 7)).astype(np.int16)


# -- pydicom's sample files against SimpleITK ------------------------------------------

@pytest.mark.parametrize("name", ["CT_small.dcm", "MR_small.dcm", "MR_small_RLE.dcm",
                                  "MR_small_jp2klossless.dcm", "MR_small_bigendian.dcm",
                                  "JPEG-LL.dcm", "SC_jpeg_no_color_transform.dcm"])
def test_single_files_match_simpleitk(name):
    path = get_testdata_file(name)
    if name == "SC_jpeg_no_color_transform.dcm":  # colour: refused, one line
        with pytest.raises(FormatError, match="greyscale") as err:
            read_dicom(path)
        assert "\n" not in str(err.value)
        return
    vol = read_dicom(path)
    img = sitk.ReadImage(path)
    assert_same_geometry(vol, img)
    expected = sitk.GetArrayFromImage(img)
    assert vol.dtype == expected.dtype
    np.testing.assert_array_equal(vol.data, expected)


def test_ct_small_rescale_is_int32_with_negative_hu():
    path = get_testdata_file("CT_small.dcm")
    ds = pydicom.dcmread(path)
    vol = read_dicom(path)
    # BitsStored 16 signed + intercept -1024 does not fit int16: int32, like ITK
    assert vol.dtype == np.int32
    np.testing.assert_array_equal(vol.data[0], ds.pixel_array.astype(np.int64) - 1024)


def test_jpeg2000_float_slope_is_float32():
    path = get_testdata_file("MR2_J2KR.dcm")
    vol = read_dicom(path)
    img = sitk.ReadImage(path)
    assert_same_geometry(vol, img)
    assert vol.dtype == np.float32  # ITK gives float64; volwarp float32
    np.testing.assert_allclose(vol.data, sitk.GetArrayFromImage(img), rtol=1e-6, atol=1e-3)
    # the direction is oblique here: row and column cosines are the first two columns
    ds = pydicom.dcmread(path, stop_before_pixels=True)
    iop = np.array([float(v) for v in ds.ImageOrientationPatient])
    np.testing.assert_allclose(vol.direction[:, 0], iop[:3] / np.linalg.norm(iop[:3]), atol=1e-9)


def test_enhanced_ct_matches_simpleitk_in_world():
    path = get_testdata_file("eCT_Supplemental.dcm")
    vol = read_dicom(path)
    img = sitk.ReadImage(path)
    # GDCM keeps the file's frame order (z up, a left-handed frame here); volwarp sorts along
    # the normal (row x column = -z): the same samples at the same world points
    np.testing.assert_allclose(vol.direction[:, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(vol.origin, [99.5, -301.5, -149.0], atol=ATOL)
    np.testing.assert_allclose(vol.spacing, img.GetSpacing(), atol=ATOL)
    assert_same_world(vol, img)


def test_enhanced_mr_without_geometry_as_simpleitk():
    """An Enhanced MR without functional groups: stacked SpacingBetweenSlices (1.2) apart.

    SimpleITK (GDCM) looks for the spacing only in an Enhanced MR's functional
    groups, which this file lacks (1 mm); everything else is its geometry.
    """
    path = get_testdata_file("emri_small.dcm")
    vol = read_dicom(path)
    img = sitk.ReadImage(path)
    assert vol.spacing[2] == pytest.approx(1.2) and img.GetSpacing()[2] == 1.0
    img.SetSpacing(img.GetSpacing()[:2] + (1.2,))
    assert_same_geometry(vol, img)
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(img))
    assert vol.meta["DICOM_geometry"] == ("assumed: origin 0 (no ImagePositionPatient), "
                                          "identity orientation (no ImageOrientationPatient), "
                                          "1 mm pixels (no PixelSpacing)")


def test_segmentation_multiframe_with_functional_groups():
    path = get_testdata_file("liver.dcm")
    vol = read_dicom(path)
    img = sitk.ReadImage(path)
    assert_same_geometry(vol, img)
    # 1-bit segments: pydicom unpacks to 0/1, GDCM to 0/255
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(img) > 0)


def test_rtdose_scaled_by_dose_grid_scaling_in_the_files_units():
    """The values are stored x DoseGridScaling in the file's DoseUnits: RELATIVE here, not Gy."""
    path = get_testdata_file("rtdose.dcm")
    vol = read_dicom(path)
    img = sitk.ReadImage(path)
    assert_same_geometry(vol, img)
    ds = pydicom.dcmread(path)
    # SimpleITK leaves out DoseGridScaling; the expectation is pydicom's stored values x scaling
    expected = (ds.pixel_array.astype(np.float64) * float(ds.DoseGridScaling)).astype(np.float32)
    assert vol.dtype == np.float32
    np.testing.assert_array_equal(vol.data, expected)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(img), ds.pixel_array)
    assert vol.meta["DICOM_DoseUnits"] == str(ds.DoseUnits) == "RELATIVE"
    assert vol.meta["DICOM_Modality"] == "RTDOSE"


def test_rtdose_absolute_grid_offsets(tmp_path):
    ds = pydicom.dcmread(get_testdata_file("rtdose.dcm"))
    z0 = float(ds.ImagePositionPatient[2])
    relative = [float(v) for v in ds.GridFrameOffsetVector]
    ds.GridFrameOffsetVector = [z0 + v for v in relative]  # type b: absolute z positions
    ds.save_as(tmp_path / "abs.dcm")
    a = read_dicom(get_testdata_file("rtdose.dcm"))
    b = read_dicom(tmp_path / "abs.dcm")
    assert b.same_grid(a, atol=1e-6)
    np.testing.assert_array_equal(a.data, b.data)


def write_dose(path, offsets, *, orientation=(1, 0, 0, 0, 1, 0), position=(10.0, 20.0, 30.0)):
    """An RT Dose of len(offsets) 4x3 frames, frame k all 10 * (k + 1) x DoseGridScaling 0.1."""
    n = len(offsets)
    write_slice(path, np.zeros((4, 3)), position=position, orientation=orientation,
                modality="RTDOSE", extra={"SOPClassUID": RTDoseStorage})
    ds = pydicom.dcmread(path)
    ds.file_meta.MediaStorageSOPClassUID = RTDoseStorage
    ds.NumberOfFrames = n
    ds.FrameIncrementPointer = 0x3004000C
    ds.GridFrameOffsetVector = [float(v) for v in offsets]
    ds.DoseGridScaling = 0.1
    ds.DoseUnits, ds.DoseType, ds.DoseSummationType = "GY", "PHYSICAL", "PLAN"
    ds.PixelData = np.repeat(10 * np.arange(1, n + 1, dtype="<i2"), 12).tobytes()
    ds.save_as(path, enforce_file_format=True)


def frame_z(vol) -> dict[int, float]:
    """World z of each frame of a :func:`write_dose` file (frame k holds the value k + 1)."""
    return {round(float(vol.data[s, 0, 0])) - 1: float(vol.index_to_world([0, 0, s])[2])
            for s in range(vol.shape_xyz[2])}


@pytest.mark.parametrize("orientation, offsets, z", [
    ((1, 0, 0, 0, 1, 0), [0, 2.5, 5, 7.5], [30, 32.5, 35, 37.5]),       # relative
    ((-1, 0, 0, 0, 1, 0), [0, 2.5, 5, 7.5], [30, 27.5, 25, 22.5]),      # relative, normal -z
    ((1, 0, 0, 0, 1, 0), [30, 32.5, 35, 37.5], [30, 32.5, 35, 37.5]),   # absolute z
    ((1, 0, 0, 0, 1, 0), [30, 27.5, 25, 22.5], [30, 27.5, 25, 22.5]),
    ((-1, 0, 0, 0, 1, 0), [30, 32.5, 35, 37.5], [30, 32.5, 35, 37.5]),  # absolute, normal -z
])
def test_rtdose_frames_lie_at_their_grid_offsets(tmp_path, orientation, offsets, z):
    """Relative offsets step along the normal from ImagePositionPatient; absolute ones are z.

    Absolute offsets with the slice normal along -z were taken as positions along the
    normal: the grid landed 2 x z away (origin z -30 for 30).
    """
    write_dose(tmp_path / "d.dcm", offsets, orientation=orientation)
    vol = read_dicom(tmp_path / "d.dcm")
    got = frame_z(vol)
    np.testing.assert_allclose([got[k] for k in range(4)], z, atol=1e-9)
    np.testing.assert_allclose(vol.index_to_world([0, 0, 0])[:2], [10, 20], atol=1e-9)
    if offsets[0] == 0 or orientation[0] == 1:  # SimpleITK reads these right
        img = sitk.ReadImage(str(tmp_path / "d.dcm"))
        assert_same_world(vol, img, values=sitk.GetArrayFromImage(img) * np.float32(0.1))


@pytest.mark.parametrize("orientation, offsets, why", [
    ((1, 0, 0, 0, 1, 0), [32, 34.5, 37, 39.5], "ImagePositionPatient's z is 30"),
    ((0, 1, 0, 0, 0, -1), [30, 32.5, 35, 37.5], "has no z component"),
])
def test_rtdose_absolute_offsets_that_contradict_the_file_are_refused(run, tmp_path,
                                                                        orientation, offsets,
                                                                        why):
    """Frame 0 was moved silently to the first offset (2 mm here) or placed along x."""
    path = tmp_path / "d.dcm"
    write_dose(path, offsets, orientation=orientation)
    with pytest.raises(FormatError, match=why):
        read_dicom(path)
    res = run("convert", path, "-o", tmp_path / "o.nrrd")
    assert res.code == 1 and not (tmp_path / "o.nrrd").exists(), res
    line, = res.stderr.strip().splitlines()
    assert line.startswith(f"volwarp: error: {path}: GridFrameOffsetVector starts at "
                           f"{offsets[0]:g}") and why in line, line


NM, MR = "1.2.840.10008.5.1.4.1.1.20", "1.2.840.10008.5.1.4.1.1.4"


def write_multiframe(path, stored, *, sop=CTImageStorage, modality="CT", drop=(), **tags):
    """A classic multi-frame image (no functional groups): stored[frame, row, column].

    ``tags`` are set (DICOM keywords), ``drop`` removed; SliceThickness is 9.5.
    """
    write_slice(path, stored[0], position=(-10.0, 20.0, 30.0), orientation=(1, 0, 0, 0, 0, -1),
                modality=modality, extra={"SOPClassUID": sop})
    ds = pydicom.dcmread(path)
    ds.file_meta.MediaStorageSOPClassUID = sop
    ds.NumberOfFrames = len(stored)
    for k, v in tags.items():
        setattr(ds, k, v)
    for k in drop:
        delattr(ds, k)
    ds.PixelData = stored.astype("<i2").tobytes()
    ds.save_as(path, enforce_file_format=True)


@pytest.mark.parametrize("sop, modality", [(NM, "NM"), (MR, "MR"), (CTImageStorage, "CT")])
@pytest.mark.parametrize("between", [3.5, -3.5])
def test_classic_multiframe_frames_lie_spacing_between_slices_apart(tmp_path, ramp, caplog, sop,
                                                                      modality, between):
    """Frames without per-frame positions were stacked 1 mm apart whatever the file said.

    SimpleITK (GDCM) stacks them SpacingBetweenSlices apart, along the normal or,
    negative, against it. (It leaves an NM origin at 0 unless the detector gives one:
    the top-level ImagePositionPatient is taken here, so NM is compared in spacing.)
    """
    path = tmp_path / "mf.dcm"
    write_multiframe(path, ramp, sop=sop, modality=modality, SpacingBetweenSlices=between)
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        vol = read_dicom(path)
    assert caplog.text == "" and "DICOM_geometry" not in vol.meta
    img = sitk.ReadImage(str(path))
    assert vol.spacing[2] == pytest.approx(3.5) and img.GetSpacing()[2] == pytest.approx(3.5)
    if modality == "NM":
        img.SetOrigin((-10.0, 20.0, 30.0))
    assert_same_world(vol, img)


@pytest.mark.parametrize("drop", [("SpacingBetweenSlices",),
                                  ("SpacingBetweenSlices", "SliceThickness")])
def test_classic_multiframe_without_spacing_says_so(run, tmp_path, ramp, drop):
    """No SpacingBetweenSlices: unit spacing as ITK (SliceThickness is no spacing), not silently.

    The key said "none in the file: unit spacing, origin 0" with the origin taken from
    ImagePositionPatient; it names what was assumed, and a warning says it too.
    """
    path = tmp_path / "mf.dcm"
    write_multiframe(path, ramp, modality="MR", sop=MR, SpacingBetweenSlices=3.5, drop=drop)
    vol = read_dicom(path)
    img = sitk.ReadImage(str(path))
    assert_same_geometry(vol, img)
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(img))
    assert vol.meta["DICOM_geometry"] == "assumed: unit slice spacing (no SpacingBetweenSlices)"
    res = run("convert", path, "-o", tmp_path / "o.nrrd")
    assert res.code == 0, res
    line, = res.stderr.strip().splitlines()
    assert line == (f"volwarp: warning: {path}: 6 frames without positions of their own, "
                    "stacked with unit slice spacing (no SpacingBetweenSlices)")
    assert read_volume(tmp_path / "o.nrrd").meta["DICOM_geometry"] == \
        vol.meta["DICOM_geometry"]


def test_a_multiframe_reference_is_refused_in_one_line(tmp_path, ramp, caplog):
    """Its frames have no positions a segmentation's could match: no warning before that."""
    write_multiframe(tmp_path / "mf.dcm", ramp, modality="MR", sop=MR)
    with caplog.at_level(logging.WARNING, logger="volwarp"), \
            pytest.raises(FormatError, match="gives no position per image"):
        read_reference(tmp_path / "mf.dcm")
    assert caplog.text == ""


def detector(position, orientation):
    item = Dataset()
    item.ImagePositionPatient = [float(v) for v in position]
    item.ImageOrientationPatient = [float(v) for v in orientation]
    return item


@pytest.mark.parametrize("top", [True, False])
def test_nm_takes_its_geometry_from_the_detector_information(tmp_path, ramp, top):
    """An NM image's plane is in DetectorInformationSequence, where GDCM reads it first."""
    path = tmp_path / "nm.dcm"
    write_multiframe(path, ramp, sop=NM, modality="NM", SpacingBetweenSlices=3.5,
                     DetectorInformationSequence=[detector((-5, 7, 11), (0, 1, 0, 0, 0, -1))],
                     drop=() if top else ("ImagePositionPatient", "ImageOrientationPatient"))
    vol = read_dicom(path)
    img = sitk.ReadImage(str(path))
    assert_same_geometry(vol, img)
    np.testing.assert_allclose(vol.origin, [-5, 7, 11])
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(img))
    assert "DICOM_geometry" not in vol.meta


def test_nm_detectors_placed_apart_are_refused(tmp_path, ramp):
    path = tmp_path / "nm.dcm"
    write_multiframe(path, ramp, sop=NM, modality="NM", SpacingBetweenSlices=3.5,
                     DetectorInformationSequence=[detector((-5, 7, 11), (0, 1, 0, 0, 0, -1)),
                                                  detector((5, 7, 11), (0, 1, 0, 0, 0, -1))])
    with pytest.raises(FormatError, match=r"nm.dcm: DetectorInformationSequence places its 2 "
                                          "detectors' frames differently"):
        read_dicom(path)


def test_dicomdir_and_folder_list_the_same_candidates():
    base = os.path.join(os.path.dirname(get_testdata_file("CT_small.dcm")), "dicomdirtests")
    by_dir = scan_dicom(os.path.join(base, "DICOMDIR"))
    by_folder = scan_dicom(base)
    assert [c.describe() for c in by_dir] == [c.describe() for c in by_folder]
    assert len(by_dir) > 5
    with pytest.raises(DicomSeriesChoiceError) as err:
        read_dicom(os.path.join(base, "DICOMDIR"))
    assert "[0]" in str(err.value) and by_dir[-1].series_uid in str(err.value)
    ct = next(c for c in by_dir if c.description == "SmartScore - Gated 0.5 sec")
    assert ct.n_files == 5 and ct.describe()["shape_xyz"] == [16, 16, 5]
    vol = read_dicom(os.path.join(base, "DICOMDIR"), series=ct.series_uid)
    img = sitk_series(os.path.join(base, "98892001", "CT5N"))
    assert_same_geometry(vol, img)
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(img))
    # the folder itself is split into candidates: the DICOMDIR is not one of them
    assert is_dicom_path(base) and is_dicom_path(os.path.join(base, "DICOMDIR"))


def test_localizers_in_another_orientation_are_candidates_or_dropped(tmp_path, ramp):
    write_series(tmp_path / "s", ramp)
    for k, iop in enumerate([(0, 1, 0, 0, 0, -1), (1, 0, 0, 0, 0, -1)]):
        write_slice(tmp_path / "s" / f"LOC{k}.dcm", ramp[0], position=(0, 0, 0), orientation=iop,
                    extra={"ImageType": ["ORIGINAL", "PRIMARY", "LOCALIZER"]})
    cands = scan_dicom(tmp_path / "s")
    assert len(cands) == 1 and "2 localizer image(s)" in cands[0].why
    vol = read_dicom(tmp_path / "s")
    np.testing.assert_array_equal(vol.data, ramp)
    # without ImageType LOCALIZER an image in another orientation is a candidate of its own
    write_slice(tmp_path / "s" / "OBL.dcm", ramp[0], position=(0, 0, 0),
                orientation=(0, 1, 0, 0, 0, -1))
    cands = scan_dicom(tmp_path / "s")
    assert len(cands) == 2 and "ImageOrientationPatient" in cands[1].why
    with pytest.raises(DicomSeriesChoiceError):
        read_dicom(tmp_path / "s")


# -- synthetic series ------------------------------------------------------------

def test_shuffled_files_and_wrong_instance_numbers(tmp_path, ramp):
    write_series(tmp_path / "s", ramp, spacing_z=2.5)
    vol = read_dicom(tmp_path / "s")
    img = sitk_series(tmp_path / "s")
    assert_same_geometry(vol, img)
    np.testing.assert_array_equal(vol.data, ramp)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(img), ramp)
    assert vol.spacing[2] == pytest.approx(2.5)  # not SliceThickness (9.5)
    assert vol.dtype == np.int16


def test_oblique_descending_stack_matches_simpleitk(tmp_path, ramp):
    c, s = np.cos(0.4), np.sin(0.4)
    iop = (c, s, 0, 0, 0, -1)  # coronal-ish oblique: normal is (s, -c, 0)
    write_series(tmp_path / "s", ramp, orientation=iop, spacing_z=-1.7)  # written reversed
    vol = read_dicom(tmp_path / "s")
    img = sitk_series(tmp_path / "s")
    assert_same_geometry(vol, img)
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(img))
    np.testing.assert_array_equal(vol.data, ramp[::-1])
    assert np.linalg.det(vol.direction) == pytest.approx(1.0)


def test_two_series_need_a_choice(tmp_path, ramp):
    a, b = "1.2.826.0.1.3680043.8.498.1", "1.2.826.0.1.3680043.8.498.2"
    write_series(tmp_path / "s", ramp, series=a)
    write_series(tmp_path / "s", ramp[:4] + 1, series=b, names=[f"B{k}.dcm" for k in range(4)])
    with pytest.raises(DicomSeriesChoiceError) as err:
        read_dicom(tmp_path / "s")
    msg = str(err.value)
    assert a in msg and b in msg and "[0]" in msg and "[1]" in msg and "series 2" in msg
    assert "\n" not in msg
    assert not isinstance(err.value, FormatError) and isinstance(err.value, VolwarpError)
    cands = scan_dicom(tmp_path / "s")
    assert [c.series_uid for c in cands] == [a, b]
    assert cands[1].shape_xyz == (7, 5, 4) and cands[1].n_files == 4
    assert cands[0].describe()["spacing"] == [0.7, 0.8, 2.5]  # PixelSpacing is (row, column)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s", series=b).data, ramp[:4] + 1)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s", series=1).data, ramp[:4] + 1)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s", series=a).data, ramp)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s", series="0").data, ramp)
    with pytest.raises(DicomSeriesChoiceError, match="outside"):
        read_dicom(tmp_path / "s", series=5)


def test_echo_numbers_split_a_series(tmp_path, ramp):
    write_series(tmp_path / "s", ramp, per_slice=[{"EchoNumbers": 1}] * 6)
    write_series(tmp_path / "s", ramp, per_slice=[{"EchoNumbers": 2}] * 6,
                 names=[f"E2_{k}.dcm" for k in range(6)])
    cands = scan_dicom(tmp_path / "s")
    assert len(cands) == 2 and "EchoNumbers" in cands[1].why


def _ramp_world(pts):
    return 1000 + 3 * pts[..., 0] - 2 * pts[..., 1] + 5 * pts[..., 2]


def _tilted(tmp_path, tilt_deg=12.0, n=8, shape=(24, 20)):
    """A stack whose slice origins move in +y as z rises (gantry tilt); samples = a world ramp."""
    spacing = (0.8, 0.7)  # (row spacing = y, column spacing = x)
    dz = 2.0
    shift = dz * np.tan(np.radians(tilt_deg))
    positions = [np.array([-5.0, 10.0 + k * shift, 40.0 + k * dz]) for k in range(n)]
    stored = np.empty((n,) + shape, dtype=np.int16)
    j, i = np.mgrid[0:shape[0], 0:shape[1]]
    for k, p in enumerate(positions):
        pts = np.stack([p[0] + i * spacing[1], p[1] + j * spacing[0], p[2] + 0 * i], axis=-1)
        stored[k] = np.rint(_ramp_world(pts))
    write_series(tmp_path / "t", stored, positions=positions, spacing=spacing)
    return tmp_path / "t", stored, positions


def test_gantry_tilt_resampled_keeps_the_world_ramp(tmp_path, caplog):
    folder, stored, positions = _tilted(tmp_path)
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        vol = read_dicom(folder)
    assert "gantry tilt of 12 degrees" in caplog.text
    np.testing.assert_allclose(vol.direction, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(vol.origin, positions[0], atol=ATOL)
    np.testing.assert_allclose(vol.spacing, [0.7, 0.8, 2.0], atol=ATOL)
    assert vol.dtype == np.float32
    ijk = np.indices(vol.shape_xyz).reshape(3, -1).T
    world = vol.index_to_world(ijk)
    got = vol.data[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    # inside the tilted field of view the ramp is reproduced (linear interpolation is exact)
    inside = np.ones(len(ijk), bool)
    for k, p in enumerate(positions):
        on = ijk[:, 2] == k
        y = (world[:, 1] - p[1]) / 0.8
        inside &= ~on | ((y >= 0) & (y <= stored.shape[1] - 1))
    assert inside.sum() > 0.6 * len(ijk)
    np.testing.assert_allclose(got[inside], _ramp_world(world[inside]), atol=0.51)
    assert got[~inside].min() == stored.min()  # outside: filled with the minimum


def test_gantry_tilt_keep_shear_matches_simpleitk(tmp_path):
    folder, stored, positions = _tilted(tmp_path)
    vol = read_dicom(folder, keep_shear=True)
    img = sitk_series(folder, orthogonal=False)  # ITK's default forces the cross product
    assert_same_geometry(vol, img)
    np.testing.assert_array_equal(vol.data, stored)
    step = positions[1] - positions[0]
    np.testing.assert_allclose(vol.direction[:, 2], step / np.linalg.norm(step), atol=1e-6)
    assert vol.spacing[2] == pytest.approx(np.linalg.norm(step), abs=1e-5)


def test_missing_slice_names_the_gap(tmp_path, ramp):
    names = [f"S{k}.dcm" for k in range(len(ramp))]
    write_series(tmp_path / "s", ramp, names=names, spacing_z=2.0)
    (tmp_path / "s" / "S3.dcm").unlink()
    with pytest.raises(FormatError) as err:
        read_dicom(tmp_path / "s")
    msg = str(err.value)
    assert "missing slice(s)" in msg and "S2.dcm and S4.dcm" in msg and "4 mm" in msg
    assert "\n" not in msg


def test_irregular_spacing_error_or_resample(tmp_path, caplog):
    z = [0.0, 2.0, 4.0, 6.0, 9.0, 10.0, 12.0]  # gaps 2 2 2 3 1 2
    # (an intensity ramp: planes of one value each would be a label map by the rule)
    stored = np.stack([np.full((4, 3), 100 + 10 * v, np.int16)
                       + np.arange(12, dtype=np.int16).reshape(4, 3) * 7 for v in z])
    write_series(tmp_path / "s", stored, positions=[(0, 0, v) for v in z])
    with pytest.raises(FormatError, match=r"irregular slice spacing.* is 3 mm.*1 more") as err:
        read_dicom(tmp_path / "s")
    assert "elsewhere 2 mm" in str(err.value)
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        vol = read_dicom(tmp_path / "s", irregular="resample")
    assert "resampled linearly" in caplog.text
    # onto the smallest gap (1 mm): 13 slices, linear in z like the samples
    assert vol.shape_xyz[2] == 13 and vol.spacing[2] == pytest.approx(1.0)
    assert vol.dtype == np.float32
    np.testing.assert_allclose(vol.data[:, 0, 0], 100 + 10 * np.arange(13.0), atol=1e-4)


def test_duplicate_positions(tmp_path, ramp):
    write_series(tmp_path / "s", ramp, names=[f"A{k}.dcm" for k in range(6)])
    write_slice(tmp_path / "s" / "B.dcm", ramp[2] + 7, position=(-10.0, 20.0, 35.0))
    with pytest.raises(FormatError, match="A2.dcm and B.dcm"):
        read_dicom(tmp_path / "s")
    np.testing.assert_array_equal(read_dicom(tmp_path / "s", duplicates="first").data, ramp)
    last = read_dicom(tmp_path / "s", duplicates="last").data
    np.testing.assert_array_equal(last[2], ramp[2] + 7)
    np.testing.assert_array_equal(np.delete(last, 2, 0), np.delete(ramp, 2, 0))


def test_duplicates_split_by_acquisition_number(tmp_path, ramp):
    write_series(tmp_path / "s", ramp, per_slice=[{"AcquisitionNumber": 1}] * 6)
    write_series(tmp_path / "s", ramp + 1, per_slice=[{"AcquisitionNumber": 2}] * 6,
                 names=[f"B{k}.dcm" for k in range(6)])
    cands = scan_dicom(tmp_path / "s")
    assert len(cands) == 2 and all("AcquisitionNumber" in c.why for c in cands)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s", series=1).data, ramp + 1)


def test_rescale_per_slice(tmp_path, ramp):
    # integer slope/intercept: int16 when the stored range maps into it (12 bits stored)
    stored = np.abs(ramp) % 4096
    per = [{"RescaleSlope": 1, "RescaleIntercept": -1024 + 10 * k} for k in range(6)]
    write_series(tmp_path / "a", stored, per_slice=per, bits_stored=12, signed=False)
    vol = read_dicom(tmp_path / "a")
    assert vol.dtype == np.int16
    expected = stored.astype(np.int64) - 1024 + 10 * np.arange(6)[:, None, None]
    np.testing.assert_array_equal(vol.data, expected)
    assert vol.data.min() < 0
    # uint16 with all 16 bits stored and intercept -1024: int32, no wrap-around
    big = stored.astype(np.uint16)
    big[0, 0, 0] = 65535
    write_series(tmp_path / "b", big, signed=False, slope=1, intercept=-1024)
    vol = read_dicom(tmp_path / "b")
    assert vol.dtype == np.int32
    np.testing.assert_array_equal(vol.data, big.astype(np.int64) - 1024)
    assert vol.data[0, 0, 0] == 65535 - 1024
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(sitk_series(tmp_path / "b")))
    # a float slope on one slice: float32 for the whole volume
    per = [{"RescaleSlope": 1, "RescaleIntercept": 0}] * 5 + [{"RescaleSlope": 0.5,
                                                              "RescaleIntercept": -3}]
    write_series(tmp_path / "c", ramp, per_slice=per)
    vol = read_dicom(tmp_path / "c")
    assert vol.dtype == np.float32
    np.testing.assert_array_equal(vol.data[:5], ramp[:5])
    np.testing.assert_allclose(vol.data[5], ramp[5] * 0.5 - 3)


def test_high_bits_above_bits_stored_are_ignored(tmp_path):
    stored = np.array([[[0x0FFF, 0x1005]]], dtype=np.uint16)  # 0x1005: garbage bit 12
    write_series(tmp_path / "s", stored.view(np.int16), bits_stored=12, signed=False)
    vol = read_dicom(tmp_path / "s")
    assert vol.dtype == np.uint16
    np.testing.assert_array_equal(vol.data.ravel(), [0x0FFF, 0x0005])


def test_compressed_series_matches_uncompressed(tmp_path, ramp):
    write_series(tmp_path / "raw", ramp, shuffle=False)
    write_series(tmp_path / "rle", ramp, shuffle=False, transfer_syntax=RLELossless)
    a, b = read_dicom(tmp_path / "raw"), read_dicom(tmp_path / "rle")
    assert a.same_grid(b)
    np.testing.assert_array_equal(a.data, b.data)


def test_undecodable_transfer_syntax(tmp_path):
    ds = pydicom.dcmread(get_testdata_file("MR_small_RLE.dcm"))
    ds.file_meta.TransferSyntaxUID = "1.2.840.10008.1.2.4.100"  # MPEG2: pydicom has no decoder
    ds.save_as(tmp_path / "mpeg.dcm")
    with pytest.raises(FormatError) as err:
        read_dicom(tmp_path / "mpeg.dcm")
    assert "1.2.840.10008.1.2.4.100" in str(err.value) and "MPEG2" in str(err.value)


def test_truncated_files(tmp_path, ramp, caplog):
    write_series(tmp_path / "s", ramp, names=[f"S{k}.dcm" for k in range(6)])
    p = tmp_path / "s" / "S3.dcm"
    p.write_bytes(p.read_bytes()[:-20])
    with pytest.raises(FormatError, match="S3.dcm.*truncated"):
        read_dicom(tmp_path / "s")
    p.write_bytes(p.read_bytes()[:300])  # inside the header: refused in its folder...
    with pytest.raises(FormatError) as err:
        read_dicom(tmp_path / "s")
    assert "\n" not in str(err.value)
    assert "S3.dcm: CT Image Storage without PixelData (truncated file?)" in str(err.value)
    with pytest.raises(FormatError, match=r"S3.dcm: .*truncated"):  # ...and on its own
        read_dicom(p)
    rle = tmp_path / "rle.dcm"
    rle.write_bytes(Path(get_testdata_file("MR_small_RLE.dcm")).read_bytes()[:3000])
    with pytest.raises(FormatError, match="rle.dcm"):
        read_dicom(rle)


def test_truncated_files_leave_no_descriptor_open(tmp_path, ramp):
    """read_dicom and the lazy DICOM reader close every file on their error paths, before
    the error leaves them (checked while its traceback, which holds their frames, lives)."""
    from conftest import open_files

    from volwarp_cli.io.lazy import open_volume_lazy

    write_series(tmp_path / "s", ramp, names=[f"S{k}.dcm" for k in range(6)])
    p = tmp_path / "s" / "S3.dcm"
    rle = tmp_path / "rle.dcm"
    rle.write_bytes(Path(get_testdata_file("MR_small_RLE.dcm")).read_bytes()[:3000])
    for cut in (-20, 300):
        p.write_bytes(p.read_bytes()[:cut])
        for path in (tmp_path / "s", p, rle):
            for read in (read_dicom, open_volume_lazy):
                for _ in range(2):
                    try:
                        got = read(path)
                        if read is open_volume_lazy:  # the damage may show on reading
                            np.asarray(got[1][...])
                    except FormatError as exc:
                        assert open_files(tmp_path) == [], (read.__name__, str(exc))
                        continue
                    raise AssertionError(f"{path}: a truncated file was read")


@pytest.mark.parametrize("name", ["rtstruct.dcm", "rtplan.dcm", "test-SR.dcm"])
def test_non_image_dicom_is_refused(name):
    path = get_testdata_file(name)
    with pytest.raises(FormatError, match="no PixelData") as err:
        read_dicom(path)
    assert "\n" not in str(err.value)


def test_empty_and_non_dicom_folders(tmp_path, ramp):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError, match=r"is a folder with no DICOM files \(0 file"):
        read_dicom(tmp_path / "empty")
    (tmp_path / "txt").mkdir()
    for k in range(3):
        (tmp_path / "txt" / f"note{k}.txt").write_text("hello")
    with pytest.raises(FormatError, match=r"3 file\(s\) looked at"):
        read_dicom(tmp_path / "txt")
    assert not is_dicom_path(tmp_path / "txt")
    # a README next to the slices is skipped
    write_series(tmp_path / "txt" / "sub", ramp)
    assert is_dicom_path(tmp_path / "txt")
    np.testing.assert_array_equal(read_dicom(tmp_path / "txt").data, ramp)


def test_bad_file_is_one_line(tmp_path):
    bad = tmp_path / "x.dcm"
    bad.write_bytes(b"\0" * 128 + b"DICM" + b"\x02\x00\x10\x00garbage")
    with pytest.raises(FormatError, match="x.dcm") as err:
        read_dicom(bad)
    assert "\n" not in str(err.value)
    assert not is_dicom_path(tmp_path / "nothing.dcm")


def test_phi_only_with_keep_phi(tmp_path, ramp):
    write_series(tmp_path / "s", ramp)
    meta = read_dicom(tmp_path / "s").meta
    assert meta["DICOM_Modality"] == "CT"
    assert meta["DICOM_SeriesInstanceUID"] == "1.2.826.0.1.3680043.8.498.1"
    assert meta["DICOM_FrameOfReferenceUID"] == "1.2.826.0.1.3680043.8.498.7"
    assert all(isinstance(v, str) for v in meta.values())
    text = repr(meta)
    assert "Doe" not in text and "ID-12345" not in text and "19700101" not in text
    kept = read_dicom(tmp_path / "s", keep_phi=True).meta
    assert kept["DICOM_PatientName"] == "Doe^Jane" and kept["DICOM_PatientID"] == "ID-12345"


def test_option_values_are_checked(tmp_path, ramp):
    write_series(tmp_path / "s", ramp)
    with pytest.raises(VolwarpError, match="irregular"):
        read_dicom(tmp_path / "s", irregular="maybe")
    with pytest.raises(VolwarpError, match="duplicates"):
        read_dicom(tmp_path / "s", duplicates="middle")


def test_enhanced_stacks_and_per_frame_rescale(tmp_path):
    src = get_testdata_file("eCT_Supplemental.dcm")
    ds = pydicom.dcmread(src)
    shared = ds.SharedFunctionalGroupsSequence[0].PixelValueTransformationSequence[0]
    slope, inter = float(shared.RescaleSlope), float(shared.RescaleIntercept)
    # a per-frame transformation overrides the shared one for frame 2 only
    item = Dataset()
    item.RescaleSlope, item.RescaleIntercept, item.RescaleType = 2, inter + 5, "HU"
    ds.PerFrameFunctionalGroupsSequence[1].PixelValueTransformationSequence = [item]
    ds.save_as(tmp_path / "rescaled.dcm")
    raw = ds.pixel_array.astype(np.int64)
    vol = read_dicom(tmp_path / "rescaled.dcm")
    # frame 2 lies at z -149, the first along the normal (0, 0, -1)
    np.testing.assert_array_equal(vol.data[0], raw[1] * 2 + int(inter) + 5)
    np.testing.assert_array_equal(vol.data[1], raw[0] * int(slope) + int(inter))
    # two StackIDs in one file: two candidates
    ds.PerFrameFunctionalGroupsSequence[1].FrameContentSequence[0].StackID = "2"
    ds.save_as(tmp_path / "stacks.dcm")
    cands = scan_dicom(tmp_path / "stacks.dcm")
    assert len(cands) == 2 and "StackID" in cands[1].why
    assert all(c.shape_xyz == (512, 512, 1) for c in cands)
    with pytest.raises(DicomSeriesChoiceError):
        read_dicom(tmp_path / "stacks.dcm")
    np.testing.assert_array_equal(read_dicom(tmp_path / "stacks.dcm", series=1).data[0],
                                  raw[1] * 2 + int(inter) + 5)


def test_gantry_tilt_with_irregular_gap_resampled(tmp_path):
    folder, stored, positions = _tilted(tmp_path, n=6)
    victim = next(p for p in sorted(folder.iterdir())  # a middle slice: a 4 mm gap
                  if float(pydicom.dcmread(p).ImagePositionPatient[2]) == positions[2][2])
    victim.unlink()
    with pytest.raises(FormatError, match="missing slice"):
        read_dicom(folder)
    vol = read_dicom(folder, irregular="resample")
    assert vol.shape_xyz[2] == 6 and vol.spacing[2] == pytest.approx(2.0)
    np.testing.assert_allclose(vol.direction, np.eye(3), atol=1e-9)
    ijk = np.indices(vol.shape_xyz).reshape(3, -1).T
    world = vol.index_to_world(ijk)
    got = vol.data[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
    # every voxel is the world ramp (the tilt correction and the slice interpolation are
    # linear: exact for it) or the fill; none at the field's rim blends the fill with data
    # between two slices, as 28 of 1512 did in the review's case
    fov = got != stored.min()
    assert fov.mean() > 0.5
    np.testing.assert_allclose(got[fov], _ramp_world(world[fov]), atol=0.51)


def test_projection_images_take_the_imager_pixel_spacing():
    """A CR image has no PixelSpacing, only ImagerPixelSpacing (0.1 mm): SimpleITK (GDCM)
    reads that, volwarp read 1 mm (physical points 10x apart)."""
    import pydicom.data

    path = str(Path(pydicom.data.__file__).parent / "test_files" / "dicomdirtests" / "77654033"
               / "CR1" / "6154")
    vol = read_dicom(path)
    img = sitk.ReadImage(path)
    np.testing.assert_allclose(vol.spacing[:2], img.GetSpacing()[:2], rtol=1e-9)
    np.testing.assert_allclose(vol.spacing[:2], [0.1, 0.1])


@pytest.mark.parametrize("orientation", [(1, 0, 0, 0, 1, 0), (0.6, 0.8, 0, 0, 0, -1)])
def test_volume_matches_highdicom_voxel_by_voxel(tmp_path, ramp, orientation):
    """highdicom's own series reader (its Volume: an affine from (slice, row, column) to
    the patient frame, LPS) places every sample where volwarp does: each of highdicom's
    voxels, mapped through volwarp's world_to_index, lands on a whole index holding the
    same value (its slice order may differ; the world may not)."""
    import highdicom as hd
    import pydicom

    write_series(tmp_path / "s", ramp, orientation=orientation, slope=2, intercept=-1024)
    ref = hd.get_volume_from_series([pydicom.dcmread(p) for p in
                                     sorted((tmp_path / "s").iterdir())], dtype=np.float64)
    vol = read_dicom(tmp_path / "s")
    k, j, i = np.indices(ref.spatial_shape).reshape(3, -1)
    world = (ref.affine @ np.stack([k, j, i, np.ones_like(k)]))[:3].T
    ijk = vol.world_to_index(world)
    np.testing.assert_allclose(ijk, np.rint(ijk), atol=1e-6)
    x, y, z = np.rint(ijk).astype(int).T
    np.testing.assert_array_equal(vol.data[z, y, x], np.asarray(ref.array)[k, j, i])
