"""NIfTI data integrity: gzip checks, sform/qform codes on writing, 5-D vector files,
truncated and CIFTI files.

References: nibabel's shipped test files, files written by nibabel and SimpleITK;
nibabel (the sform whenever its code is above 0, as FSL and SPM) and SimpleITK
(ITK's rule) must place a file volwarp writes where volwarp placed its input.
"""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from nibabel.testing import data_path

from volwarp_cli.errors import ChoiceNeeded, FormatError, VolwarpError
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.lazy import open_volume_lazy

NB = Path(data_path)
LPS = np.diag([-1.0, -1.0, 1.0])
WARP_SPEC = """version: 1
capture: {lattice: 5, oversample: 1}
steps:
  - move:
      - {index: [2, 2, 2], by: [1.0, 0.0, 0.0]}
"""


def one_error_line(res, path, code: int = 1) -> str:
    """The run failed with one line naming ``path`` (no internal error, no traceback)."""
    assert res.code == code, res
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"volwarp: error: {path}: "), lines
    assert "internal error" not in lines[0] and "Traceback" not in res.stderr
    return lines[0]


# -- 1. gzip streams are checked to their end ------------------------------------

@pytest.fixture
def anatomical_gz(tmp_path, run):
    path = tmp_path / "a.nii.gz"
    assert run("convert", "-q", NB / "anatomical.nii", "-o", path).code == 0
    return path


def test_every_byte_flip_near_the_end_is_refused_or_harmless(anatomical_gz, tmp_path):
    """The tester's sweep: over the last 300 compressed bytes, 55 of 59 single-byte flips
    were read with wrong samples. Now a flip either fails gzip's CRC-32 / length check
    (or the inflate itself), or leaves every sample as it was (a padding bit)."""
    want = read_volume(NB / "anatomical.nii").data
    good = anatomical_gz.read_bytes()
    refused = 0
    bad = tmp_path / "flip.nii.gz"
    for back in range(1, 301, 5):
        raw = bytearray(good)
        raw[len(raw) - back] ^= 0x10
        bad.write_bytes(bytes(raw))
        try:
            vol = read_volume(bad)
        except FormatError as exc:
            assert str(exc).startswith(f"{bad}: cannot read NIfTI data ("), exc
            refused += 1
            continue
        assert np.array_equal(vol.data, want), f"flip {back} bytes from the end read wrong"
    assert refused >= 55


def test_the_testers_corrupt_file_on_the_command_line(run, anatomical_gz, tmp_path):
    raw = bytearray(anatomical_gz.read_bytes())
    raw[len(raw) - 60] ^= 0x10
    bad = tmp_path / "corrupt.nii.gz"
    bad.write_bytes(bytes(raw))
    with pytest.raises(OSError):  # gzip -t's verdict
        gzip.decompress(bytes(raw))
    out = tmp_path / "out.nrrd"
    line = one_error_line(run("convert", bad, "-o", out), bad)
    assert "gzip stream is corrupt" in line
    assert not out.exists() and not list(tmp_path.glob(".*"))  # no partial output


@pytest.mark.parametrize("volume_index", [0, 1])
def test_a_damaged_4d_file_is_refused_whichever_volume_is_read(tmp_path, volume_index):
    """Volume 0 of example4d.nii.gz lies before the damage: its bytes were enough for
    nibabel's proxy, which then never reached gzip's check."""
    raw = bytearray((NB / "example4d.nii.gz").read_bytes())
    raw[len(raw) - 40] ^= 0x01
    bad = tmp_path / "e4.nii.gz"
    bad.write_bytes(bytes(raw))
    with pytest.raises(FormatError, match=r"e4\.nii\.gz: cannot read NIfTI data"):
        read_volume(bad, volume_index=volume_index)
    good = read_volume(NB / "example4d.nii.gz", volume_index=volume_index)
    arr = np.asanyarray(nib.load(NB / "example4d.nii.gz").dataobj)[..., volume_index]
    np.testing.assert_array_equal(good.data, arr.transpose(2, 1, 0))


@pytest.mark.parametrize("keep", [-4, -8, -500, 2000, 400])
def test_truncated_gzip_is_one_clear_error(run, anatomical_gz, tmp_path, keep):
    raw = anatomical_gz.read_bytes()
    cut = tmp_path / "cut.nii.gz"
    cut.write_bytes(raw[:keep])
    with pytest.raises(FormatError, match=r"cut\.nii\.gz: "):
        read_volume(cut)
    out = tmp_path / "o.nrrd"
    one_error_line(run("convert", cut, "-o", out), cut)
    assert not out.exists()


