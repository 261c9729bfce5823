"""`volwarp apply` against SimpleITK where a hunt found it wrong."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume
from volwarp_cli.transforms import read_chain

sitk = pytest.importorskip("SimpleITK")


def _rotation(ax, ay, az) -> np.ndarray:
    t = sitk.Euler3DTransform()
    t.SetRotation(ax, ay, az)
    return np.asarray(t.GetMatrix()).reshape(3, 3)


def _fixed(spacing, direction) -> sitk.Image:
    img = sitk.Image([34, 30, 26], sitk.sitkFloat32)
    img.SetSpacing(spacing)
    img.SetOrigin([-8.3, 6.1, 4.7])
    img.SetDirection(np.asarray(direction).ravel().tolist())
    return img


def _ants_bspline(fixed: sitk.Image) -> sitk.BSplineTransform:
    """A B-spline placed as antsRegistration places it: from the first voxel centre to the last."""
    b = sitk.BSplineTransform(3, 3)
    b.SetTransformDomainOrigin(fixed.GetOrigin())
    b.SetTransformDomainDirection(fixed.GetDirection())
    b.SetTransformDomainPhysicalDimensions(
        [s * (n - 1) for s, n in zip(fixed.GetSpacing(), fixed.GetSize(), strict=True)])
    b.SetTransformDomainMeshSize([5, 4, 3])
    rng = np.random.default_rng(1)
    b.SetParameters(rng.normal(0, 2.0, len(b.GetParameters())).tolist())
    return b


def _far_faces(fixed: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """The fixed grid's voxels on a last plane of some axis and on no first plane: indices, points."""
    size = fixed.GetSize()
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in size], indexing="ij"), -1).reshape(-1, 3)
    far = np.any(idx == np.asarray(size) - 1, axis=1) & np.all(idx > 0, axis=1)
    idx = idx[far]
    pts = np.array([fixed.TransformIndexToPhysicalPoint([int(v) for v in i]) for i in idx])
    return idx, pts


@pytest.mark.parametrize("spacing, direction", [
    ((1.0, 1.0, 1.0), np.eye(3)),
    ((0.9, 1.1, 1.7), np.eye(3)),
    ((0.7, 0.7, 3.0), _rotation(0.1, 0.25, -0.3)),
])
def test_itk_bspline_moves_its_far_face_as_itk(tmp_path, spacing, direction):
    """ITK's BSplineTransform takes a point on its valid region's far face (grid index n - 2) as
    inside (InsideValidRegion: within 4 ULPs of it, the spline's limit). A grid placed as ANTs
    places it puts the fixed grid's last voxels there: volwarp left them unmoved (the
    displacement 0 where ITK's was up to 5 mm; in the resampled volume half the range off
    on those faces)."""
    fixed = _fixed(spacing, direction)
    b = _ants_bspline(fixed)
    sitk.WriteTransform(b, str(tmp_path / "b.h5"))
    _, pts = _far_faces(fixed)
    theirs = np.array([b.TransformPoint(p.tolist()) for p in pts])
    ours = read_chain([str(tmp_path / "b.h5")]).map(pts)
    moved = np.abs(theirs - pts).max(axis=1) > 0
    assert moved.mean() > 0.9  # (ITK's own rounding leaves a few beyond its 4 ULPs)
    assert np.abs(ours - theirs)[moved].max() < 1e-9


def test_itk_bspline_far_face_resampled_as_sitk(run, tmp_path):
    """The same through the command: the fixed grid's last planes resampled as sitk.Resample."""
    fixed = _fixed((0.9, 1.1, 1.7), np.eye(3))
    b = _ants_bspline(fixed)
    sitk.WriteTransform(b, str(tmp_path / "b.h5"))
    z, y, x = np.mgrid[:30, :36, :40].astype(np.float32)
    moving = sitk.GetImageFromArray(np.sin(x / 3) * 100 + np.cos(y / 4) * 80 + z)
    moving.SetSpacing([1.2, 0.9, 2.1])
    moving.SetOrigin([-10.0, 5.0, 3.0])
    moving.SetDirection(_rotation(0.3, -0.2, 0.5).ravel().tolist())
    sitk.WriteImage(moving, str(tmp_path / "moving.nrrd"))
    sitk.WriteImage(fixed, str(tmp_path / "fixed.nrrd"))
    res = run("apply", tmp_path / "moving.nrrd", "-o", tmp_path / "out.nrrd", "--reference",
              tmp_path / "fixed.nrrd", "-t", tmp_path / "b.h5", "--background-value", "0")
    assert res.code == 0, res
    ours = read_volume(tmp_path / "out.nrrd").data.astype(float)
    theirs = sitk.GetArrayFromImage(sitk.Resample(moving, fixed, b, sitk.sitkLinear, 0.0,
                                                  sitk.sitkFloat64))
    idx, _ = _far_faces(fixed)
    k = (idx[:, 2], idx[:, 1], idx[:, 0])
    assert np.abs(ours[k] - theirs[k]).max() <= 1e-4 * float(np.ptp(theirs))


