"""The lazy readers' headers carry read_volume's key/values, so outputs by blocks are
the in-memory outputs byte for byte (metadata included).

NIfTI with several sform/qform codes, descrip, intent, units and volwarp's extension
(files from nibabel, its shipped test files); MetaImage with MetaIO's descriptive
fields and user keys (written by SimpleITK and by hand); NRRD with content, space
units, a measurement frame in another frame and key/values.
"""

from __future__ import annotations

from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from nibabel.testing import data_path

from volwarp_cli.errors import FormatError
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_header

NB = Path(data_path)
WARP_SPEC = """version: 1
capture: {lattice: 5, oversample: 1}
steps:
  - move:
      - {index: [2, 2, 2], by: [1.0, 0.0, 0.0]}
"""


def blob(shape=(14, 15, 13)) -> np.ndarray:
    """Smooth int16 samples with a bright ball ([z, y, x]): something to warp and threshold."""
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape], indexing="ij")
    return (1000 * np.exp(-(x * x + y * y + z * z) / 0.3)).astype(np.int16)


def assert_header_is_read_volume(path, **kw):
    """The lazy Header (read without loading) has read_volume's geometry, frame and meta."""
    header, array = open_volume_header(path, require_lazy=True, **kw)
    assert not isinstance(array, np.ndarray)  # (require_lazy: read on slicing)
    ref = read_volume(path, **kw)
    assert Geometry.of(header) == Geometry.of(ref)
    assert (header.space, header.file_space) == (ref.space, ref.file_space)
    assert header.meta == ref.meta
    assert header.shape == ref.data.shape and header.dtype == ref.data.dtype
    np.testing.assert_array_equal(np.asarray(array[:, :, :]), ref.data)
    return header


# -- NIfTI ----------------------------------------------------------------------

def nifti(path, scode, qcode, *, same=True, **fields):
    aff = np.eye(4)
    aff[:3, :3] = np.diag([1.5, 2.0, 2.5])
    aff[:3, 3] = (-10.0, 20.0, -30.0)
    other = aff.copy()
    other[:3, 3] = (-90.0, -126.0, -72.0)
    img = nib.Nifti1Image(blob().transpose(2, 1, 0), None)
    img.set_qform(aff, code=qcode)
    img.set_sform(aff if same else other, code=scode)
    for key, value in fields.items():
        img.header[key] = value
    nib.save(img, path)
    return path


@pytest.mark.parametrize("scode,qcode,same", [
    (1, 1, True), (4, 2, True), (2, 0, True), (0, 1, True), (0, 0, True),
    (4, 1, False),   # the qform is read, the MNI sform not carried (code 0 in both)
    (1, 1, False),
])
def test_nifti_headers_carry_the_header_fields(tmp_path, scode, qcode, same):
    path = nifti(tmp_path / "v.nii", scode, qcode, same=same, descrip=b"a description",
                 xyzt_units=10, intent_code=1002, intent_p1=3.0)
    header = assert_header_is_read_volume(path)
    assert header.meta["descrip"] == "a description"
    assert header.meta["NIfTI_xyzt_units"] == "10"
    assert header.meta["NIfTI_intent_code"] == "1002"
    if (scode, qcode) != (1, 1) or not same:
        assert "NIfTI_sform_code" in header.meta


def test_big_endian_nifti(tmp_path):
    img = nib.Nifti1Image(blob().transpose(2, 1, 0), np.diag([1.5, 2.0, 2.5, 1.0]),
                          header=nib.Nifti1Header(endianness=">"))
    img.set_data_dtype(">i2")
    img.header["descrip"] = b"big"
    nib.save(img, tmp_path / "be.nii")
    assert nib.load(tmp_path / "be.nii").get_data_dtype() == np.dtype(">i2")
    header = assert_header_is_read_volume(tmp_path / "be.nii")
    assert header.meta["descrip"] == "big"


@pytest.mark.parametrize("name", ["anatomical.nii", "reoriented_anat_moved.nii",
                                  "resampled_anat_moved.nii"])
def test_nibabels_files(name):
    header = assert_header_is_read_volume(NB / name)
    assert header.meta  # codes 2 and 2, units, descrip


def test_volwarps_extension(tmp_path, run):
    out = tmp_path / "w.nii"
    spec = tmp_path / "w.yaml"
    spec.write_text(WARP_SPEC)
    assert run("warp", "-q", NB / "anatomical.nii", "--spec", spec, "-o", out).code == 0
    header = assert_header_is_read_volume(out)
    assert header.meta["volwarp_command"] == "warp"


# -- MetaImage ------------------------------------------------------------------

def test_metaimage_from_simpleitk_with_its_metadata(tmp_path):
    img = sitk.GetImageFromArray(blob())
    img.SetSpacing((0.5, 0.6, 0.7))
    img.SetOrigin((1.0, 2.0, 3.0))
    img.SetMetaData("PatientName", "anonymous")
    img.SetMetaData("site", "A")
    path = tmp_path / "s.mha"
    sitk.WriteImage(img, str(path), useCompression=False)
    header = assert_header_is_read_volume(path)
    assert header.meta["site"] == "A" and header.meta["PatientName"] == "anonymous"


