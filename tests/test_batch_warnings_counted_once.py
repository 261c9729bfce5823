"""Review of the batch's step warnings (fdd52c4), the slips43 merge and the NRRD axes (c33240a).

Batch: the summary's ``N ok (M with warnings)`` counted failed scans and the
warnings a skipped step's record carried (said by the run that made them); a
step killed after a warning had that warning as its error; a step's own ``-q``
silenced its warnings without a word.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import summary, volwarp  # noqa: E402

from volwarp_cli.io import write_volume  # noqa: E402
from volwarp_cli.volume import Volume  # noqa: E402

_MOVED = '  - {name: moved, run: apply, output: "{stem}_moved.nrrd", options: ["-t", "t.tfm"%s]}\n'


def _tree(root: Path, *steps: str, quiet: bool = False) -> Path:
    """One scan moved 5 m off itself by its first step (every voxel the background: a warning)."""
    (root / "scans").mkdir(parents=True)
    data = np.random.default_rng(3).random((6, 7, 8)).astype(np.float32) + 1
    write_volume(Volume(data, spacing=(1.0, 1.0, 1.0)), root / "scans" / "a.nrrd")
    (root / "t.tfm").write_text("#Insight Transform File V1.0\n#Transform 0\n"
                                "Transform: AffineTransform_double_3_3\n"
                                "Parameters: 1 0 0 0 1 0 0 0 1 5000 0 0\n"
                                "FixedParameters: 0 0 0\n")
    (root / "m.yaml").write_text('version: 1\ninputs: {glob: "scans/*.nrrd"}\noutput_dir: out\n'
                                 "steps:\n" + _MOVED % (', "-q"' if quiet else "")
                                 + "".join(steps))
    return root / "m.yaml"


def test_a_failed_scan_s_warnings_are_not_counted_among_the_ok(tmp_path):
    """'0 ok (1 with warnings), 1 failed': the warned scan failed in its next step."""
    manifest = _tree(tmp_path, '  - {name: surf, run: mesh, input: moved, output: "{stem}.ply",'
                               ' options: ["--iso", "1.2"]}\n')
    res = volwarp("batch", manifest, "--jobs", "1")
    assert res.returncode == 1, res.stderr
    assert summary(res).startswith("volwarp batch: 1 scan, 0 ok, 0 skipped, 1 failed: a (")
    assert "  warning: moved: every voxel of" in res.stderr  # (said under its failed line)


def test_a_skipped_step_s_warnings_are_not_counted_again(tmp_path):
    """A scan whose warned step is skipped and whose next step runs: counted, said again."""
    manifest = _tree(tmp_path, '  - {name: copy, run: convert, input: moved, '
                               'output: "{stem}_copy.nrrd", options: ["--compress"]}\n')
    first = volwarp("batch", manifest, "--jobs", "1")
    assert "1 ok (1 with warnings)" in summary(first), first.stderr
    manifest.write_text(manifest.read_text().replace('"--compress"', '"--no-compress"'))
    again = volwarp("batch", manifest, "--jobs", "1", "--report", tmp_path / "r.json")
    assert again.returncode == 0, again.stderr
    assert summary(again) == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    assert "warning" not in again.stderr
    assert "is the background" in (tmp_path / "r.json").read_text()  # (kept in the report)


def test_a_step_killed_after_a_warning_does_not_fail_with_that_warning(tmp_path):
    """The out-of-memory killer leaves no error line: 'killed by SIGKILL (volwarp: warning: ...)'."""
    from volwarp_cli.batch.manifest import find_scans, load_manifest
    from volwarp_cli.batch.run import ScanRunner

    manifest = load_manifest(_tree(tmp_path))
    runner = ScanRunner(manifest)
    runner._call = lambda argv: (-9, "volwarp: warning: samples clipped\n", None, {})
    step = runner.run(find_scans(manifest)[0]).steps[0]
    assert (step.status, step.error) == ("failed", "killed by SIGKILL")
    assert step.warnings == ["samples clipped"]


def test_a_step_s_own_quiet_is_said(tmp_path):
    """-q in a step's options silenced the warnings the batch reports, without a word."""
    res = volwarp("batch", _tree(tmp_path, quiet=True), "--jobs", "1")
    assert res.returncode == 0, res.stderr
    said = [ln for ln in res.stderr.splitlines() if ln.startswith("volwarp: warning:")]
    assert len(said) == 1 and "steps[0].options: -q (--quiet) hides the step's warnings" in said[0]
