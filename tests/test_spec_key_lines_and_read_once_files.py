"""Specs and spec options refused as DESIGN says: exit 2, one line naming the file, the
key and its line, nothing written (cases a hunt over the spec surface found otherwise)."""

from __future__ import annotations

import pytest

BALL_STEP = "steps:\n  - move:\n      - {index: [4, 6, 4], by: [0.0, -3.0, 0.0]}\n"


def one_line(res) -> str:
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("volwarp: error: "), res
    return res.stderr


def test_a_sweep_field_named_by_an_unquoted_yaml_boolean_is_a_spec_error(run, tmp_path):
    """``on:`` is True to YAML 1.1: the schema's name pattern passed it (a pattern checks
    strings only) and sweep stopped on an internal TypeError, exit 1."""
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\ngrid: {spacing: 0.5, margin: 1.0}\nfields:\n  opacity: 1\n"
                    "  on: 0.5\ntrajectory:\n  - line: {from: [0, 0, 0], to: [10, 0, 0]}\n"
                    "scale: [4, 4]\n")
    res = run("sweep", spec, "-o", tmp_path / "s_{field}.nrrd")
    assert res.code == 2
    assert one_line(res).startswith(f"volwarp: error: {spec}:5: fields.True: ")
    assert "quote a name" in res.stderr
    assert not list(tmp_path.glob("*.nrrd"))


@pytest.mark.parametrize("key, said", [("on", "steps[0].True"), ("~", "steps[0].None"),
                                       ("1", "steps[0][1]")])
def test_an_unknown_key_that_yaml_reads_as_no_name_is_reported_at_its_own_line(
        run, data_dir, tmp_path, key, said):
    """The line was that of the key's mapping (line 1 at the top level): the key's
    text ('on') was compared with the data's key (True)."""
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\n" + BALL_STEP + f"\n    {key}: 3\n")
    out = tmp_path / "o.nrrd"
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", out)
    assert res.code == 2
    assert one_line(res).startswith(f"volwarp: error: {spec}:6: {said}: unknown key ")
    assert not out.exists()


@pytest.mark.parametrize("folder", [True, False])
def test_a_spec_that_is_a_folder_or_empty_is_said_so_not_blamed_on_the_output(
        run, data_dir, tmp_path, monkeypatch, folder):
    """``--spec ""`` (an unset shell variable, quoted) or a folder was declared an input
    folder, and an output inside it was refused as "would overwrite the input folder"."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "o.nrrd"
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", str(tmp_path) if folder else "",
              "-o", "o.nrrd")
    assert res.code == 2
    assert "Invalid value for '--spec'" in one_line(res) and "overwrite" not in res.stderr
    assert ("is a folder" if folder else "is empty") in res.stderr
    assert not out.exists()


def test_a_batch_step_spec_that_is_a_folder_is_said_to_be_one(run, data_dir, tmp_path):
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "a.nrrd").write_bytes((data_dir / "ball_30_uint8.nrrd").read_bytes())
    manifest = tmp_path / "m.yaml"
    manifest.write_text('version: 1\ninputs: {glob: "scans/*.nrrd"}\noutput_dir: out\nsteps:\n'
                        '  - {name: w, run: warp, spec: scans, output: "{stem}.nrrd"}\n')
    res = run("batch", manifest, "--progress", "none")
    assert res.code == 2
    assert f"{manifest}:5: steps[0].spec: " in one_line(res) and "is a folder" in res.stderr
    assert not (tmp_path / "out" / "a.nrrd").exists()
