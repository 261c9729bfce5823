"""Robustness of the command line: unknown output extensions are usage errors found
before any work, `info` statistics that do not overflow, spec values that used to be
internal errors (exit 1) reported as spec errors with key path and line, and the cron
wrapper of examples/batch on a missing input folder, relative paths and every format."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import ball

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).parent / "data"
BALL = DATA / "ball_30_uint8.nrrd"


def one_error_line(res, code: int, *needles: str) -> str:
    assert res.code == code, res
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    line = lines[0]
    assert line.startswith("volwarp: error: ")
    assert "internal error" not in line and "Traceback" not in res.stderr
    for needle in needles:
        assert needle in line, (needle, line)
    return line


# --- 2. unknown output extensions: exit 2, before any input is read -----------------

MISSING = "no-such-input.nrrd"  # never read: the usage error must come first

UNKNOWN_OUTPUTS = [
    (["mesh", MISSING, "-o", "x.xyz"], "'--output'", ".ply .stl .obj .vtp .vtk"),
    (["mesh", MISSING, "--render", "x.gif"], "'--render'", ".png .jpg"),
    (["mesh", MISSING, "--render", "x"], "'--render'", ".png .jpg"),
    (["mesh", MISSING, "--render", "x.gif", "--turntable", "4"], "'--render'", ".png"),
    (["sweep", "no-such-spec.yaml", "-o", "s.nrrd", "--render", "x.gif"], "'--render'",
     ".png .jpg"),
    (["sweep", "no-such-spec.yaml", "-o", "s.xyz"], "'--output'", ".nrrd"),
    (["sweep", "no-such-spec.yaml", "-o", "s.nii", "--multi"], "'-o'", ".nrrd or .nhdr"),
    (["morph", MISSING, MISSING, "--frames", "2", "--iso", "1", "-o", "f{i}.xyz"],
     "'--output'", ".nrrd"),
    (["morph", MISSING, MISSING, "--frames", "2", "--iso", "1", "-o", "f{i}.nrrd",
      "--mesh-to", "f{i}.xyz"], "'--mesh-to'", ".ply .stl"),
    (["morph", MISSING, MISSING, "--frames", "2", "--iso", "1", "-o", "f{i}.nrrd",
      "--render-to", "f{i}.gif"], "'--render-to'", ".png .jpg"),
    (["morph", MISSING, MISSING, "--frames", "2", "--iso", "1", "-o", "f{i}.nrrd",
      "--render-to", "f{i}.png", "--sheet", "s.gif"], "'--sheet'", ".png .jpg"),
    (["morph", "--spec", "no-such-spec.yaml", "-o", "f{i}.xyz"], "'--output'", ".nrrd"),
    (["warp", MISSING, "--spec", "no-such-spec.yaml", "-o", "x.xyz"], "'--output'", ".nrrd"),
    (["warp", MISSING, "--spec", "no-such-spec.yaml", "-o", "x.nrrd",
      "--frames-to", "f{frame}.xyz"], "'--frames-to'", ".nrrd"),
    (["distance", MISSING, "-o", "x.xyz"], "'--output'", ".nrrd"),
    (["convert", MISSING, "-o", "x.xyz"], "'--output'", ".nrrd"),
    (["capture", MISSING, "-o", "x.xyz"], "'-o'", ".vwc"),
]


@pytest.mark.parametrize("args, option, known", UNKNOWN_OUTPUTS,
                         ids=[" ".join(a[:1] + a[-2:]) for a, _, _ in UNKNOWN_OUTPUTS])
def test_unknown_output_extension_is_a_usage_error_before_any_work(run, tmp_path, monkeypatch, args,
                                                                   option, known):
    monkeypatch.chdir(tmp_path)
    res = run(*args)
    one_error_line(res, 2, option, known)
    assert "no such" not in res.stderr  # the input was never looked at
    assert list(tmp_path.iterdir()) == []


def test_known_extensions_still_work(run, tmp_path):
    res = run("mesh", BALL, "--iso", 100, "-o", tmp_path / "b.STL", "--render",
              tmp_path / "b.PNG", "--size", "40x30", "-q")
    assert res.code == 0, res
    assert (tmp_path / "b.STL").is_file() and (tmp_path / "b.PNG").is_file()


# --- 3. info statistics near the largest double ---------------------------------------

def _info(run, tmp_path, data, *args):
    path = tmp_path / "v.nrrd"
    write_volume(Volume(np.asarray(data)), path)
    return run("info", path, *args)


@pytest.mark.parametrize("fill, mean", [
    ("all", 1.7e308),
    ("half", 0.0),           # +-1.7e308, as many of each: the sum overflows both ways
    ("interleaved", 0.0),
    ("three", 1.7e308 / 3),  # two positive, one negative in every three
])
def test_info_mean_does_not_overflow(run, tmp_path, fill, mean):
    a = np.full(4 * 5 * 6, 1.7e308)
    if fill == "half":
        a[:60] = -1.7e308
    elif fill == "interleaved":
        a[::2] = -1.7e308
    elif fill == "three":
        a[2::3] = -1.7e308
    data = a.reshape(4, 5, 6)
    res = _info(run, tmp_path, data, "--json")
    assert res.code == 0, res
    assert "Warning" not in res.stderr and res.stderr == ""
    d = json.loads(res.stdout)
    assert d["min"] == float(a.min()) and d["max"] == float(a.max())
    assert d["mean"] == pytest.approx(mean, rel=1e-12, abs=1e290)
    text = _info(run, tmp_path, data)
    assert text.code == 0 and "inf" not in text.stdout and "nan" not in text.stdout
    assert text.stderr == ""


def test_info_mean_with_nonfinite_and_huge_samples(run, tmp_path):
    a = np.full(24, 1.7e308)
    a[0], a[1] = np.nan, -np.inf
    res = _info(run, tmp_path, a.reshape(2, 3, 4), "--json")
    assert res.code == 0 and res.stderr == "", res
    d = json.loads(res.stdout)
    assert d["nonfinite"] == 2 and d["mean"] == pytest.approx(1.7e308)


@pytest.mark.parametrize("dtype", ["uint8", "int16", "uint32", "float32", "float64"])
def test_info_mean_of_ordinary_data_is_unchanged(run, tmp_path, dtype):
    rng = np.random.default_rng(1)
    data = (rng.random((7, 8, 9)) * 100).astype(dtype)
    d = json.loads(_info(run, tmp_path, data, "--json").stdout)
    assert d["mean"] == float(data.mean(dtype=np.float64))  # exactly today's value


# --- 4. spec values that were internal errors -----------------------------------------

def _spec(tmp_path, text: str) -> Path:
    path = tmp_path / "s.yaml"
    path.write_text(text)
    return path


def _sweep(scale: str, grid: str = "{shape: [10, 10, 10]}") -> str:
    return (f"version: 1\ngrid: {grid}\nfields:\n  opacity: 1\ntrajectory:\n"
            "  - line: {from: [0, 0, 0], to: [10, 0, 0]}\nup: [0, 0, 1]\n"
            f"scale: {scale}\n")


@pytest.mark.parametrize("scale, key, line, needle", [
    ("{expr: '" + "1" * 400 + "'}", "scale.expr", 8, "number too large"),
    ("{expr: '" + "1" * 400 + " * u + 1'}", "scale.expr", 8, "number too large"),
    ("{expr: ['1', '" + "9" * 400 + "']}", "scale.expr[1]", 8, "number too large"),
    ("1e300", "scale", 8, "too large"),
])
def test_sweep_spec_huge_numbers_are_spec_errors(run, tmp_path, scale, key, line, needle):
    spec = _spec(tmp_path, _sweep(scale))
    res = run("sweep", spec, "-o", tmp_path / "o.nrrd", "-q")
    one_error_line(res, 2, f"{spec}:{line}: {key}: ", needle)
    assert not (tmp_path / "o.nrrd").exists()


@pytest.mark.parametrize("grid, key", [
    ("{spacing: 1.0e-300}", "grid.spacing"),
    ("{spacing: 1.0e+300}", "grid.spacing"),
    ("{spacing: 0.5, margin: 1.0e+300}", "grid.margin"),
])
def test_sweep_spec_absurd_grids_are_spec_errors(run, tmp_path, grid, key):
    spec = _spec(tmp_path, _sweep("[4, 4]", grid))
    res = run("sweep", spec, "-o", tmp_path / "o.nrrd", "-q")
    one_error_line(res, 2, f"{spec}:2: {key}: ")
    assert res.stderr.count("\n") == 1  # no RuntimeWarning either


def _morph(extra: str) -> str:
    return (f"version: 1\nsource: {{volume: {BALL}, iso: 100}}\n"
            f"target: {{volume: {BALL}, iso: 100}}\nframes: 2\n{extra}")


@pytest.mark.parametrize("extra, key, line", [
    ("align:\n  target: {scale: 1.0e+300}\n", "align.target.scale", 6),
    ("align:\n  target: {scale: [1.0e+300, 1, 1]}\n", "align.target.scale[0]", 6),
    ("align:\n  target: {scale: 1.0e-300}\n", "align.target.scale", 6),
    ("align:\n  target: {translate: [1.0e+300, 0, 0]}\n", "align.target.translate[0]", 6),
    ("align:\n  target:\n    matrix: [[1.0e+300, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], "
     "[0, 0, 0, 1]]\n", "align.target.matrix[0][0]", 7),
    ("grid: {origin: [0, 0, 0], spacing: 1, size: [10, 10, 10],\n"
     "       direction: [[1, 0, 0], [1, 0, 0], [0, 0, 1]]}\n", "grid.direction", 6),
    ("grid: {origin: [0, 0, 0], spacing: 1, size: [10, 10, 10],\n"
     "       direction: [[0, 0, 0], [0, 0, 0], [0, 0, 0]]}\n", "grid.direction", 6),
    ("grid: {origin: [0, 0, 0], spacing: 1.0e+300, size: [10, 10, 10]}\n", "grid.spacing", 5),
    ("grid: {origin: [1.0e+300, 0, 0], spacing: 1, size: [10, 10, 10]}\n", "grid.origin[0]",
     5),
    ("align:\n  target: {scale: 1.1}\nmargin: 1.0e+300\n", "margin", 7),
    ("warp:\n  pairs:\n    - [[1.0e+300, 0, 0], [1, 1, 1]]\n", "warp.pairs[0][0][0]", 7),
])
def test_morph_spec_bad_geometry_is_a_spec_error(run, tmp_path, extra, key, line):
    spec = _spec(tmp_path, _morph(extra))
    res = run("morph", "--spec", spec, "-o", tmp_path / "f{i}.nrrd", "-q")
    one_error_line(res, 2, f"{spec}:{line}: {key}: ")
    assert not list(tmp_path.glob("f*.nrrd"))


def test_expression_with_a_huge_integer_is_a_spec_error_in_the_core():
    from volwarp_cli.errors import SpecError
    from volwarp_cli.spec.functions import parse_function

    with pytest.raises(SpecError, match="number too large"):
        parse_function({"expr": "1" * 400}, ("scale",))
    f = parse_function({"expr": "1" * 300}, ("scale",))  # 1e299: a double
    assert f(0.5)[0] == pytest.approx(float("1" * 300))


# --- 5. examples/batch/volwarp-batch.sh -----------------------------------------------

BIN = Path(sys.executable).parent


def _batch(folder: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("IN", None)
    env.pop("OUT", None)
    return subprocess.run(["bash", str(folder / "volwarp-batch.sh"), "-C", str(folder),
                           f"VOLWARP={BIN / 'volwarp'}", f"PYTHON={sys.executable}", *args],
                          capture_output=True, text=True, timeout=300, env=env, cwd=cwd)


@pytest.fixture
def batch_dir(tmp_path):
    if shutil.which("make") is None or shutil.which("flock") is None:
        pytest.fail("make and flock are needed (the README's install provides them)")
    work = tmp_path / "batch"
    shutil.copytree(ROOT / "examples" / "batch", work,
                    ignore=shutil.ignore_patterns("scans", "processed", "logs", ".batch.lock"))
    return work


@pytest.mark.examples
def test_batch_missing_input_folder_fails(batch_dir, tmp_path):
    res = _batch(batch_dir, "IN=not-mounted", "OUT=out", cwd=tmp_path)
    assert res.returncode == 1, res.stderr
    assert res.stdout.strip() == (f"volwarp-batch: input folder {tmp_path}/not-mounted does "
                                  "not exist or is not a folder (not mounted?): 0 scans, "
                                  "nothing done")
    assert not (tmp_path / "out").exists() and not (batch_dir / "processed").exists()
    assert "not-mounted" in (batch_dir / "logs" / "batch.log").read_text()


@pytest.mark.examples
def test_batch_empty_input_folder_fails(batch_dir, tmp_path):
    (tmp_path / "mnt").mkdir()  # a mount point with nothing mounted on it
    res = _batch(batch_dir, "IN=mnt", cwd=tmp_path)
    assert res.returncode == 1, res.stderr
    assert "no scan found" in res.stdout and str(tmp_path / "mnt") in res.stdout


@pytest.mark.examples
def test_batch_relative_paths_are_the_callers_and_every_format_is_read(batch_dir, tmp_path):
    scans = tmp_path / "incoming"
    (scans / "site").mkdir(parents=True)
    vol = Volume((ball(24, dtype=np.uint8) * 120), spacing=(2.0, 2.0, 2.0))
    exts = ["nrrd", "nhdr", "nii", "nii.gz", "mha", "mhd", "tif", "tiff"]
    for ext in exts:
        write_volume(vol, scans / "site" / f"s_{ext.replace('.', '_')}.{ext}")
    # a scan folder next to the script with the same name must not be the one read
    (batch_dir / "incoming").mkdir()
    res = _batch(batch_dir, "IN=incoming", "OUT=results", "SIZE=60x40",
                 cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip() == "volwarp-batch: 8 scans, 8 ok, 0 failed"
    for ext in exts:
        stem = f"s_{ext.replace('.', '_')}"
        for out in ("nrrd", "ply", "png"):
            assert (tmp_path / "results" / "site" / f"{stem}.{out}").is_file(), (stem, out)
    assert not (batch_dir / "results").exists()


def test_numpy_warnings_never_reach_stderr(data_dir, tmp_path):
    """A handle at 1e300 overflowed numpy's norm: its RuntimeWarning (two lines of numpy
    source) came before the spec error on stderr."""
    spec = tmp_path / "s.yaml"
    spec.write_text("{version: 1, capture: {lattice: 7}, steps: [{drag: [{from: [1e300, 0, 0], "
                    "to: [0, 0, 0]}]}]}\n")
    # a process of its own: pytest would capture the warning before it reached stderr
    volwarp = Path(sys.executable).parent / "volwarp"
    res = subprocess.run([str(volwarp), "warp", str(data_dir / "ball_30_uint8.nrrd"), "--spec",
                          str(spec), "-o", str(tmp_path / "o.nrrd")], capture_output=True,
                         text=True)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "steps[0].drag[0].from" in lines[0], res.stderr


def test_a_file_of_several_volumes_asks_for_one_as_a_usage_error(run, tmp_path):
    """A 4-D NIfTI or MetaImage, a multi-component NRRD: the user must say which volume
    (--volume-index), as a DICOM folder of several series asks for --series: exit 2."""
    import nibabel as nib

    four = tmp_path / "t.nii"
    nib.save(nib.Nifti1Image(np.zeros((4, 5, 6, 3), np.float32), np.eye(4)), four)
    field = tmp_path / "f.nrrd"
    field.write_text("NRRD0004\ntype: float\ndimension: 4\nsizes: 3 4 5 6\n"
                     "kinds: vector domain domain domain\nendian: little\nencoding: raw\n"
                     "data file: f.raw\n")
    (tmp_path / "f.raw").write_bytes(np.zeros(3 * 4 * 5 * 6, "<f4").tobytes())
    for path in (four, field):
        res = run("convert", path, "-o", tmp_path / "o.nrrd")
        assert res.code == 2, (path, res.stderr)
        assert "--volume-index" in res.stderr and res.stderr.strip().count("\n") == 0
        assert run("convert", path, "-o", tmp_path / "o.nrrd", "--volume-index", "1").code == 0


def test_morph_of_a_file_of_several_volumes_says_how_to_extract_one(run, tmp_path):
    """morph has no --volume-index: a 4-D input is the input's fault (exit 1), and the
    message says how to take one volume out of it."""
    import nibabel as nib

    four = tmp_path / "v.nii.gz"
    nib.save(nib.Nifti1Image(np.zeros((8, 9, 10, 2), np.float32), np.eye(4)), four)
    res = run("morph", four, four, "--frames", "2", "--iso", "0.5", "-o", tmp_path / "f{i}.nrrd")
    assert res.code == 1 and res.stderr.strip().count("\n") == 0, res.stderr
    assert "volwarp convert IN --volume-index N" in res.stderr
