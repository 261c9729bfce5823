"""Morph and distance --update on grids that coincide but for rounding: border voxels stay covered.

A NIfTI's float32 geometry beside a NRRD's, or a quarter turn of an oblique
grid onto itself, put the frame's border voxels a rounding error outside the
input's grid; they were taken for uncovered and filled as outside the shape,
so a shape touching the border lost voxels there, with exit 0. The inputs are
written by SimpleITK and nibabel, the references are scipy's exact distance.
"""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from scipy import ndimage

SPACING = (0.7, 0.7, 3.0)
ORIGIN = (-12.3, 40.1, -7.5)


def _rotation(axis: int, degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    i, j = [k for k in range(3) if k != axis]
    r = np.eye(3)
    r[i, i] = r[j, j] = c
    r[i, j], r[j, i] = -s, s
    return r


#: oblique: 20 degrees about z, then about x
DIRECTION = _rotation(2, 20) @ _rotation(0, 20)


def _ball_touching_border(size, spacing=SPACING) -> sitk.Image:
    """A 0/1 uint8 ball centred on the x = 0 face of an oblique anisotropic grid (LPS)."""
    img = sitk.Image([int(n) for n in size], sitk.sitkUInt8)
    img.SetSpacing(spacing)
    img.SetOrigin(ORIGIN)
    img.SetDirection(DIRECTION.ravel().tolist())
    k, j, i = np.meshgrid(*(np.arange(n) for n in size[::-1]), indexing="ij")
    world = (np.stack([i, j, k], -1) * np.asarray(spacing)) @ DIRECTION.T + np.asarray(ORIGIN)
    centre = np.asarray(ORIGIN) + DIRECTION @ (np.asarray(spacing) * (0, size[1] // 2,
                                                                      size[2] // 2))
    mask = (np.linalg.norm(world - centre, axis=-1) <= 10.0).astype(np.uint8)
    out = sitk.GetImageFromArray(mask)
    out.CopyInformation(img)
    return out


def _nifti_ras_flipped_x(img: sitk.Image, path) -> None:
    """``img`` as nibabel writes it: a RAS affine, the x axis stored reversed."""
    lps = np.eye(4)
    lps[:3, :3] = np.asarray(img.GetDirection()).reshape(3, 3) * np.asarray(img.GetSpacing())
    lps[:3, 3] = img.GetOrigin()
    flip = np.eye(4)
    flip[0, 0], flip[0, 3] = -1, img.GetSize()[0] - 1
    data = np.transpose(sitk.GetArrayFromImage(img), (2, 1, 0))[::-1].copy()
    nib.save(nib.Nifti1Image(data, np.diag([-1, -1, 1, 1]) @ lps @ flip), str(path))


def _exact_sdf(img: sitk.Image) -> np.ndarray:
    """scipy's exact signed distance between voxel centres, negative inside ([z, y, x])."""
    mask = sitk.GetArrayFromImage(img).astype(bool)
    sampling = img.GetSpacing()[::-1]
    return (ndimage.distance_transform_edt(~mask, sampling=sampling)
            - ndimage.distance_transform_edt(mask, sampling=sampling))


def _on_grid_of(path, img: sitk.Image) -> np.ndarray:
    """The samples of ``path`` at ``img``'s voxel centres (SimpleITK, nearest: same points)."""
    moved = sitk.Resample(sitk.ReadImage(str(path)), img, sitk.Transform(),
                          sitk.sitkNearestNeighbor, float("nan"))
    return sitk.GetArrayFromImage(moved)


@pytest.mark.parametrize("chunked", [False, True])
def test_morph_of_one_grid_stored_lps_and_ras_flipped_keeps_its_border(run, tmp_path, chunked):
    """Frame 0 on the target's grid (the source's, stored RAS and flipped) is the source's field."""
    mask = _ball_touching_border((40, 36, 12))
    sitk.WriteImage(mask, str(tmp_path / "src.nrrd"))
    _nifti_ras_flipped_x(mask, tmp_path / "tgt.nii.gz")
    extra = ("--chunked", "--block", "4,8,8") if chunked else ()
    r = run("morph", tmp_path / "src.nrrd", tmp_path / "tgt.nii.gz", "--frames", 2,
            "--grid", "target", "-o", tmp_path / "f_{i}.nrrd", *extra)
    assert r.code == 0, r.stderr
    ref = _exact_sdf(mask)
    for i in (0, 1):
        frame = _on_grid_of(tmp_path / f"f_{i}.nrrd", mask)
        assert not np.isnan(frame).any()
        np.testing.assert_allclose(frame, ref, atol=1e-4)


def test_distance_update_quarter_turn_of_an_oblique_grid_is_exact(run, tmp_path):
    """A quarter turn about the grid's own axis through its centre maps the grid onto itself."""
    size, spacing = (24, 24, 10), (0.8, 0.8, 2.0)
    mask = _ball_touching_border(size, spacing)
    sitk.WriteImage(mask, str(tmp_path / "m.nrrd"))
    ref = _exact_sdf(mask).astype(np.float32)
    r = run("distance", tmp_path / "m.nrrd", "-o", tmp_path / "d.nrrd")
    assert r.code == 0, r.stderr
    np.testing.assert_allclose(sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "d.nrrd"))),
                               ref, atol=1e-4)
    centre = np.asarray(ORIGIN) + DIRECTION @ (np.asarray(spacing) * (np.asarray(size) - 1) / 2)
    axis = DIRECTION[:, 2]
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    turn = np.eye(3) + cross + cross @ cross  # 90 degrees about the grid's z axis
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = turn, centre - turn @ centre
    (tmp_path / "turn.yaml").write_text(yaml.safe_dump({"version": 1,
                                                        "matrix": matrix.tolist()}))
    r = run("distance", "--update", tmp_path / "d.nrrd", "--transform", tmp_path / "turn.yaml",
            "-o", tmp_path / "u.nrrd")
    assert r.code == 0, r.stderr
    moved = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "u.nrrd")))
    # new(p) = old(turn^-1 p): each voxel's pre-image is a voxel (the turn in index terms)
    back = np.rint(np.linalg.inv(DIRECTION) @ turn.T @ DIRECTION).astype(int)
    k, j, i = np.meshgrid(*(np.arange(n) for n in size[::-1]), indexing="ij")
    half = (np.asarray(size) - 1) / 2
    pre = np.rint(np.tensordot(back, np.stack([i, j, k]) - half[:, None, None, None], 1)
                  + half[:, None, None, None]).astype(int)
    np.testing.assert_allclose(moved, ref[pre[2], pre[1], pre[0]], atol=1e-4)


def test_default_morph_of_a_nrrd_and_its_nifti_copy_keeps_the_target_border(run, tmp_path):
    """No --grid: the grids are the same (float32 NIfTI within 1e-6), frame 1 is the target's field."""
    mask = _ball_touching_border((40, 36, 12))
    sitk.WriteImage(mask, str(tmp_path / "src.nrrd"))
    sitk.WriteImage(mask, str(tmp_path / "tgt.nii.gz"))
    r = run("morph", tmp_path / "src.nrrd", tmp_path / "tgt.nii.gz", "--frames", 2,
            "-o", tmp_path / "f_{i}.nrrd")
    assert r.code == 0, r.stderr
    np.testing.assert_allclose(_on_grid_of(tmp_path / "f_1.nrrd", mask), _exact_sdf(mask),
                               atol=1e-4)
