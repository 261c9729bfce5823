"""The command line's two silent slips: an option given twice, and an empty value.

click kept the last of two values of a one-value option (``-o a.nrrd -o
b.nrrd`` wrote b.nrrd alone, exit 0), and took an empty value as something
(``--threads=`` every core, ``--frames-to=`` no frames, an empty INPUT the
working folder). Both are usage errors now (exit 2, one line, nothing
written), for every subcommand (:class:`volwarp_cli.cli.options.Command`).
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.cli.main import COMMANDS
from volwarp_cli.cli.options import Command
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

TFM = ("#Insight Transform File V1.0\n#Transform 0\nTransform: TranslationTransform_double_3_3\n"
       "Parameters: {} 0 0\nFixedParameters:\n")


@pytest.fixture
def d(tmp_path, monkeypatch):
    """A folder with a 16^3 ball, two specs and two translations; the working folder."""
    n = 16
    z, y, x = np.mgrid[:n, :n, :n]
    ball = ((x - 7.5) ** 2 + (y - 7.2) ** 2 + (z - 7.9) ** 2 <= 25).astype(np.uint8) * 100
    write_volume(Volume(ball, spacing=(1.0, 1.0, 1.0)), tmp_path / "in.nrrd")
    for name, lattice in (("a.yaml", 5), ("b.yaml", 6)):
        (tmp_path / name).write_text(f"version: 1\nunits: voxel\ncapture: {{lattice: "
                                     f"{lattice}}}\nsteps: []\n")
    for name, dx in (("t1.tfm", 1), ("t2.tfm", 2), ("t3.tfm", 3)):
        (tmp_path / name).write_text(TFM.format(dx))
    monkeypatch.chdir(tmp_path)
    return tmp_path


#: a command line of each command, its output last: ``-o OUT``
BASE = {
    "warp": ["warp", "in.nrrd", "--spec", "a.yaml"],
    "apply": ["apply", "in.nrrd", "-t", "t1.tfm"],
    "distance": ["distance", "in.nrrd", "--iso", "50"],
    "convert": ["convert", "in.nrrd"],
    "mesh": ["mesh", "in.nrrd", "--iso", "50"],
}
EXT = {"mesh": ".ply"}


def test_every_subcommand_is_the_checking_command():
    for name in COMMANDS:
        assert isinstance(importlib.import_module(f"volwarp_cli.cli.{name}").command, Command)


@pytest.mark.parametrize("name", list(BASE))
def test_two_outputs_are_refused_and_neither_is_written(run, d, name):
    ext = EXT.get(name, ".nrrd")
    (d / f"b{ext}").write_bytes(b"existing")
    res = run(*BASE[name], "-o", f"a{ext}", "-o", f"b{ext}")
    assert res.code == 2, res
    line = res.stderr.strip()
    assert "\n" not in line and "--output" in line and f"'a{ext}'" in line and f"'b{ext}'" in line
    assert not (d / f"a{ext}").exists() and (d / f"b{ext}").read_bytes() == b"existing"


@pytest.mark.parametrize("name, twice", [
    ("warp", ["--spec", "b.yaml"]),  # (a second --spec: BASE has one)
    ("warp", ["--threads", "1", "--threads", "4"]),
    ("apply", ["--interpolation", "linear", "--interpolation=nearest"]),
    ("distance", ["--iso", "60"]),
    ("distance", ["--metric", "euclidean", "--metric", "minnorm"]),
    ("convert", ["--compress", "--no-compress"]),
    ("convert", ["--dtype", "uint8", "--dtype", "int16"]),
    ("convert", ["--memory-limit", "1G", "--memory-limit", "2G"]),
    ("mesh", ["--iso", "60"]),
    ("mesh", ["--smooth", "2", "--smooth", "5"]),
])
def test_an_option_given_twice_with_two_values_is_a_usage_error(run, d, name, twice):
    out = d / f"o{EXT.get(name, '.nrrd')}"
    res = run(*BASE[name], *twice, "-o", out)
    assert res.code == 2, res
    option = next(a for a in twice if a.startswith("--")).split("=")[0]
    line = res.stderr.strip()
    assert "\n" not in line and (option in line or "--no-compress" in line), line
    assert "twice" in line or "both given" in line, line
    assert not out.exists()


@pytest.mark.parametrize("name, once, twice", [
    ("warp", [], ["--spec", "a.yaml"]),  # (BASE has it once)
    ("warp", ["--threads", "2"], ["--threads", "2", "--threads=2"]),
    ("distance", [], ["--iso", "50"]),
    ("convert", ["--compress"], ["--compress", "--compress", "-q", "--quiet"]),
    ("mesh", [], ["--iso", "50", "-v", "-v"]),
])
def test_the_same_value_twice_runs_as_once(run, d, name, once, twice):
    ext = EXT.get(name, ".nrrd")
    assert run(*BASE[name], *once, "-o", f"once{ext}").code == 0
    res = run(*BASE[name], *twice, "-o", f"twice{ext}", "-o", f"twice{ext}")
    assert res.code == 0, res
    assert (d / f"twice{ext}").read_bytes() == (d / f"once{ext}").read_bytes()


def test_apply_takes_every_transform_still(run, d):
    """-t t1 -t t2 composes the two translations (1 and 2 mm): the one of 3 mm, and
    SimpleITK's resampling through the same composite."""
    assert run("apply", "in.nrrd", "-t", "t1.tfm", "-t", "t2.tfm", "-o", "two.nrrd").code == 0
    assert run("apply", "in.nrrd", "-t", "t3.tfm", "-o", "one.nrrd").code == 0
    two, one = read_volume(d / "two.nrrd").data, read_volume(d / "one.nrrd").data
    np.testing.assert_array_equal(two, one)
    image = sitk.ReadImage(str(d / "in.nrrd"))
    composite = sitk.CompositeTransform([sitk.ReadTransform(str(d / "t1.tfm")),
                                         sitk.ReadTransform(str(d / "t2.tfm"))])
    ref = sitk.GetArrayFromImage(sitk.Resample(image, image, composite, sitk.sitkLinear, 0))
    assert ref.any() and not np.array_equal(ref, sitk.GetArrayFromImage(image))
    np.testing.assert_array_equal(two, ref)


