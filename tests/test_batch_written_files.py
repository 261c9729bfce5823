"""What batch records and checks for a step are the files its command writes.

A review found a mesh step's ``--render {stem}.png --turntable 4`` taken for
the one file ``{stem}.png``, while the command writes ``{stem}-000.png`` ...
``{stem}-003.png`` only: a frame deleted or changed by hand was never noticed,
an old ``{stem}.png`` was recorded as the step's output (without one the step
ran every time), and a second step writing a frame was not refused. A name
still a pattern after ``{stem}`` (``--frames-to '{stem}_{{frame:03d}}.nrrd'``)
had the same blind spot: it is refused.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import volwarp  # noqa: E402
from test_batch_content import _one_error_line  # noqa: E402

DATA = Path(__file__).parent / "data"
FRAMES = [f"p01-{k:03d}.png" for k in range(4)]
#: a mesh step rendering a turntable of four frames beside its mesh
TURNTABLE = ('  - {name: surf, run: mesh, output: "{stem}.ply", options: ["--render", '
             '"{stem}.png", "--render-size", "64x48", "--turntable", "4"]}\n')


def _tree(root: Path, steps: str) -> Path:
    (root / "scans").mkdir()
    (root / "scans" / "p01.nrrd").write_bytes((DATA / "ball_30_uint8.nrrd").read_bytes())
    (root / "m.yaml").write_text('version: 1\ninputs: {glob: "scans/*.nrrd"}\n'
                                 f"output_dir: out\nsteps:\n{steps}")
    return root / "m.yaml"


def _summary(manifest: Path, *options) -> str:
    res = volwarp("batch", manifest, *options)
    assert res.returncode == 0, res.stderr
    return [line for line in res.stderr.splitlines() if line.startswith("volwarp batch:")][0]


def _recorded(root: Path) -> list[str]:
    state = json.loads((root / "out" / ".volwarp-batch" / "state.json").read_text())
    return sorted(state["outputs"])


RAN = "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
SKIPPED = "volwarp batch: 1 scan, 0 ok, 1 skipped, 0 failed"


@pytest.mark.parametrize("how", ["deleted", "changed"])
def test_a_turntable_frame_deleted_or_changed_redoes_the_step(tmp_path, how):
    manifest = _tree(tmp_path, TURNTABLE)
    out = tmp_path / "out"
    out.mkdir()  # (as the review's run found it: a render without --turntable before)
    (out / "p01.png").write_bytes(b"an earlier run's render")
    assert _summary(manifest) == RAN
    made = {name: (out / name).read_bytes() for name in FRAMES}
    assert _summary(manifest) == SKIPPED  # (recorded: not redone every run)
    if how == "deleted":
        (out / FRAMES[2]).unlink()
    else:
        (out / FRAMES[1]).write_bytes(b"garbage")
    assert _summary(manifest) == RAN
    assert {name: (out / name).read_bytes() for name in FRAMES} == made  # restored
    assert _summary(manifest) == SKIPPED


def test_the_recorded_outputs_are_the_frames_not_a_stale_render(tmp_path):
    """An old p01.png (a render without --turntable) is not this step's output."""
    manifest = _tree(tmp_path, TURNTABLE)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "p01.png").write_bytes(b"an earlier run's render")
    assert _summary(manifest, "--report-json", tmp_path / "run.json") == RAN
    assert _recorded(tmp_path) == sorted(["p01.ply", *FRAMES])
    (step,) = json.loads((tmp_path / "run.json").read_text())["scans"][0]["steps"]
    assert [Path(p).name for p in step["outputs"]] == ["p01.ply", *FRAMES]
    (tmp_path / "out" / "p01.png").unlink()  # (not the step's: nothing to redo)
    assert _summary(manifest) == SKIPPED


def test_a_second_step_writing_a_frame_is_refused(tmp_path):
    manifest = _tree(tmp_path, TURNTABLE + (
        '  - {name: again, run: mesh, output: "{stem}_2.ply", options: ["--render", '
        '"{stem}-001.png"]}\n'))
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    assert re.search(r"m\.yaml:6: steps\[1\]\.options: \S*p01-001\.png is also written by "
                     r"step 'surf'", _one_error_line(res)), res.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("step, key", [
    ('{name: w, run: warp, spec: warp.yaml, output: "{stem}_w.nrrd", '
     'options: ["--frames-to", "{stem}_{{frame:03d}}.nrrd"]}', r"steps\[0\]\.options"),
    ('{name: m, run: mesh, output: "{stem}_{{label}}.ply", options: ["--labels"]}',
     r"steps\[0\]\.output"),
])
def test_an_output_still_a_pattern_is_refused(tmp_path, step, key):
    """A file per frame or label: batch could neither record nor check them."""
    manifest = _tree(tmp_path, f"  - {step}\n")
    (tmp_path / "warp.yaml").write_text(
        "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\nsteps:\n"
        "  - move:\n      - {index: [2, 2, 2], by: [1.0, 0.5, 0.0]}\n")
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    assert re.search(key + r": (--frames-to|-o) \{stem\}_\{\{(frame:03d|label)\}\}\.(nrrd|ply): "
                     r"a pattern, which the step fills per frame or label",
                     _one_error_line(res)), res.stderr
    assert not (tmp_path / "out").exists()


def test_braces_in_names_are_names(tmp_path):
    """The pattern check looks at the options that take patterns, their placeholders
    filled: a scan, a folder or an output folder with braces in its name (a {GUID}
    folder), or a convert output with escaped braces, was refused as "a pattern"."""
    root = tmp_path / "run_{1}"
    root.mkdir()
    (root / "scans").mkdir()
    (root / "scans" / "{GUID-1}.nrrd").write_bytes((DATA / "ball_30_uint8.nrrd").read_bytes())
    (root / "m.yaml").write_text(
        'version: 1\ninputs: {glob: "scans/*.nrrd"}\noutput_dir: "out_{x}"\nsteps:\n'
        '  - {name: c, run: convert, output: "{stem}_{{y}}.nii"}\n')
    res = volwarp("batch", root / "m.yaml")
    assert res.returncode == 0, res.stderr
    assert (root / "out_{x}" / "{GUID-1}_{y}.nii").exists()
