"""`volwarp apply` through ITK B-splines against SimpleITK, voxel by voxel, edges included."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume
from volwarp_cli.transforms import read_chain
from volwarp_cli.transforms.vnl import itk_inverse

sitk = pytest.importorskip("SimpleITK")


def _rotation(ax, ay, az) -> list:
    t = sitk.Euler3DTransform()
    t.SetRotation(ax, ay, az)
    return list(t.GetMatrix())


def _image(size, spacing, origin, direction, pixels=None) -> sitk.Image:
    img = (sitk.Image(list(size), sitk.sitkFloat32) if pixels is None
           else sitk.GetImageFromArray(pixels))
    img.SetSpacing(spacing)
    img.SetOrigin(origin)
    img.SetDirection(direction)
    return img


def _ants_placed(fixed: sitk.Image, mesh, seed: int) -> sitk.BSplineTransform:
    """As antsRegistration places its grid: from the fixed image's first voxel centre to its last
    (the first voxels at grid index 1, the last at n - 2: both edges of the valid region)."""
    b = sitk.BSplineTransform(3, 3)
    b.SetTransformDomainOrigin(fixed.GetOrigin())
    b.SetTransformDomainDirection(fixed.GetDirection())
    b.SetTransformDomainPhysicalDimensions(
        [s * (n - 1) for s, n in zip(fixed.GetSpacing(), fixed.GetSize(), strict=True)])
    b.SetTransformDomainMeshSize(mesh)
    b.SetParameters(np.random.default_rng(seed).normal(0, 2.0, len(b.GetParameters())).tolist())
    return b


def _initializer_placed(fixed: sitk.Image, mesh, seed: int) -> sitk.BSplineTransform:
    b = sitk.BSplineTransformInitializer(fixed, mesh, 3)
    b.SetParameters(np.random.default_rng(seed).normal(0, 2.0, len(b.GetParameters())).tolist())
    return b


def _moving(tmp_path, ext: str) -> str:
    z, y, x = np.mgrid[:26, :30, :34].astype(np.float32)
    img = _image(None, [1.2, 0.9, 1.1], [-10.0, 5.0, 3.0], _rotation(0.03, -0.02, 0.05),
                 np.sin(x / 3) * 100 + np.cos(y / 4) * 80 + z + 300)
    path = str(tmp_path / f"moving.{ext}")
    sitk.WriteImage(img, path)
    return path


@pytest.mark.parametrize("spacing, direction, mesh, place, ext", [
    ((0.7, 0.8, 1.3), _rotation(0.1, 0.25, -0.3), [5, 4, 3], _ants_placed, "mha"),
    ((0.7, 0.8, 1.3), _rotation(0.1, 0.25, -0.3), [2, 2, 2], _ants_placed, "nrrd"),
    ((1.0, 1.0, 1.0), _rotation(0.0, 0.0, np.pi / 2), [5, 4, 3], _ants_placed, "mha"),
    ((0.9, 1.1, 1.7), _rotation(0.3, -0.2, 0.5), [7, 6, 5], _ants_placed, "nrrd"),
    ((0.7, 0.8, 1.3), _rotation(0.1, 0.25, -0.3), [5, 4, 3], _initializer_placed, "mha"),
])
@pytest.mark.parametrize("transform_ext", ["h5", "tfm"])
def test_bspline_resampled_as_sitk_on_every_voxel(run, tmp_path, spacing, direction, mesh, place,
                                                  ext, transform_ext):
    """An ANTs-placed B-spline on an oblique fixed grid: volwarp moved hundreds of voxels of the
    first planes that ITK leaves (its valid region's lower edge, grid index 1, is strict, and
    ITK's index there is 1 +- a few ULPs: its SVD-based inverse of the grid's matrix, its point
    summed from the origin), and left some it moves. Each voxel now equals sitk.Resample's
    (both reading the same files), linear and nearest; an oblique NRRD's but a voxel or two."""
    fixed = _image((26, 22, 18), spacing, (-8.3, 6.1, 4.7), direction)
    fixed_path = str(tmp_path / f"fixed.{ext}")
    sitk.WriteImage(fixed, fixed_path)
    b = place(sitk.ReadImage(fixed_path), mesh, 12)
    tfm = str(tmp_path / f"b.{transform_ext}")
    sitk.WriteTransform(b, tfm)
    moving = _moving(tmp_path, ext)
    for interpolation, kind in (("linear", sitk.sitkLinear), ("nearest", sitk.sitkNearestNeighbor)):
        out = tmp_path / f"out_{interpolation}.mha"
        res = run("apply", moving, "-o", out, "--reference", fixed_path, "-t", tfm,
                  "--interpolation", interpolation, "--background-value", "-1000",
                  "--dtype", "float64")
        assert res.code == 0, res
        ours = read_volume(out).data
        theirs = sitk.GetArrayFromImage(sitk.Resample(
            sitk.ReadImage(moving), sitk.ReadImage(fixed_path), sitk.ReadTransform(tfm), kind,
            -1000.0, sitk.sitkFloat64))
        # (an oblique NRRD's axes are read as written, spacing * direction giving them back,
        # where teem takes the reciprocal of the length: an ULP apart, a voxel of the edge
        # planes may fall otherwise; docs/apply.md. The first version differed on 34-296.)
        allowed = 0 if ext == "mha" else 2
        assert np.count_nonzero(np.abs(ours - theirs) > 1e-6) <= allowed, interpolation


