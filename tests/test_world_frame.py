"""volwarp's world frame is LPS: every reader converts the file's frame once, every writer
converts back, and an output's anatomy lies exactly where the input's did.

The reference is SimpleITK (ITK's NrrdImageIO converts RAS and LAS to LPS on read): the
physical point of an index is the same in the input and in every output.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.errors import FormatError, VolwarpError
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import LPS, Volume

#: NRRD's frames (long and short names) and the signs taking them to LPS
FRAMES = {
    "right-anterior-superior": (-1, -1, 1), "RAS": (-1, -1, 1),
    "left-anterior-superior": (1, -1, 1), "LAS": (1, -1, 1),
    "left-posterior-superior": (1, 1, 1), "LPS": (1, 1, 1),
    # ITK keeps the numbers of these, and so does volwarp
    "scanner-xyz": (1, 1, 1), "3D-right-handed": (1, 1, 1), "3D-left-handed": (1, 1, 1),
}
INDICES = [(0, 0, 0), (10, 10, 5), (11, 3, 6)]
SIZES = (12, 13, 7)  # x y z


def _rotation() -> np.ndarray:
    a, b = np.deg2rad(17.0), np.deg2rad(-31.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rz @ rx


def _nrrd_in_frame(path, space: str, *, data=None, extra: str = "") -> np.ndarray:
    """Write a NRRD by hand (no volwarp code) whose header's numbers are in ``space``."""
    if data is None:
        data = np.arange(np.prod(SIZES), dtype=np.int16).reshape(SIZES[::-1])
    axes = _rotation() * np.array([0.7, 1.3, 2.1])[None, :]  # columns: the index axes
    dirs = " ".join("(" + ",".join(repr(float(v)) for v in axes[:, a]) + ")" for a in range(3))
    nx, ny, nz = data.shape[::-1]
    header = (f"NRRD0004\ntype: short\ndimension: 3\nspace: {space}\nsizes: {nx} {ny} {nz}\n"
              f"space directions: {dirs}\nkinds: domain domain domain\nendian: little\n"
              f"encoding: raw\nspace origin: (12.5,-40.25,77)\n{extra}\n")
    path.write_bytes(header.encode() + data.astype("<i2").tobytes())
    return data


def _sitk_points(path) -> np.ndarray:
    img = sitk.ReadImage(str(path))
    return np.array([img.TransformIndexToPhysicalPoint(ijk) for ijk in INDICES])


def _volwarp_points(vol: Volume) -> np.ndarray:
    return vol.index_to_world(np.array(INDICES, dtype=float))


@pytest.mark.parametrize("space", list(FRAMES))
def test_nrrd_frame_is_converted_to_lps_as_simpleitk_reads_it(tmp_path, space):
    src = tmp_path / "in.nrrd"
    _nrrd_in_frame(src, space)
    vol = read_volume(src)
    assert vol.space == LPS
    expected = _sitk_points(src)
    np.testing.assert_allclose(_volwarp_points(vol), expected, rtol=0, atol=1e-9)
    # the conversion is the frame's signs applied to the file's own numbers
    file_origin = np.array([12.5, -40.25, 77.0])
    np.testing.assert_allclose(vol.origin, np.array(FRAMES[space]) * file_origin, atol=0)
    assert vol.file_space == space.lower() or vol.file_space.startswith(space[0].lower())


#: every writer SimpleITK can read the geometry of (TIFF: volwarp's own reader only)
WRITERS = ["o.nrrd", "o.nhdr", "o.nii", "o.nii.gz", "o.mha", "o.mhd"]


@pytest.mark.parametrize("space", ["right-anterior-superior", "LAS", "LPS", "scanner-xyz"])
@pytest.mark.parametrize("name", WRITERS + ["o.tif"])
def test_every_writer_keeps_the_physical_points(tmp_path, space, name):
    src = tmp_path / "in.nrrd"
    data = _nrrd_in_frame(src, space)
    expected = _sitk_points(src)
    out = tmp_path / name
    write_volume(read_volume(src), out)
    back = read_volume(out)
    atol = 1e-4 if ".nii" in name else 1e-9  # NIfTI keeps float32 matrices
    np.testing.assert_allclose(_volwarp_points(back), expected, rtol=0, atol=atol)
    np.testing.assert_array_equal(back.data, data)
    assert back.space == LPS
    if name != "o.tif":
        np.testing.assert_allclose(_sitk_points(out), expected, rtol=0, atol=atol)
        np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(out))), data)


def test_a_ras_nrrd_output_is_converted_not_relabelled(tmp_path):
    src = tmp_path / "ras.nrrd"
    _nrrd_in_frame(src, "right-anterior-superior")
    out = tmp_path / "out.nrrd"
    write_volume(read_volume(src), out)
    text = out.read_bytes().split(b"\n\n", 1)[0].decode()
    assert "space: left-posterior-superior" in text
    assert "space origin: (-12.5,40.25,77.0)" in text  # x and y negated, no negative zero
    np.testing.assert_allclose(_sitk_points(out), _sitk_points(src), atol=1e-9)


