"""DICOM SEG input: highdicom's own BINARY, FRACTIONAL and LABELMAP SEGs read back exactly.

The SEGs are built by highdicom from a small oblique CT series written here (shuffled
file names, wrong InstanceNumbers), with a slice inside the segmented range left empty
(highdicom omits its frames) and empty slices at both ends.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

from pydicom.dataset import Dataset, FileMetaDataset  # noqa: E402
from pydicom.sr.codedict import codes  # noqa: E402
from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid  # noqa: E402

from volwarp_cli.errors import BadUsage, VolwarpError  # noqa: E402
from volwarp_cli.io import read_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402

OBLIQUE = (0.6, 0.8, 0.0, 0.0, 0.0, -1.0)
SHAPE = (7, 10, 12)  # z, y, x


def write_ct(folder: Path, shape=SHAPE, *, spacing=(0.8, 0.7, 2.5), origin=(-10.0, 20.0, 30.0),
             orientation=OBLIQUE, series_uid=None, frame_uid=None, study_uid=None,
             seed=3, tilt_deg=0.0) -> list[Path]:
    """A CT series, one file per slice, names shuffled, InstanceNumbers not in position order.

    ``spacing`` is (x, y, z): PixelSpacing is (row spacing y, column spacing x).
    ``tilt_deg``: a gantry tilt, the slice origins moving along the column cosine.
    """
    folder.mkdir(parents=True, exist_ok=True)
    row, col = np.array(orientation[:3], float), np.array(orientation[3:], float)
    normal = np.cross(row, col)
    series_uid = series_uid or generate_uid()
    study_uid = study_uid or generate_uid()
    frame_uid = frame_uid or generate_uid()
    nz, ny, nx = shape
    order = list(range(nz))
    random.Random(seed).shuffle(order)
    paths = []
    for rank, k in enumerate(order):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.PatientName = "Doe^Jane"
        ds.PatientID = "P-1"
        for kw in ("PatientBirthDate", "PatientSex", "StudyDate", "StudyTime",
                   "AccessionNumber", "ReferringPhysicianName"):
            setattr(ds, kw, "")
        ds.StudyID = "1"
        ds.Manufacturer = "test"
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series_uid
        ds.SeriesNumber = 1
        ds.FrameOfReferenceUID = frame_uid
        ds.InstanceNumber = (k * 3) % nz + 1
        pos = np.array(origin) + k * spacing[2] * (normal + np.tan(np.radians(tilt_deg)) * col)
        ds.ImagePositionPatient = [f"{v:.6f}" for v in pos]
        ds.ImageOrientationPatient = [f"{v:.8f}" for v in orientation]
        ds.PixelSpacing = [spacing[1], spacing[0]]
        ds.SliceThickness = spacing[2]
        ds.Rows, ds.Columns = ny, nx
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.PixelData = np.full((ny, nx), 100 * k, "<i2").tobytes()
        path = folder / f"IM{rank:04d}.dcm"
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
    return paths


def sorted_sources(paths) -> list:
    """The series' data sets in volwarp's z order (along row cosine x column cosine)."""
    ds = [pydicom.dcmread(p) for p in paths]

    def along(d):
        iop = np.array(d.ImageOrientationPatient, float)
        return float(np.array(d.ImagePositionPatient, float) @ np.cross(iop[:3], iop[3:]))
    return sorted(ds, key=along)


def descriptions(numbers):
    return [hd.seg.SegmentDescription(
        segment_number=n, segment_label=f"organ {n}",
        segmented_property_category=codes.SCT.Organ,
        segmented_property_type=codes.SCT.Kidney if n % 2 else codes.SCT.Liver,
        algorithm_type=hd.seg.SegmentAlgorithmTypeValues.MANUAL) for n in numbers]


def make_seg(paths, pixels, kind: str, out: Path, **kw) -> Path:
    """highdicom's SEG of ``pixels`` ([z, y, x, segment] masks, or a [z, y, x] label map)."""
    n = pixels.shape[-1] if pixels.ndim == 4 else int(pixels.max())
    seg = hd.seg.Segmentation(
        source_images=sorted_sources(paths), pixel_array=pixels, segmentation_type=kind,
        segment_descriptions=descriptions(range(1, n + 1)), series_instance_uid=hd.UID(),
        series_number=5, sop_instance_uid=hd.UID(), instance_number=1, manufacturer="test",
        manufacturer_model_name="test", software_versions="1", device_serial_number="1", **kw)
    seg.save_as(out)
    return out