def test_elastix_bspline_keeps_its_far_face_outside(tmp_path):
    """elastix's B-spline is another rule: its valid region is [1, n - 2) to the letter
    (AdvancedBSplineDeformableTransformBase::InsideValidRegion). Measured with itk-elastix
    0.25.4's TransformixFilter (deformation field of a grid whose last voxels lie on the far
    face: zero there, 5.9e-8 mm from volwarp elsewhere); the ITK rule above would move them."""
    fixed = _fixed((1.0, 1.0, 1.0), np.eye(3))
    b = _ants_bspline(fixed)
    f = np.asarray(b.GetFixedParameters())
    words = lambda v: " ".join(repr(float(a)) for a in v)  # noqa: E731
    (tmp_path / "tp.txt").write_text("\n".join([
        '(Transform "BSplineTransform")', "(FixedImageDimension 3)", "(MovingImageDimension 3)",
        '(InitialTransformParameterFileName "NoInitialTransform")',
        '(HowToCombineTransforms "Compose")', "(Size 34 30 26)", "(Index 0 0 0)",
        f"(Spacing {words(fixed.GetSpacing())})", f"(Origin {words(fixed.GetOrigin())})",
        "(Direction 1 0 0 0 1 0 0 0 1)", '(UseDirectionCosines "true")',
        f"(GridSize {' '.join(str(int(v)) for v in f[:3])})", "(GridIndex 0 0 0)",
        f"(GridOrigin {words(f[3:6])})", f"(GridSpacing {words(f[6:9])})",
        "(GridDirection 1 0 0 0 1 0 0 0 1)", "(BSplineTransformSplineOrder 3)",
        f"(TransformParameters {words(b.GetParameters())})", ""]))
    idx, pts = _far_faces(fixed)
    ours = read_chain([str(tmp_path / "tp.txt")]).map(pts)
    inside = np.all(idx < np.asarray(fixed.GetSize()) - 1, axis=1)
    # (a point on a far face: its grid index n - 2 on that axis, or a hair off by rounding)
    grid_idx = (pts - f[3:6]) / f[6:9]
    on_face = np.any(np.abs(grid_idx - (f[:3] - 2)) < 1e-9, axis=1)
    assert not inside.any() and on_face.all()
    exactly = np.any(grid_idx >= f[:3] - 2, axis=1)  # (beyond by rounding: outside either way)
    assert exactly.any()
    assert np.array_equal(ours[exactly], pts[exactly])


def test_bspline_by_blocks_gives_the_whole_bytes(run, tmp_path):
    """By blocks = in memory, the same bytes, through a B-spline whose valid region's edge the
    grid's points lie on: a block's parts of fewer than 4096 points were mapped to the grid's
    indices by numpy's matmul, the whole's by the kernel, a few ULPs apart, and a point on the
    edge moved in one and not in the other (voxels up to half the range apart, exit 0)."""
    fixed = _fixed((1.0, 1.0, 1.0), _rotation(0.1, 0.25, -0.3))
    sitk.WriteTransform(_ants_bspline(fixed), str(tmp_path / "b.h5"))
    z, y, x = np.mgrid[:30, :36, :40].astype(np.float32)
    moving = sitk.GetImageFromArray(np.sin(x / 3) * 100 + np.cos(y / 4) * 80 + z)
    moving.SetOrigin([-10.0, 5.0, 3.0])
    sitk.WriteImage(moving, str(tmp_path / "moving.nrrd"))
    sitk.WriteImage(fixed, str(tmp_path / "fixed.nrrd"))
    outs = _whole_and_blocks(run, tmp_path, "5,6,7", "-t", tmp_path / "b.h5")
    assert np.array_equal(outs[0], outs[1])


