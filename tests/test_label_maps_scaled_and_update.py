"""Label maps handled as intensities, silently: the traps the labels44 hunt found.

Each test compares with an independent reader or resampler (nibabel, SimpleITK).
"""

from __future__ import annotations

import numpy as np
import pytest

nib = pytest.importorskip("nibabel")


def _scaled_label_map(path, inter: float, slope: float = 1.0, dtype=np.int16):
    """A NIfTI label map (intent label) of ids 0, 1, 3 stored with scl_slope/scl_inter."""
    ids = np.zeros((10, 9, 8), dtype)  # (x, y, z)
    ids[2:5, 2:5, 2:5] = 1
    ids[5:8, 5:8, 5:7] = 3
    img = nib.Nifti1Image(ids, np.eye(4), dtype=dtype)
    img.header.set_slope_inter(slope, inter)
    img.header.set_intent("label")
    img.to_filename(str(path))
    return nib.load(str(path)).get_fdata()  # float64: every id exact


@pytest.mark.parametrize("slope, inter", [(1.0, 16777216.0), (-3.0, -16777216.0)])
def test_scaled_nifti_label_ids_read_exactly_as_nibabel(tmp_path, run, slope, inter):
    """Whole slope and intercept past 2**24: float32 merged ids 0 and 1 (16777216 and
    16777217) and moved id 3; nibabel's get_fdata holds them, and so does volwarp now."""
    from volwarp_cli.io import read_volume
    from volwarp_cli.io.lazy import open_volume_lazy

    path = tmp_path / "scaled.nii.gz"
    theirs = _scaled_label_map(path, inter, slope)
    want = np.ascontiguousarray(theirs.transpose(2, 1, 0))  # [z, y, x]
    assert len(np.unique(want)) == 3
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.data, want)
    _, lazy = open_volume_lazy(path)
    np.testing.assert_array_equal(np.asarray(lazy[...]), want)
    out = tmp_path / "ids.nrrd"
    res = run("convert", path, "-o", out)
    assert res.code == 0, res.stderr
    np.testing.assert_array_equal(read_volume(out).data, want)


def test_scaled_nifti_within_float32_stays_float32(tmp_path):
    """Scaled 16-bit samples whose whole values float32 holds are float32, as ITK reads them."""
    from volwarp_cli.io import read_volume

    path = tmp_path / "small.nii"
    theirs = _scaled_label_map(path, -1024.0, 2.0)
    vol = read_volume(path)
    assert vol.dtype == np.float32
    np.testing.assert_array_equal(vol.data, theirs.transpose(2, 1, 0))


def _label_map(path):
    """Ids -5, 1 and 1000 in blocks (int32), a map the label rule takes for labels."""
    import SimpleITK as sitk

    ids = np.zeros((24, 26, 28), np.int32)
    ids[4:12, 4:12, 4:12] = 1
    ids[12:20, 4:12, 4:16] = 1000
    ids[4:20, 14:22, 8:20] = -5
    sitk.WriteImage(sitk.GetImageFromArray(ids), str(path))
    return ids


def test_distance_update_refuses_a_label_map(tmp_path, run):
    """`distance --update` resampled a label map's ids trilinearly as distances (137
    values between -5 and 1000, exit 0): a label map is no field; its field is."""
    sitk = pytest.importorskip("SimpleITK")
    from volwarp_cli.io import read_volume

    src = tmp_path / "ids.nrrd"
    ids = _label_map(src)
    move = tmp_path / "move.yaml"
    move.write_text("version: 1\nrotate: [0, 0, 10]\n")
    out = tmp_path / "moved.nrrd"
    res = run("distance", "--update", src, "--transform", move, "-o", out)
    assert res.code == 2, res.stderr
    assert "label map" in res.stderr and not out.exists()
    # a field made by another tool (SimpleITK, no volwarp key) still moves
    field = sitk.SignedMaurerDistanceMap(sitk.GetImageFromArray((ids != 0).astype(np.uint8)),
                                         insideIsPositive=False, squaredDistance=False,
                                         useImageSpacing=True)
    sdf = tmp_path / "sdf.nrrd"
    sitk.WriteImage(sitk.Cast(field, sitk.sitkFloat32), str(sdf))
    res = run("distance", "--update", sdf, "--transform", move, "-o", out)
    assert res.code == 0, res.stderr
    assert read_volume(out).data.dtype == np.float32
