"""A labelled voxel is at the same LPS point in every file a segmentation becomes.

An asymmetric phantom (an L on one slice, a single voxel off centre on another, a
2-voxel bar in a corner of a third) is placed on a reference CT series, slice by
slice and pixel by pixel, and its voxels' LPS points are computed by hand from
each slice file's own tags (``ImagePositionPatient + i * PixelSpacing[1] * row
cosine + j * PixelSpacing[0] * column cosine``, files ordered along row x column
cosine), never from volwarp's reading of the series. The phantom is then a SEG
and an RTSTRUCT written by other code (highdicom's BINARY and LABELMAP SEGs;
contours through the voxels' centres, a POINT and a 2-point contour, in world
coordinates computed by hand), and by volwarp from a NRRD label map that pynrrd
wrote with the hand geometry. Each is converted by ``volwarp convert`` (on the
reference's grid, and a SEG also on its own frames' grid) to NIfTI (RAS on disk)
and NRRD (``space: left-posterior-superior``, the one frame volwarp's NRRD writer
writes); that NRRD is rewritten by hand with ``right-anterior-superior`` and
``left-anterior-superior`` headers (numbers converted, samples the same), the
two other anatomical frames volwarp's NRRD reader takes, and those are converted
again. Every file's labelled voxels must lie at the hand-computed points, read
by volwarp, by SimpleITK (``TransformIndexToPhysicalPoint``) and, for NIfTI, by
this file's own parse of the header's sform and qform (RAS, flipped to LPS here).
Two reference geometries: an oblique (coronal-like) series and a tilted sagittal
one whose NIfTI matrix is left-handed (qfac -1), both with unequal pixel spacings
and rows != columns, so a transposed, flipped or shifted axis moves a voxel.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
pytest.importorskip("highdicom")
sitk = pytest.importorskip("SimpleITK")
nrrd = pytest.importorskip("nrrd")

from test_dicom_seg import OBLIQUE, make_seg, masks_of, write_ct  # noqa: E402
from test_rtstruct import write_rtstruct  # noqa: E402

from volwarp_cli.io import read_volume  # noqa: E402

SHAPE = (7, 10, 12)  # z, y, x of the reference series
GEOMETRIES = {
    "oblique": dict(orientation=OBLIQUE, spacing=(0.8, 0.7, 2.5), origin=(-10.0, 20.0, 30.0)),
    "tilted-sagittal": dict(orientation=(0.0, 1.0, 0.0, 0.6, 0.0, -0.8),
                            spacing=(0.9, 0.6, 1.5), origin=(35.0, -12.0, 8.0)),
}
#: label -> its voxels (i = column, j = row, k = slice in position order)
PHANTOM = {
    1: [(i, j, 2) for j in (3, 4) for i in range(2, 7)]
       + [(i, j, 2) for j in range(5, 9) for i in (2, 3)],          # an L
    2: [(9, 1, 4)],                                                 # one voxel, off centre
    3: [(0, 9, 0), (1, 9, 0)],                                      # a bar in a corner
}
SOURCES = ("highdicom-binary", "highdicom-labelmap", "hand-rtstruct", "volwarp-seg",
           "volwarp-labelmap-seg", "volwarp-rtstruct")
#: how close (mm) a voxel must be to its hand-computed point: NIfTI holds float32
TOL = {"nrrd": 1e-5, "nii": 2e-3}


def hand_slices(folder: Path) -> list[tuple]:
    """``(ImagePositionPatient, row cosine, column cosine, PixelSpacing)`` per file, in position order."""
    items = []
    for p in folder.iterdir():
        ds = pydicom.dcmread(p, stop_before_pixels=True)
        iop = np.array(ds.ImageOrientationPatient, float)
        items.append((np.array(ds.ImagePositionPatient, float), iop[:3], iop[3:],
                      np.array(ds.PixelSpacing, float)))
    normal = np.cross(items[0][1], items[0][2])
    return sorted(items, key=lambda t: float(t[0] @ normal))


def hand_point(slices, i: float, j: float, k: int) -> np.ndarray:
    """The LPS point of (column i, row j) of slice file k, from that file's tags alone."""
    ipp, row, col, ps = slices[k]
    return ipp + i * ps[1] * row + j * ps[0] * col


def phantom_map() -> np.ndarray:
    lab = np.zeros(SHAPE, np.uint8)
    for value, voxels in PHANTOM.items():
        for i, j, k in voxels:
            lab[k, j, i] = value
    return lab


def expected_points(slices) -> dict[int, np.ndarray]:
    return {v: np.array([hand_point(slices, i, j, k) for i, j, k in vox])
            for v, vox in PHANTOM.items()}


def assert_same_points(got: dict, want: dict, tol: float, what: str) -> None:
    """Each label's voxels at the wanted points (one each: the grid is coarser than ``tol``)."""
    assert sorted(got) == sorted(want), (what, sorted(got))
    for v, pts in want.items():
        g = got[v]
        assert g.shape == pts.shape, (what, v, g.shape, pts.shape)
        d = np.linalg.norm(g[:, None, :] - pts[None, :, :], axis=2)
        assert d.min(axis=0).max() <= tol and d.min(axis=1).max() <= tol, \
            (what, v, d.min(axis=0).max())