def test_the_environment_s_threads_are_not_a_second_value(run, d, monkeypatch):
    monkeypatch.setenv("VOLWARP_THREADS", "1")
    assert run("convert", "in.nrrd", "--threads", "2", "-o", "o.nrrd").code == 0


def test_an_empty_environment_variable_is_an_unset_one(run, d, monkeypatch):
    """(documented: README's Threads, docs/conventions.md)"""
    monkeypatch.setenv("VOLWARP_THREADS", "")
    monkeypatch.setenv("VOLWARP_MEMORY_LIMIT", "")
    assert run("convert", "in.nrrd", "-o", "o.nrrd").code == 0


@pytest.mark.parametrize("args", [
    ["convert", "in.nrrd", "--threads="],  # (was every core)
    ["convert", "in.nrrd", "--threads", " "],
    ["distance", "in.nrrd", "--iso", "50", "--scheduler="],  # (was the default)
    ["warp", "in.nrrd", "--spec", "a.yaml", "--frames-to="],  # (was: no frames)
    ["apply", "in.nrrd", "-t", "t1.tfm", "--reference="],  # (said "would overwrite")
    ["apply", "in.nrrd", "-t", "t1.tfm", "-t", ""],
    ["convert", "in.nrrd", "--series="],
    ["mesh", "in.nrrd", "--iso", "50", "--camera-to="],
])
def test_an_empty_option_value_is_a_usage_error(run, d, args):
    out = d / "sub" / ("o.ply" if args[0] == "mesh" else "o.nrrd")
    out.parent.mkdir()
    res = run(*args, "-o", out)
    assert res.code == 2, res
    assert "is empty" in res.stderr or "is blank" in res.stderr, res
    assert not list(out.parent.iterdir())


def test_an_empty_input_is_not_the_working_folder(run, tmp_path, monkeypatch):
    """`volwarp convert "$(SCAN)" -o out.nrrd`, SCAN unset, in a DICOM series' folder:
    the folder's series was converted, exit 0."""
    from test_io_dicom import write_series

    write_series(tmp_path / "series", np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6),
                 series="1.2.826.0.1.3680043.8.498.1")
    monkeypatch.chdir(tmp_path / "series")
    res = run("convert", "", "-o", tmp_path / "out.nrrd")
    assert res.code == 2 and "an empty name" in res.stderr, res
    assert not (tmp_path / "out.nrrd").exists()
    assert run("info", "").code == 2


BATCH = """version: 1
inputs: {{glob: "scans/*.nrrd"}}
output_dir: out
steps:
  - {{name: sdf, run: distance, output: "{{stem}}_sdf.nrrd", options: {options}}}
"""


def _batch(run, d, options):
    (d / "scans").mkdir(exist_ok=True)
    (d / "scans" / "s.nrrd").write_bytes((d / "in.nrrd").read_bytes())
    (d / "m.yaml").write_text(BATCH.format(options=options))
    return run("batch", "m.yaml", "--progress", "none")


def test_a_batch_step_s_own_quiet_is_not_a_second_value(run, d):
    """The batch adds -q to each step's command line: a step's -q or --quiet repeats it."""
    res = _batch(run, d, '["--iso", 50, "-q", "--quiet", "--threads", 1]')
    assert res.code == 0, res
    assert (d / "out" / "s_sdf.nrrd").exists()


def test_a_batch_step_with_an_option_twice_is_refused_before_any_work(run, d):
    res = _batch(run, d, '["--iso", 50, "--iso", 60]')
    assert res.code == 2, res
    assert "steps[0].options" in res.stderr and "--iso given twice" in res.stderr, res
    assert not (d / "out" / "s_sdf.nrrd").exists()