@pytest.mark.parametrize("suffix", [".mha", ".mhd"])
def test_metaimage_descriptive_and_user_fields(tmp_path, suffix):
    data = blob()
    header = ("ObjectType = Image\nNDims = 3\nComment = scanned twice\nName = head\n"
              "Modality = MET_MOD_MR\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
              "CompressedData = False\nTransformMatrix = 1 0 0 0 1 0 0 0 1\n"
              "Offset = 1 2 3\nCenterOfRotation = 1 1 1\nAnatomicalOrientation = LPS\n"
              "ElementSpacing = 1 1 2\nsite = B\nsubject_id = s01\n"
              f"DimSize = {data.shape[2]} {data.shape[1]} {data.shape[0]}\n"
              "ElementType = MET_SHORT\n")
    path = tmp_path / f"m{suffix}"
    if suffix == ".mha":
        path.write_bytes((header + "ElementDataFile = LOCAL\n").encode() + data.tobytes())
    else:
        (tmp_path / "m.raw").write_bytes(data.tobytes())
        path.write_text(header + "ElementDataFile = m.raw\n")
    header = assert_header_is_read_volume(path)
    assert len(header.meta) == 7, header.meta  # 8 keys became 4 before


# -- NRRD -----------------------------------------------------------------------

def nrrd_with_fields(path, space="right-anterior-superior"):
    data = blob()
    header = ("NRRD0005\ntype: short\ndimension: 3\n"
              f"space: {space}\nsizes: {data.shape[2]} {data.shape[1]} {data.shape[0]}\n"
              "space directions: (1.5,0,0) (0,2,0) (0,0,2.5)\n"
              "kinds: domain domain domain\nendian: little\nencoding: raw\n"
              "space origin: (10,-20,30)\ncontent: a head\nspace units: \"mm\" \"mm\" \"mm\"\n"
              "measurement frame: (1,0,0) (0,0,1) (0,1,0)\n"
              "site:=C\nmodality:=MR\n\n")
    path.write_bytes(header.encode() + data.astype("<i2").tobytes())
    return path


@pytest.mark.parametrize("space", ["right-anterior-superior", "left-posterior-superior"])
def test_nrrd_kept_fields_and_measurement_frame(tmp_path, space):
    header = assert_header_is_read_volume(nrrd_with_fields(tmp_path / "n.nrrd", space))
    assert header.meta["NRRD_content"] == "a head"
    assert header.meta["NRRD_space units"] == '"mm" "mm" "mm"'
    assert "NRRD_measurement frame" in header.meta and header.meta["site"] == "C"


def test_truncated_nifti_header_is_refused_before_any_work(tmp_path):
    trunc = tmp_path / "trunc.nii"
    trunc.write_bytes((NB / "anatomical.nii").read_bytes()[:40000])
    with pytest.raises(FormatError, match=r"trunc\.nii: cannot read NIfTI data \(truncated"):
        open_volume_header(trunc)


# -- by blocks: the same bytes as in memory ----------------------------------------

@pytest.fixture
def inputs(tmp_path, run):
    """The same scan as NIfTI (nibabel's), MetaImage with extra keys, NRRD with kept fields."""
    nii = tmp_path / "in.nii"
    nii.write_bytes((NB / "anatomical.nii").read_bytes())
    mha = tmp_path / "in.mha"
    assert run("convert", "-q", nii, "-o", mha).code == 0
    text = mha.read_bytes()
    mha.write_bytes(text.replace(b"ObjectType = Image\n",
                                 b"ObjectType = Image\nComment = two\nModality = MET_MOD_MR\n"))
    nrrd = nrrd_with_fields(tmp_path / "in.nrrd")
    spec = tmp_path / "w.yaml"
    spec.write_text(WARP_SPEC)
    return {"nii": nii, "mha": mha, "nrrd": nrrd, "spec": spec}


@pytest.mark.parametrize("src", ["nii", "mha", "nrrd"])
@pytest.mark.parametrize("out", ["o.nrrd", "o.mha"])
def test_warp_by_blocks_writes_the_in_memory_bytes(run, tmp_path, inputs, src, out):
    mem, blk = tmp_path / f"mem_{out}", tmp_path / f"blk_{out}"
    res = run("warp", "-q", inputs[src], "--spec", inputs["spec"], "-o", mem)
    assert res.code == 0, res.stderr
    res = run("warp", "-q", inputs[src], "--spec", inputs["spec"], "-o", blk, "--chunked",
              "--block", "16")
    assert res.code == 0, res.stderr
    assert read_volume(blk).meta == read_volume(mem).meta
    assert blk.read_bytes() == mem.read_bytes()


@pytest.mark.parametrize("src", ["nii", "mha", "nrrd"])
def test_distance_by_blocks_writes_the_in_memory_bytes(run, tmp_path, inputs, src):
    mem, blk = tmp_path / "mem.nrrd", tmp_path / "blk.nrrd"
    args = ("distance", inputs[src], "--iso", 500, "--surface", "voxel")
    assert run(*args, "-o", mem).code == 0
    res = run(*args, "-o", blk, "--chunked", "--block", "16")
    assert res.code == 0, res.stderr
    assert read_volume(blk).meta == read_volume(mem).meta
    assert blk.read_bytes() == mem.read_bytes()