def labels_fixture() -> np.ndarray:
    """Three segments on slices 1, 2 and 4 (slice 3 empty, slices 0, 5, 6 empty)."""
    lab = np.zeros(SHAPE, np.uint8)
    lab[1:3, 2:5, 2:6] = 1
    lab[4, 6:9, 7:11] = 2
    lab[1, 0:2, 0:2] = 3
    lab[2, 7, 0] = 3
    return lab


def masks_of(lab, n=3) -> np.ndarray:
    return np.stack([lab == k for k in range(1, n + 1)], axis=-1)


@pytest.fixture
def ct(tmp_path):
    paths = write_ct(tmp_path / "ct")
    return tmp_path / "ct", paths


def test_binary_seg_reads_its_own_grid_with_the_empty_slice_as_zeros(ct, tmp_path):
    folder, paths = ct
    lab = labels_fixture()
    seg_path = make_seg(paths, masks_of(lab), "BINARY", tmp_path / "seg.dcm")
    assert pydicom.dcmread(seg_path).NumberOfFrames == 5  # the empty slices are left out
    ref = read_dicom(folder)
    vol = read_volume(seg_path)
    # the frames span slices 1..4; slice 3 has no frame and reads as zeros
    np.testing.assert_array_equal(vol.data, lab[1:5])
    assert vol.data.dtype == np.uint8
    np.testing.assert_allclose(vol.direction, ref.direction, atol=1e-9)
    np.testing.assert_allclose(vol.spacing, ref.spacing, rtol=1e-9)
    np.testing.assert_allclose(vol.origin, ref.index_to_world([0, 0, 1]), atol=1e-6)
    assert vol.meta["DICOM_SegmentationType"] == "BINARY"
    assert vol.meta["DICOM_ReferencedSeriesInstanceUID"] == ref.meta["DICOM_SeriesInstanceUID"]
    assert "DICOM_PatientName" not in vol.meta


def test_binary_seg_on_the_reference_grid(ct, tmp_path):
    folder, paths = ct
    lab = labels_fixture()
    seg_path = make_seg(paths, masks_of(lab), "BINARY", tmp_path / "seg.dcm")
    ref = read_dicom(folder)
    vol = read_dicom(seg_path, reference=folder)
    np.testing.assert_array_equal(vol.data, lab)
    assert vol.same_grid(ref)
    np.testing.assert_allclose(vol.origin, ref.origin, atol=1e-9)


@pytest.mark.parametrize("kind", ["FRACTIONAL", "LABELMAP"])
def test_fractional_and_labelmap_segs(ct, tmp_path, kind):
    folder, paths = ct
    lab = labels_fixture()
    if kind == "FRACTIONAL":
        probs = masks_of(lab).astype(np.float32) * 0.75  # above one half: inside
        probs[..., 0][lab == 0] = 0.25  # below one half: outside, though not zero
        seg_path = make_seg(paths, probs, kind, tmp_path / "f.dcm")
    else:
        seg_path = make_seg(paths, lab, kind, tmp_path / "l.dcm")
        assert str(pydicom.dcmread(seg_path).SOPClassUID) == "1.2.840.10008.5.1.4.1.1.66.7"
    vol = read_dicom(seg_path, reference=folder)
    np.testing.assert_array_equal(vol.data, lab)
    assert vol.same_grid(read_dicom(folder))
    one = read_dicom(seg_path, reference=folder, segment=2)
    np.testing.assert_array_equal(one.data, (lab == 2).astype(np.uint8))


def test_segment_option_gives_a_mask(ct, tmp_path, run):
    folder, paths = ct
    lab = labels_fixture()
    seg_path = make_seg(paths, masks_of(lab), "BINARY", tmp_path / "seg.dcm")
    out = tmp_path / "three.nrrd"
    res = run("convert", seg_path, "--segment", 3, "--reference", folder, "-o", out)
    assert res.code == 0, res.stderr
    vol = read_volume(out)
    np.testing.assert_array_equal(vol.data, (lab == 3).astype(np.uint8))
    assert vol.same_grid(read_dicom(folder))


