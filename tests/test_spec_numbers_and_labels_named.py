"""Spec values that do not fit: named by their key and line, exit 2, nothing written.

Found by the spec-messages hunt: a morph spec's ``label`` the volume lacks (exit 1, no
key); extreme numbers (a sweep's tau of 1e-300, points of 1e300: a ZeroDivisionError or
the wrong key; a transform's scale of 1e300: exit 0 and a field of -inf; a morph's
max_distance of 1e-300: exit 0 and frames of 0). And the NIfTI writer, which refused a
rotation rounded to 6 decimals (2.7% of them) or 5 (nearly all): such a grid is written
and lands where it lay in nibabel and SimpleITK.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DATA

from volwarp_cli.errors import VolwarpError
from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

BALL = DATA / "ball_30_uint8.nrrd"  # a 0/200 mask, 1 mm voxels
TEMPLATES = DATA.parent.parent / "specs" / "templates"


def _refused(res, out, *words, code=2):
    """One line on stderr, the exit code, every word in it, nothing in ``out``."""
    assert res.code == code, res.stderr
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("volwarp: error: "), res.stderr
    assert "internal error" not in res.stderr
    for w in words:
        assert w in res.stderr, res.stderr
    assert not any(out.iterdir()), sorted(p.name for p in out.iterdir())


@pytest.fixture
def out(tmp_path):
    d = tmp_path / "out"
    d.mkdir()
    return d


# -- a label the volume lacks --------------------------------------------------------
@pytest.mark.parametrize("side, line", [("source", 3), ("target", 4)])
def test_morph_spec_label_absent_names_its_key(run, tmp_path, out, side, line):
    """``label: 7`` on the 0/200 ball: a spec error at ``source.label``'s line (was exit 1, no key)."""
    shapes = {"source": f"{{volume: {BALL}}}", "target": f"{{volume: {BALL}}}"}
    shapes[side] = f"{{volume: {BALL}, label: 7}}"
    spec = tmp_path / "m.yaml"
    spec.write_text(f"version: 1\n# a comment\nsource: {shapes['source']}\n"
                    f"target: {shapes['target']}\nframes: 3\n")
    res = run("morph", "--spec", spec, "-o", out / "m_{i}.nrrd")
    _refused(res, out, f"m.yaml:{line}: {side}.label: ", "label 7 does not occur")


# -- extreme numbers ------------------------------------------------------------------
_SWEEP = (f"version: 1\ngrid: {{spacing: 0.5, margin: 0.5}}\nfields:\n"
          f"  opacity: {{image: {TEMPLATES}/at_opacity.png, channel: 0}}\n")
_LINE = "trajectory:\n  - line: {from: [0, 0, 0], to: [10, 0, 0]}\n"


@pytest.mark.parametrize("body, key, line", [
    # a tau of 1e-300 asks for more templates than a segment may have (exit 1, no key)
    (_LINE + "scale: [4, 4]\ntau: 1e-300\n", "tau", 8),
    # points, radii and angles of 1e300: a ZeroDivisionError, or "up" named
    (_LINE.replace("[10, 0, 0]", "[1e300, 0, 0]") + "scale: [4, 4]\n",
     "trajectory[0].line.to[0]", 6),
    (_LINE.replace("[10, 0, 0]", "[1e16, 0, 0]") + "scale: [4, 4]\n",
     "trajectory[0].line.to[0]", 6),  # (was "scale")
    ("trajectory:\n  - arc: {center: [0, 0, 0], radius: 1e300, axis: [0, 0, 1]}\n"
     "scale: [4, 4]\n", "trajectory[0].arc.radius", 6),
    ("trajectory:\n  - arc: {center: [0, 0, 0], radius: 5, end: 1e300}\nscale: [4, 4]\n",
     "trajectory[0].arc.end", 6),
    ("trajectory:\n  - arc: {center: [1e300, 0, 0], radius: 5}\nscale: [4, 4]\n",
     "trajectory[0].arc.center[0]", 6),  # (was "scale")
    ("trajectory:\n  - bezier: {points: [[0, 0, 0], [1e300, 5, 0], [25, -5, 0], [40, 0, 0]]}\n"
     "scale: [4, 4]\n", "trajectory[0].bezier.points[1][0]", 6),
    ("trajectory:\n  - polyline: {points: [[0, 0, 0], [1e300, 5, 0], [25, -5, 0]]}\n"
     "scale: [4, 4]\n", "trajectory[0].polyline.points[1][0]", 6),  # (was "scale", nan)
    (_LINE + "scale: [4, 4]\ndirection: [1e300, 1e300, 0]\n", "direction[0]", 8),
    (_LINE + "scale: [4, 4]\nup: [0, 1e300, 1e300]\n", "up[1]", 8),  # (was "is zero")
])
def test_sweep_extreme_numbers_name_their_key(run, tmp_path, out, body, key, line):
    spec = tmp_path / "s.yaml"
    spec.write_text(_SWEEP + body)
    res = run("sweep", spec, "-o", out / "s_{field}.nrrd")
    _refused(res, out, f"s.yaml:{line}: {key}: ")


