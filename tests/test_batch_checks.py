"""`volwarp batch` checks each step as its command would, before any work, from any folder.

Found by a review of the content-addressed batch: a step option naming a file
failed unless the batch was started in the manifest's folder; an output could
replace a file a step reads (or the manifest, by the report); options that do
not go together failed once per scan after the earlier steps ran; ``--help``
in a step's options printed help and exited 0; an output folder holding the
scans said "no scan matches".
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import volwarp  # noqa: E402
from test_batch_content import MANIFEST, _one_error_line, make_tree  # noqa: E402

#: one scan, through a conversion, then a mesh with a render
ONE_SCAN = """version: 1
inputs: {list: [scans/site-a/p01.nrrd], root: scans}
output_dir: out
steps:
  - {name: conv, run: convert, output: "{stem}.nrrd"}
"""


def _mesh(name: str, options: str, input_step: str = "conv") -> str:
    return (f'  - {{name: {name}, run: mesh, input: {input_step}, output: "{{stem}}_{name}.ply", '
            f"options: {options}}}\n")


def _camera(root: Path) -> Path:
    """A camera file beside the manifest, as a mesh render writes it."""
    cam = root / "cam.json"
    res = volwarp("mesh", root / "scans" / "site-a" / "p01.nrrd", "--iso", 50, "--render",
                  root / "first.png", "--camera-to", cam)
    assert res.returncode == 0, res.stderr
    return cam


def test_relative_option_file_from_another_folder(tmp_path):
    """`cd / && volwarp batch /abs/my.yaml`: the step's --camera-from is the manifest's cam.json."""
    manifest = make_tree(tmp_path, ONE_SCAN + _mesh(
        "m", '["--iso", "50", "--render", "{stem}.png", "--camera-from", "cam.json"]'))
    _camera(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    res = volwarp("batch", manifest, cwd=elsewhere)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "out" / "site-a" / "p01.png").is_file()
    assert not list(elsewhere.iterdir())


def test_step_output_over_a_file_a_step_reads(tmp_path):
    """m reads cam.json, m2 would write it: refused, naming both, cam.json untouched."""
    manifest = make_tree(tmp_path, ONE_SCAN + _mesh(
        "m", '["--iso", "50", "--render", "{stem}.png", "--camera-from", "cam.json"]') + _mesh(
        "m2", '["--iso", "50", "--render", "{stem}_2.png", "--camera-to", "cam.json"]'))
    cam = _camera(tmp_path)
    before = cam.read_bytes()
    res = volwarp("batch", manifest, cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    line = _one_error_line(res)
    assert re.search(r"manifest\.yaml:7: steps\[2\]\.options: --camera-to \S*cam\.json would "
                     r"overwrite the input \S*cam\.json; .* \(read by step 'm', steps\[1\]\)",
                     line), line
    assert cam.read_bytes() == before and not (tmp_path / "out").exists()


@pytest.mark.parametrize("report, message", [
    ("cam.json", r"--report-json \S*cam\.json would overwrite the input \S*cam\.json.*"
                 r"read by step 'm'"),
    ("manifest.yaml", r"--report-json \S*manifest\.yaml would overwrite the input "
                      r"\S*manifest\.yaml"),
    ("scans/site-a/p01.nrrd", r"--report-json \S*p01\.nrrd would overwrite the (input|scan)"),
    ("out/site-a/p01.png", r"--report-json \S*p01\.png is also written by step 'm' "
                           r"\(steps\[1\]\) for scan site-a/p01"),
])
def test_report_over_an_input_or_an_output(tmp_path, report, message):
    manifest = make_tree(tmp_path, ONE_SCAN + _mesh(
        "m", '["--iso", "50", "--render", "{stem}.png", "--camera-from", "cam.json"]'))
    cam = _camera(tmp_path)
    before = {p: p.read_bytes() for p in (cam, manifest)}
    res = volwarp("batch", manifest, "--report-json", report, cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert re.search(message, _one_error_line(res)), res.stderr
    assert {p: p.read_bytes() for p in before} == before
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("steps, message", [
    (_mesh("m", '["--iso", "50", "--render", "{stem}.png", "--camera-to", "c.json"]')
     + _mesh("m2", '["--iso", "50", "--render", "{stem}_2.png", "--camera-to", "c.json"]'),
     r"manifest\.yaml:7: steps\[2\]\.options: \S*c\.json is also written by step 'm'"),
    (_mesh("m", '["--iso", "50", "--render", "{stem}.png", "--camera-to", "{stem}.png"]'),
     r"manifest\.yaml:6: steps\[1\]\.options: --camera-to \S*p01\.png is also the step's "
     r"--render output"),
])
def test_one_file_written_twice(tmp_path, steps, message):
    res = volwarp("batch", make_tree(tmp_path, ONE_SCAN + steps))
    assert res.returncode == 2, res.stderr
    assert re.search(message, _one_error_line(res)), res.stderr
    assert not (tmp_path / "out").exists() and not (tmp_path / "c.json").exists()


def test_one_name_for_every_scan(tmp_path):
    """Two scans, --camera-to without {stem}: the second would replace the first's."""
    manifest = make_tree(tmp_path, MANIFEST + _mesh(
        "m", '["--iso", "50", "--render", "{stem}.png", "--camera-to", "c.json"]'))
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    assert re.search(r"steps\[2\]\.options: --camera-to \S*c\.json would be written by every "
                     r"scan \(site-a/p01, site-b/p02, \.\.\.\): put \{stem\} in its name",
                     _one_error_line(res)), res.stderr
    # (the step's dry run got to its read of the scan, and wrote nothing)
    assert not (tmp_path / "c.json").exists() and not (tmp_path / "out").exists()


