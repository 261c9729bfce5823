"""elastix TransformParameters files (as elastix 5 writes them) against SimpleITK's transforms.

The files are written here in elastix's layout (checked against files
itk-elastix 0.25 wrote: column-major Direction/GridDirection, the initial
transform named relative to where elastix ran); SimpleITK's transforms with
the same numbers map the points.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.transforms import read_chain
from volwarp_cli.volume import Volume

sitk = pytest.importorskip("SimpleITK")

ROT = np.array([[np.cos(0.1), -np.sin(0.1), 0], [np.sin(0.1), np.cos(0.1), 0], [0, 0, 1]])
GRID = {"Size": [20, 18, 16], "Spacing": [1.1, 1.0, 1.2], "Origin": [-5.0, 3.0, 2.0]}


def numbers(values) -> str:
    return " ".join(repr(float(v)) for v in values)


def header(kind: str, n: int, initial: str = "NoInitialTransform") -> str:
    return "\n".join([
        f'(Transform "{kind}")', f"(NumberOfParameters {n})",
        f'(InitialTransformParameterFileName "{initial}")', '(HowToCombineTransforms "Compose")',
        "(FixedImageDimension 3)", "(MovingImageDimension 3)",
        f"(Size {' '.join(str(v) for v in GRID['Size'])})", "(Index 0 0 0)",
        f"(Spacing {numbers(GRID['Spacing'])})", f"(Origin {numbers(GRID['Origin'])})",
        f"(Direction {numbers(ROT.T.ravel())})", '(UseDirectionCosines "true")',
        "// ResampleInterpolator specific", '(ResampleInterpolator "FinalBSplineInterpolator")',
        "(FinalBSplineInterpolationOrder 3)", ""])


def euler_file(path, initial="NoInitialTransform"):
    e = sitk.Euler3DTransform()
    e.SetRotation(0.05, -0.1, 0.15)
    e.SetTranslation([0.7, -0.4, 1.1])
    e.SetCenter([6.0, 12.0, 11.0])
    path.write_text(header("EulerTransform", 6, initial)
                    + f"(TransformParameters {numbers(e.GetParameters())})\n"
                    + f"(CenterOfRotationPoint {numbers(e.GetCenter())})\n"
                    + '(ComputeZYX "false")\n')
    return e


def bspline_file(path, initial, grid_index=(0, 0, 0)):
    ref = sitk.Image(GRID["Size"], sitk.sitkFloat32)
    ref.SetSpacing(GRID["Spacing"])
    ref.SetOrigin(GRID["Origin"])
    ref.SetDirection(ROT.ravel().tolist())
    b = sitk.BSplineTransformInitializer(ref, [3, 3, 3])
    rng = np.random.default_rng(3)
    b.SetParameters(rng.normal(0, 0.8, len(b.GetParameters())).tolist())
    fixed = np.asarray(b.GetFixedParameters())
    # (transformix: the coefficients start at GridIndex of a grid whose index 0 is GridOrigin)
    grid_origin = fixed[3:6] - fixed[9:18].reshape(3, 3) @ (fixed[6:9] * np.asarray(grid_index))
    path.write_text(header("BSplineTransform", len(b.GetParameters()), initial)
                    + f"(TransformParameters {numbers(b.GetParameters())})\n"
                    + f"(GridSize {' '.join(str(int(v)) for v in fixed[:3])})\n"
                    + f"(GridIndex {' '.join(str(int(v)) for v in grid_index)})\n"
                    + f"(GridOrigin {numbers(grid_origin)})\n"
                    + f"(GridSpacing {numbers(fixed[6:9])})\n"
                    + f"(GridDirection {numbers(fixed[9:18].reshape(3, 3).T.ravel())})\n"
                    + "(BSplineTransformSplineOrder 3)\n"
                    + '(UseCyclicTransform "false")\n')
    return b


@pytest.mark.parametrize("grid_index", [(0, 0, 0), (1, 2, -1)])
def test_chain_through_initial_transforms(tmp_path, monkeypatch, grid_index):
    """An initial transform first; a B-spline grid's non-zero GridIndex as transformix takes it
    (it was ignored: 3.07 mm off transformix's field for GridIndex 1 1 1)."""
    e = euler_file(tmp_path / "TransformParameters.0.txt")
    b = bspline_file(tmp_path / "TransformParameters.1.txt", "./TransformParameters.0.txt",
                     grid_index)
    monkeypatch.chdir(tmp_path.parent)  # (not where elastix ran: found beside the file)
    chain = read_chain([str(tmp_path / "TransformParameters.1.txt")])
    assert len(chain.steps) == 2
    pts = np.random.default_rng(1).uniform([-3, 4, 3], [15, 18, 20], (100, 3))
    theirs = np.array([b.TransformPoint(e.TransformPoint(p.tolist())) for p in pts])
    assert np.abs(chain.map(pts) - theirs).max() < 1e-9
    assert chain.grid.shape_xyz == tuple(GRID["Size"])
    assert np.allclose(chain.grid.direction, ROT)
    assert any("FinalBSplineInterpolator of order 3" in n for n in chain.notes)


def test_apply_on_the_fixed_grid_it_states(run, tmp_path):
    """Without --reference, the output grid is the parameter file's fixed grid (as transformix)."""
    e = euler_file(tmp_path / "tp.txt")
    nz, ny, nx = 18, 20, 22
    z, y, x = np.mgrid[:nz, :ny, :nx].astype(np.float32)
    vol = Volume(np.sin(x / 3) * np.cos(y / 4) * 50 + z, spacing=(1.0, 1.1, 1.0),
                 origin=(-4.0, 2.0, 3.0), space="left-posterior-superior")
    write_volume(vol, tmp_path / "moving.nrrd")
    res = run("apply", "-v", tmp_path / "moving.nrrd", "-o", tmp_path / "out.nrrd", "-t",
              tmp_path / "tp.txt", "--interpolation", "bspline", "--background-value", "0")
    assert res.code == 0, res
    out = read_volume(tmp_path / "out.nrrd")
    assert out.shape_xyz == tuple(GRID["Size"]) and np.allclose(out.direction, ROT)
    size = "x".join(map(str, GRID["Size"]))  # (not the input's: said, as --help says)
    assert f"output grid: {size} (the elastix file's fixed grid)" in res.stderr, res.stderr
    mov = sitk.GetImageFromArray(vol.data)
    mov.SetSpacing([1.0, 1.1, 1.0])
    mov.SetOrigin([-4.0, 2.0, 3.0])
    ref = sitk.Image(GRID["Size"], sitk.sitkFloat32)
    ref.SetSpacing(GRID["Spacing"])
    ref.SetOrigin(GRID["Origin"])
    ref.SetDirection(ROT.ravel().tolist())
    theirs = sitk.GetArrayFromImage(sitk.Resample(mov, ref, e, sitk.sitkBSpline, 0.0))
    assert np.abs(out.data - theirs).max() <= 1e-4 * float(np.ptp(vol.data))


def test_missing_initial_transform(run, tmp_path):
    euler_file(tmp_path / "tp.txt", initial="/nowhere/TransformParameters.0.txt")
    write_volume(Volume(np.zeros((4, 4, 4), np.float32)), tmp_path / "in.nrrd")
    res = run("apply", tmp_path / "in.nrrd", "-o", tmp_path / "o.nrrd", "-t", tmp_path / "tp.txt")
    assert res.code == 1 and "initial transform" in res.stderr
    assert not (tmp_path / "o.nrrd").exists()


@pytest.mark.parametrize("initial", [False, True])
def test_use_direction_cosines_false_is_refused(run, tmp_path, initial):
    """(UseDirectionCosines "false"): elastix takes the images' directions as identity, the
    command-line transformix both images' (it reads them so), itk-elastix's TransformixFilter
    the output grid's only (measured with itk-elastix 0.25.4). volwarp read the file as
    "true", half the range off on a rotated grid; it refuses it, naming the file (an initial
    transform's too)."""
    first = tmp_path / "TransformParameters.0.txt"
    euler_file(first)
    last = first
    if initial:
        last = tmp_path / "TransformParameters.1.txt"
        bspline_file(last, str(first))
    first.write_text(first.read_text().replace('(UseDirectionCosines "true")',
                                               '(UseDirectionCosines "false")'))
    write_volume(Volume(np.zeros((4, 4, 4), np.float32)), tmp_path / "in.nrrd")
    res = run("apply", tmp_path / "in.nrrd", "-o", tmp_path / "o.nrrd", "-t", last)
    assert res.code == 1, res
    assert res.stderr.count("\n") == 1
    assert res.stderr.startswith(f'volwarp: error: {first}: (UseDirectionCosines "false")')
    assert not (tmp_path / "o.nrrd").exists()
    (tmp_path / "p.csv").write_text("x,y,z\n1,2,3\n")  # (points move by the same chain)
    res = run("apply", "-t", last, "--points-in", tmp_path / "p.csv", "--points-to",
              tmp_path / "q.csv")
    assert res.code == 1 and f'{first}: (UseDirectionCosines "false")' in res.stderr, res
    assert not (tmp_path / "q.csv").exists()


@pytest.mark.parametrize("edit", [
    ("(Size 20 18 16)", "(Size 20 18.5 16)", "(Size ...) must be whole numbers"),
    ("(Index 0 0 0)", "(Index 0 0.5 0)", "(Index ...) must be whole numbers"),
    ("(GridIndex 0 0 0)", "(GridIndex 0.25 0 0)", "(GridIndex ...) must be whole numbers"),
    ("(GridSize 6 6 6)", "(GridSize 6.5 6 6)", "(GridSize ...) must be whole numbers"),
    ("(Size 20 18 16)", "(Size 20 18.0000001 16)", "not 20.0 18.0000001 16.0"),
])
def test_a_fraction_elastix_would_not_read_is_refused(run, tmp_path, edit):
    """A fractional size or index was cut to an integer (``(Size 20 18.5 16)``: 18 rows), the
    output written as if the file said otherwise; transformix refuses such a file."""
    old, new, said = edit
    path = tmp_path / "tp.txt"
    bspline_file(path, "NoInitialTransform")
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    write_volume(Volume(np.zeros((4, 4, 4), np.float32)), tmp_path / "in.nrrd")
    res = run("apply", tmp_path / "in.nrrd", "-o", tmp_path / "o.nrrd", "-t", path)
    assert res.code == 1 and said in res.stderr and str(path) in res.stderr, res
    assert not (tmp_path / "o.nrrd").exists()
