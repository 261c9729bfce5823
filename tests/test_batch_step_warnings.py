"""A batch says what its steps warned: on the scan's progress line, in the summary, the reports.

Steps ran with ``-q`` and a step's stderr was kept only for a failure's last
line: an apply through a transform that moved every point 5 m off the scan
wrote all background and warned, and the batch said "2 ok" and nothing more.
The warnings are also kept in the batch's record, so a later run that skips
the step reports them again: the output made with them is still there.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import summary, volwarp  # noqa: E402

from volwarp_cli.io import write_volume  # noqa: E402
from volwarp_cli.volume import Volume  # noqa: E402

MANIFEST = """version: 1
inputs: {glob: "scans/*.nrrd"}
output_dir: out
steps:
  - {name: moved, run: apply, output: "{stem}_moved.nrrd", options: ["-t", "%s"]}
"""


def _tree(root: Path, x_mm: float) -> Path:
    (root / "scans").mkdir(parents=True)
    rng = np.random.default_rng(3)
    for name in ("near", "far"):
        write_volume(Volume(rng.random((10, 11, 12)).astype(np.float32) + 1,
                            spacing=(1.0, 1.0, 1.0)), root / "scans" / f"{name}.nrrd")
    (root / "t.tfm").write_text("#Insight Transform File V1.0\n#Transform 0\n"
                                "Transform: AffineTransform_double_3_3\n"
                                f"Parameters: 1 0 0 0 1 0 0 0 1 {x_mm} 0 0\n"
                                "FixedParameters: 0 0 0\n")
    (root / "m.yaml").write_text(MANIFEST % "t.tfm")
    return root / "m.yaml"


def test_a_step_s_warning_reaches_the_progress_summary_and_reports(tmp_path):
    manifest = _tree(tmp_path, 5000.0)
    report = tmp_path / "night.json"
    res = volwarp("batch", manifest, "--jobs", "1", "--report", report,
                  "--report", tmp_path / "night.html")
    assert res.returncode == 0, res.stderr
    assert "2 ok (2 with warnings)" in summary(res)
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("  warning: moved: ")]
    assert len(lines) == 2 and all("no output point maps inside" in ln for ln in lines)
    steps = [s for scan in json.loads(report.read_text())["scans"] for s in scan["steps"]]
    assert all(len(s["warnings"]) == 1 and "is the background" in s["warnings"][0]
               for s in steps)
    assert "no output point maps inside" in (tmp_path / "night.html").read_text()
    # a later run skips the steps and reports what their outputs were made with
    again = volwarp("batch", manifest, "--jobs", "1", "--report", report)
    assert again.returncode == 0 and "2 skipped" in summary(again)
    assert "with warnings" not in summary(again)  # (said by the run that made them)
    steps = [s for scan in json.loads(report.read_text())["scans"] for s in scan["steps"]]
    assert [s["status"] for s in steps] == ["skipped"] * 2
    assert all("is the background" in s["warnings"][0] for s in steps)


def test_a_step_without_warnings_says_nothing_more(tmp_path):
    manifest = _tree(tmp_path, 1.0)
    report = tmp_path / "night.json"
    res = volwarp("batch", manifest, "--jobs", "1", "--report", report)
    assert res.returncode == 0, res.stderr
    assert "warning" not in res.stderr and "2 ok, 0 skipped" in summary(res)
    steps = [s for scan in json.loads(report.read_text())["scans"] for s in scan["steps"]]
    assert [s["warnings"] for s in steps] == [[], []]


def test_folders_a_glob_matches_are_said_left_out(tmp_path):
    """A glob over series folders (`scans/*`) took their files only: a DICOM series or a
    store beside the scans was left out without a word, the summary one scan short."""
    manifest = _tree(tmp_path, 1.0)
    (tmp_path / "scans" / "series-7").mkdir()  # (a DICOM series folder, say)
    manifest.write_text(MANIFEST.replace("scans/*.nrrd", "scans/*") % "t.tfm")
    res = volwarp("batch", manifest, "--jobs", "1")
    assert res.returncode == 0, res.stderr
    assert "inputs.glob matches 1 folder (scans/series-7), left out" in res.stderr
    assert "2 scans, 2 ok" in summary(res)
