"""DICOM files in Deflated Explicit VR Little Endian (1.2.840.10008.1.2.1.99).

pydicom's pixel functions, given a path, do not inflate the data set, so these files read
as "no Pixel Data". References: pydicom's ``dcmread(...).pixel_array`` (samples) and
SimpleITK (GDCM: geometry and samples).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from pydicom.uid import DeflatedExplicitVRLittleEndian

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_lazy

PYD = Path(os.path.dirname(pydicom.__file__)) / "data" / "test_files"
DFL = PYD / "image_dfl.dcm"


def ignore_invalid_uid() -> None:
    """Ignore pydicom's one complaint about its own rtdose.dcm (in a ``catch_warnings``):
    its UIDs have components with leading zeros ("1.2.123.456.78.9.0123...")."""
    warnings.filterwarnings("ignore", message="Invalid value for VR UI", category=UserWarning,
                            module=r"pydicom\.valuerep")


def deflated_copy(name: str, out: Path) -> Path:
    """pydicom's test file ``name`` saved again as Deflated Explicit VR Little Endian."""
    with warnings.catch_warnings():
        ignore_invalid_uid()  # (rtdose.dcm has a UID pydicom finds invalid)
        ds = pydicom.dcmread(PYD / name)
        ds.file_meta.TransferSyntaxUID = DeflatedExplicitVRLittleEndian
        ds.save_as(out, enforce_file_format=True)
    assert pydicom.dcmread(out).file_meta.TransferSyntaxUID == DeflatedExplicitVRLittleEndian
    return out


def assert_geometry_is_simpleitks(vol, path: Path):
    ref = sitk.ReadImage(str(path))
    np.testing.assert_allclose(vol.origin, ref.GetOrigin(), atol=1e-6)
    np.testing.assert_allclose(vol.spacing, ref.GetSpacing(), rtol=1e-6)
    np.testing.assert_allclose(vol.direction.ravel(), ref.GetDirection(), atol=1e-6)
    assert vol.shape_xyz == ref.GetSize()
    return ref


def test_image_dfl_reads_as_pydicom_and_simpleitk_read_it(run):
    """The tester's case: `volwarp info image_dfl.dcm` was exit 1 "no 'Pixel Data' element"."""
    vol = read_volume(DFL)
    ref = pydicom.dcmread(DFL).pixel_array
    assert ref.shape == (512, 512) and ref.dtype == np.uint8
    assert vol.data.dtype == np.uint8 and vol.data.shape == (1, 512, 512)
    np.testing.assert_array_equal(vol.data[0], ref)
    image = assert_geometry_is_simpleitks(vol, DFL)
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(image))
    res = run("info", DFL)
    # (the file has no PixelSpacing: the 1 mm SimpleITK takes too, said)
    assert res.code == 0 and res.stderr.splitlines() == [
        f"volwarp: warning: {DFL}: no PixelSpacing (nor ImagerPixelSpacing): 1 mm pixels "
        "assumed, as ITK does (recorded in DICOM_geometry)"], res.stderr
    assert "shape:     512 512 1" in res.stdout and "dtype:     uint8" in res.stdout


def test_convert_of_a_deflated_file(run, tmp_path):
    out = tmp_path / "dfl.nrrd"
    res = run("convert", "-q", DFL, "-o", out)
    assert res.code == 0 and res.stderr == "", res.stderr
    np.testing.assert_array_equal(read_volume(out).data[0], pydicom.dcmread(DFL).pixel_array)


@pytest.mark.parametrize("name", ["CT_small.dcm", "MR_small.dcm", "rtdose.dcm"])
def test_deflated_copies_read_as_their_originals(tmp_path, name):
    """A rescaled CT (int16 + intercept), an MR, and a multi-frame RT dose (15 frames,
    DoseGridScaling): the same volume as the uncompressed original, SimpleITK's geometry."""
    path = deflated_copy(name, tmp_path / f"dfl_{name}")
    vol = read_volume(path)
    orig = read_volume(PYD / name)
    assert vol.data.dtype == orig.data.dtype
    np.testing.assert_array_equal(vol.data, orig.data)
    np.testing.assert_array_equal(vol.origin, orig.origin)
    np.testing.assert_array_equal(vol.spacing, orig.spacing)
    assert_geometry_is_simpleitks(vol, path)
    with warnings.catch_warnings():
        ignore_invalid_uid()
        ds = pydicom.dcmread(path)
    stored = ds.pixel_array
    if stored.ndim == 2:
        stored = stored[None]
    if name == "rtdose.dcm":
        np.testing.assert_allclose(vol.data, (stored * float(ds.DoseGridScaling))
                                   .astype(np.float32))
    else:
        slope, inter = float(ds.get("RescaleSlope", 1)), float(ds.get("RescaleIntercept", 0))
        np.testing.assert_array_equal(vol.data, stored * slope + inter)


def test_a_deflated_multi_frame_file_read_by_slabs(tmp_path):
    path = deflated_copy("rtdose.dcm", tmp_path / "dose.dcm")
    whole = read_volume(path).data
    _, lazy = open_volume_lazy(path)
    assert lazy.shape == whole.shape
    np.testing.assert_array_equal(np.asarray(lazy[3:9, 2:7, :]), whole[3:9, 2:7, :])
    np.testing.assert_array_equal(np.asarray(lazy[14:15]), whole[14:15])


@pytest.mark.parametrize("keep", [0.9, 0.5, 0.1])
def test_a_truncated_deflated_file_is_a_one_line_error(run, tmp_path, keep):
    path = deflated_copy("CT_small.dcm", tmp_path / "full.dcm")
    data = path.read_bytes()
    cut = tmp_path / "cut.dcm"
    cut.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(FormatError, match=r"cut\.dcm: "):
        read_volume(cut)
    res = run("info", cut)
    assert res.code == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"volwarp: error: {cut}: "), res.stderr