def test_gzip_members_padding_and_trailing_garbage(anatomical_gz, tmp_path):
    """gzip allows members one after another and NUL padding (as `gzip -t` and Python's
    gzip read them); anything else after the stream is corrupt."""
    want = read_volume(anatomical_gz).data
    plain = gzip.decompress(anatomical_gz.read_bytes())
    two = tmp_path / "two.nii.gz"
    two.write_bytes(gzip.compress(plain[:5000]) + gzip.compress(plain[5000:]))
    np.testing.assert_array_equal(read_volume(two).data, want)
    padded = tmp_path / "pad.nii.gz"
    padded.write_bytes(anatomical_gz.read_bytes() + b"\0" * 37)
    np.testing.assert_array_equal(read_volume(padded).data, want)
    junk = tmp_path / "junk.nii.gz"
    junk.write_bytes(anatomical_gz.read_bytes() + b"garbage")
    with pytest.raises(FormatError, match=r"junk\.nii\.gz: cannot read NIfTI data"):
        read_volume(junk)


def test_gzip_files_of_nibabel_and_simpleitk_read_as_they_do(tmp_path):
    data = np.arange(5 * 6 * 7, dtype=np.float32).reshape(5, 6, 7) * 0.5  # x, y, z
    nib.save(nib.Nifti1Image(data, np.diag([2.0, 3.0, 4.0, 1.0])), tmp_path / "n.nii.gz")
    np.testing.assert_array_equal(read_volume(tmp_path / "n.nii.gz").data,
                                  data.transpose(2, 1, 0))
    img = sitk.GetImageFromArray(data.transpose(2, 1, 0).astype(np.int16))
    img.SetSpacing((0.5, 0.7, 1.5))
    sitk.WriteImage(img, str(tmp_path / "s.nii.gz"))
    vol = read_volume(tmp_path / "s.nii.gz")
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(img))
    np.testing.assert_allclose(vol.spacing, (0.5, 0.7, 1.5), atol=1e-6)


def test_scaled_samples_are_read_as_before(tmp_path):
    """functional.nii: scaled int16, float32 as SimpleITK reads it; also gzipped."""
    src = NB / "functional.nii"
    gz = tmp_path / "f.nii.gz"
    gz.write_bytes(gzip.compress(src.read_bytes()))
    want = sitk.GetArrayFromImage(sitk.ReadImage(str(src)))[7]
    for path in (src, gz):
        vol = read_volume(path, volume_index=7)
        assert vol.data.dtype == np.float32
        np.testing.assert_array_equal(vol.data, want)


# -- 2. a written form code is paired with that form's matrix ----------------------

def _affine(origin, scales=(2.0, 2.0, 2.0), angle=0.0):
    a = np.deg2rad(angle)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rot * np.asarray(scales, float)[None, :]
    m[:3, 3] = origin
    return m


MNI_SFORM = _affine((-90.0, -126.0, -72.0))
SCANNER_QFORM = _affine((-10.0, -12.0, -8.0), angle=10.0)


def two_forms(path, sform, scode, qform, qcode):
    img = nib.Nifti1Image(np.arange(6 * 7 * 8, dtype=np.int16).reshape(6, 7, 8), None)
    img.set_qform(qform, code=qcode)
    img.set_sform(sform, code=scode)
    img.header["descrip"] = b"two forms"
    nib.save(img, path)
    return path


def sitk_matrix(path) -> np.ndarray:
    """The voxel-to-RAS matrix SimpleITK (ITK's rule) reads."""
    img = sitk.ReadImage(str(path))
    m = np.eye(4)
    lin = np.reshape(img.GetDirection(), (3, 3)) * np.array(img.GetSpacing())[None, :]
    m[:3, :3] = LPS @ lin
    m[:3, 3] = LPS @ np.array(img.GetOrigin())
    return m


