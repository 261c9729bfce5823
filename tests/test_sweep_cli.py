"""`volwarp sweep` on the command line: outputs, bad specs, and every example spec."""

from __future__ import annotations

import importlib.util
import shutil
from pathlib import Path

import nrrd
import numpy as np
import pytest

from volwarp_cli.io import read_volume
from volwarp_cli.io.images import read_image

ROOT = Path(__file__).resolve().parents[1]
SPECS = sorted((ROOT / "specs").glob("sweep-*.yaml"))

GOOD = """version: 1
grid: {spacing: 0.5}
fields:
  opacity: {value: 0.8}
  red: 0.25
trajectory:
  - line: {from: [0, 0, 0], to: [6, 1, 0]}
up: [0, 0, 1]
scale: [3, 3]
"""


def _make_templates():
    spec = importlib.util.spec_from_file_location(
        "make_templates", ROOT / "examples" / "sweep-at" / "make_templates.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def spec_dir():
    """The example specs where they are shipped, beside their shipped templates."""
    return ROOT / "specs"


def test_shipped_templates_are_the_generators(tmp_path):
    """specs/templates/ holds exactly what examples/sweep-at/make_templates.py draws."""
    made = _make_templates().make_all(tmp_path, frames=256)
    shipped = ROOT / "specs" / "templates"
    assert sorted(p.name for p in shipped.glob("*.png")) == sorted(p.name for p in made)
    for p in made:
        np.testing.assert_array_equal(read_image(shipped / p.name), read_image(p), p.name)


def test_every_template_a_spec_names_is_shipped():
    """Each sweep spec loads as shipped: the parser reads every image and frame it names."""
    from volwarp_cli.spec.loader import load_spec
    from volwarp_cli.sweep.model import parse_sweep_spec

    for spec in SPECS:
        fields = parse_sweep_spec(load_spec(spec, "sweep")).field_names()
        assert "opacity" in fields, spec.name


def test_outputs_one_volume_per_field(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd")
    assert res.code == 0, res.stderr
    o = read_volume(tmp_path / "o_opacity.nrrd")
    r = read_volume(tmp_path / "o_red.nrrd")
    assert o.data.dtype == np.float32 and o.same_grid(r)
    assert set(np.unique(o.data)) == {0.0, np.float32(0.8)}
    assert np.all((r.data == 0.25) == (o.data == np.float32(0.8)))
    assert np.allclose(o.spacing, 0.5) and np.allclose(o.direction, np.eye(3))
    # the voxel grid lies around the sweep: its centre voxel lies on the trajectory
    lo, hi = o.world_bounds()
    assert np.all(lo < [0, -1.5, -1.5]) and np.all(hi > [6, 2.5, 1.5])


def test_outputs_are_deterministic(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "a_{field}.nrrd")
    run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "b_{field}.nrrd")
    assert (tmp_path / "a_opacity.nrrd").read_bytes() == (tmp_path / "b_opacity.nrrd").read_bytes()


def test_multi_component_output_matches_single_files(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    assert run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd").code == 0
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "all.nrrd", "--multi")
    assert res.code == 0, res.stderr
    data, header = nrrd.read(str(tmp_path / "all.nrrd"), index_order="C")
    assert header["volwarp_components"] == "opacity red"
    assert np.array_equal(data[..., 0], read_volume(tmp_path / "o_opacity.nrrd").data)
    assert np.array_equal(data[..., 1], read_volume(tmp_path / "o_red.nrrd").data)


def test_uint8_scales_unit_range(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd", "--dtype", "uint8")
    assert res.code == 0, res.stderr
    o = read_volume(tmp_path / "o_opacity.nrrd").data
    assert o.dtype == np.uint8 and set(np.unique(o)) == {0, 204}  # 0.8 * 255


def test_grid_overrides(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    assert run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "a_{field}.nrrd",
               "--shape", "20", "11", "12").code == 0
    assert read_volume(tmp_path / "a_opacity.nrrd").shape_xyz == (20, 11, 12)
    assert run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "b_{field}.nrrd",
               "--spacing", "0.25").code == 0
    assert np.allclose(read_volume(tmp_path / "b_opacity.nrrd").spacing, 0.25)
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "c_{field}.nrrd",
              "--spacing", "0.25", "--shape", "4", "4", "4")
    assert res.code == 2


def test_methods_agree_on_the_command_line(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    assert run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "v_{field}.nrrd").code == 0
    assert run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "d_{field}.nrrd",
               "--method", "direct").code == 0
    v = read_volume(tmp_path / "v_opacity.nrrd").data
    d = read_volume(tmp_path / "d_opacity.nrrd").data
    assert np.count_nonzero(v != d) <= 0.01 * np.count_nonzero(v)


