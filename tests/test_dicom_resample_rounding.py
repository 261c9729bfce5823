"""Resamplings onto a grid that coincides with the input's but for rounding keep every sample.

DICOM positions are decimal strings of a few digits, a NIfTI's spacing is
float32: the output grid of an irregular series, of a gantry tilt, of a
``distance --update`` translation then lies 1e-7..1e-15 voxel off the input's
samples, and the resampling took its first or last slice, row or plane for
outside (the fill) or for between two samples, with exit 0. References:
SimpleITK's series reader, pydicom's positions, scipy's exact distance, and
linear ramps that linear interpolation reproduces exactly.
"""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage
from test_io_dicom import sitk_series, write_series

from volwarp_cli.io.dicom import read_dicom


def _ds(values) -> np.ndarray:
    """A position as the series holds it (write_slice writes six decimals)."""
    return np.array([float(f"{v:.6f}") for v in values])


def _ramp_world(pts):
    return 1000 + 3 * pts[..., 0] - 2 * pts[..., 1] + 5 * pts[..., 2]


@pytest.mark.parametrize("dz, n", [(1 / 3, 8), (2 / 3, 12), (0.39999998, 40)])
def test_irregular_series_of_decimal_positions_keeps_its_slices(tmp_path, dz, n):
    """Slices dz apart at six-decimal positions, one missing, read with --irregular resample:
    the grid is the smallest gap's (n slices), and each input slice is on it as it is
    (SimpleITK's samples of it), the missing one the mean of its neighbours. The extent
    was 1e-5 over a whole number of gaps, and the grid had n + 1 slices, none an input's."""
    z = [_ds((0, 0, 12.3 + k * dz))[2] for k in range(n)]
    gone = n // 2
    j, i = np.mgrid[0:5, 0:4]
    stored = np.stack([np.rint(_ramp_world(np.stack([i * 0.7, j * 0.8, 0 * i + v], -1)))
                       for v in z]).astype(np.int16)
    keep = [k for k in range(n) if k != gone]
    write_series(tmp_path / "s", stored[keep], positions=[(0, 0, z[k]) for k in keep])
    vol = read_dicom(tmp_path / "s", irregular="resample")
    assert vol.shape_xyz == (4, 5, n)
    assert vol.spacing[2] == pytest.approx((z[-1] - z[0]) / (n - 1), abs=1e-9)
    ref = sitk.GetArrayFromImage(sitk_series(tmp_path / "s"))  # the input slices by position
    np.testing.assert_array_equal(vol.data[keep], ref)
    np.testing.assert_allclose(vol.data[gone], (ref[gone - 1] + ref[gone].astype(float)) / 2,
                               atol=1e-3)


def _tilted_with_gap(tmp_path, dz, z0, n=9, gone=4, tilt=15.0, shape=(24, 20)):
    spacing = (0.8, 0.7)  # (rows = y, columns = x)
    rise = dz * np.tan(np.radians(tilt))
    positions = [_ds((-5.0, 10.0 + k * rise, z0 + k * dz)) for k in range(n)]
    j, i = np.mgrid[0:shape[0], 0:shape[1]]
    stored = np.stack([np.rint(_ramp_world(np.stack([p[0] + i * spacing[1], p[1] + j * spacing[0],
                                                     p[2] + 0 * i], -1))) for p in positions])
    keep = [k for k in range(n) if k != gone]
    write_series(tmp_path / "t", stored[keep].astype(np.int16),
                 positions=[positions[k] for k in keep], spacing=spacing)
    return tmp_path / "t", positions, spacing, shape


@pytest.mark.parametrize("dz, z0", [(0.6, 12.3), (1.25, 7.1), (0.8, 40.3)])
def test_tilted_irregular_series_keeps_the_field_rows_of_each_slice(tmp_path, dz, z0):
    """A gantry-tilted series with a slice missing, at six-decimal positions: each output
    slice on an input slice (but for 1e-15 mm) holds that slice's field, shifted, and the
    ramp there. It was weighed 1e-15 against the next slice, whose out-of-field rim (NaN)
    took a whole row of the field to the fill."""
    folder, positions, spacing, shape = _tilted_with_gap(tmp_path, dz, z0)
    vol = read_dicom(folder, irregular="resample")
    assert vol.shape_xyz == (shape[1], shape[0], len(positions))
    for m, p in enumerate(positions):
        if m == 4:
            continue
        rows = np.arange(shape[0]) - (p[1] - positions[0][1]) / spacing[0]
        field = (rows > -1e-3) & (rows < shape[0] - 1 + 1e-3)
        ijk = np.stack(np.meshgrid(np.arange(shape[1]), np.flatnonzero(field), [m],
                                   indexing="xy"), -1).reshape(-1, 3)
        got = vol.data[ijk[:, 2], ijk[:, 1], ijk[:, 0]]
        np.testing.assert_allclose(got, _ramp_world(vol.index_to_world(ijk)), atol=0.51,
                                   err_msg=f"slice {m}")


def test_distance_update_by_whole_voxels_of_a_nifti_keeps_the_border_plane(run, tmp_path):
    """A ball on a NIfTI's x = n - 1 face (spacing 0.7: 0.69999999 in float32) moved 1.4 mm
    back along x by ``distance --update``: the field is the old one two voxels on, the
    border plane too. 1.4 / 0.69999999 was 2.00000003 voxels; the plane read a hair past
    the last one took the fill, and its 81 inside voxels came out outside, exit 0."""
    nx, ny, nz = 30, 24, 8
    spacing = (0.7, 0.7, 3.0)
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    world = np.stack([i, j, k], -1) * spacing
    centre = np.array([nx - 1, ny // 2, nz // 2]) * spacing
    mask = np.linalg.norm(world - centre, axis=-1) <= 7.0  # [z, y, x]
    affine = np.diag([-spacing[0], -spacing[1], spacing[2], 1.0])  # RAS of LPS axes
    nib.save(nib.Nifti1Image(np.transpose(mask, (2, 1, 0)).astype(np.uint8), affine),
             str(tmp_path / "m.nii.gz"))
    r = run("distance", tmp_path / "m.nii.gz", "-o", tmp_path / "d.nrrd")
    assert r.code == 0, r.stderr
    img = sitk.ReadImage(str(tmp_path / "d.nrrd"))
    assert img.GetSpacing()[0] != 0.7  # float32's 0.7, as the NIfTI holds it
    old = sitk.GetArrayFromImage(img)
    samp = img.GetSpacing()[::-1]
    exact = (ndimage.distance_transform_edt(~mask, sampling=samp)
             - ndimage.distance_transform_edt(mask, sampling=samp))
    np.testing.assert_allclose(old, exact, atol=1e-4)
    (tmp_path / "t.yaml").write_text("version: 1\ntranslate: [-1.4, 0, 0]\n")
    r = run("distance", "--update", tmp_path / "d.nrrd", "--transform", tmp_path / "t.yaml",
            "-o", tmp_path / "u.nrrd")
    assert r.code == 0, r.stderr
    new = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "u.nrrd")))
    np.testing.assert_array_equal(new[..., :nx - 2], old[..., 2:])
    assert (new[..., nx - 3] < 0).sum() == mask[..., nx - 1].sum()