def test_sweep_grid_shape_over_an_axis_names_its_key(run, tmp_path, out):
    """``shape: [1e20, 3, 3]`` was an OverflowError (an internal error, exit 1)."""
    spec = tmp_path / "s.yaml"
    spec.write_text(_SWEEP.replace("spacing: 0.5, margin: 0.5", "shape: [100000000000000000000, 3, 3]")
                    + _LINE + "scale: [4, 4]\n")
    res = run("sweep", spec, "-o", out / "s_{field}.nrrd")
    _refused(res, out, "s.yaml:2: grid.shape[0]: ")


def test_sweep_constant_field_beyond_float32_says_so(run, tmp_path, out):
    """A field ``v: 1e39`` was said to have "non-finite values"."""
    spec = tmp_path / "s.yaml"
    spec.write_text(_SWEEP + "  v: 1e39\n" + _LINE + "scale: [4, 4]\n")
    res = run("sweep", spec, "-o", out / "s_{field}.nrrd")
    _refused(res, out, "s.yaml:5: fields.v: ", "float32")


def test_sweep_path_far_beyond_the_stack_is_clamped(tmp_path):
    """A path f(u) beyond the stack is clamped (as documented), not subdivided without end.

    ``path: {expr: 'u * 1e12'}`` asked for over 2000000 templates (exit 1, naming tau);
    clamped it is the stack's last frame from just after u = 0, as the samplers take it.
    """
    from volwarp_cli.spec.loader import load_spec
    from volwarp_cli.sweep import evaluate
    from volwarp_cli.sweep.model import output_grid, parse_sweep_spec

    frames = sorted(TEMPLATES.glob("flame_00*.png"))
    fields = {"far": "{expr: 'u * 1e12'}", "last": str(len(frames) - 1)}
    got = {}
    for name, path in fields.items():
        spec = tmp_path / f"{name}.yaml"
        spec.write_text(f"version: 1\ngrid: {{spacing: 0.5, margin: 0.5}}\nfields:\n"
                        f"  f: {{frames: {[str(f) for f in frames]}, path: {path}}}\n"
                        + _LINE + "scale: [4, 4]\n")
        model = parse_sweep_spec(load_spec(spec, "sweep"))
        got[name] = evaluate(model, output_grid(model))["f"]
    assert got["far"].shape == got["last"].shape
    # (the first template, at u = 0, is frame 0 in the far one)
    inner = np.s_[:, :, 3:]
    np.testing.assert_allclose(got["far"][inner], got["last"][inner], atol=1e-6)


_WARP = ("version: 1\nunits: world\ncapture: {lattice: [5, 5, 5], placement: uniform, "
         "oversample: 1, pad: 2, sampling: linear}\nsteps:\n")


@pytest.mark.parametrize("step, key, line", [
    ("  - move:\n      - {index: [2, 2, 2], by: [1e300, 0.0, 0.0]}\n", "steps[0].move[0].by", 6),
    ("  - move:\n      - {index: [1, 1, 1], by: [1, 0, 0]}\n"
     "      - {index: [2, 2, 2], to: [1e300, 0.0, 0.0]}\n", "steps[0].move[1].to", 7),
    # (was "steps[0]", after a warning about a compromise)
    ("  - drag:\n      - {from: [14.5, 14.5, 14.5], to: [14.5, 14.5, 1e300]}\n",
     "steps[0].drag[0].to", 6),
])
def test_warp_huge_moves_name_their_key(run, tmp_path, out, step, key, line):
    spec = tmp_path / "w.yaml"
    spec.write_text(_WARP + step)
    res = run("warp", BALL, "--spec", spec, "-o", out / "w.nrrd")
    _refused(res, out, f"w.yaml:{line}: {key}: ", "input voxels")


@pytest.fixture
def sdf(tmp_path, run):
    path = tmp_path / "sdf.nrrd"
    assert run("distance", BALL, "-o", path).code == 0
    return path


@pytest.mark.parametrize("body, key", [
    ("scale: 1e300\n", "scale"),  # (was exit 0: a field of -inf)
    ("matrix: [[1e300, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n",
     "matrix[0][0]"),  # (was exit 0: a field of +inf)
    ("rotate: [0, 0, 1e300]\n", "rotate[2]"),  # (was exit 0: an angle with no digits left)
    ("translate: [1e300, 0, 0]\n", "translate[0]"),  # (was exit 1, no key)
    ("scale: 1e-300\n", "scale"),
])
def test_transform_spec_extreme_numbers_refused(run, tmp_path, out, sdf, body, key):
    spec = tmp_path / "t.yaml"
    spec.write_text("version: 1\n" + body)
    res = run("distance", "--update", sdf, "--transform", spec, "-o", out / "t.nrrd")
    _refused(res, out, f"t.yaml:2: {key}: ")