def test_overlapping_segments_need_the_option(ct, tmp_path, run):
    folder, paths = ct
    lab = labels_fixture()
    masks = masks_of(lab)
    masks[1, 2, 2, 2] = True  # segment 3 also covers a voxel of segment 1
    seg_path = make_seg(paths, masks, "BINARY", tmp_path / "over.dcm")
    out = tmp_path / "out.nrrd"
    res = run("convert", seg_path, "-o", out)
    assert res.code == 1
    assert len(res.stderr.strip().splitlines()) == 1
    assert "overlap" in res.stderr and "--segment N" in res.stderr
    assert not out.exists()
    out.write_bytes(b"keep")  # an existing output is untouched
    assert run("convert", seg_path, "-o", out).code == 1
    assert out.read_bytes() == b"keep"
    assert list(tmp_path.glob(".out.nrrd*")) == []
    res = run("convert", seg_path, "--segment", 1, "-o", out)
    assert res.code == 0, res.stderr
    np.testing.assert_array_equal(read_volume(out).data, masks[1:5, ..., 0].astype(np.uint8))


def test_info_lists_segments(ct, tmp_path, run):
    _, paths = ct
    seg_path = make_seg(paths, masks_of(labels_fixture()), "BINARY", tmp_path / "seg.dcm")
    res = run("info", seg_path, "--json")
    assert res.code == 0, res.stderr
    desc = json.loads(res.stdout)
    assert desc["segmentation_type"] == "BINARY"
    assert [s["number"] for s in desc["segments"]] == [1, 2, 3]
    assert desc["segments"][0]["label"] == "organ 1"
    assert desc["segments"][0]["category"] == {"value": str(codes.SCT.Organ.value),
                                               "scheme": "SCT", "meaning": "Organ"}
    assert desc["segments"][0]["type"]["meaning"] == "Kidney"
    assert desc["segments"][1]["type"]["meaning"] == "Liver"
    assert desc["shape"] == [12, 10, 4] and desc["max"] == 3
    text = run("info", seg_path)
    assert text.code == 0 and "[2] 'organ 2'" in text.stdout


def test_bad_requests_are_one_line(ct, tmp_path, run):
    folder, paths = ct
    seg_path = make_seg(paths, masks_of(labels_fixture()), "BINARY", tmp_path / "seg.dcm")
    out = tmp_path / "o.nrrd"
    for args, code, words in [
        (("--segment", 9), 2, "segments 1 2 3"),
        (("--structure", "x"), 2, "--segment N"),
        (("--series", "0"), 2, "--reference"),
    ]:
        res = run("convert", seg_path, "-o", out, *args)
        assert res.code == code, (args, res.stderr)
        assert len(res.stderr.strip().splitlines()) == 1 and words in res.stderr, res.stderr
        assert not out.exists()
    # another patient's series (another frame of reference) is not the reference
    other = tmp_path / "other"
    write_ct(other)
    res = run("convert", seg_path, "--reference", other, "-o", out)
    assert res.code == 1 and "frame of reference" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not out.exists()
    # a CT series is not a segmentation
    res = run("convert", folder, "--segment", 1, "-o", out)
    assert res.code == 2 and "SEG and RTSTRUCT" in res.stderr and not out.exists()
    with pytest.raises(BadUsage):
        read_dicom(seg_path, segment=4)
    assert issubclass(BadUsage, VolwarpError)


def test_reference_with_several_series_takes_the_referenced_one(ct, tmp_path):
    folder, paths = ct
    lab = labels_fixture()
    seg_path = make_seg(paths, masks_of(lab), "BINARY", tmp_path / "seg.dcm")
    ref = read_dicom(folder)
    # a second series of the same frame of reference in the same folder
    f0 = pydicom.dcmread(paths[0])
    write_ct(folder / "more", shape=(3, 10, 12), frame_uid=f0.FrameOfReferenceUID,
             study_uid=f0.StudyInstanceUID)
    vol = read_dicom(seg_path, reference=folder)
    np.testing.assert_array_equal(vol.data, lab)
    assert vol.same_grid(ref)


@pytest.mark.parametrize("kind", ["BINARY", "FRACTIONAL", "LABELMAP"])
def test_a_seg_cut_inside_its_pixel_data_is_truncated(ct, tmp_path, run, kind):
    """A file cut short inside its frames is one 'truncated' error naming it, every type."""
    _, paths = ct
    lab = labels_fixture()
    pixels = lab if kind == "LABELMAP" else masks_of(lab).astype(
        np.float32 if kind == "FRACTIONAL" else bool)
    whole = make_seg(paths, pixels, kind, tmp_path / "seg.dcm").read_bytes()
    cut = tmp_path / "cut.dcm"
    cut.write_bytes(whole[:-7])  # (the pixel data is the last element)
    out = tmp_path / "o.nrrd"
    res = run("convert", cut, "-o", out)
    assert res.code == 1 and not out.exists()
    assert len(res.stderr.strip().splitlines()) == 1
    assert f"{cut}: the pixel data is truncated" in res.stderr, res.stderr