def test_info_json_prints_lps_and_the_files_own_frame(run, tmp_path):
    src = tmp_path / "ras.nrrd"
    _nrrd_in_frame(src, "RAS")
    res = run("info", src, "--json")
    assert res.code == 0, res
    desc = json.loads(res.stdout)
    assert desc["space"] == LPS and desc["file_space"] == "right-anterior-superior"
    assert desc["origin"] == [-12.5, 40.25, 77.0]
    img = sitk.ReadImage(str(src))
    np.testing.assert_allclose(np.array(desc["direction"]).ravel(), img.GetDirection(),
                               atol=1e-12)
    text = run("info", src).stdout
    assert "left-posterior-superior (the file's own: right-anterior-superior" in text


def test_measurement_frame_is_converted_with_the_geometry(tmp_path):
    src = tmp_path / "mf.nrrd"
    _nrrd_in_frame(src, "RAS", extra="measurement frame: (1,0,0) (0,0,1) (0,1,0)\n")
    vol = read_volume(src)
    # the columns (world vectors) get x and y negated: (-1,0,0) (0,0,1) (0,-1,0)
    assert vol.meta["NRRD_measurement frame"] == "(-1.0,0.0,0.0) (0.0,0.0,1.0) (0.0,-1.0,0.0)"


def test_an_unknown_frame_is_refused_naming_the_file(tmp_path):
    src = tmp_path / "odd.nrrd"
    _nrrd_in_frame(src, "right-anterior-superior-time")
    with pytest.raises(FormatError, match=r"odd\.nrrd.*unknown world frame"):
        read_volume(src)


def test_one_scan_as_ras_nrrd_and_as_nifti_is_one_volume_and_warps_alike(run, tmp_path):
    """The issue's defect: the same warp spec in millimetres pushed the patient's left side of
    the NIfTI copy and the right side of the RAS NRRD copy. Both copies must read as the same
    LPS volume, so a world-coordinate warp changes the same anatomy in both."""
    rng = np.random.default_rng(3)
    z, y, x = np.mgrid[:14, :16, :18]
    data = ((x - 5) ** 2 + (y - 8) ** 2 + (z - 7) ** 2 < 20).astype(np.int16) * 100
    data += rng.integers(0, 5, data.shape, dtype=np.int16)
    ras = tmp_path / "scan_ras.nrrd"
    _nrrd_in_frame(ras, "right-anterior-superior", data=data)
    nii = tmp_path / "scan.nii.gz"
    sitk.WriteImage(sitk.ReadImage(str(ras)), str(nii))  # the NIfTI copy made by another tool
    a, b = read_volume(ras), read_volume(nii)
    np.testing.assert_array_equal(a.data, b.data)
    np.testing.assert_allclose(b.origin, a.origin, atol=1e-4)
    np.testing.assert_allclose(b.direction, a.direction, atol=1e-6)
    # a move of the lattice point nearest the blob's centre, in LPS world millimetres
    centre = [float(v) for v in a.index_to_world([5.0, 8.0, 7.0])]
    spec = tmp_path / "w.yaml"
    target = [centre[0] + 4.0, *centre[1:]]
    spec.write_text("version: 1\nunits: world\ncapture: {lattice: 6, oversample: 1}\n"
                    f"steps:\n  - drag:\n      - {{from: {centre}, to: {target}}}\n"
                    "    radius: 12.0\n")
    outs = []
    for src in (ras, nii):
        out = tmp_path / f"w_{src.name.split('.')[0]}.nrrd"
        res = run("warp", src, "--spec", spec, "-o", out, "--crop")
        assert res.code == 0, res
        outs.append(read_volume(out))
    changed = outs[0].data != a.data
    assert changed.any()  # the warp did something
    np.testing.assert_array_equal(outs[0].data, outs[1].data)
    np.testing.assert_allclose(outs[0].origin, outs[1].origin, atol=1e-4)


def test_a_sheared_grid_is_refused_by_nifti_and_kept_by_nrrd_and_metaimage(tmp_path):
    # (a gantry-tilted DICOM read with --keep-shear): ITK reads a NIfTI's qform, which has
    # no shear, so the NIfTI writer refuses instead of moving the anatomy
    d = np.array([[1.0, 0.0, 0.2], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    d[:, 2] /= np.linalg.norm(d[:, 2])
    vol = Volume(np.arange(120, dtype=np.int16).reshape(4, 5, 6), direction=d, space="LPS")
    with pytest.raises(VolwarpError, match=r"sheared.*write \.nrrd or \.mha"):
        write_volume(vol, tmp_path / "s.nii.gz")
    assert not list(tmp_path.iterdir())
    for name in ("s.nrrd", "s.mha"):
        write_volume(vol, tmp_path / name)
        img = sitk.ReadImage(str(tmp_path / name))
        np.testing.assert_allclose(np.array(img.GetDirection()).reshape(3, 3), d, atol=1e-12)