@pytest.mark.parametrize("align, key", [
    ("{rotate: [0, 0, 1e300]}", "align.target.rotate[2]"),  # (was exit 0)
    ("{scale: 1e-300}", "align.target.scale"),  # (was "the grid does not overlap")
])
def test_morph_align_extreme_numbers_name_their_key(run, tmp_path, out, align, key):
    spec = tmp_path / "m.yaml"
    spec.write_text(f"version: 1\nsource: {{volume: {BALL}, iso: 100}}\n"
                    f"target: {{volume: {BALL}, iso: 100}}\nframes: 3\n"
                    f"align:\n  target: {align}\n")
    res = run("morph", "--spec", spec, "-o", out / "m_{i}.nrrd")
    _refused(res, out, f"m.yaml:6: {key}: ")


def test_band_below_float32_refused(run, tmp_path, out):
    """A band of 1e-300 is 0 in float32: frames and fields of 0 with exit 0."""
    spec = tmp_path / "m.yaml"
    spec.write_text(f"version: 1\nsource: {{volume: {BALL}, iso: 100}}\n"
                    f"target: {{volume: {BALL}, iso: 100}}\nframes: 3\nmax_distance: 1e-300\n")
    res = run("morph", "--spec", spec, "-o", out / "m_{i}.nrrd")
    _refused(res, out, "m.yaml:5: max_distance: ", "float32")
    res = run("distance", BALL, "--max-distance", "1e-300", "-o", out / "d.nrrd")
    _refused(res, out, "--max-distance", "float32")


# -- NIfTI: rotations rounded to a few decimals -----------------------------------------
SHAPE_XYZ = (64, 48, 40)
SPACING = np.array([0.7, 0.8, 2.5])
ORIGIN = np.array([-120.3, 85.2, -40.7])


def _far_corner_errors(path, direction, spacing):
    """World (LPS) error of the far corner's centre in nibabel and SimpleITK."""
    import nibabel as nib
    import SimpleITK as sitk

    far = np.array(SHAPE_XYZ, dtype=np.float64) - 1
    want = ORIGIN + direction @ (spacing * far)
    ras = nib.load(str(path)).affine @ np.r_[far, 1.0]
    by_nibabel = ras[:3] * np.array([-1.0, -1.0, 1.0])
    by_sitk = np.array(sitk.ReadImage(str(path)).TransformContinuousIndexToPhysicalPoint(
        [float(v) for v in far]))
    return np.abs(by_nibabel - want).max(), np.abs(by_sitk - want).max()


def _write(path, direction, meta):
    write_volume(Volume(np.zeros(SHAPE_XYZ[::-1], np.int16), spacing=SPACING, origin=ORIGIN,
                        direction=direction, meta=meta), path)
    return _far_corner_errors(path, direction, SPACING)


@pytest.mark.parametrize("decimals", [5, 6])
@pytest.mark.parametrize("codes", [None, ("0", "1")])
def test_nifti_writes_rounded_rotations_in_place(tmp_path, decimals, codes):
    """Rotations rounded to 6 (2.7% were refused) or 5 decimals (nearly all were) are written.

    Both forms coded 1: every reader takes the sform, written as given: the far corner
    lands within float32's rounding (measured 8.7e-6 mm, 113 mm from an origin 150 mm
    out). The sform coded 0: readers take the qform, the nearest rotation: the rounding
    adds at most half the tolerance times the grid's extent to what the exact rotation's
    qform gives (itself up to 0.037 mm off here: its quaternion's float32 ``b, c, d``
    leave little of a small ``a``).
    """
    from scipy.spatial.transform import Rotation

    from volwarp_cli.io.nifti import ORTHONORMAL_TOLERANCE

    meta = {} if codes is None else {"NIfTI_sform_code": codes[0], "NIfTI_qform_code": codes[1]}
    extent = float(np.linalg.norm(SPACING * (np.array(SHAPE_XYZ) - 1)))
    for i, rot in enumerate(Rotation.random(40, random_state=7).as_matrix()):
        rounded = _write(tmp_path / f"r{i}.nii", np.round(rot, decimals), meta)
        if codes is None:
            assert max(rounded) <= 5e-5, (i, rounded)
        else:
            exact = _write(tmp_path / f"e{i}.nii", rot, meta)
            for got, base in zip(rounded, exact, strict=True):
                assert got <= base + 0.5 * ORTHONORMAL_TOLERANCE * extent, (i, got, base)


def test_nifti_still_refuses_a_shear(tmp_path):
    """A real shear (1e-3, a gantry tilt's scale) is refused, never made orthogonal."""
    d = np.eye(3)
    d[0, 2] = 1e-3
    with pytest.raises(VolwarpError, match="sheared"):
        write_volume(Volume(np.zeros((4, 4, 4), np.int16), direction=d), tmp_path / "s.nii")
    assert not (tmp_path / "s.nii").exists()
