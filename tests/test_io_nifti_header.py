"""NIfTI header fields volwarp keeps, its own header extension, and damaged headers.

References: nibabel reads back the header fields and matrices volwarp writes;
SimpleITK (ITK's NiftiImageIO, niftilib) must read every file volwarp writes with
the same geometry and samples; nibabel's own shipped test files are read with the
geometry SimpleITK reports.
"""

from __future__ import annotations

import gzip
import json
import struct
import warnings

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from conftest import ball
from nibabel.testing import data_path

from volwarp_cli.cli.common import provenance
from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

LPS = np.diag([-1.0, -1.0, 1.0])


def affine(scales=(2.0, 3.0, 4.0), shift=(10.0, -20.0, 30.0), angle=25.0):
    a = np.deg2rad(angle)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rot * np.asarray(scales, float)[None, :]
    m[:3, 3] = shift
    return m


def nifti(path, scode=1, qcode=1, aff=None, data=None, units=("mm", "sec"), **fields):
    aff = affine() if aff is None else aff
    data = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6) if data is None else data
    img = nib.Nifti1Image(data, None)
    img.set_qform(aff, code=qcode)
    img.set_sform(aff, code=scode)
    img.header.set_xyzt_units(*units)
    for key, value in fields.items():
        img.header[key] = value
    nib.save(img, path)
    return path


def sitk_geometry(path):
    img = sitk.ReadImage(str(path))
    n = img.GetDimension()
    return (np.array(img.GetSpacing())[:3], np.array(img.GetOrigin())[:3],
            np.reshape(img.GetDirection(), (n, n))[:3, :3], img)


def assert_matches_simpleitk(vol, path, atol=1e-5):
    spacing, origin, direction, _ = sitk_geometry(path)
    np.testing.assert_allclose(vol.spacing, spacing, rtol=0, atol=atol)
    np.testing.assert_allclose(vol.origin, origin, rtol=0, atol=atol)
    np.testing.assert_allclose(vol.direction, direction, rtol=0, atol=atol)


# -- sform / qform codes ------------------------------------------------------

@pytest.mark.parametrize("scode,qcode", [
    (4, 2),   # MNI152 template sform, aligned qform
    (4, 0),   # only the sform coded (e.g. FSL's MNI152 files)
    (0, 2),   # only the qform coded
    (2, 2),
    (3, 1),   # Talairach sform, scanner qform
    (1, 1),
])
def test_form_codes_and_matrices_survive_a_round_trip(tmp_path, scode, qcode):
    src = nifti(tmp_path / "in.nii", scode, qcode)
    vol = read_volume(src)
    assert vol.space == "left-posterior-superior"
    assert vol.file_space == "right-anterior-superior"
    # kept where they differ from the writer's default (1 and 1): absent for 1, 1
    assert vol.meta.get("NIfTI_sform_code", "1") == str(scode)
    assert vol.meta.get("NIfTI_qform_code", "1") == str(qcode)
    assert ("NIfTI_sform_code" in vol.meta) == ((scode, qcode) != (1, 1))
    write_volume(vol, tmp_path / "out.nii.gz")
    a, b = nib.load(src).header, nib.load(tmp_path / "out.nii.gz").header
    assert int(b["sform_code"]) == scode and int(b["qform_code"]) == qcode
    for getter in ("get_sform", "get_qform"):
        want, wcode = getattr(a, getter)(coded=True)
        got, gcode = getattr(b, getter)(coded=True)
        assert gcode == wcode
        if wcode:
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
    back = read_volume(tmp_path / "out.nii.gz")
    assert back.same_grid(vol, atol=1e-5)
    assert_matches_simpleitk(vol, src)
    assert_matches_simpleitk(back, tmp_path / "out.nii.gz")