@pytest.mark.parametrize("pattern, multi, words", [
    ("o.nrrd", False, "put {field}"),
    ("o_{field}.nrrd", True, "drop {field}"),
    ("o.tif", True, ".nrrd or .nhdr"),
])
def test_output_pattern_is_validated(tmp_path, run, pattern, multi, words):
    (tmp_path / "s.yaml").write_text(GOOD)
    args = ["sweep", tmp_path / "s.yaml", "-o", tmp_path / pattern] + (["--multi"] if multi else [])
    res = run(*args)
    assert res.code == 2 and words in res.stderr
    assert list(tmp_path.iterdir()) == [tmp_path / "s.yaml"]


def test_output_folder_checked_before_work(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "missing" / "o_{field}.nrrd")
    assert res.code == 1 and "does not exist" in res.stderr


def test_render_writes_png(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd", "--render",
              tmp_path / "r.png", "--render-size", "64x48", "--view", "0,0")
    assert res.code == 0, res.stderr
    img = read_image(tmp_path / "r.png")
    assert img.shape == (48, 64, 3) and img.max() > 0.3 and img[0, 0].max() == 0


def test_bad_view_is_a_usage_error(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD)
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd", "--render",
              tmp_path / "r.png", "--view", "sideways")
    assert res.code == 2 and "view" in res.stderr
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd", "--render",
              tmp_path / "r.png", "--render-size", "64 48")
    assert res.code == 2 and "--render-size" in res.stderr and "WIDTHxHEIGHT" in res.stderr
    assert not list(tmp_path.glob("o_*")) and not (tmp_path / "r.png").exists()


BAD = [
    # (spec text, key in the message, line, words)
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [0, 0, 5]}\n"
     "up: [0, 0, 1]\n", "up", 5, "collinear"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory: []\n", "trajectory", 3, "at least one segment"),
    ("version: 1\nfields:\n  opacity: {image: nothere.png}\n"
     "trajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n", "fields.opacity.image", 3,
     "does not exist"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
     "scale: {expr: 'grow(u)'}\n", "scale.expr", 5, "unknown function 'grow'"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
     "scale: {expr: 'u.__class__'}\n", "scale.expr", 5, "attribute access"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
     "scale:\n  expr: \"__import__('os').system('touch x')\"\n", "scale.expr", 6,
     "attribute access"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
     "scale: {expr: 'eval(u)'}\n", "scale.expr", 5, "unknown function 'eval'"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
     "combine: {opacity: xor}\n", "combine", 5, ""),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
     "combine: {colour: union}\n", "combine.colour", 5, "no field named 'colour'"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [0, 0, 0]}\n",
     "trajectory[0].line", 4, "two different points"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - spiral: {turns: 3}\n",
     "trajectory[0]", 4, ""),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
     "scale: {keyframes: [[0, 1], [1, -1]]}\n", "scale", 5, "positive"),
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
     "up: binormal\n", "up", 5, "binormal is undefined"),
    # (found when the sweep ran: no line, exit 1)
    ("version: 1\nfields: {opacity: 1}\ntrajectory:\n"
     "  - polyline: {points: [[0, 0, 0], [10, 0, 0], [0, 0, 0]]}\n",
     "trajectory[0].polyline.points[1]", 4, "turns back on itself (180 degrees)"),
]


@pytest.mark.parametrize("text, key, line, words", BAD)
def test_bad_specs_exit_2_with_key_and_line(tmp_path, run, text, key, line, words):
    spec = tmp_path / "bad.yaml"
    spec.write_text(text)
    res = run("sweep", spec, "-o", tmp_path / "o_{field}.nrrd", "--render", tmp_path / "r.png")
    assert res.code == 2, res.stderr
    assert f"bad.yaml:{line}: {key}" in res.stderr and words in res.stderr
    assert res.stderr.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]  # nothing written
    assert not (Path.cwd() / "x").exists()


def test_bottle_is_a_solid_of_revolution(spec_dir, tmp_path, run):
    res = run("sweep", spec_dir / "sweep-bottle.yaml", "-o", tmp_path / "o_{field}.nrrd",
              "--spacing", "0.4")
    assert res.code == 0, res.stderr
    o = read_volume(tmp_path / "o_opacity.nrrd")
    z0 = o.data.shape[0] // 3
    sl = o.data[z0]
    # rotating the slice by 90 degrees about the axis (the grid is centred on it) keeps it
    assert np.abs(sl - np.rot90(sl)).mean() < 0.02 * sl.mean()
    assert o.data.sum() > 0


