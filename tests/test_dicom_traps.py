"""DICOM series that were read wrong with exit 0: each case now reads right or is refused.

Found by a hunt against SimpleITK and pydicom (session 38): a colour file that was
not the first of its series, a PixelData element parsed by the meta's VR encoding
instead of the body's, slice files skipped without a word, compressed fragments or
extra frames under an uncompressed syntax, a modality LUT ignored, and the gap
tolerance at micro-CT spacing.
"""

from __future__ import annotations

import io
import os

import numpy as np
import pydicom
import pytest
from pydicom.filewriter import write_file_meta_info
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian, RLELossless
from test_io_dicom import write_series

from volwarp_cli.errors import FormatError
from volwarp_cli.io.dicom import read_dicom


@pytest.fixture
def stack():
    return np.random.default_rng(38).integers(-1000, 2000, size=(5, 6, 8)).astype(np.int16)


def _in_position_order(paths):
    return sorted(paths, key=lambda p: float(pydicom.dcmread(p).ImagePositionPatient[2]))


@pytest.mark.parametrize("kind", ["RGB", "PALETTE COLOR"])
def test_a_colour_file_anywhere_in_the_series_is_refused(tmp_path, stack, kind):
    paths = write_series(tmp_path / "s", stack, shuffle=False, names=[f"S{k}.dcm" for k in range(5)])
    ds = pydicom.dcmread(paths[2])  # the middle file: not the first the reader meets
    if kind == "RGB":
        ds.SamplesPerPixel, ds.PhotometricInterpretation, ds.PlanarConfiguration = 3, "RGB", 0
        ds.BitsAllocated = ds.BitsStored = 8
        ds.HighBit = 7
        ds.PixelRepresentation = 0
        ds.PixelData = np.repeat(stack[2].astype(np.uint8)[..., None], 3, -1).tobytes()
    else:
        ds.PhotometricInterpretation = "PALETTE COLOR"
    ds.save_as(paths[2])
    with pytest.raises(FormatError, match=r"S2\.dcm: colour image"):
        read_dicom(tmp_path / "s")


def _relabel(path, syntax):
    """Rewrite the file meta's transfer syntax, leaving the data set's bytes as they are."""
    raw = path.read_bytes()
    meta_end = 132 + 12 + int.from_bytes(raw[140:144], "little")
    meta = pydicom.dcmread(path).file_meta
    meta.TransferSyntaxUID = syntax
    buf = io.BytesIO()
    buf.write(b"\0" * 128 + b"DICM")
    write_file_meta_info(buf, meta, enforce_standard=True)
    buf.write(raw[meta_end:])
    path.write_bytes(buf.getvalue())


@pytest.mark.parametrize("written, said", [(ExplicitVRLittleEndian, ImplicitVRLittleEndian),
                                           (ImplicitVRLittleEndian, ExplicitVRLittleEndian)])
def test_pixel_data_is_parsed_as_written_not_as_the_meta_says(tmp_path, stack, written, said):
    # The value started 4 bytes early (or late): samples shifted by two, exit 0.
    paths = write_series(tmp_path / "s", stack)
    for p in paths:
        ds = pydicom.dcmread(p)
        ds.file_meta.TransferSyntaxUID = written
        ds.save_as(p)
        _relabel(p, said)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s").data, stack)


def test_compressed_fragments_under_an_uncompressed_syntax_are_refused(tmp_path, stack):
    paths = write_series(tmp_path / "s", stack[:2])
    for p in paths:
        ds = pydicom.dcmread(p)
        ds.compress(RLELossless)
        ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian  # the fragments stay
        ds.save_as(p, implicit_vr=False, little_endian=True)
    with pytest.raises(FormatError, match="encapsulated"):
        read_dicom(tmp_path / "s")


def test_pixel_data_with_frames_the_header_does_not_count_is_refused(tmp_path, stack):
    paths = write_series(tmp_path / "s", stack[:1])
    ds = pydicom.dcmread(paths[0])
    ds.PixelData = stack.tobytes()  # five frames; NumberOfFrames absent (1)
    ds.save_as(paths[0])
    with pytest.raises(FormatError, match="5 frames of 6 x 8.*NumberOfFrames says 1"):
        read_dicom(paths[0])
    ds.PixelData = stack[0].tobytes() + b"\0\0\0\0"  # less than a frame more: said, not read
    ds.save_as(paths[0])
    np.testing.assert_array_equal(read_dicom(paths[0]).data[0], stack[0])


def _cut_before_pixels(path):
    raw = path.read_bytes()
    path.write_bytes(raw[:raw.index(b"\xe0\x7f\x10\x00")])