def assert_forms_are_their_own(path, want: np.ndarray):
    """Every coded form of ``path`` holds ``want``; nibabel and SimpleITK read ``want``."""
    h = nib.load(path).header
    for getter in ("get_sform", "get_qform"):
        matrix, code = getattr(h, getter)(coded=True)
        if code:
            np.testing.assert_allclose(matrix, want, rtol=0, atol=1e-4, err_msg=getter)
    if any(codes(path)):  # (uncoded: nibabel has its own default, not ITK's "method 1")
        np.testing.assert_allclose(nib.load(path).affine, want, rtol=0, atol=1e-4)
    np.testing.assert_allclose(sitk_matrix(path), want, rtol=0, atol=1e-4)


def codes(path) -> tuple[int, int]:
    h = nib.load(path).header
    return int(h["sform_code"]), int(h["qform_code"])


def test_forms_mirrored_about_one_origin_say_where_others_read_them(run, tmp_path):
    """An aligned sform and a scanner qform that differ by a mirror of the third voxel axis
    (one origin). volwarp reads the qform (they differ); ITK's check compares only the two
    SVDs' left factors, which a mirror on the voxel side leaves alike, and SimpleITK 2.5
    read the sform of this file, as nibabel does: the warning says so (it claimed ITK's
    rule only, and the image was mirrored in z against every other reader)."""
    rot = nib.eulerangles.euler2mat(0.3, -0.2, 0.5) @ np.diag([1.2, 0.9, 2.0])
    sform = np.eye(4)
    sform[:3, :3], sform[:3, 3] = rot, (-10.0, 20.0, 5.0)
    qform = sform.copy()
    qform[:3, 2] *= -1
    src = two_forms(tmp_path / "in.nii", sform, 2, qform, 1)
    np.testing.assert_allclose(nib.load(src).affine, sform, atol=1e-5)  # nibabel: the sform
    assert any(np.allclose(sitk_matrix(src), m, atol=1e-4) for m in (sform, qform))
    res = run("convert", src, "-o", tmp_path / "copy.nii")
    assert res.code == 0, res.stderr
    assert "nibabel, FSL and SPM read the sform of this file" in res.stderr, res.stderr
    assert "so may SimpleITK" in res.stderr and "set the qform code to 0" in res.stderr
    assert res.stderr.count("places the image elsewhere") == 1
    np.testing.assert_allclose(nib.load(tmp_path / "copy.nii").affine, qform, atol=1e-4)
    # the other way round (the sform read, the qform dropped) every reader agrees: not said
    res = run("convert", two_forms(tmp_path / "s.nii", sform, 1, qform, 1), "-o",
              tmp_path / "s.nrrd")
    assert res.code == 0 and "places the image elsewhere" in res.stderr
    assert "nibabel" not in res.stderr


def test_sform_voxel_sizes_other_than_pixdim_are_said(run, tmp_path):
    """An sform alone whose column lengths are not pixdim's: volwarp (as nibabel) takes the
    sform's, SimpleITK pixdim's (its own warning), so the image's extent differs between
    them; volwarp said nothing. Sizes that agree (to float32) say nothing."""
    rot = nib.eulerangles.euler2mat(0.3, -0.2, 0.5)
    sform = np.eye(4)
    sform[:3, :3], sform[:3, 3] = rot @ np.diag([1.2, 0.9, 2.0]), (-10.0, 20.0, 5.0)
    img = nib.Nifti1Image(np.arange(6 * 7 * 8, dtype=np.int16).reshape(6, 7, 8), None)
    img.set_sform(sform, code=2)
    img.set_qform(None, code=0)
    nib.save(img, tmp_path / "in.nii")
    assert tuple(nib.load(tmp_path / "in.nii").header["pixdim"][1:4]) == (1, 1, 1)
    np.testing.assert_allclose(sitk.ReadImage(str(tmp_path / "in.nii")).GetSpacing(), 1.0)
    res = run("convert", tmp_path / "in.nii", "-o", tmp_path / "out.nrrd")
    assert res.code == 0
    said = [line for line in res.stderr.splitlines() if "pixdim" in line]
    assert len(said) == 1 and "voxel sizes (1.2, 0.9, 2) are not pixdim's (1, 1, 1)" in said[0]
    # a metre file's 1 mm against 2 mm (0.001 against 0.002 in its units) is said too
    metre = nib.Nifti1Image(np.zeros((4, 5, 6), np.int16), None)
    metre.set_sform(np.diag([0.002, 0.002, 0.002, 1.0]), code=2)
    metre.set_qform(None, code=0)
    metre.header.set_zooms((0.001, 0.001, 0.001))
    metre.header.set_xyzt_units("meter")
    nib.save(metre, tmp_path / "metre.nii.gz")
    (tmp_path / "id.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 0 0 0\nFixedParameters: 0 0 0\n")
    res = run("apply", tmp_path / "metre.nii.gz", "-o", tmp_path / "metre.nrrd", "-t",
              tmp_path / "id.tfm")
    assert res.code == 0, res.stderr
    assert res.stderr.count("are not pixdim's") == 1, res.stderr  # (once, the file read twice)
    np.testing.assert_allclose(read_volume(tmp_path / "out.nrrd").spacing, (1.2, 0.9, 2.0),
                               rtol=1e-6)
    img.header.set_zooms((1.2, 0.9, 2.0))  # (now both say the same)
    nib.save(img, tmp_path / "same.nii")
    res = run("convert", tmp_path / "same.nii", "-o", tmp_path / "same.nrrd")
    assert res.code == 0 and "pixdim" not in res.stderr, res.stderr