WARP = '  - {name: w, run: warp, input: conv, spec: warp.yaml, output: "{stem}_w.nrrd", options: %s}\n'


@pytest.mark.parametrize("step, message", [
    (WARP % '["--crop", "--grid", "grow"]', r"steps\[2\]\.options: warp: --crop puts the output "
                                            r"on the input's grid"),
    (WARP % '["--labels", "--dtype", "float32"]', r"steps\[2\]\.options: warp: labels keep the "
                                                  r"label map's own integer type"),
    (WARP % '["--points-in", "pts.csv"]', r"steps\[2\]\.options: warp: --points-in and "
                                          r"--points-to go together"),
    (WARP % '["--points-in", "missing.csv", "--points-to", "{stem}.csv"]',
     r"steps\[2\]\.options: warp: \S+/missing\.csv: no such file \(the step reads it\)"),
    (_mesh("m", '["--iso", "20", "--turntable", "4", "--camera-to", "c.json"]'),
     r"steps\[2\]\.options: mesh: --turntable needs --render"),
    (_mesh("m", '["--iso", "20", "--help"]'),
     r"steps\[2\]\.options\[2\]: --help prints and ends the command instead of running it"),
    (_mesh("m", '["--iso", "20", "--stats", "--json"]'),
     r"steps\[2\]\.options\[2\]: --stats writes to the step's console, which the batch does "
     r"not keep"),
    (WARP % '["-v"]', r"steps\[2\]\.options\[0\]: -v writes to the step's console"),
    (_mesh("m", '["--iso"]'), r"steps\[2\]\.options: mesh: Option '--iso' requires an "
                              r"argument\.$"),
    (_mesh("m", '["--render", "{stem}.png", "--camera-from", "{stem}.json"]'),
     r"steps\[2\]\.options\[3\]: --camera-from '\{stem\}\.json': \{stem\} and \{relpath\} name "
     r"outputs"),
])
def test_step_usage_error_before_any_work(tmp_path, step, message):
    """Each failed once per scan (exit 1) after the conversions ran; --help exited 0."""
    (tmp_path / "pts.csv").write_text("x,y,z\n0,0,0\n")
    res = volwarp("batch", make_tree(tmp_path, MANIFEST + step))
    assert res.returncode == 2, res.stderr
    line = _one_error_line(res)
    assert re.search(r"manifest\.yaml:7: " + message, line), line
    assert "'-q'" not in line
    assert not (tmp_path / "out").exists() and not (tmp_path / "c.json").exists()


@pytest.mark.parametrize("output_dir, glob, how", [
    ("scans", "scans/**/*.n*", "is"), (".", "scans/**/*.n*", "holds")])
def test_output_folder_holding_the_scans(tmp_path, output_dir, glob, how):
    """It said: no scan matches ... (empty or not mounted?)."""
    manifest = make_tree(tmp_path, MANIFEST.replace("output_dir: out", f"output_dir: {output_dir}")
                         .replace("scans/**/*.n*", glob))
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    assert re.search(r"manifest\.yaml:3: output_dir: outputs there would be taken for scans: "
                     rf"it {how} the folder inputs\.glob searches",
                     _one_error_line(res)), res.stderr
    # a folder inside the scans' folder is left out of the glob, as before
    inside = MANIFEST.replace("output_dir: out", "output_dir: scans/out")
    manifest.write_text(inside)
    res = volwarp("batch", manifest)
    assert res.returncode == 0, res.stderr
    assert "2 scans, 2 ok" in res.stderr
    assert "left out as outputs" not in res.stderr  # (its own outputs: recorded)
    res = volwarp("batch", manifest)
    assert res.returncode == 0 and "2 skipped" in res.stderr, res.stderr
    assert "left out as outputs" not in res.stderr


