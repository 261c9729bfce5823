"""A run that writes fewer numbered files than an earlier one says which files are not its own.

`--frames-to 'f_{frame:02d}.nrrd'` with 6 frames, then with 3: f_03..f_05 stay
(they may be a user's), and a glob of the pattern mixed the two runs without a
word. Each numbered pattern (warp frames, a morph's frames, mesh --labels) now
names the files it matches that this run did not write, once its outputs are in
place; nothing is removed.
"""

from __future__ import annotations

import numpy as np
from conftest import ball

from volwarp_cli.io import write_volume
from volwarp_cli.io.inputs import earlier_pattern_files
from volwarp_cli.volume import Volume

SPEC = """version: 1
units: voxel
capture: {{lattice: 5}}
steps:
  - move:
      - {{index: [2, 2, 2], by: [1.0, 0.5, 0.0]}}
    frames: {frames}
"""


def _files(tmp_path, prefix):
    return sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(prefix))


def test_warp_frames_of_an_earlier_longer_run_are_named_not_removed(run, tmp_path):
    src = tmp_path / "in.nrrd"
    write_volume(Volume(ball(20).astype(np.float32)), src)
    spec = tmp_path / "w.yaml"
    pattern = str(tmp_path / "f_{frame:02d}.nrrd")
    spec.write_text(SPEC.format(frames=5))
    first = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--frames-to", pattern)
    assert first.code == 0 and "not this run's" not in first.stderr
    assert _files(tmp_path, "f_") == [f"f_{i:02d}.nrrd" for i in range(6)]
    spec.write_text(SPEC.format(frames=2))
    second = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--frames-to",
                 pattern)
    assert second.code == 0, second.stderr
    lines = [line for line in second.stderr.splitlines() if "not this run's" in line]
    assert len(lines) == 1 and "--frames-to" in lines[0]
    assert "f_03.nrrd, f_04.nrrd, f_05.nrrd match the pattern" in lines[0]
    assert "f_02.nrrd" not in lines[0]  # (this run's own last frame)
    assert _files(tmp_path, "f_") == [f"f_{i:02d}.nrrd" for i in range(6)]  # nothing removed
    third = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--frames-to",
                pattern, "-q")
    assert third.code == 0 and third.stderr == ""  # (-q: errors only)


def test_a_morphs_frames_and_a_label_meshes_pattern_are_checked_too(run, tmp_path):
    a, b = tmp_path / "a.nrrd", tmp_path / "b.nrrd"
    write_volume(Volume(ball(20, 5).astype(np.float32)), a)
    write_volume(Volume(ball(20, 7).astype(np.float32)), b)
    out = str(tmp_path / "m_{i}.nrrd")
    for frames in (5, 3):
        res = run("morph", a, b, "--iso", "0.5", "--frames", str(frames), "-o", out)
        assert res.code == 0, res.stderr
    assert "m_3.nrrd, m_4.nrrd match the pattern" in res.stderr
    assert res.stderr.count("match the pattern") == 1  # (it was said for -o and --output)
    seg = np.zeros((20, 20, 20), np.uint8)
    seg[3:8, 3:8, 3:8], seg[10:16, 10:16, 10:16] = 1, 2
    write_volume(Volume(seg), tmp_path / "s.nrrd")
    pattern = str(tmp_path / "s_{label}.ply")
    assert run("mesh", tmp_path / "s.nrrd", "--labels", "-o", pattern).code == 0
    seg[seg == 2] = 0
    write_volume(Volume(seg), tmp_path / "s.nrrd")
    res = run("mesh", tmp_path / "s.nrrd", "--labels", "-o", pattern)
    assert res.code == 0, res.stderr
    assert "s_2.ply matches the pattern but is not this run's" in res.stderr


def test_the_match_is_the_patterns_numbers_only(tmp_path):
    """Other names beside the frames are not the pattern's: a word where the number is, a
    longer stem, another extension; a decimal time ({t:.2f}) is a number."""
    for name in ("f_01.nrrd", "f_7.nrrd", "f_-1.nrrd", "f_ab.nrrd", "f_01.nrrd.bak",
                 "ff_01.nrrd", "f_01.nii", "g_0.25.nrrd", "g_x.nrrd"):
        (tmp_path / name).write_bytes(b"")
    assert earlier_pattern_files(str(tmp_path / "f_{frame:02d}.nrrd"),
                                 [tmp_path / "f_01.nrrd"]) == ["f_-1.nrrd", "f_7.nrrd"]
    assert earlier_pattern_files(str(tmp_path / "g_{t:.2f}.nrrd"), []) == ["g_0.25.nrrd"]
    assert earlier_pattern_files(str(tmp_path / "{i}" / "f.nrrd"), []) == []