@pytest.mark.parametrize("damage", ["empty", "foreign", "cut-before-pixels", "dangling-link"])
def test_a_lost_last_slice_is_refused_not_skipped(tmp_path, stack, damage):
    # The first or last slice skipped left a volume a slice short with exit 0: nothing
    # else (no gap) shows it.
    paths = _in_position_order(write_series(tmp_path / "s", stack))
    last = paths[-1]
    if damage == "empty":
        last.write_bytes(b"")
    elif damage == "foreign":
        last.write_bytes(b"<html>502 Bad Gateway</html>")
    elif damage == "cut-before-pixels":
        _cut_before_pixels(last)
    else:  # a file that cannot be opened (as one without read permission, even for root)
        last.unlink()
        last.symlink_to(tmp_path / "gone.dcm")
    with pytest.raises(FormatError, match=rf"{last.name}"):
        read_dicom(tmp_path / "s")


def test_files_without_the_preamble_are_read_when_they_are_dicom(tmp_path, stack):
    paths = _in_position_order(write_series(tmp_path / "s", stack))
    for p in (paths[0], paths[-1]):
        p.write_bytes(p.read_bytes()[132:])  # no preamble, no "DICM": GDCM reads these
    (tmp_path / "s" / "notes.txt").write_text("scanned 2026-12-01\n")  # skipped, said
    np.testing.assert_array_equal(read_dicom(tmp_path / "s").data, stack)
    assert pydicom.dcmread(paths[0], force=True).ImagePositionPatient is not None


def test_a_series_of_stripped_image_objects_is_no_slice_of_another(tmp_path, stack):
    # An image object without pixels whose series has no image (a DICOMDIR's examples)
    # is skipped, as before: no candidate is short of it.
    write_series(tmp_path / "s", stack)
    other = write_series(tmp_path / "o", stack[:1], series="1.2.826.0.1.3680043.8.498.2")[0]
    _cut_before_pixels(other)
    os.replace(other, tmp_path / "s" / "stripped.dcm")
    np.testing.assert_array_equal(read_dicom(tmp_path / "s").data, stack)


def test_a_modality_lut_is_refused_not_ignored():
    from pydicom.data import get_testdata_file

    with pytest.raises(FormatError, match="ModalityLUTSequence"):
        read_dicom(get_testdata_file("mlut_18.dcm"))


@pytest.mark.parametrize("spacing", [0.008, 0.01, 0.05])
def test_a_missing_slice_at_micro_ct_spacing_is_found(tmp_path, stack, spacing):
    # The gap tolerance was 0.01 mm whatever the spacing: at 0.01 mm a missing slice
    # passed and the stack was placed on an even grid, off by up to half a slice.
    positions = [(0.0, 0.0, spacing * k) for k in (0, 1, 2, 4, 5)]
    write_series(tmp_path / "s", stack, positions=positions, spacing=(0.01, 0.01))
    with pytest.raises(FormatError, match="missing slice"):
        read_dicom(tmp_path / "s")
    write_series(tmp_path / "r", stack, spacing_z=spacing, spacing=(0.01, 0.01))
    assert read_dicom(tmp_path / "r").spacing[2] == pytest.approx(spacing)


@pytest.mark.parametrize("layout", ["tilted", "irregular"])
def test_a_label_map_stored_as_a_series_is_resampled_without_blending_ids(tmp_path, layout):
    # A gantry tilt's resampling (automatic) or --irregular resample blended ids 7 and
    # 300 into 3.5, 150, ... (float32), and the rule then called the volume intensities.
    ids = np.zeros((8, 20, 24), np.int16)
    ids[1:7, 4:16, 5:19] = 7
    ids[2:6, 6:12, 8:14] = 300
    ids[3:5, 12:15, 14:17] = 1000
    if layout == "tilted":  # 15 degrees: each slice 2.5 tan(15) mm further along y
        positions = [(0.0, 2.5 * k * np.tan(np.radians(15)), 2.5 * k) for k in range(8)]
    else:
        positions = [(0.0, 0.0, z) for z in (0, 2.5, 5, 7.5, 12.5, 15, 17.5, 20)]
    write_series(tmp_path / "s", ids, positions=positions, spacing=(1.0, 1.0))
    vol = read_dicom(tmp_path / "s", irregular="resample")
    assert vol.data.dtype == np.int16
    assert set(np.unique(vol.data).tolist()) <= {0, 7, 300, 1000}
    assert set(np.unique(vol.data).tolist()) >= {7, 300, 1000}
    if layout == "irregular":  # the missing slice's place takes its nearer neighbour's ids
        np.testing.assert_array_equal(vol.data[:4], ids[:4])
        np.testing.assert_array_equal(vol.data[5:], ids[4:])
        np.testing.assert_array_equal(vol.data[4], ids[3])


def test_a_cut_file_of_one_series_blocks_that_series_only(tmp_path, stack):
    """A file of series B cut before its pixels refused every read of the folder, series A's
    and the listing too; B alone is refused now, and listed with the reason."""
    from volwarp_cli.io.dicom import scan_dicom

    write_series(tmp_path / "d" / "A", stack)
    b = write_series(tmp_path / "d" / "B", stack[:2], series="1.2.826.0.1.3680043.8.498.2")
    _cut_before_pixels(b[0])
    cands = scan_dicom(tmp_path / "d")
    assert len(cands) == 2
    a_index = next(c.index for c in cands if c.series_uid.endswith(".1"))
    b_cand = next(c for c in cands if c.series_uid.endswith(".2"))
    assert "without PixelData" in b_cand.why
    np.testing.assert_array_equal(read_dicom(tmp_path / "d", series=a_index).data, stack)
    with pytest.raises(FormatError, match=rf"{b[0].name}: CT Image Storage without PixelData"):
        read_dicom(tmp_path / "d", series=b_cand.index)


