"""Hostile geometry: every reader refuses spacing, origin or direction no computation survives.

A NRRD whose ``space directions`` overflow (1e308) was read with exit 0 by ``info`` and
``convert``, and ``distance`` ended in "internal error: ZeroDivisionError"; a spacing of
1e20 gave distances of inf (float32), one of 1e-300 a division by zero. One rule
(:func:`volwarp_cli.geometry.check_placement`) refuses them, for every format, in memory
and by blocks, with one line naming the file and the field the number came from, and
nothing written. The files are written here byte by byte (TIFF with tifffile, DICOM with
pydicom: the field's libraries).
"""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from volwarp_cli.errors import FormatError, VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.volume import Volume

EIGHT = bytes(range(1, 9))  # 2x2x2 uint8 samples


def nrrd(fields: str) -> bytes:
    return (b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n"
            + fields.encode() + b"\n" + EIGHT)


def nifti(*, pixdim=(1.0, 1.0, 1.0), qform=None, sform=None) -> bytes:
    """A NIfTI-1 file of 2x2x2 uint8: ``qform`` (quatern b, c, d, qoffset x, y, z), ``sform`` 3x4."""
    hdr = bytearray(348)
    struct.pack_into("<i", hdr, 0, 348)
    struct.pack_into("<8h", hdr, 40, 3, 2, 2, 2, 1, 1, 1, 1)
    struct.pack_into("<2h", hdr, 70, 2, 8)  # DT_UINT8, 8 bits
    struct.pack_into("<8f", hdr, 76, 1.0, *pixdim, 1.0, 1.0, 1.0, 1.0)
    struct.pack_into("<f", hdr, 108, 352.0)  # vox_offset
    struct.pack_into("<f", hdr, 112, 1.0)  # scl_slope
    hdr[123] = 2  # mm
    if qform is not None:
        struct.pack_into("<h", hdr, 252, 1)
        struct.pack_into("<6f", hdr, 256, *qform)
    if sform is not None:
        struct.pack_into("<h", hdr, 254, 1)
        struct.pack_into("<12f", hdr, 280, *np.ravel(sform))
    hdr[344:348] = b"n+1\0"
    return bytes(hdr) + bytes(4) + EIGHT


def metaimage(fields: str) -> bytes:
    return ("ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementType = MET_UCHAR\n"
            + fields + "ElementDataFile = LOCAL\n").encode() + EIGHT


def omezarr(folder, scale_zyx) -> None:
    """A Zarr v2 OME-NGFF 0.4 store of 2x2x2 uint8 (one uncompressed chunk)."""
    folder.mkdir()
    (folder / ".zgroup").write_text('{"zarr_format": 2}')
    axes = [{"name": n, "type": "space", "unit": "millimeter"} for n in "zyx"]
    ms = {"version": "0.4", "axes": axes, "datasets": [
        {"path": "0", "coordinateTransformations": [{"type": "scale", "scale": scale_zyx}]}]}
    (folder / ".zattrs").write_text(json.dumps({"multiscales": [ms]}))
    (folder / "0").mkdir()
    (folder / "0" / ".zarray").write_text(json.dumps({
        "zarr_format": 2, "shape": [2, 2, 2], "chunks": [2, 2, 2], "dtype": "|u1",
        "compressor": None, "fill_value": 0, "filters": None, "order": "C"}))
    (folder / "0" / "0.0.0").write_bytes(EIGHT)


def tiff(path, spacing) -> None:
    import tifffile

    tifffile.imwrite(path, np.arange(8, dtype=np.uint8).reshape(2, 2, 2), imagej=True,
                     metadata={"spacing": spacing, "unit": "mm", "axes": "ZYX"})


def dicom(folder, x=None, **kw) -> str:
    """A two-slice CT series (``x``: its ImagePositionPatient x); the first slice's path."""
    import pydicom
    from test_io_dicom import write_series

    paths = write_series(folder, np.zeros((2, 3, 4), np.int16), shuffle=False, **kw)
    for p in paths if x is not None else []:
        ds = pydicom.dcmread(p)
        ds.ImagePositionPatient = [x] + list(ds.ImagePositionPatient)[1:]
        ds.save_as(p)
    return str(paths[0])