def test_volume_without_codes_is_written_scanner_coded(tmp_path):
    vol = Volume(np.zeros((3, 4, 5), np.uint8), spacing=(1, 2, 3), origin=(4, 5, 6))
    write_volume(vol, tmp_path / "n.nii")
    h = nib.load(tmp_path / "n.nii").header
    assert (int(h["sform_code"]), int(h["qform_code"])) == (1, 1)
    assert h.get_xyzt_units()[0] == "mm"
    assert h.extensions == []  # nothing beyond the header fields: no extension


def test_uncoded_file_keeps_its_codes_until_its_geometry_needs_one(tmp_path):
    """Both codes 0 ("method 1": pixdim only, read like ITK): kept while the geometry is
    still that; an origin moved by a step needs a coded matrix (code 1), else the
    written file would put the samples back at 0."""
    img = nib.Nifti1Image(np.zeros((4, 5, 6), np.uint8), None)
    img.header.set_zooms((2.0, 3.0, 4.0))
    img.set_sform(None, code=0)
    img.set_qform(None, code=0)
    nib.save(img, tmp_path / "m1.nii")
    vol = read_volume(tmp_path / "m1.nii")
    assert_matches_simpleitk(vol, tmp_path / "m1.nii")
    write_volume(vol, tmp_path / "same.nii")
    h = nib.load(tmp_path / "same.nii").header
    assert (int(h["sform_code"]), int(h["qform_code"])) == (0, 0)
    assert_matches_simpleitk(vol, tmp_path / "same.nii")
    moved = vol.with_data(vol.data, origin=(1.0, 2.0, 3.0))
    write_volume(moved, tmp_path / "moved.nii")
    h = nib.load(tmp_path / "moved.nii").header
    assert (int(h["sform_code"]), int(h["qform_code"])) == (1, 1)
    assert_matches_simpleitk(moved, tmp_path / "moved.nii")


# -- other header fields ------------------------------------------------------

def test_intent_is_kept(tmp_path):
    img = nib.Nifti1Image(np.zeros((3, 4, 5), np.float32), np.eye(4))
    img.header.set_intent("t test", (12.0,), name="tstat1")
    nib.save(img, tmp_path / "t.nii")
    vol = read_volume(tmp_path / "t.nii")
    assert vol.meta["NIfTI_intent_code"] == "3"
    write_volume(vol, tmp_path / "t2.nii")
    h = nib.load(tmp_path / "t2.nii").header
    assert h.get_intent() == ("t test", (12.0,), "tstat1")
    assert int(h["intent_code"]) == 3


@pytest.mark.parametrize("units", [("mm", "msec"), ("micron", "sec"), ("meter", "unknown"),
                                   ("unknown", "hz")])
def test_xyzt_units_are_kept_and_scaled_like_simpleitk(tmp_path, units):
    """ITK reads metres and microns in mm (x1000, x1/1000): so does volwarp; the output
    keeps the file's units, its matrix in them."""
    src = nifti(tmp_path / "u.nii", 1, 1, units=units)
    vol = read_volume(src)
    assert_matches_simpleitk(vol, src, atol=1e-5 * max(1.0, np.abs(vol.origin).max()))
    write_volume(vol, tmp_path / "u2.nii")
    out = nib.load(tmp_path / "u2.nii")
    assert out.header.get_xyzt_units() == units
    np.testing.assert_allclose(out.affine, nib.load(src).affine, rtol=1e-6, atol=1e-6)
    assert_matches_simpleitk(read_volume(tmp_path / "u2.nii"), tmp_path / "u2.nii",
                             atol=1e-5 * max(1.0, np.abs(vol.origin).max()))


def test_descrip_is_kept(tmp_path):
    src = nifti(tmp_path / "d.nii", descrip=b"FSL5.0 brain mask")
    vol = read_volume(src)
    assert vol.meta["descrip"] == "FSL5.0 brain mask"
    write_volume(vol, tmp_path / "d2.nii")
    assert nib.load(tmp_path / "d2.nii").header["descrip"].tobytes().rstrip(b"\0") == \
        b"FSL5.0 brain mask"