def labelled(data_zyx: np.ndarray) -> dict[int, np.ndarray]:
    """label -> its voxels' (i, j, k) indices."""
    return {int(v): np.argwhere(data_zyx == v)[:, ::-1] for v in np.unique(data_zyx) if v}


def points_volwarp(path: Path) -> dict:
    vol = read_volume(path)
    return {v: vol.index_to_world(ijk) for v, ijk in labelled(vol.data).items()}


def points_sitk(path: Path) -> dict:
    img = sitk.ReadImage(str(path))
    return {v: np.array([img.TransformIndexToPhysicalPoint(tuple(int(n) for n in p))
                         for p in ijk])
            for v, ijk in labelled(sitk.GetArrayFromImage(img)).items()}


_NIFTI_TYPES = {2: np.uint8, 4: np.int16, 8: np.int32, 16: np.float32, 256: np.int8,
                512: np.uint16, 768: np.uint32}


def points_nifti_by_hand(path: Path) -> dict[str, dict]:
    """``{"sform": points, "qform": points}`` from the NIfTI-1 header's fields (nifti1.h), in LPS."""
    raw = path.read_bytes()
    assert struct.unpack("<i", raw[:4])[0] == 348  # little-endian NIfTI-1
    dim = struct.unpack("<8h", raw[40:56])
    datatype = struct.unpack("<h", raw[70:72])[0]
    pixdim = struct.unpack("<8f", raw[76:108])
    vox_offset = int(struct.unpack("<f", raw[108:112])[0])
    slope, inter = struct.unpack("<2f", raw[112:120])
    assert slope in (0.0, 1.0) and inter == 0.0  # a label map is stored as it is
    qform_code, sform_code = struct.unpack("<2h", raw[252:256])
    b, c, d, qx, qy, qz = struct.unpack("<6f", raw[256:280])
    srow = np.array(struct.unpack("<12f", raw[280:328]), float).reshape(3, 4)
    assert qform_code > 0 and sform_code > 0
    nx, ny, nz = dim[1:4]
    data = np.frombuffer(raw, _NIFTI_TYPES[datatype], count=nx * ny * nz,
                         offset=vox_offset).reshape(nz, ny, nx)
    a = np.sqrt(max(0.0, 1.0 - (b * b + c * c + d * d)))
    rot = np.array([[a * a + b * b - c * c - d * d, 2 * (b * c - a * d), 2 * (b * d + a * c)],
                    [2 * (b * c + a * d), a * a + c * c - b * b - d * d, 2 * (c * d - a * b)],
                    [2 * (b * d - a * c), 2 * (c * d + a * b), a * a + d * d - c * c - b * b]])
    qfac = -1.0 if pixdim[0] < 0 else 1.0
    qform = np.column_stack([rot * np.array([pixdim[1], pixdim[2], qfac * pixdim[3]]),
                             [qx, qy, qz]])
    ras_to_lps = np.array([-1.0, -1.0, 1.0])
    out = {}
    for name, m in (("sform", srow), ("qform", qform)):
        out[name] = {v: (ijk @ m[:, :3].T + m[:, 3]) * ras_to_lps
                     for v, ijk in labelled(data).items()}
    return out


def nrrd_in_frame(lps: Path, frame: str, out: Path) -> Path:
    """``lps`` (an attached raw NRRD in LPS) with its header rewritten in ``frame``, by hand."""
    flip = {"right-anterior-superior": np.array([-1.0, -1.0, 1.0]),
            "left-anterior-superior": np.array([1.0, -1.0, 1.0])}[frame]
    head, data = lps.read_bytes().split(b"\n\n", 1)
    lines = head.decode().split("\n")

    def vec(text):
        return np.array([float(v) for v in text.strip().strip("()").split(",")])

    def fmt(v):
        return "(" + ",".join(repr(float(x) + 0.0) for x in v) + ")"
    new = []
    for line in lines:
        if line.startswith("space: "):
            assert line == "space: left-posterior-superior"
            line = f"space: {frame}"
        elif line.startswith("space directions: "):
            dirs = re.findall(r"\([^)]*\)", line)
            line = "space directions: " + " ".join(fmt(vec(d) * flip) for d in dirs)
        elif line.startswith("space origin: "):
            line = "space origin: " + fmt(vec(line[len("space origin: "):]) * flip)
        elif line.startswith("encoding: "):
            assert line == "encoding: raw"
        new.append(line)
    out.write_bytes("\n".join(new).encode() + b"\n\n" + data)
    return out