HUGE = "(1e308,0,0) (0,1e308,0) (0,0,1e308)"  # the hostile run's file

CASES = {
    "nrrd-directions": ("h.nrrd", lambda p: p.write_bytes(nrrd(
        f"space: LPS\nspace directions: {HUGE}\n")), "'space directions'"),
    "nrrd-overflowing-axis": ("h.nrrd", lambda p: p.write_bytes(nrrd(
        "space: RAS\nspace directions: (1e308,1e308,1e308) (0,1,0) (0,0,1)\n")),
        "'space directions'"),
    "nrrd-tiny": ("h.nrrd", lambda p: p.write_bytes(nrrd(
        "space: LPS\nspace directions: (1e-300,0,0) (0,1e-300,0) (0,0,1e-300)\n")),
        "'space directions'"),
    "nrrd-origin": ("h.nrrd", lambda p: p.write_bytes(nrrd(
        "space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (1e308,0,0)\n")),
        "'space origin'"),
    "nrrd-spacings": ("h.nrrd", lambda p: p.write_bytes(nrrd("spacings: 1e-300 1 1\n")),
                      "'spacings'"),
    "nifti-pixdim": ("h.nii", lambda p: p.write_bytes(nifti(pixdim=(3e38, 1, 1))), "pixdim"),
    # no form names a matrix: the voxel sizes alone (NaN was read as 1)
    "nifti-pixdim-nan": ("h.nii", lambda p: p.write_bytes(nifti(pixdim=(float("nan"), 1, 1))),
                         "NIfTI pixdim[1] = nan"),
    "nifti-sform-nan": ("h.nii", lambda p: p.write_bytes(nifti(
        sform=[[1, 0, 0, float("nan")], [0, 1, 0, 0], [0, 0, 1, 0]])),
        "NIfTI sform matrix has non-finite numbers (1 0 0 nan;"),
    "nifti-sform": ("h.nii", lambda p: p.write_bytes(nifti(
        sform=[[1e30, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])), "sform (srow_x"),
    "nifti-qoffset": ("h.nii", lambda p: p.write_bytes(nifti(qform=(0, 0, 0, 1e30, 0, 0))),
                      "qform (qoffset_x"),
    "metaimage-spacing": ("h.mha", lambda p: p.write_bytes(metaimage(
        "ElementSpacing = 1e308 1 1\n")), "ElementSpacing"),
    "metaimage-origin": ("h.mha", lambda p: p.write_bytes(metaimage(
        "Origin = 0 1e300 0\n")), "Origin"),
    "metaimage-matrix": ("h.mha", lambda p: p.write_bytes(metaimage(
        "TransformMatrix = 1e200 0 0 0 1 0 0 0 1\n")), "TransformMatrix"),
    "tiff-imagej-spacing": ("h.tif", lambda p: tiff(p, 1e300), "ImageJ spacing"),
    "omezarr-scale": ("h.ome.zarr", lambda p: omezarr(p, [1e300, 1.0, 1.0]),
                      "multiscales coordinateTransformations scale"),
    "dicom-pixel-spacing": ("s", lambda p: dicom(p, spacing=(1e300, 1e300)), "PixelSpacing"),
    "dicom-position": ("s", lambda p: dicom(p, x="-1e300"), "ImagePositionPatient"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_every_reader_refuses_a_hostile_geometry(run, tmp_path, case):
    name, make, field = CASES[case]
    path = tmp_path / name
    made = make(path)  # (DICOM: the first slice's file is named, not the folder)
    named = made if isinstance(made, str) else str(path)
    out = tmp_path / "out.nrrd"
    for args in (["info", path], ["convert", path, "-o", out],
                 ["distance", path, "--iso", "3", "--surface", "voxel", "-o", out],
                 ["distance", path, "--iso", "3", "--surface", "voxel", "-o", out, "--chunked",
                  "--block", "2,2,2"]):
        res = run(*args)
        lines = res.stderr.strip().splitlines()
        assert res.code == 1 and len(lines) == 1, (args, res)
        assert lines[0].startswith(f"volwarp: error: {named}: {field}"), (args, res.stderr)
        assert "internal error" not in lines[0]
        assert not out.exists()


def test_raw_options_name_the_option(run, tmp_path):
    (tmp_path / "v.raw").write_bytes(EIGHT)
    out = tmp_path / "out.nrrd"
    for spacing, why in ((["1e300", "1", "1"], "1e+300 along x"), (["1", "1e-300", "1"],
                                                                    "1e-300 along y")):
        for chunked in ([], ["--chunked", "--block", "2,2,2"]):
            res = run("distance", tmp_path / "v.raw", "--raw-shape", "2", "2", "2", "--raw-dtype",
                      "uint8", "--raw-spacing", *spacing, "--iso", "3", "--surface", "voxel",
                      "-o", out, *chunked)
            assert res.code == 1 and len(res.stderr.strip().splitlines()) == 1, res
            assert res.stderr.startswith(f"volwarp: error: {tmp_path / 'v.raw'}: --raw-spacing: "
                                         "spacing "), res.stderr
            assert why in res.stderr and not out.exists()


@pytest.mark.parametrize("kwargs,needle", [
    ({"spacing": (1e300, 1, 1)}, "spacing 1e\\+300 along x is outside"),
    ({"spacing": (1, 1e-300, 1)}, "spacing 1e-300 along y is outside"),
    ({"spacing": (1, 1, np.inf)}, "spacing must be finite"),
    ({"origin": (0, 0, -1e300)}, "origin -1e\\+300 along z is beyond"),
    ({"direction": np.diag([1.0, 1e-300, 1.0])}, "direction axis y"),
    ({"direction": [[1, 1, 0], [0, 0, 0], [0, 0, 1.0]]}, "direction matrix is singular"),
    ({"spacing": 1e14, "shape": (100, 1, 1)}, "reaches 9\\.9e\\+15 along world x"),
])
def test_volume_and_geometry_keep_the_rule(kwargs, needle):
    kwargs = dict(kwargs)
    shape_xyz = kwargs.pop("shape", (2, 2, 2))
    with pytest.raises(VolwarpError, match=needle):
        Volume(np.zeros(shape_xyz[::-1], np.uint8), **kwargs)
    with pytest.raises(VolwarpError, match=needle):
        Geometry(shape_xyz[::-1], **kwargs)


def test_the_rule_names_the_files_field_and_takes_the_limits():
    from volwarp_cli.geometry import PLACEMENT_LIMIT, check_placement

    with pytest.raises(FormatError, match=r"^a\.nrrd: 'space origin': origin 2e\+15 along x"):
        check_placement(1.0, (2e15, 0, 0), np.eye(3), where="a.nrrd",
                        fields={"origin": "'space origin'"})
    with pytest.raises(FormatError, match=r"^s/1\.dcm: SpacingBetweenSlices: spacing must be "
                       "positive"):
        check_placement((1, 1, 0), 0, np.eye(3), where="s/1.dcm",
                        fields={"spacing": ("PixelSpacing", "PixelSpacing",
                                            "SpacingBetweenSlices")})
    lo, hi = 1.0 / PLACEMENT_LIMIT, PLACEMENT_LIMIT
    Volume(np.zeros((1, 1, 2), np.uint8), spacing=(hi, lo, lo), origin=(0, -hi / 2, hi / 2))
    Geometry((1, 1, 2), spacing=(hi, lo, 1.0), origin=(0, hi, -hi))


@pytest.mark.parametrize("spacing", [1e-15, 1e14])
def test_distances_at_the_limits_are_exact(run, tmp_path, spacing):
    """The bound is where volwarp's float32 outputs still hold the grid (1e20 gave inf)."""
    from volwarp_cli.io import read_volume, write_volume

    cube = np.zeros((6, 6, 6), np.uint8)
    cube[2:4, 2:4, 2:4] = 1
    write_volume(Volume(cube, spacing=spacing), tmp_path / "c.nrrd")
    out = tmp_path / "d.nrrd"
    res = run("distance", tmp_path / "c.nrrd", "--iso", "0.5", "--surface", "voxel", "-o", out)
    assert res.code == 0, res
    d = read_volume(out).data / spacing
    assert np.isfinite(d).all()
    np.testing.assert_allclose([d.min(), d.max()], [-1.0, np.sqrt(12)], rtol=1e-5)