def _whole_and_blocks(run, tmp_path, block: str, *options) -> list:
    """``apply moving.nrrd --reference fixed.nrrd OPTIONS`` in memory and by ``block`` blocks."""
    outs = []
    for name, extra in (("whole", ()), ("blocks", ("--chunked", "--block", block))):
        res = run("apply", tmp_path / "moving.nrrd", "-o", tmp_path / f"{name}.nrrd",
                  "--reference", tmp_path / "fixed.nrrd", *options,
                  "--background-value", "0", *extra)
        assert res.code == 0, res
        outs.append(read_volume(tmp_path / f"{name}.nrrd").data)
    return outs


def test_field_on_the_output_grid_across_its_edge_by_blocks_gives_the_whole_bytes(run, tmp_path):
    """A field whose nodes are the output's voxels but which covers part of the grid
    (--allow-outside-field): in memory the whole box was off the field and interpolated, by
    blocks the blocks on it took the nodes' vectors as they lie, 4e-13 apart in a float64
    output (not the same bytes). Now every block adds the nodes, the rest unmoved."""
    fixed = _fixed((1.1, 0.7, 1.3), _rotation(0.1, 0.25, -0.3))
    rng = np.random.default_rng(2)
    field = sitk.GetImageFromArray(rng.normal(0, 2, (30, 28, 30, 3)), isVector=True)
    field.SetSpacing(fixed.GetSpacing())
    field.SetDirection(fixed.GetDirection())
    field.SetOrigin(fixed.TransformContinuousIndexToPhysicalPoint([-3, 2, -1]))
    sitk.WriteImage(field, str(tmp_path / "field.nrrd"))
    z, y, x = np.mgrid[:30, :36, :40].astype(np.float64)
    moving = sitk.GetImageFromArray(np.sin(x / 3) * 100 + np.cos(y / 4) * 80 + z)
    moving.SetOrigin([-10.0, 5.0, 3.0])
    sitk.WriteImage(moving, str(tmp_path / "moving.nrrd"))
    sitk.WriteImage(fixed, str(tmp_path / "fixed.nrrd"))
    outs = _whole_and_blocks(run, tmp_path, "5,7,9", "-t", tmp_path / "field.nrrd",
                             "--allow-outside-field")
    assert outs[0].dtype == np.float64 and np.array_equal(outs[0], outs[1])
    theirs = sitk.GetArrayFromImage(sitk.Resample(
        moving, fixed, sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64)),
        sitk.sitkLinear, 0.0, sitk.sitkFloat64))
    assert np.abs(outs[0] - theirs).max() <= 1e-9 * float(np.ptp(theirs))


@pytest.mark.parametrize("order", [1, 2])
def test_a_bspline_of_another_order_is_refused_by_its_order(run, tmp_path, order):
    """Refused before as "' BSplineTransform_double_3_3_1' is not an ITK transform name"
    (a name ITK does write, a leading space): now by what it is."""
    img = sitk.Image([8, 8, 8], sitk.sitkFloat32)
    sitk.WriteImage(img, str(tmp_path / "i.nrrd"))
    tfm = tmp_path / "b.tfm"
    sitk.WriteTransform(sitk.BSplineTransformInitializer(img, [2, 2, 2], order), str(tfm))
    r = run("apply", tmp_path / "i.nrrd", "-o", tmp_path / "o.nrrd", "-t", tfm)
    assert r.code == 1
    assert f"BSplineTransform of spline order {order} is not supported" in r.stderr, r.stderr
    assert not (tmp_path / "o.nrrd").exists()


def test_the_unsupported_class_message_lists_every_supported_class(run, tmp_path):
    img = sitk.Image([8, 8, 8], sitk.sitkFloat32)
    sitk.WriteImage(img, str(tmp_path / "i.nrrd"))
    tfm = tmp_path / "s.tfm"
    sitk.WriteTransform(sitk.ScaleSkewVersor3DTransform(), str(tfm))
    r = run("apply", tmp_path / "i.nrrd", "-o", tmp_path / "o.nrrd", "-t", tfm)
    assert r.code == 1 and "ScaleSkewVersor3DTransform is not supported" in r.stderr
    for name in ("ScaleTransform", "Rigid3DTransform", "ScalableAffineTransform"):
        assert name in r.stderr, r.stderr