def write_hand_nrrd(path: Path, lab: np.ndarray, slices) -> Path:
    """The label map as pynrrd writes it, its geometry from the slices' tags (LPS)."""
    ipp0, row, col, ps = slices[0]
    normal = slices[1][0] - slices[0][0]  # (the slice gap and direction, from two files)
    header = {"space": "left-posterior-superior",
              "space directions": np.array([row * ps[1], col * ps[0], normal]),
              "space origin": ipp0, "kinds": ["domain"] * 3, "encoding": "raw"}
    nrrd.write(str(path), lab, header, index_order="C")
    return path


def make_source(kind: str, ct: Path, paths, slices, tmp: Path, run) -> Path:
    lab = phantom_map()
    out = tmp / f"{kind}.dcm"
    if kind == "highdicom-binary":
        return make_seg(paths, masks_of(lab, 3), "BINARY", out)
    if kind == "highdicom-labelmap":
        return make_seg(paths, lab, "LABELMAP", out)
    if kind == "hand-rtstruct":
        l_path = [(2, 3), (6, 3), (6, 4), (3, 4), (3, 8), (2, 8)]  # through boundary centres
        rois = {1: ("L", [("CLOSED_PLANAR", np.array([hand_point(slices, i, j, 2)
                                                      for i, j in l_path]))]),
                2: ("dot", [("POINT", np.array([hand_point(slices, 9, 1, 4)]))]),
                3: ("bar", [("OPEN_PLANAR", np.array([hand_point(slices, 0, 9, 0),
                                                      hand_point(slices, 1, 9, 0)]))])}
        return write_rtstruct(out, paths, rois)
    src = write_hand_nrrd(tmp / "phantom.nrrd", lab, slices)
    dicom_type = {"volwarp-seg": "seg", "volwarp-labelmap-seg": "labelmap-seg",
                  "volwarp-rtstruct": "rtstruct"}[kind]
    res = run("convert", src, "--reference", ct, "--dicom-type", dicom_type, "-o", out)
    assert res.code == 0, res.stderr
    return out


def check_file(path: Path, want: dict) -> None:
    tol = TOL["nii" if path.suffix == ".nii" else "nrrd"]
    assert_same_points(points_volwarp(path), want, tol, f"volwarp {path.name}")
    assert_same_points(points_sitk(path), want, tol, f"SimpleITK {path.name}")
    if path.suffix == ".nii":
        for form, pts in points_nifti_by_hand(path).items():
            assert_same_points(pts, want, tol, f"{form} of {path.name}")


@pytest.mark.parametrize("source", SOURCES)
@pytest.mark.parametrize("geometry", list(GEOMETRIES))
def test_labelled_voxels_keep_their_lps_points_in_every_format(tmp_path, run, geometry, source):
    ct = tmp_path / "ct"
    paths = write_ct(ct, SHAPE, **GEOMETRIES[geometry])
    slices = hand_slices(ct)
    want = expected_points(slices)
    # the hand formula is ITK's reading of the series: each point is its voxel's index there
    series = sitk.ImageSeriesReader()
    series.SetFileNames(series.GetGDCMSeriesFileNames(str(ct)))
    img = series.Execute()
    for v, vox in PHANTOM.items():
        for (i, j, k), p in zip(vox, want[v], strict=True):
            assert img.TransformPhysicalPointToContinuousIndex(tuple(p)) == \
                pytest.approx((i, j, k), abs=1e-6)

    seg = make_source(source, ct, paths, slices, tmp_path, run)
    grids = [("ref", ["--reference", ct])]
    if "rtstruct" not in source:
        grids.append(("own", []))  # a SEG on its own frames' grid (slices 0 to 4 here)
    checked = 0
    for grid, options in grids:
        for ext in ("nrrd", "nii"):
            out = tmp_path / f"{grid}.{ext}"
            res = run("convert", seg, *options, "-o", out)
            assert res.code == 0, res.stderr
            check_file(out, want)
            checked += 1
        lps = tmp_path / f"{grid}.nrrd"
        for frame in ("right-anterior-superior", "left-anterior-superior"):
            other = nrrd_in_frame(lps, frame, tmp_path / f"{grid}_{frame[:4]}.nrrd")
            check_file(other, want)
            for ext in ("nrrd", "nii"):
                again = tmp_path / f"{grid}_{frame[:4]}_again.{ext}"
                res = run("convert", other, "-o", again)
                assert res.code == 0, res.stderr
                check_file(again, want)
                checked += 1
            checked += 1
    assert checked == 8 * len(grids)


def test_a_flipped_axis_is_caught(tmp_path):
    """The check can fail: the phantom's map with x reversed (same grid) is refused."""
    ct = tmp_path / "ct"
    write_ct(ct, SHAPE, **GEOMETRIES["oblique"])
    slices = hand_slices(ct)
    want = expected_points(slices)
    path = write_hand_nrrd(tmp_path / "flipped.nrrd", phantom_map()[:, :, ::-1].copy(), slices)
    with pytest.raises(AssertionError):
        check_file(path, want)
    good = write_hand_nrrd(tmp_path / "good.nrrd", phantom_map(), slices)
    check_file(good, want)