def test_scans_in_the_output_folder_are_said_not_dropped_without_a_word(tmp_path):
    """An output_dir inside the scans' tree that already holds scans (`scans/site-a`):
    they were left out as outputs, the run said "1 scan" and exit 0. Files the glob
    matches there that no run of the batch recorded writing are now said."""
    manifest = make_tree(tmp_path, MANIFEST.replace("output_dir: out", "output_dir: scans/site-a"))
    scans_there = sorted((tmp_path / "scans" / "site-a").rglob("*.n*"))
    assert scans_there
    res = volwarp("batch", manifest)
    assert res.returncode == 0, res.stderr
    assert re.search(rf"inputs\.glob: {scans_there[0].name}\S* in the output folder \S*site-a "
                     r"left out as outputs, though no run of this batch recorded writing them",
                     res.stderr), res.stderr


def test_another_batchs_outputs_under_the_glob_are_not_scans(tmp_path):
    """A batch whose output folder lies under another manifest's scans: the second batch's
    `**` glob took its outputs for scans (a user-day review). Folders holding a batch's
    book (.volwarp-batch) below the glob's folder are left out, and said; a glob in a
    batch's output folder itself takes its outputs (a batch that goes on from another's)."""
    first = make_tree(tmp_path, MANIFEST.replace("output_dir: out", "output_dir: scans/out1"))
    res = volwarp("batch", first)
    assert res.returncode == 0 and "2 scans, 2 ok" in res.stderr, res.stderr
    second = tmp_path / "second.yaml"
    second.write_text(MANIFEST.replace("output_dir: out", "output_dir: out2"))
    res = volwarp("batch", second)
    assert res.returncode == 0, res.stderr
    assert "2 scans, 2 ok" in res.stderr  # (not 6: the first batch's 4 outputs)
    assert re.search(r"inputs\.glob: 4 files under \S*scans/out1, another batch's output "
                     r"folder, left out", res.stderr), res.stderr
    third = tmp_path / "third.yaml"
    third.write_text(MANIFEST.replace("output_dir: out", "output_dir: out3")
                     .replace("scans/**/*.n*", "scans/out1/**/*_f.nrrd"))
    res = volwarp("batch", third)
    assert res.returncode == 0 and "2 scans, 2 ok" in res.stderr, res.stderr


def test_dry_run_stops_at_every_reader(tmp_path):
    """In a dry run each reader's entry stops, before it opens anything."""
    from volwarp_cli.io import read_volume
    from volwarp_cli.io.lazy import open_volume_header, open_volume_lazy
    from volwarp_cli.runscope import DryRunStop, run_scope
    from volwarp_cli.warp.capture_file import open_capture_lazy, read_capture

    missing = tmp_path / "missing.nrrd"
    for read in (read_volume, open_volume_lazy, open_volume_header, read_capture,
                 open_capture_lazy):
        with run_scope() as files:
            files.dry_run = True
            with pytest.raises(DryRunStop):
                read(missing)


def test_a_report_inside_a_scans_dicom_folder_is_refused(tmp_path):
    """`--report ser/p01/run.json` was written into the scan's series folder (a step's
    output there is refused): the series' digest changed every run, so the scan was
    redone every night."""
    import numpy as np
    from test_io_dicom import write_series

    write_series(tmp_path / "ser" / "p01", np.full((3, 5, 6), 7, np.int16)
                 + np.arange(30, dtype=np.int16).reshape(5, 6))
    manifest = tmp_path / "m.yaml"
    manifest.write_text("version: 1\ninputs: {list: [ser/p01], root: ser}\noutput_dir: out\n"
                        "steps:\n  - {name: c, run: convert, output: '{stem}.nrrd'}\n")
    for option in ("--report", "--report-json"):
        res = volwarp("batch", manifest, option, tmp_path / "ser" / "p01" / "run.json")
        assert res.returncode == 2, res.stderr
        assert "input folder" in res.stderr and "the scan 'p01'" in res.stderr
        assert not (tmp_path / "ser" / "p01" / "run.json").exists()
        assert not (tmp_path / "out" / "p01.nrrd").exists()
