"""NRRD ``axis mins`` / ``axis maxs`` / ``centerings`` without ``space directions``: the
geometry SimpleITK reads (ITK's NrrdImageIO: teem's nrrdOriginCalculate, cell centering by
default; the spacing from ``spacings`` only).

The reference is SimpleITK itself for every header: its origin and spacing, and its
TransformIndexToPhysicalPoint for the corners.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_lazy

SIZES = (4, 5, 6)
DATA = np.arange(int(np.prod(SIZES)), dtype=np.uint8)

SP = "spacings: 1.5 2 2.5\n"
MINS = "axis mins: 1 2 3\n"
MAXS = "axis maxs: 7 12 18\n"

CASES = {
    # the tester's case: axis mins without centerings (was origin (1, 2, 3))
    "mins": SP + MINS,
    "mins, cell": SP + MINS + "centerings: cell cell cell\n",
    "mins, node": SP + MINS + "centerings: node node node\n",
    "mins, none": SP + MINS + "centerings: none none none\n",
    "mins, ???": SP + MINS + "centerings: ??? ??? ???\n",
    "mins, mixed": SP + MINS + "centerings: cell node none\n",
    "mins, upper case": SP + MINS + "centerings: CELL Node cell\n",
    "mins, 'centers'": SP + MINS + "centers: node cell node\n",
    # axis mins + axis maxs: the half voxel from (max - min) / size; ITK's spacing stays 1
    "mins+maxs": MINS + MAXS,
    "mins+maxs, cell": MINS + MAXS + "centerings: cell cell cell\n",
    "mins+maxs, node": MINS + MAXS + "centerings: node node node\n",
    "mins+maxs, none": MINS + MAXS + "centerings: none none none\n",
    "mins+maxs, mixed": MINS + MAXS + "centerings: node cell ???\n",
    "mins+maxs reversed": "axis mins: 7 12 18\naxis maxs: 1 2 3\n",
    "mins+maxs+spacings": SP + MINS + MAXS,
    "mins+maxs+spacings, node": SP + MINS + MAXS + "centerings: node node node\n",
    # spacings win over maxs per axis; an axis with neither: no origin (teem's
    # NoMaxOrSpacing), as without any min on the first axis (NoMin)
    "one spacing missing, maxs": "spacings: 1.5 nan 2.5\n" + MINS + MAXS,
    "one spacing missing": "spacings: 1.5 nan 2.5\n" + MINS,
    "mins, no spacings": MINS,
    "mins, no spacings, node": MINS + "centerings: node node node\n",
    "first min missing": SP + "axis mins: nan 2 3\n",
    "a max missing": MINS + "axis maxs: 7 nan 18\n",
    "maxs only": SP + MAXS,
    "centerings only": SP + "centerings: cell cell cell\n",
    "spacings only": SP,
}


def write(path, extra: str, sizes=SIZES, dim: int = 3, data=DATA) -> str:
    hdr = (f"NRRD0004\ntype: uint8\ndimension: {dim}\nsizes: {' '.join(map(str, sizes))}\n"
           f"encoding: raw\n{extra}\n")
    path.write_bytes(hdr.encode() + data.tobytes())
    return str(path)


def corners():
    return [(i, j, k) for i in (0, SIZES[0] - 1) for j in (0, SIZES[1] - 1)
            for k in (0, SIZES[2] - 1)]


@pytest.mark.parametrize("name", list(CASES))
def test_geometry_is_simpleitks(tmp_path, name):
    path = write(tmp_path / "c.nrrd", CASES[name])
    ref = sitk.ReadImage(path)
    vol = read_volume(path)
    np.testing.assert_allclose(vol.origin, ref.GetOrigin(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(vol.spacing, ref.GetSpacing(), rtol=1e-15)
    np.testing.assert_array_equal(vol.direction, np.eye(3))
    for ijk in corners():
        np.testing.assert_allclose(vol.index_to_world(np.array(ijk, dtype=float)),
                                   ref.TransformIndexToPhysicalPoint(ijk), atol=1e-12)
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(ref))
    # the mapped (lazy) reading has the same geometry
    geom, _ = open_volume_lazy(path)
    np.testing.assert_allclose(geom.origin, ref.GetOrigin(), atol=1e-12)
    np.testing.assert_allclose(geom.spacing, ref.GetSpacing(), rtol=1e-15)


def test_the_testers_numbers(tmp_path):
    vol = read_volume(write(tmp_path / "t.nrrd", SP + MINS))
    np.testing.assert_allclose(vol.origin, [1.75, 3.0, 4.25])
    vol = read_volume(write(tmp_path / "m.nrrd", MINS + MAXS))
    # (7 - 1) / 4, (12 - 2) / 5, (18 - 3) / 6: half of each past the mins
    np.testing.assert_allclose(vol.origin, [1.75, 3.0, 4.25])
    np.testing.assert_allclose(vol.spacing, [1, 1, 1])


@pytest.mark.parametrize("extra,sizes", [
    (MINS + "axis maxs: 7 12 3\ncenterings: node node node\n", (4, 5, 1)),
    ("spacings: 1 1 1\n" + MINS + "centerings: node node cell\n", (4, 5, 1)),
    (MINS + "axis maxs: 7 12 4\n", (4, 5, 1)),
])
def test_single_slices(tmp_path, extra, sizes):
    n = int(np.prod(sizes))
    path = write(tmp_path / "s.nrrd", extra, sizes=sizes, data=DATA[:n])
    ref = sitk.ReadImage(path)
    vol = read_volume(path)
    np.testing.assert_allclose(vol.origin, ref.GetOrigin(), atol=1e-12)
    np.testing.assert_allclose(vol.spacing, ref.GetSpacing(), rtol=1e-15)


@pytest.mark.parametrize("extra,sizes", [
    ("kinds: vector domain domain domain\nspacings: nan 1.5 2 2.5\naxis mins: nan 1 2 3\n",
     (2, 4, 5, 6)),
    ("kinds: vector domain domain domain\nspacings: nan 1.5 2 2.5\naxis mins: nan 1 2 3\n"
     "centerings: ??? node cell node\n", (2, 4, 5, 6)),
    ("kinds: domain domain domain vector\naxis mins: 1 2 3 nan\naxis maxs: 7 12 18 nan\n"
     "centerings: cell node cell ???\n", (4, 5, 6, 2)),
])
def test_four_dimensional_files_take_the_domain_axes(tmp_path, extra, sizes):
    path = write(tmp_path / "v.nrrd", extra, sizes=sizes, dim=4,
                 data=np.zeros(int(np.prod(sizes)), np.uint8))
    ref = sitk.ReadImage(path)
    assert ref.GetNumberOfComponentsPerPixel() == 2
    vol = read_volume(path, volume_index=1)
    np.testing.assert_allclose(vol.origin, ref.GetOrigin(), atol=1e-12)
    np.testing.assert_allclose(vol.spacing, ref.GetSpacing(), rtol=1e-15)


@pytest.mark.parametrize("extra,match", [
    (SP + "axis mins: 1 2\n", r"'axis mins' has 2 entries, 'dimension' is 3"),
    ("spacings: 1.5 2\n" + MINS, r"'spacings' has 2 entries, 'dimension' is 3"),
    (MINS + "axis maxs: 1 2 3 4\n", r"'axis maxs' has 4 entries, 'dimension' is 3"),
    (SP + MINS + "centerings: node node\n", r"'centerings' has 2 entries"),
    (SP + MINS + "centerings: cell middle cell\n", r"'centerings' entry 'middle' is not cell"),
    (SP + "axis mins: inf 2 3\n", r"'axis mins' must be finite"),
    (MINS + "axis maxs: 7 -inf 18\n", r"'axis maxs' must be finite"),
    # ITK reads a NaN origin for y here (teem checks the first axis' min only)
    (SP + "axis mins: 1 nan 3\n", r"'axis mins' has no value \(nan\) for axis 1"),
])
def test_headers_simpleitk_cannot_place_are_one_line_errors(run, tmp_path, extra, match):
    path = write(tmp_path / "bad.nrrd", extra)
    with pytest.raises(FormatError, match=r"bad\.nrrd: " + match):
        read_volume(path)
    res = run("info", path)
    assert res.code == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("volwarp: error: ") and "bad.nrrd" in lines[0]


def test_info_and_convert_keep_the_cell_origin(run, tmp_path):
    src = write(tmp_path / "c.nrrd", SP + MINS)
    out = tmp_path / "c.nii.gz"
    assert run("convert", "-q", src, "-o", out).code == 0
    ref = sitk.ReadImage(src)
    back = sitk.ReadImage(str(out))
    np.testing.assert_allclose(back.GetOrigin(), ref.GetOrigin(), atol=1e-5)
    np.testing.assert_allclose(back.GetSpacing(), ref.GetSpacing(), atol=1e-6)
