"""Issue 28, item 6: the last failures of a hostile test run.

A morph onto a 10^15-voxel grid ran until killed (it is refused at once, with the
sizes, as sweep refuses its grid); the expression checker's grammar; an infinite
sample made `mesh` say "isosurface level must be finite, got inf" (no file, no
cause), or with --iso write a mesh of NaN vertices with exit 0.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

DATA = Path(__file__).parent / "data"
BALL = DATA / "ball_30_uint8.nrrd"
VOLWARP = Path(sys.executable).with_name("volwarp")
HUGE = "100000x100000x100000"


def volwarp(*args, cwd=None, timeout=60):
    """The command as a user runs it, in its own process: a hang fails here, not forever."""
    t0 = time.monotonic()
    res = subprocess.run([str(VOLWARP), *map(str, args)], capture_output=True, text=True,
                         cwd=cwd, timeout=timeout)
    return res, time.monotonic() - t0


def _morph_spec(tmp_path, body: str) -> Path:
    spec = tmp_path / "huge.yaml"
    spec.write_text(f"version: 1\nsource: {{volume: {BALL}, iso: 100}}\n"
                    f"target: {{volume: {BALL}, iso: 100}}\nframes: 2\n{body}")
    return spec


# -- a morph onto an absurd grid ---------------------------------------------------------
@pytest.mark.parametrize("mode", [[], ["--chunked"], ["--no-chunked"]])
def test_morph_onto_a_huge_explicit_grid_is_refused_at_once(tmp_path, mode):
    spec = _morph_spec(tmp_path, "grid: {origin: [0, 0, 0], spacing: 1, "
                                 "size: [100000, 100000, 100000]}\n")
    res, seconds = volwarp("morph", "--spec", spec, "-o", tmp_path / "f_{i}.nrrd", "-v", *mode)
    assert res.returncode == 1, res.stderr
    error = [line for line in res.stderr.splitlines() if "error" in line]
    assert len(error) == 1 and HUGE in error[0] and "PiB" in error[0], res.stderr
    assert "distance" not in res.stderr  # refused before any work: no field was computed
    assert seconds < 20
    assert sorted(p.name for p in tmp_path.iterdir()) == ["huge.yaml"]


@pytest.mark.parametrize("spacing, key", [("1e-300", "grid.spacing:"),
                                          ("[1, 1, 0.0]", "grid.spacing[2]:")])
def test_a_morph_grid_spacing_no_volume_keeps_is_a_spec_error(run, tmp_path, spacing, key):
    """As a too large one is: exit 2 with the key path (it was exit 1 without one)."""
    spec = _morph_spec(tmp_path, f"grid: {{origin: [0, 0, 0], spacing: {spacing}, "
                                 "size: [10, 10, 10]}\n")
    res = run("morph", "--spec", spec, "-o", tmp_path / "f_{i}.nrrd")
    assert res.code == 2 and f"huge.yaml:5: {key}" in res.stderr, res


def test_morph_aligned_far_beyond_memory_is_refused_before_its_fields(tmp_path):
    """A scale about the shape's centroid (known only from the samples): the grid's least size."""
    spec = _morph_spec(tmp_path, "align: {target: {scale: 4000}}\n")
    res, seconds = volwarp("morph", "--spec", spec, "-o", tmp_path / "f_{i}.nrrd", "-v")
    assert res.returncode == 1, res.stderr
    assert "a morph on a " in res.stderr and "grid needs" in res.stderr
    assert "distance" not in res.stderr and seconds < 20


def test_least_frame_shape_is_exact_or_a_lower_bound(tmp_path):
    from volwarp_cli.geometry import Geometry
    from volwarp_cli.io import read_volume
    from volwarp_cli.morph.grid import least_frame_shape
    from volwarp_cli.morph.pipeline import prepare
    from volwarp_cli.morph.spec import job_from_spec
    from volwarp_cli.spec.loader import load_spec

    specs = Path(__file__).parent.parent / "specs"
    for name, exact in (("morph-ball-block.yaml", False), ("morph-ball-egg-warp.yaml", False),
                        ("morph-head-brain.yaml", True)):
        job = job_from_spec(load_spec(specs / name, "morph"))
        source, target = read_volume(job.source.path), read_volume(job.target.path)
        least = least_frame_shape(job, Geometry.of(source), Geometry.of(target))
        grid = prepare(job, source, target).grid.shape_xyz
        assert all(a <= b for a, b in zip(least, grid, strict=True)), (name, least, grid)
        if exact:  # (a translation: the headers fix the grid)
            assert tuple(least) == tuple(grid), (name, least, grid)


# -- sweep: the same refusal, by blocks too -----------------------------------------------
@pytest.mark.parametrize("mode", [[], ["--chunked"]])
def test_sweep_onto_a_huge_grid_is_refused_with_its_sizes(tmp_path, mode):
    spec = tmp_path / "huge.yaml"
    spec.write_text("version: 1\ngrid: {shape: [100000, 100000, 100000], spacing: 1}\n"
                    "fields: {opacity: 1}\ntrajectory:\n  - line: {from: [0, 0, 0], to: [0, 0, 9]}\n"
                    "scale: [3, 3]\n")
    res, seconds = volwarp("sweep", spec, "-o", tmp_path / "o_{field}.nrrd", *mode)
    assert res.returncode == 1, res.stderr
    assert res.stderr.count("\n") == 1 and HUGE in res.stderr, res.stderr  # ("File too large")
    assert "free" in res.stderr and seconds < 20
    assert sorted(p.name for p in tmp_path.iterdir()) == ["huge.yaml"]


# -- the expression checker's message, on the command line ----------------------------------
def test_attribute_access_message_reads_right(tmp_path, run):
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\nfields: {opacity: 1}\ntrajectory:\n"
                    "  - line: {from: [0, 0, 0], to: [0, 0, 9]}\nscale: {expr: 'u.real'}\n")
    res = run("sweep", spec, "-o", tmp_path / "o_{field}.nrrd")
    assert res.code == 2
    assert "s.yaml:5: scale.expr: attribute access is not allowed in expression 'u.real'" \
        in res.stderr


# -- infinite samples ------------------------------------------------------------------------
@pytest.fixture
def infinite(tmp_path):
    """A cube of 1s in 0s with +inf inside it and -inf just outside it: on the surface."""
    a = np.zeros((12, 12, 12), np.float32)
    a[3:9, 3:9, 3:9] = 1
    a[5, 5, 5] = np.inf
    a[2, 5, 5] = -np.inf
    path = tmp_path / "scan_inf.nrrd"
    write_volume(Volume(a), path)
    return path


@pytest.mark.parametrize("args", [[], ["--iso", "0.5"], ["--iso", "0.5", "--cap"],
                                  ["--chunked"], ["--iso", "0.5", "--chunked"]],
                         ids=["default-level", "iso", "cap", "chunked", "iso-chunked"])
def test_mesh_of_infinite_samples_names_the_file_and_the_cause(run, infinite, args):
    res = run("mesh", infinite, *args, "-o", infinite.with_suffix(".ply"), "--stats")
    assert res.code == 1, res.stdout
    assert res.stderr == (f"volwarp: error: {infinite}: the volume contains infinite samples "
                          "(-inf and +inf); an isosurface is not defined there\n")
    assert not infinite.with_suffix(".ply").exists()  # (with --iso: NaN vertices, exit 0)


def test_one_sign_of_infinity_is_named(run, tmp_path):
    a = np.zeros((8, 8, 8), np.float32)
    a[2:6, 2:6, 2:6] = 1
    a[0, 0, 0] = np.inf
    write_volume(Volume(a), tmp_path / "v.nrrd")
    res = run("mesh", tmp_path / "v.nrrd", "-o", tmp_path / "v.ply")
    assert res.code == 1 and "infinite samples (+inf);" in res.stderr, res.stderr
    assert "isosurface level must be finite" not in res.stderr


@pytest.mark.parametrize("command", [["mesh", BALL, "-o", "x.ply"],
                                     ["morph", BALL, BALL, "--frames", "2", "-o", "f{i}.nrrd"],
                                     ["distance", BALL, "--values", "intensity", "-o", "d.nrrd"]])
@pytest.mark.parametrize("level", ["inf", "nan"])
def test_a_non_finite_iso_option_is_a_usage_error(run, tmp_path, monkeypatch, command, level):
    monkeypatch.chdir(tmp_path)
    res = run(*command, "--iso", level)
    assert res.code == 2 and "'--iso'" in res.stderr and "finite" in res.stderr, res.stderr
    assert not list(tmp_path.iterdir())
