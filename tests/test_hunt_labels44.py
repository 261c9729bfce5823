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