def test_the_testers_mni_sform_beside_a_scanner_qform(run, tmp_path):
    """ITK reads the qform (the sform's code is not 1 and they differ); the copy had the
    qform's matrix under the sform's MNI code, so nibabel/FSL/SPM moved the image."""
    src = two_forms(tmp_path / "in.nii", MNI_SFORM, 4, SCANNER_QFORM, 1)
    want = sitk_matrix(src)
    np.testing.assert_allclose(want, SCANNER_QFORM, atol=1e-4)  # ITK's choice
    res = run("convert", src, "-o", tmp_path / "copy.nii")
    assert res.code == 0
    assert "sform (code 4) places the image elsewhere" in res.stderr  # one warning
    # (their origins differ: ITK's check cannot pass, SimpleITK reads the qform as volwarp)
    assert "nibabel, FSL and SPM read the sform" in res.stderr
    assert "SimpleITK" not in res.stderr
    assert codes(tmp_path / "copy.nii") == (0, 1)
    assert_forms_are_their_own(tmp_path / "copy.nii", want)
    assert run("convert", src, "-o", tmp_path / "c.nrrd").code == 0
    assert run("convert", tmp_path / "c.nrrd", "-o", tmp_path / "back.nii.gz").code == 0
    assert codes(tmp_path / "back.nii.gz") == (0, 1)
    assert_forms_are_their_own(tmp_path / "back.nii.gz", want)
    assert read_volume(tmp_path / "back.nii.gz").meta["descrip"] == "two forms"


@pytest.mark.parametrize("scode,qcode,same,expect", [
    (4, 1, False, (0, 1)),   # qform read; the MNI sform is not carried
    (2, 1, False, (0, 1)),
    (1, 1, False, (1, 0)),   # scanner sform read; the other qform is not carried
    (1, 2, False, (1, 0)),
    (4, 0, False, (4, 0)),
    (0, 2, False, (0, 2)),
    (4, 2, True, (4, 2)),    # one matrix in both forms: both codes kept
    (2, 2, True, (2, 2)),
    (3, 1, True, (3, 1)),
    (0, 0, True, (0, 0)),
])
def test_written_codes_go_with_their_own_matrices(tmp_path, scode, qcode, same, expect):
    qform = SCANNER_QFORM
    sform = qform if same else MNI_SFORM
    src = two_forms(tmp_path / "in.nii", sform, scode, qform, qcode)
    want = sitk_matrix(src)
    vol = read_volume(src)
    for out in ("o.nii", "o.nii.gz"):
        write_volume(vol, tmp_path / out)
        assert codes(tmp_path / out) == expect
        assert_forms_are_their_own(tmp_path / out, want)
        assert read_volume(tmp_path / out).same_grid(vol, atol=1e-4)


def test_a_skewed_sform_beside_its_qform_is_not_carried(tmp_path):
    """SPM-like: a sheared sform, its rigid approximation in the qform. ITK reads the
    qform, so does volwarp; the sform's matrix is not volwarp's and is written uncoded."""
    sform = _affine((5.0, 6.0, 7.0), scales=(1.0, 1.2, 1.5))
    sform[0, 1] = 0.3
    src = two_forms(tmp_path / "in.nii", sform, 2, _affine((5.0, 6.0, 7.0)), 2)
    want = sitk_matrix(src)
    write_volume(read_volume(src), tmp_path / "o.nii")
    assert codes(tmp_path / "o.nii") == (0, 2)
    assert_forms_are_their_own(tmp_path / "o.nii", want)