# -- volwarp's extension ------------------------------------------------------

def provenance_volume():
    meta = provenance("warp", ["/some/dir/in.nii.gz"])
    meta["volwarp_spec_sha256"] = "ab" * 32
    meta.update({"NRRD_content": "from an NRRD input", "modality": "MR",
                 "unicode": "\u00b5m \u2192 mm", "descrip": "kept in the header"})
    data = np.arange(5 * 6 * 7, dtype=np.int16).reshape(5, 6, 7)
    a = np.deg2rad(20.0)
    direction = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return Volume(data, spacing=(0.7, 1.3, 2.9), origin=(-3.25, 11.5, 101.0),
                  direction=direction, space="left-posterior-superior", meta=meta)


def raw_extensions(path) -> tuple[float, list[tuple[int, bytes]]]:
    """vox_offset and the (code, content) of each extension, parsed by the NIfTI-1 layout
    (what a niftilib/FSL-style reader does), not by nibabel."""
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        raw = gzip.decompress(raw)
    assert struct.unpack_from("<i", raw, 0)[0] == 348 and raw[344:348] == b"n+1\0"
    vox = struct.unpack_from("<f", raw, 108)[0]
    exts, pos = [], 352
    if raw[348] == 1:
        while pos < vox:
            esize, ecode = struct.unpack_from("<ii", raw, pos)
            assert esize >= 16 and esize % 16 == 0  # the format's rule
            exts.append((ecode, raw[pos + 8:pos + esize]))
            pos += esize
    assert pos == vox  # the extensions fill the space before the samples exactly
    return vox, exts


def test_provenance_round_trips_through_the_extension(tmp_path):
    vol = provenance_volume()
    path = tmp_path / "p.nii.gz"
    write_volume(vol, path)
    back = read_volume(path)
    nifti_keys = {k for k in back.meta if k.startswith("NIfTI_")}
    assert nifti_keys == set()  # codes 1, 1 and mm are the writer's defaults: no keys
    assert {k: v for k, v in back.meta.items() if k not in nifti_keys} == vol.meta
    # the extension: one, code 6, volwarp's prefix, then sorted ASCII JSON without the
    # header fields
    vox, exts = raw_extensions(path)
    assert len(exts) == 1 and exts[0][0] == 6
    content = exts[0][1].rstrip(b"\0")
    prefix, text = content.split(b"\n", 1)
    assert prefix == b"volwarp-meta-json/1"
    assert text.isascii()
    values = json.loads(text)
    assert list(values) == sorted(values) and "descrip" not in values
    assert values["volwarp_command"] == "warp" and values["volwarp_input"] == "in.nii.gz"
    # SimpleITK reads the file: same samples and same physical points
    spacing, origin, direction, img = sitk_geometry(path)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(img), vol.data)
    for ijk in [(0, 0, 0), (6, 5, 4), (3, 1, 2)]:
        np.testing.assert_allclose(img.TransformIndexToPhysicalPoint(ijk),
                                   vol.index_to_world(ijk), rtol=0, atol=1e-4)
    assert_matches_simpleitk(vol, path)
    # nibabel too, with the same samples
    np.testing.assert_array_equal(np.asanyarray(nib.load(path).dataobj),
                                  vol.data.transpose(2, 1, 0))


def test_extension_bytes_are_deterministic(tmp_path):
    vol = provenance_volume()
    reordered = vol.with_data(vol.data, meta=dict(reversed(list(vol.meta.items()))))
    write_volume(vol, tmp_path / "a.nii")
    write_volume(reordered, tmp_path / "b.nii")
    assert (tmp_path / "a.nii").read_bytes() == (tmp_path / "b.nii").read_bytes()