def test_ring_of_fire_follows_the_flame_frames(spec_dir):
    """f(u) = 255 u / 2 pi picks the frames: the field at angle u is frame f(u)'s."""
    from volwarp_cli.spec.loader import load_spec
    from volwarp_cli.sweep.model import parse_sweep_spec

    spec = parse_sweep_spec(load_spec(spec_dir / "sweep-ring-of-fire.yaml", "sweep"))
    t = spec.root.templates["opacity"]
    seg = spec.root.segments[0]
    assert t.n_slices == 256
    s = np.array([0.0, 0.25, 0.5, 1.0])
    assert np.allclose(t.slice_coords(seg, s), 255 * s)


def test_relative_spec_path_with_frame_glob(tmp_path, run, monkeypatch):
    (tmp_path / "t").mkdir()
    from volwarp_cli.io.images import write_image
    for k in range(3):
        write_image(tmp_path / "t" / f"f{k}.tif", np.full((2, 2, 1), float(k), dtype=np.float32))
    (tmp_path / "s.yaml").write_text(GOOD.replace("red: 0.25", "red: {frames: 't/f*.tif'}"))
    monkeypatch.chdir(tmp_path.parent)
    res = run("sweep", Path(tmp_path.name) / "s.yaml", "-o", Path(tmp_path.name) / "o_{field}.nrrd")
    assert res.code == 0, res.stderr
    assert 1.9 < read_volume(tmp_path / "o_red.nrrd").data.max() <= 2.0  # last frame at u = 1


def test_an_output_the_frames_glob_matches_is_refused(tmp_path, run):
    """--render t/f3.tif beside frames 't/f*.tif' was written, and the next run of the same
    command read it as a fourth frame (a review: 67.4 then 54.9 mm^3). An output an input
    glob matches is refused before any work; a name beside it that it does not match is
    written."""
    (tmp_path / "t").mkdir()
    from volwarp_cli.io.images import write_image
    for k in range(3):
        write_image(tmp_path / "t" / f"f{k}.tif", np.full((2, 2, 1), float(k), dtype=np.float32))
    (tmp_path / "s.yaml").write_text(GOOD.replace("red: 0.25", "red: {frames: 't/f*.tif'}"))
    before = sorted(p.name for p in (tmp_path / "t").iterdir())
    for option, name in (("--render", "f3.tif"), ("-o", "f_{field}.tif")):
        args = ["-o", tmp_path / "o_{field}.nrrd"] if option == "--render" else []
        res = run("sweep", tmp_path / "s.yaml", *args, option, tmp_path / "t" / name)
        assert res.code == 2 and "matches the input pattern" in res.stderr, res.stderr
        assert sorted(p.name for p in (tmp_path / "t").iterdir()) == before
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd", "--render",
              tmp_path / "t" / "g3.png")
    assert res.code == 0, res.stderr
    (tmp_path / "t" / "sub").mkdir()  # (a folder below: the glob's * does not reach it)
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd", "--render",
              tmp_path / "t" / "sub" / "f9.tif")
    assert res.code == 0, res.stderr


def test_render_needs_opacity(tmp_path, run):
    (tmp_path / "s.yaml").write_text(GOOD.replace("opacity: {value: 0.8}", "density: 0.8"))
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd",
              "--render", tmp_path / "r.png")
    assert res.code == 2 and "opacity" in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.yaml"]


@pytest.mark.examples
def test_example_makefile_pipeline(tmp_path):
    """examples/sweep-at: templates -> sweep -> PNG, through make, at a coarse grid."""
    import subprocess
    import sys

    if shutil.which("make") is None:
        pytest.fail("make is not installed")
    work = tmp_path / "sweep-at"
    shutil.copytree(ROOT / "examples" / "sweep-at", work,
                    ignore=shutil.ignore_patterns("out", "templates"))
    bindir = Path(sys.executable).parent
    res = subprocess.run(
        ["make", "-C", str(work), "out/at-bezier.png", f"SPECS={ROOT / 'specs'}",
         f"VOLWARP={bindir / 'volwarp'}", f"PYTHON={sys.executable}", "GRID=--spacing 0.8"],
        capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    img = read_image(work / "out" / "at-bezier.png")
    assert img.shape == (512, 512, 3) and img.max() > 0.3
    assert read_volume(work / "out" / "at-bezier_geometry.nrrd").data.max() > 0.5


def test_render_with_part_of_a_colour_says_it_is_white(tmp_path, run):
    """Red and green without blue rendered a white picture without a word."""
    (tmp_path / "s.yaml").write_text(GOOD.replace("  red: 0.25\n", "  red: 0.25\n  green: 1\n"))
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o_{field}.nrrd", "--render",
              tmp_path / "r.png")
    assert res.code == 0, res.stderr
    assert "has red, green but no blue: rendered in white" in res.stderr
    img = read_image(tmp_path / "r.png")
    assert np.allclose(img[..., 0], img[..., 1]) and np.allclose(img[..., 1], img[..., 2])