def test_a_warp_writes_the_form_it_warped_in(run, tmp_path):
    src = two_forms(tmp_path / "in.nii", MNI_SFORM, 4, SCANNER_QFORM, 1)
    spec = tmp_path / "w.yaml"
    spec.write_text(WARP_SPEC)
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "w.nii.gz")
    assert res.code == 0, res.stderr
    out = tmp_path / "w.nii.gz"
    assert codes(out) == (0, 1)
    want = sitk_matrix(out)  # the warp's output grid (padded): in the qform's frame
    np.testing.assert_allclose(want[:3, :3], SCANNER_QFORM[:3, :3], atol=1e-5)
    assert_forms_are_their_own(out, want)
    vol = read_volume(out)
    np.testing.assert_allclose(vol.index_to_world_matrix[:3, 3], LPS @ want[:3, 3], atol=1e-4)


def test_forms_that_differ_by_rounding_keep_both_codes(tmp_path, caplog):
    """example_nifti2.nii.gz: both codes 1, the qform's quaternion off by 1.4e-4 (4e-3 mm
    at the grid's corners, 0.002 voxel): the same frame, both codes kept, no warning.
    ITK's rule reads the sform (code 1), as nibabel does (SimpleITK does not open this
    NIfTI-2 file)."""
    src = NB / "example_nifti2.nii.gz"
    header = nib.load(src).header
    sform, qform = header.get_sform(), header.get_qform()
    assert 1e-4 < np.abs(sform - qform).max() < 1e-3
    vol = read_volume(src, volume_index=0)
    np.testing.assert_allclose(vol.index_to_world_matrix[:3, :3], LPS @ sform[:3, :3],
                               atol=1e-5)
    assert "NIfTI_sform_code" not in vol.meta  # (1, 1): the writer's default
    assert "places the image elsewhere" not in caplog.text
    write_volume(vol, tmp_path / "o.nii")
    assert codes(tmp_path / "o.nii") == (1, 1)
    assert_forms_are_their_own(tmp_path / "o.nii", sform)


# -- 3. 5-D files: one component per read ----------------------------------------

@pytest.fixture(scope="module")
def fields(tmp_path_factory):
    """volwarp's own displacement field as .nii.gz and .nrrd (the tester's command)."""
    from click.testing import CliRunner

    from volwarp_cli.cli.main import cli

    tmp = tmp_path_factory.mktemp("fields")
    spec = tmp / "w.yaml"
    spec.write_text(WARP_SPEC)
    src = Path(__file__).parent / "data" / "ball_30_uint8.nrrd"
    for name in ("disp.nii.gz", "disp.nrrd"):
        res = CliRunner().invoke(cli, ["warp", "-q", str(src), "--spec", str(spec), "-o",
                                       str(tmp / f"w_{name}.nrrd"), "--displacement-to",
                                       str(tmp / name)], catch_exceptions=False)
        assert res.exit_code == 0, res.stderr
    return tmp / "disp.nii.gz", tmp / "disp.nrrd"


@pytest.mark.parametrize("k", [0, 1, 2])
def test_volwarps_nifti_field_reads_like_its_nrrd_field(fields, k):
    nii, nrrd = fields
    a, b = read_volume(nii, volume_index=k), read_volume(nrrd, volume_index=k)
    assert a.same_grid(b, atol=1e-5)
    np.testing.assert_array_equal(a.data, b.data)
    assert a.meta["volwarp_component"] == b.meta["volwarp_component"] == "xyz"[k]
    assert a.meta["volwarp_field"] == b.meta["volwarp_field"]
    assert not any(key.startswith("NIfTI_intent") for key in a.meta)  # the 5th axis's


def test_a_field_without_volume_index_asks_for_one(run, fields):
    nii, _ = fields
    with pytest.raises(ChoiceNeeded, match=r"3 components per voxel .*--volume-index 0\.\.2"):
        read_volume(nii)
    # (info describes volume 0 and counts them; the other commands ask)
    res = run("info", nii)
    assert res.code == 0 and "volumes:   3 in the file" in res.stdout
    line = one_error_line(run("convert", nii, "-o", nii.with_name("c.nrrd")), nii, code=2)
    assert "choose one with --volume-index" in line
    with pytest.raises(VolwarpError, match=r"--volume-index 3 is outside 0\.\.2"):
        read_volume(nii, volume_index=3)
    res = run("info", nii, "--volume-index", 1)
    assert res.code == 0 and "volwarp_component = y" in res.stdout