def _itk_inverse_by_sitk(matrix_spacing, direction) -> np.ndarray:
    """ITK's PhysicalPointToIndex matrix, read through an image at origin 0 (its columns)."""
    img = sitk.Image([2, 2, 2], sitk.sitkUInt8)
    img.SetSpacing(list(matrix_spacing))
    img.SetDirection(list(np.ravel(direction)))
    return np.array([img.TransformPhysicalPointToContinuousIndex(list(e))
                     for e in np.eye(3)]).T


def test_itk_inverse_is_itks_to_the_bit():
    """The grid's world-to-index matrix is ITK's (vnl's SVD pseudo-inverse), bit for bit, on
    rotations, signed permutations, right angles and skewed directions: numpy's inverse was
    up to 8e-17 off it, enough to put a point on the valid region's edge on the other side."""
    rng = np.random.default_rng(0)
    for k in range(240):
        if k % 4 == 0:
            q = rng.normal(size=(3, 3))
        elif k % 4 == 1:
            q = np.reshape(_rotation(*rng.uniform(-np.pi, np.pi, 3)), (3, 3))
        elif k % 4 == 2:
            q = np.eye(3)[rng.permutation(3)] * rng.choice([-1, 1], 3)[None]
        else:
            q = np.reshape(_rotation(*(rng.integers(-4, 5, 3) * np.pi / 2)), (3, 3))
        spacing = rng.uniform(0.2, 5, 3) if k % 3 else rng.choice([0.5, 0.7, 0.9, 1.0, 1.1], 3)
        ours = itk_inverse(q * spacing[None, :])
        assert np.array_equal(ours, _itk_inverse_by_sitk(spacing, q)), (spacing, q)


def test_an_axis_along_a_world_axis_keeps_its_spacing_as_written(tmp_path):
    """teem's sqrt(x * x) is not always x: 3.3000000000000003 came back 3.3, and a convert
    changed a file's spacing; an axis with one entry keeps it (its direction a unit)."""
    import nrrd

    for sp in (1.1, 0.30000000000000004, 3.3000000000000003, 0.123456789, 2.2):
        axes = np.diag([sp, 2 * sp, -3 * sp])[[1, 0, 2]]  # (pynrrd: a row an axis)
        path = tmp_path / "a.nrrd"
        nrrd.write(str(path), np.zeros((4, 4, 4), np.uint8),
                   {"space": "left-posterior-superior", "space directions": axes,
                    "space origin": [0.0, 0.0, 0.0]})
        vol = read_volume(path)
        np.testing.assert_array_equal((vol.direction * vol.spacing[None, :]).T, axes)
        assert set(np.unique(vol.direction)) <= {-1.0, 0.0, 1.0}


def test_bspline_deformable_transform_keeps_its_far_face_outside(tmp_path):
    """ITK's older BSplineDeformableTransform (ITK 3, older ANTs) has the same grid as
    BSplineTransform but its InsideValidRegion is [1, n - 2) to the letter (ValidRegionLast
    = n - 2, no far-face exception): volwarp read it as a BSplineTransform and moved the fixed
    grid's last planes, which ITK leaves. SimpleITK cannot read the class (not registered in
    its transform factory), so ITK's result is computed here from its code: a
    BSplineTransform's point where ITK's grid index is inside [1, n - 2) on every axis, the
    point itself elsewhere."""
    fixed = _image((22, 20, 18), (0.7, 0.8, 1.3), (-8.3, 6.1, 4.7), _rotation(0.1, 0.25, -0.3))
    b = _ants_placed(fixed, [5, 4, 3], 3)
    sitk.WriteTransform(b, str(tmp_path / "b.tfm"))
    text = (tmp_path / "b.tfm").read_text()
    assert "BSplineTransform_double_3_3" in text
    (tmp_path / "d.tfm").write_text(text.replace("BSplineTransform_double_3_3",
                                                 "BSplineDeformableTransform_double_3_3"))
    size = fixed.GetSize()
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in size], indexing="ij"), -1).reshape(-1, 3)
    pts = np.array([fixed.TransformIndexToPhysicalPoint([int(v) for v in i]) for i in idx])
    f = np.asarray(b.GetFixedParameters())
    inv = _itk_inverse_by_sitk(f[6:9], f[9:18].reshape(3, 3))
    c = pts - f[3:6]
    grid = (inv[:, 0][None] * c[:, [0]] + inv[:, 1][None] * c[:, [1]]) + inv[:, 2][None] * c[:, [2]]
    inside = np.all((grid >= 1.0) & (grid < f[:3] - 2), axis=1)
    theirs = np.where(inside[:, None], np.array([b.TransformPoint(p.tolist()) for p in pts]), pts)
    ours = read_chain([str(tmp_path / "d.tfm")]).map(pts)
    far = np.any(np.abs(grid - (f[:3] - 2)) < 1e-9, axis=1) & ~np.any(grid < 1.0, axis=1)
    assert far.sum() > 500  # (the last planes: on the far face, ITK's BSplineTransform moves them)
    assert np.count_nonzero(np.abs(ours - theirs).max(axis=1) > 1e-9) == 0
    # and the newer class, from the same numbers, moves them as ITK does
    newer = read_chain([str(tmp_path / "b.tfm")]).map(pts[far])
    expect = np.array([b.TransformPoint(p.tolist()) for p in pts[far]])
    assert np.abs(newer - expect).max() < 1e-9