def test_info_lists_the_segments_of_a_seg_whose_segments_overlap(ct, tmp_path, run):
    """No label map holds overlapping segments, but info still lists them (to choose
    ``--segment N``) and says they overlap."""
    _, paths = ct
    masks = masks_of(labels_fixture())
    masks[1, 2, 2, 2] = True  # segment 3 also covers a voxel of segment 1
    seg_path = make_seg(paths, masks, "BINARY", tmp_path / "over.dcm")
    res = run("info", seg_path, "--json")
    assert res.code == 0, res.stderr
    desc = json.loads(res.stdout)
    assert desc["dicom_type"] == "SEG" and desc["segmentation_type"] == "BINARY"
    assert [s["number"] for s in desc["segments"]] == [1, 2, 3]
    assert [s["label"] for s in desc["segments"]] == ["organ 1", "organ 2", "organ 3"]
    assert desc["segments_overlap"] is True and "shape" not in desc
    text = run("info", seg_path)
    assert text.code == 0, text.stderr
    assert "[3] 'organ 3'" in text.stdout and "overlap" in text.stdout
    assert "--segment N" in text.stdout
    one = json.loads(run("info", seg_path, "--segment", 3, "--json").stdout)
    assert one["max"] == 1 and "segments_overlap" not in one


def test_a_seg_is_a_label_map_whatever_its_segments_look_like(ct, tmp_path, run):
    """The rule looks at neighbours, and single-voxel segments fail its region test: a
    warp took such a SEG for intensities and blended segment 2's voxel into id 1, and
    convert --dtype uint8 merged ids 300 and 1000 of a map read from a SEG into 255
    (found by a review). A volume read from a SEG (or a file that carries its
    DICOM_Modality, as volwarp's outputs do) is a label map in every command."""
    from volwarp_cli.labelmap import keep_label_ids, looks_like_labels, segmentation_of
    from volwarp_cli.volume import Volume

    folder, paths = ct
    lab = np.zeros(SHAPE, np.uint8)
    for k, (z, y, x) in enumerate([(1, 2, 3), (3, 7, 9), (5, 5, 5), (2, 8, 1)], start=1):
        lab[z, y, x] = k
    seg = make_seg(paths, masks_of(lab, 4), "BINARY", tmp_path / "dots.dcm")
    vol = read_volume(seg, dicom={"reference": folder})
    assert not looks_like_labels(vol.data)  # (the rule alone: not a label map)
    assert segmentation_of(vol.meta) == "a DICOM SEG"
    spec = tmp_path / "move.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 5}\nsteps:\n  - move:\n"
                    "      - {index: [2, 2, 2], by: [0.7, 0.4, 0.3]}\n")
    res = run("warp", seg, "--reference", folder, "--spec", spec, "-o", tmp_path / "w.nrrd",
              "--json")
    assert res.code == 0, res.stderr
    assert json.loads(res.stdout)["values_why"] == "read from a DICOM SEG: 5 labels"
    assert set(np.unique(read_volume(tmp_path / "w.nrrd").data)) <= {0, 1, 2, 3, 4}
    res = run("mesh", seg, "--reference", folder, "--json")
    assert res.code == 0 and json.loads(res.stdout)["values"] == "labels", res.stderr
    res = run("distance", seg, "--reference", folder, "--iso", "2.5", "-o", tmp_path / "d.nrrd")
    assert res.code == 2 and "is a label map (a DICOM SEG, 5 labels)" in res.stderr
    # a NRRD converted from a SEG keeps the key, and with it its ids
    far = np.zeros(SHAPE, np.uint16)
    far[1, 2, 3], far[4, 6, 8] = 300, 1000
    keep_label_ids(far, "uint8", "x.nrrd")  # (the rule alone lets them merge)
    with pytest.raises(BadUsage, match="300, 1000"):
        keep_label_ids(far, "uint8", "x.nrrd", meta={"DICOM_Modality": "SEG"})
    from volwarp_cli.io import write_volume

    write_volume(Volume(far, meta={"DICOM_Modality": "SEG"}), tmp_path / "far.nrrd")
    res = run("convert", tmp_path / "far.nrrd", "--dtype", "uint8", "-o", tmp_path / "f8.nrrd")
    assert res.code == 2 and "300, 1000" in res.stderr and not (tmp_path / "f8.nrrd").exists()
