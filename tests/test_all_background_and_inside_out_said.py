"""Ordinary slips that gave a useless output with exit 0 and no word, now said.

- ``warp``: a spec whose moves carry the whole model off the output's grid
  (millimetres meant as voxels, a displacement 10x too large) wrote every
  voxel the background. With ``--frames-to`` it was worse: the local update
  of a lattice whose new image misses the target kept the old output, so the
  last frame and ``-o`` were the unwarped input, not the one-shot warp's
  output (which the docs say they equal byte for byte).
- ``morph`` of shapes that do not overlap (or one beside the frame grid):
  empty frames, unsaid unless meshed.
- ``mesh`` of volwarp's own distance field with the default ``--inside
  above``: its outside, wound inwards; ``--iso`` at the samples' largest
  value: a surface through the centres of the top samples (a 0/1 mask at
  ``--iso 1``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.bspline.capture import capture_volume
from volwarp_cli.bspline.scene import Scene
from volwarp_cli.io import read_volume
from volwarp_cli.volume import Volume

DATA = Path(__file__).parent / "data"
SCAN = DATA / "mri_t1_head_coronal_2x2x3mm.nrrd"


def translation_spec(path: Path, by_mm) -> Path:
    """A warp spec moving every control point of a 4^3 lattice by ``by_mm``: a translation."""
    moves = "\n".join(f"      - {{index: [{i}, {j}, {k}], by: [{by_mm[0]}, {by_mm[1]}, {by_mm[2]}]}}"
                      for i in range(4) for j in range(4) for k in range(4))
    path.write_text(f"version: 1\ncapture: {{lattice: 4, oversample: 1}}\nsteps:\n  - move:\n{moves}\n")
    return path


WARP_WORDS = "off the output's grid"


@pytest.mark.parametrize("how", [[], ["--frames-to", "f_{frame}.nrrd"],
                                 ["--chunked", "--block", "16"]])
def test_a_warp_that_moves_the_whole_model_off_the_grid_is_said(tmp_path, run, how,
                                                                 monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "o.nrrd"
    res = run("warp", SCAN, "--spec", translation_spec(tmp_path / "w.yaml", (0, 0, 5000)),
              "-o", out, *how)
    assert res.code == 0, res.stderr
    assert not read_volume(out).data.any()  # (the border's median: 0)
    assert res.stderr.count(WARP_WORDS) == 1 and "warning" in res.stderr


def test_a_warp_that_keeps_part_of_the_model_says_nothing(tmp_path, run):
    out = tmp_path / "o.nrrd"
    res = run("warp", SCAN, "--spec", translation_spec(tmp_path / "w.yaml", (60, 0, 0)),
              "-o", out)
    assert res.code == 0, res.stderr
    assert read_volume(out).data.any() and WARP_WORDS not in res.stderr
    np.testing.assert_array_equal(read_volume(out).data.shape, read_volume(SCAN).data.shape)


def test_a_local_update_that_carries_the_model_off_the_target_clears_it(local_updates):
    """The update equals a full recomputation (all background), whichever local way runs."""
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (14, 16, 18)], indexing="ij")
    data = (100.0 * np.exp(-(x * x + y * y + z * z) / 0.4)).astype(np.float32)
    cap = capture_volume(Volume(data), lattice=(6, 6, 6), oversample=1)
    scene = Scene(cap.domain, cap.grid, cap.dq, 0, update=local_updates)
    scene.compute()
    dq = cap.dq + np.array([0.0, 0.0, 500.0])  # every point 500 voxels along z
    scene.set_lattice(dq)
    full = Scene(cap.domain, cap.grid, dq, 0, update=local_updates).compute()
    assert not full.any()
    np.testing.assert_array_equal(scene.out, full)


def test_frames_of_a_warp_off_the_grid_end_as_the_one_shot_warp(tmp_path, run, monkeypatch):
    monkeypatch.chdir(tmp_path)
    spec = translation_spec(tmp_path / "w.yaml", (300, 0, 0))
    assert run("warp", SCAN, "--spec", spec, "-o", "once.nrrd").code == 0
    res = run("warp", SCAN, "--spec", spec, "-o", "framed.nrrd", "--frames-to", "f_{frame}.nrrd")
    assert res.code == 0, res.stderr
    assert (tmp_path / "once.nrrd").read_bytes() == (tmp_path / "framed.nrrd").read_bytes()
    assert (tmp_path / "f_1.nrrd").read_bytes() == (tmp_path / "framed.nrrd").read_bytes()


def balls(tmp_path: Path, centres_x, origin_x=(0.0, 0.0)) -> list[Path]:
    """0/1 balls of radius 5 voxels on 30^3 grids, one per centre (voxel x), origins given."""
    from volwarp_cli.io import write_volume

    z, y, x = np.mgrid[:30, :30, :30]
    paths = []
    for n, (cx, ox) in enumerate(zip(centres_x, origin_x, strict=True)):
        data = ((x - cx) ** 2 + (y - 15) ** 2 + (z - 15) ** 2 < 25).astype(np.uint8)
        paths.append(tmp_path / f"ball{n}.nrrd")
        write_volume(Volume(data, origin=np.array([ox, 0.0, 0.0])), paths[-1])
    return paths


MORPH_WORDS = "no voxel lies inside"


@pytest.mark.parametrize("how", [[], ["--chunked", "--block", "16"]])
def test_morph_frames_whose_shape_vanishes_are_said(tmp_path, run, how):
    """Two balls 15 voxels apart (radius 5): the middle frame's blend is positive everywhere."""
    a, b = balls(tmp_path, (7, 22))
    res = run("morph", a, b, "--frames", "3", "-o", tmp_path / "f_{i}.nrrd", *how)
    assert res.code == 0, res.stderr
    middle = read_volume(tmp_path / "f_1.nrrd").data
    assert middle.min() > 0  # (the sum of the two fields: the shape is empty there)
    assert res.stderr.count(MORPH_WORDS) == 1 and "frame 1 (t = 0.5)" in res.stderr