@pytest.mark.parametrize("pixel", [sitk.sitkVectorFloat32, sitk.sitkVectorFloat64,
                                   sitk.sitkVectorInt16])
def test_simpleitk_vector_files(tmp_path, pixel):
    rng = np.random.default_rng(3)
    arr = rng.normal(0, 5, (4, 5, 6, 3))  # z, y, x, component
    img = sitk.Cast(sitk.GetImageFromArray(arr, isVector=True), pixel)
    img.SetSpacing((0.5, 0.75, 2.0))
    img.SetOrigin((10.0, -20.0, 30.0))
    img.SetDirection((0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    path = tmp_path / "v.nii.gz"
    sitk.WriteImage(img, str(path))
    assert nib.load(path).shape == (6, 5, 4, 1, 3)
    want = sitk.GetArrayFromImage(img)
    for k in range(3):
        vol = read_volume(path, volume_index=k)
        np.testing.assert_array_equal(vol.data, want[..., k])
        np.testing.assert_allclose(vol.spacing, img.GetSpacing(), atol=1e-6)
        np.testing.assert_allclose(vol.origin, img.GetOrigin(), atol=1e-5)
        np.testing.assert_allclose(vol.direction.ravel(), img.GetDirection(), atol=1e-6)
    write_volume(read_volume(path, volume_index=2), tmp_path / "c.nii")
    h = nib.load(tmp_path / "c.nii").header
    assert int(h["intent_code"]) == 0  # a scalar volume is not a vector
    uncompressed = tmp_path / "v.nii"
    sitk.WriteImage(img, str(uncompressed))
    np.testing.assert_array_equal(read_volume(uncompressed, volume_index=1).data, want[..., 1])


def test_several_volumes_of_several_components_are_refused(tmp_path):
    data = np.zeros((3, 4, 5, 2, 3), np.float32)
    nib.save(nib.Nifti1Image(data, np.eye(4)), tmp_path / "tc.nii")
    with pytest.raises(FormatError, match=r"tc\.nii: NIfTI with shape .* 2 volumes of 3 "):
        read_volume(tmp_path / "tc.nii", volume_index=0)
    nib.save(nib.Nifti1Image(np.zeros((3, 4, 5, 1, 1, 2), np.float32), np.eye(4)),
             tmp_path / "six.nii")
    with pytest.raises(FormatError, match=r"six\.nii: .*more than 5 dimensions"):
        read_volume(tmp_path / "six.nii", volume_index=0)


# -- 4. a truncated uncompressed file ----------------------------------------------

def test_truncated_nifti_by_blocks_names_the_file(run, tmp_path):
    trunc = tmp_path / "trunc.nii"
    trunc.write_bytes((NB / "anatomical.nii").read_bytes()[:40000])
    out = tmp_path / "d.nrrd"
    line = one_error_line(run("distance", trunc, "--iso", 5000, "--chunked", "-o", out),
                          trunc)
    assert "truncated" in line and "67650 bytes" in line
    assert not out.exists()
    with pytest.raises(FormatError, match=r"trunc\.nii: cannot read NIfTI data \(truncated"):
        open_volume_lazy(trunc)
    with pytest.raises(FormatError, match=r"trunc\.nii: cannot read NIfTI data \(truncated"):
        read_volume(trunc)


# -- 5. CIFTI and other image classes ------------------------------------------------

def test_cifti_is_refused_with_one_line(run, tmp_path):
    path = NB / "row_major.dconn.nii"
    with pytest.raises(FormatError, match=r"row_major\.dconn\.nii: is a CIFTI-2 file"):
        read_volume(path)
    with pytest.raises(FormatError, match="CIFTI-2"):
        open_volume_lazy(path)
    line = one_error_line(run("info", path), path)
    assert "not a NIfTI-1/2 volume" in line
    copy = tmp_path / "c.dconn.nii"
    shutil.copy(path, copy)
    out = tmp_path / "o.nrrd"
    one_error_line(run("distance", copy, "--iso", 0.5, "--chunked", "-o", out), copy)
    assert not out.exists()