def test_nrrd_key_values_reach_nifti_and_back(tmp_path):
    vol = provenance_volume()
    write_volume(vol, tmp_path / "k.nrrd")
    write_volume(read_volume(tmp_path / "k.nrrd"), tmp_path / "k.nii")
    back = read_volume(tmp_path / "k.nii")
    for key in ("volwarp_version", "volwarp_command", "volwarp_input", "NRRD_content",
                "modality"):
        assert back.meta[key] == vol.meta[key], key


def test_info_shows_the_provenance_of_a_nifti_output(run, tmp_path):
    write_volume(Volume(ball(12)), tmp_path / "b.nii.gz")
    res = run("distance", tmp_path / "b.nii.gz", "-o", tmp_path / "d.nii.gz", "--iso", 0.5)
    assert res.code == 0, res
    res = run("info", tmp_path / "d.nii.gz", "--json")
    assert res.code == 0, res
    meta = json.loads(res.stdout)["meta"]
    assert meta["volwarp_command"].startswith("distance")
    assert meta["volwarp_input"] == "b.nii.gz"
    assert "volwarp_version" in meta


def test_foreign_extensions_are_left_alone(tmp_path):
    img = nib.Nifti1Image(np.zeros((3, 4, 5), np.uint8), np.eye(4))
    for content in (b"a plain comment", b'{"volwarp_command": "not ours"}',
                    b"volwarp-meta-json/0 {}", b"\xff\xfe binary"):
        img.header.extensions.append(nib.nifti1.Nifti1Extension(6, content))
    img.header.extensions.append(nib.nifti1.Nifti1Extension(4, b"<AFNI_attributes/>"))
    nib.save(img, tmp_path / "f.nii")
    vol = read_volume(tmp_path / "f.nii")
    assert all(k.startswith("NIfTI_") for k in vol.meta), vol.meta  # header fields only
    write_volume(vol, tmp_path / "g.nii")
    assert raw_extensions(tmp_path / "g.nii")[1] == []  # not copied, not turned into meta
    # nibabel's example4d.nii.gz carries two code-6 comments of FSL's
    path = data_path / "example4d.nii.gz"
    assert [e.get_code() for e in nib.load(path).header.extensions] == [6, 6]
    vol = read_volume(path, volume_index=0)
    assert not any(k.startswith("volwarp") for k in vol.meta)


def test_damaged_volwarp_extension_is_a_clear_error(tmp_path):
    img = nib.Nifti1Image(np.zeros((3, 4, 5), np.uint8), np.eye(4))
    img.header.extensions.append(nib.nifti1.Nifti1Extension(6, b"volwarp-meta-json/1\n{oops"))
    nib.save(img, tmp_path / "x.nii")
    with pytest.raises(FormatError, match=r"x\.nii: volwarp's NIfTI extension .* not valid"):
        read_volume(tmp_path / "x.nii")


# -- damaged headers ----------------------------------------------------------

def _patched(tmp_path, name, fmt, offset, *values, gz=False):
    raw = bytearray(nib.Nifti1Image(np.arange(60, dtype=np.uint8).reshape(3, 4, 5),
                                    np.eye(4)).to_bytes())
    struct.pack_into(fmt, raw, offset, *values)
    path = tmp_path / name
    path.write_bytes(gzip.compress(bytes(raw), mtime=0) if gz else bytes(raw))
    return path


