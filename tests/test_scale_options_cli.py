"""Options for work by blocks (--block, --scheduler, --workers, --threads-per-worker,
--progress jsonl) are never silently ignored: a command that ran in memory says so."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume


@pytest.fixture
def ball(tmp_path):
    z, y, x = np.mgrid[:16, :17, :18]
    data = (((x - 9) ** 2 + (y - 8) ** 2 + (z - 8) ** 2) < 36).astype(np.uint8) * 100
    path = tmp_path / "ball.nrrd"
    write_volume(Volume(data), path)
    return path


@pytest.mark.parametrize("options,named", [
    (["--block", "8"], "--block"),
    (["--scheduler", "processes"], "--scheduler"),
    (["--workers", "3", "--threads-per-worker", "2"], "--workers, --threads-per-worker"),
    (["--progress", "jsonl"], "--progress jsonl"),
])
def test_block_options_of_an_in_memory_run_are_reported(run, ball, tmp_path, options, named):
    res = run("distance", ball, "--iso", "50", "-o", tmp_path / "d.nrrd", *options)
    assert res.code == 0, res.stderr
    assert f"warning: {named} not used" in res.stderr
    assert "ran in memory" in res.stderr


def test_no_warning_when_they_were_used(run, ball, tmp_path):
    out = tmp_path / "d.nrrd"
    res = run("distance", ball, "--iso", "50", "-o", out, "--surface", "voxel", "--chunked",
              "--block", "5", "--scheduler", "synchronous")
    assert res.code == 0, res.stderr
    assert "warning" not in res.stderr
    plain = run("distance", ball, "--iso", "50", "-o", tmp_path / "plain.nrrd", "--surface",
                "voxel")
    assert plain.code == 0 and "warning" not in plain.stderr


def test_a_failed_run_prints_its_error_line_only(run, tmp_path):
    res = run("distance", tmp_path / "missing.nrrd", "--iso", "50", "-o", tmp_path / "d.nrrd",
              "--block", "8")
    assert res.code == 1
    assert res.stderr.strip().count("\n") == 0 and "error" in res.stderr


def test_no_warning_for_any_command_that_ran_by_blocks(run, ball, tmp_path):
    """Each command's block path counts as having used them."""
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\ngrid: {spacing: 0.5}\nfields:\n  opacity: {value: 0.8}\n"
                    "trajectory:\n  - line: {from: [0, 0, 0], to: [6, 1, 1]}\n"
                    "up: [0, 0, 1]\nscale: [2, 2]\n")
    warp = tmp_path / "w.yaml"
    warp.write_text("version: 1\ncapture: {lattice: 5, oversample: 1}\nsteps:\n"
                    "  - move:\n      - {index: [2, 2, 2], by: [0.5, 0, 0]}\n")
    for args in (["mesh", ball, "--iso", "50", "-o", tmp_path / "m.ply"],
                 ["sweep", spec, "-o", tmp_path / "s_{field}.nrrd"],
                 ["warp", ball, "--spec", warp, "-o", tmp_path / "w.nrrd"],
                 ["morph", ball, ball, "--frames", "2", "--iso", "50",
                  "-o", tmp_path / "f_{i}.nrrd"]):
        res = run(*args, "--chunked", "--block", "7")
        assert res.code == 0, (args[0], res.stderr)
        assert "warning" not in res.stderr, (args[0], res.stderr)


def test_mesh_by_blocks_runs_on_the_engine_and_uses_its_options(run, ball, tmp_path):
    """The mesh's blocks run on the executor's engine as every command's do: --workers and
    --progress jsonl apply (one JSON line per block task on stderr), nothing is said
    unused, and the PLY is the in-memory one byte for byte."""
    res = run("mesh", ball, "--iso", "50", "-o", tmp_path / "m.ply", "--chunked", "--block",
              "7", "--workers", "1", "--progress", "jsonl")
    assert res.code == 0, res.stderr
    assert "not used" not in res.stderr
    assert '"kind":"block"' in res.stderr
    assert run("mesh", ball, "--iso", "50", "-o", tmp_path / "whole.ply").code == 0
    whole = (tmp_path / "whole.ply").read_bytes()
    assert (tmp_path / "m.ply").read_bytes() == whole