def test_a_target_off_the_frame_grid_is_said(tmp_path, run):
    """--grid source with a target ball that lies beside the source's grid: frames 1, 2 empty."""
    a, b = balls(tmp_path, (7, 22), origin_x=(0.0, 20.0))
    res = run("morph", a, b, "--frames", "3", "--grid", "source", "-o", tmp_path / "f_{i}.nrrd")
    assert res.code == 0, res.stderr
    assert read_volume(tmp_path / "f_2.nrrd").data.min() > 0
    assert res.stderr.count(MORPH_WORDS) == 2 and "frame 0" not in res.stderr


def test_overlapping_shapes_morph_without_a_word(tmp_path, run):
    a, b = balls(tmp_path, (12, 17))
    res = run("morph", a, b, "--frames", "3", "-o", tmp_path / "f_{i}.nrrd", "--density")
    assert res.code == 0 and "warning" not in res.stderr, res.stderr


BALL = DATA / "ball_30_uint8.nrrd"
SDF_WORDS = "--inside below"


def test_a_distance_field_meshed_inside_out_is_said(tmp_path, run):
    """volwarp's own distance field, negative inside, meshed with the default --inside above:
    the surface of its outside, wound inwards (a negative enclosed volume)."""
    import json

    sdf = tmp_path / "sdf.nrrd"
    assert run("distance", BALL, "-o", sdf).code == 0
    res = run("mesh", sdf, "--iso", "0", "-o", tmp_path / "m.ply", "--json")
    assert res.code == 0, res.stderr
    assert json.loads(res.stdout)["volume"] < 0
    assert res.stderr.count(SDF_WORDS) == 1 and "warning" in res.stderr
    for inside in ("below", "above"):  # (asked for: as asked, no word)
        res = run("mesh", sdf, "--iso", "0", "--inside", inside, "-o", tmp_path / "m.ply",
                  "--json")
        assert res.code == 0 and SDF_WORDS not in res.stderr, res.stderr
    assert json.loads(res.stdout)["volume"] < 0 < json.loads(
        run("mesh", sdf, "--iso", "0", "--inside", "below", "--json").stdout)["volume"]


def test_a_morph_frame_meshed_inside_out_is_said_but_not_a_density(tmp_path, run):
    a, b = balls(tmp_path, (12, 17))
    assert run("morph", a, b, "--frames", "2", "-o", tmp_path / "s_{i}.nrrd").code == 0
    res = run("mesh", tmp_path / "s_1.nrrd", "--iso", "0", "-o", tmp_path / "m.ply")
    assert res.code == 0 and SDF_WORDS in res.stderr, res.stderr
    assert run("morph", a, b, "--frames", "2", "--density",
               "-o", tmp_path / "d_{i}.nrrd").code == 0
    res = run("mesh", tmp_path / "d_1.nrrd", "--iso", "0.5", "-o", tmp_path / "m.ply")
    assert res.code == 0 and "warning" not in res.stderr, res.stderr


def test_a_level_at_the_samples_largest_is_said(tmp_path, run):
    """--iso 200 on the 0/200 ball: the surface through the centres of its outer voxels
    (12% less volume than its voxels'); a one-voxel mask at --iso 1 became a speck."""
    import json

    res = run("mesh", BALL, "--iso", "200", "-o", tmp_path / "m.ply", "--json")
    assert res.code == 0, res.stderr
    assert json.loads(res.stdout)["volume"] < 0.9 * np.count_nonzero(read_volume(BALL).data)
    assert res.stderr.count("largest") == 1 and "--iso 100" in res.stderr
    res = run("mesh", BALL, "--iso", "100", "-o", tmp_path / "m.ply")
    assert res.code == 0 and "warning" not in res.stderr, res.stderr