@pytest.mark.parametrize("vox", [0.0, 100.0, 351.0, float("nan")])
@pytest.mark.parametrize("gz", [False, True])
def test_vox_offset_inside_the_header_is_refused(tmp_path, capfd, vox, gz):
    path = _patched(tmp_path, "v.nii.gz" if gz else "v.nii", "<f", 108, vox, gz=gz)
    with pytest.raises(FormatError) as info:
        read_volume(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: NIfTI header field vox_offset is ")
    assert "352" in msg and "\n" not in msg
    assert capfd.readouterr().err == ""


def test_vox_offset_on_the_command_line(run, tmp_path):
    path = _patched(tmp_path, "v0.nii", "<f", 108, 0.0)
    res = run("info", path)
    assert res.code == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "vox_offset is 0" in lines[0] and str(path) in lines[0]


@pytest.mark.parametrize("sform_code", [0, 1])
def test_invalid_quaternion_is_one_clear_error(tmp_path, run, capfd, sform_code):
    img = nib.Nifti1Image(np.zeros((3, 4, 5), np.int16), None)
    img.set_qform(np.eye(4), code=1)
    img.set_sform(np.eye(4), code=sform_code)
    raw = bytearray(img.to_bytes())
    struct.pack_into("<3f", raw, 256, 0.9, 0.9, 0.9)  # b^2 + c^2 + d^2 = 2.43
    path = tmp_path / "q.nii"
    path.write_bytes(bytes(raw))
    with pytest.raises(FormatError, match=r"q\.nii: NIfTI qform \(qform_code 1\) has an invalid "
                                          r"quaternion: quatern_b, quatern_c, quatern_d"):
        read_volume(path)
    assert capfd.readouterr().err == ""
    res = run("info", path)
    assert res.code == 1 and len(res.stderr.strip().splitlines()) == 1, res
    # rounding in a valid quaternion (a 180-degree turn stored as 1.0000001) is fine
    struct.pack_into("<3f", raw, 256, 0.0, 0.0, np.nextafter(np.float32(1), np.float32(2)))
    path.write_bytes(bytes(raw))
    read_volume(path)


def test_all_zero_sform_is_an_error_without_warnings(tmp_path, capfd):
    img = nib.Nifti1Image(np.zeros((3, 4, 5), np.int16), None)
    img.set_sform(np.zeros((4, 4)), code=1)
    img.set_qform(None, code=0)
    nib.save(img, tmp_path / "z.nii")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(FormatError, match=r"z\.nii: sform \(srow_x, srow_y, srow_z\): "
                           "spacing must be positive"):
            read_volume(tmp_path / "z.nii")
    assert [w for w in caught if issubclass(w.category, RuntimeWarning)] == []
    assert capfd.readouterr().err == ""


# -- nibabel's shipped files against SimpleITK ----------------------------------

@pytest.mark.parametrize("name,volume_index", [
    ("anatomical.nii", None),
    ("example4d.nii.gz", 0),
    ("example4d.nii.gz", 1),
    ("functional.nii", 7),
    ("reoriented_anat_moved.nii", None),
    ("resampled_anat_moved.nii", None),
    ("standard.nii.gz", None),   # sform 2, qform 0, units unknown
])
def test_nibabel_test_files_match_simpleitk(name, volume_index):
    path = data_path / name
    vol = read_volume(path, volume_index=volume_index)
    assert_matches_simpleitk(vol, path)
    img = sitk.ReadImage(str(path))
    arr = sitk.GetArrayFromImage(img)
    if volume_index is not None:
        arr = arr[volume_index]
    assert vol.data.dtype == arr.dtype  # functional.nii: scaled int16, float32 in both
    finite = np.isfinite(vol.data)  # resampled_anat_moved.nii: SimpleITK reads NaN as 0
    np.testing.assert_array_equal(vol.data[finite], arr[finite])
    h = nib.load(path).header
    assert vol.meta.get("NIfTI_sform_code", "1") == str(int(h["sform_code"]))
    assert vol.meta.get("NIfTI_qform_code", "1") == str(int(h["qform_code"]))


def test_nifti_is_read_without_pydicom_and_a_dicom_extension_is_left_alone(tmp_path):
    """nibabel imports pydicom only to show a DICOM header extension (code 2), which volwarp
    never reads: a NIfTI command imports no pydicom (0.12-0.3 s), a file with such an
    extension reads as without it, and a DICOM input in the same process still reads."""
    import subprocess
    import sys

    data = ball(14).astype(np.int16) * 300
    img = nib.Nifti1Image(data.transpose(2, 1, 0), np.diag([-1.0, -1.0, 1.0, 1.0]))
    img.header.extensions.append(nib.nifti1.Nifti1Extension(2, b"not a DICOM dataset" * 4))
    nib.save(img, str(tmp_path / "dx.nii.gz"))
    code = ("import sys\n"
            "from volwarp_cli.cli.main import main\n"
            f"assert main(['convert', r'{tmp_path / 'dx.nii.gz'}', '-o',"
            f" r'{tmp_path / 'o.nrrd'}']) == 0\n"
            "assert 'pydicom' not in sys.modules, 'pydicom imported'\n"
            "import pydicom  # (a DICOM input later in the process: importable as ever)\n"
            "from pydicom.data import get_testdata_file\n"
            "pydicom.dcmread(get_testdata_file('CT_small.dcm'))\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    assert np.array_equal(read_volume(tmp_path / "o.nrrd").data, data)


def test_nifti_command_imports_no_scipy_and_spm_images_keep_their_mat(tmp_path):
    """nibabel imports scipy only for SPM Analyze images' ``.mat``: a NIfTI command imports
    none, and nibabel used after it in the process says it has scipy and reads a ``.mat``'s
    orientation (the image's affine, not the header's default)."""
    import subprocess
    import sys

    data = ball(10).astype(np.int16)
    nib.save(nib.Nifti1Image(data.transpose(2, 1, 0), np.eye(4)), str(tmp_path / "b.nii.gz"))
    turned = np.array([[0.0, -2.0, 0.0, 10.0], [1.5, 0.0, 0.0, -4.0], [0.0, 0.0, 3.0, 7.0],
                       [0.0, 0.0, 0.0, 1.0]])
    code = ("import sys\n"
            "import numpy as np\n"
            "from volwarp_cli.cli.main import main\n"
            f"assert main(['convert', r'{tmp_path / 'b.nii.gz'}', '-o',"
            f" r'{tmp_path / 'o.nrrd'}']) == 0\n"
            "assert 'scipy' not in sys.modules, 'scipy imported'\n"
            "import nibabel as nib\n"
            "assert nib.spm99analyze.have_scipy and nib.Spm2AnalyzeImage.rw  # (as with scipy)\n"
            f"turned = np.array({turned.tolist()})\n"
            "img = nib.Spm99AnalyzeImage(np.zeros((4, 5, 6), np.int16), turned)\n"
            f"nib.save(img, r'{tmp_path / 'spm.img'}')\n"
            "import os\n"
            f"assert os.path.exists(r'{tmp_path / 'spm.mat'}'), 'no .mat written'\n"
            f"back = nib.load(r'{tmp_path / 'spm.img'}')\n"
            "assert np.allclose(back.affine, turned), back.affine\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    assert np.array_equal(read_volume(tmp_path / "o.nrrd").data, data)


def test_nifti_command_leaves_urllib_request_to_its_first_use(tmp_path):
    """nibabel imports urllib.request (and http.client, ssl, email) for ``from_url`` only:
    a NIfTI command runs none of them, and the module still works when used after, by
    nibabel and by eight threads importing it at once (a lazy module in sys.modules
    gave them a half-made one on Python 3.11)."""
    import subprocess
    import sys

    data = ball(10).astype(np.int16)
    nib.save(nib.Nifti1Image(data.transpose(2, 1, 0), np.eye(4)), str(tmp_path / "b.nii.gz"))
    code = ("import sys\n"
            "from volwarp_cli.cli.main import main\n"
            f"assert main(['convert', r'{tmp_path / 'b.nii.gz'}', '-o',"
            f" r'{tmp_path / 'o.nii'}']) == 0\n"
            "loaded = [m for m in ('http.client', 'ssl', 'email.parser') if m in sys.modules]\n"
            "assert not loaded, loaded\n"
            "import threading\n"  # (eight threads' first use at once: a real, locked import)
            "errors, go = [], threading.Barrier(8)\n"
            "def use():\n"
            "    go.wait()\n"
            "    try:\n"
            "        from urllib.request import Request, build_opener  # noqa: F401\n"
            "    except BaseException as exc:\n"
            "        errors.append(repr(exc))\n"
            "threads = [threading.Thread(target=use) for _ in range(8)]\n"
            "[t.start() for t in threads]\n"
            "[t.join() for t in threads]\n"
            "assert not errors, errors\n"
            "import nibabel.filebasedimages as fbi\n"
            "from urllib.request import Request, urlopen\n"  # (its code runs now)
            "assert 'http.client' in sys.modules\n"
            "assert fbi.request.urlopen is urlopen and Request('http://x/').host == 'x'\n"
            "import urllib.request\n"
            f"assert urllib.request.urlopen(r'{(tmp_path / 'b.nii.gz').as_uri()}').read(2)"
            " == b'\\x1f\\x8b'\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    assert np.array_equal(read_volume(tmp_path / "o.nii").data, data)


def test_threads_asking_for_nibabel_at_once_all_get_it_whole():
    """nibabel() from several threads in a new process: each gets the module imported
    whole (sys.modules holds it from the start of its import, half made)."""
    import subprocess
    import sys

    code = ("import threading\n"
            "from volwarp_cli.io.nifti import nibabel\n"
            "errors, go = [], threading.Barrier(6)\n"
            "def use():\n"
            "    go.wait()\n"
            "    try:\n"
            "        nib = nibabel()\n"
            "        nib.Nifti1Header, nib.filebasedimages.FileBasedImage, nib.Nifti2Image\n"
            "    except BaseException as exc:\n"
            "        errors.append(repr(exc))\n"
            "threads = [threading.Thread(target=use) for _ in range(6)]\n"
            "[t.start() for t in threads]\n"
            "[t.join() for t in threads]\n"
            "assert not errors, errors\n")
    for _ in range(3):
        subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("qcode, gz", [(1, False), (0, False), (1, True)])
def test_a_negative_pixdim_is_said_and_read_as_nibabel_reads_it(run, tmp_path, qcode, gz):
    """nibabel takes |pixdim| ("setting to abs"), ITK and SimpleITK mirror the axis: the
    two place the same voxel apart, and the file was read without a word."""
    import SimpleITK as sitk

    from volwarp_cli.io import read_volume

    a = np.arange(120, dtype=np.int16).reshape(4, 5, 6)
    form = np.diag([1.5, 2.0, 2.5, 1.0])
    form[:3, 3] = [-10, 20, -30]
    img = nib.Nifti1Image(a, None)
    img.set_qform(form, qcode)
    img.set_sform(form, 0)
    path = tmp_path / "neg.nii"
    nib.save(img, path)
    raw = bytearray(path.read_bytes())
    struct.pack_into("<f", raw, 80, -1.5)
    if gz:
        path = tmp_path / "neg.nii.gz"
        path.write_bytes(gzip.compress(bytes(raw)))
    else:
        path.write_bytes(bytes(raw))
    res = run("info", path)
    assert res.code == 0
    assert res.stderr.count("pixdim[1] = -1.5: a voxel size given negative") == 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        want = nib.load(path).affine  # (nibabel's reading: the size, 1.5)
    vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [1.5, 2.0, 2.5])
    if qcode:  # (no form: ITK's placement, documented, not nibabel's centred one)
        lps = np.diag([-1.0, -1.0, 1.0])
        np.testing.assert_allclose(vol.direction * vol.spacing[None, :], lps @ want[:3, :3],
                                   atol=1e-6)
        np.testing.assert_allclose(vol.origin, lps @ want[:3, 3], atol=1e-6)
    # ITK reads another image: the warning's reason
    ref = sitk.ReadImage(str(path))
    assert not np.allclose(ref.TransformIndexToPhysicalPoint((3, 0, 0)),
                           vol.index_to_world([3, 0, 0]), atol=1e-3)