def test_macos_companion_files_and_empty_lookup_tables_are_not_refused(tmp_path, stack):
    """A folder copied by macOS to FAT or SMB holds ._IM0000.dcm beside each file (its
    AppleDouble data, not DICOM), and an empty ModalityLUTSequence holds no table: the
    series reads, as before the refusals of foreign *.dcm files and of modality LUTs."""
    from pydicom.sequence import Sequence

    paths = write_series(tmp_path / "s", stack)
    for p in paths:
        (p.parent / f"._{p.name}").write_bytes(b"\x00\x05\x16\x07" + b"\x00" * 78)
        ds = pydicom.dcmread(p)
        ds.ModalityLUTSequence = Sequence([])
        ds.save_as(p)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s").data, stack)


def test_a_folder_of_files_without_the_preamble_is_a_dicom_input(tmp_path, stack):
    from volwarp_cli.io import read_volume

    for p in write_series(tmp_path / "s", stack):
        p.write_bytes(p.read_bytes()[132:])
        p.rename(p.with_suffix(""))  # (no extension either)
    np.testing.assert_array_equal(read_volume(tmp_path / "s").data, stack)


def test_apply_chooses_a_dicom_references_series(tmp_path, stack, run):
    """`apply --reference DIR` of a folder holding two series said "choose one with
    --series", which chooses INPUT's: --reference-series chooses the reference's."""
    from volwarp_cli.io import read_volume, write_volume
    from volwarp_cli.volume import Volume

    write_series(tmp_path / "ref" / "A", stack)
    write_series(tmp_path / "ref" / "B", stack[:3, :4, :5], series="1.2.826.0.1.3680043.8.498.2",
                 spacing_z=1.5)
    write_volume(Volume(stack.astype(np.float32)), tmp_path / "in.nrrd")
    (tmp_path / "t.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 0 0 0\nFixedParameters: 0 0 0\n")
    base = ["apply", tmp_path / "in.nrrd", "-t", tmp_path / "t.tfm", "--reference",
            tmp_path / "ref", "-o", tmp_path / "o.nrrd"]
    res = run(*base)
    assert res.code == 2 and "--reference-series" in res.stderr, res.stderr
    from volwarp_cli.io.dicom import scan_dicom

    b = next(c.index for c in scan_dicom(tmp_path / "ref") if c.series_uid.endswith(".2"))
    res = run(*base, "--reference-series", str(b))
    assert res.code == 0, res.stderr
    out = read_volume(tmp_path / "o.nrrd")
    assert out.shape_xyz == (5, 4, 3) and out.spacing[2] == pytest.approx(1.5)
    res = run("apply", tmp_path / "in.nrrd", "-t", tmp_path / "t.tfm", "--reference",
              tmp_path / "in.nrrd", "-o", tmp_path / "p.nrrd", "--reference-series", "1")
    assert res.code == 2 and "is not DICOM" in res.stderr


def test_hidden_files_in_a_series_folder_are_never_slices(tmp_path, stack):
    """A hidden file (a lock, a dangling .link, macOS's ._*) is skipped whatever it is: the
    refusal of an unreadable file is for the series' own files."""
    write_series(tmp_path / "s", stack)
    (tmp_path / "s" / ".lock").symlink_to(tmp_path / "gone")
    (tmp_path / "s" / ".DS_Store").write_bytes(b"\0\0\0\1Bud1")
    np.testing.assert_array_equal(read_dicom(tmp_path / "s").data, stack)


def test_a_hidden_dicom_file_is_a_copy_under_way_and_refused(tmp_path, stack, run):
    """rsync writes each file as ``.NAME.XXXXXX`` and renames it when whole: a series
    read meanwhile lacked that slice (the last one: nothing else shows it), exit 0."""
    paths = write_series(tmp_path / "s", stack, shuffle=False)
    last = max(paths, key=lambda p: pydicom.dcmread(p).ImagePositionPatient[2])
    partial = last.parent / f".{last.name}.Gx81kQ"
    whole = last.read_bytes()
    partial.write_bytes(whole[:400])  # (the copy's first bytes)
    last.unlink()
    with pytest.raises(FormatError, match=r"hidden DICOM file \(a copy under way"):
        read_dicom(tmp_path / "s")
    res = run("convert", tmp_path / "s", "-o", tmp_path / "o.nrrd")
    assert res.code == 1 and partial.name in res.stderr and not (tmp_path / "o.nrrd").exists()
    partial.write_bytes(whole)
    partial.rename(last)  # (the copy done: read whole)
    np.testing.assert_array_equal(read_dicom(tmp_path / "s").data, stack)
