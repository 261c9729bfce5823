"""Ordinary slips that gave a useless output with exit 0 and no word, now said.

- ``warp --frames-to`` of moves that carry the whole model off the output's
  grid (millimetres meant as voxels, a displacement 10x too large): the local update
  of a lattice whose new image misses the target kept the old output, so the
  last frame and ``-o`` were the unwarped input, not the one-shot warp's
  output (which the docs say they equal byte for byte).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from volwarp_cli.bspline.capture import capture_volume
from volwarp_cli.bspline.scene import Scene
from volwarp_cli.volume import Volume

DATA = Path(__file__).parent / "data"
SCAN = DATA / "mri_t1_head_coronal_2x2x3mm.nrrd"


def translation_spec(path: Path, by_mm) -> Path:
    """A warp spec moving every control point of a 4^3 lattice by ``by_mm``: a translation."""
    moves = "\n".join(f"      - {{index: [{i}, {j}, {k}], by: [{by_mm[0]}, {by_mm[1]}, {by_mm[2]}]}}"
                      for i in range(4) for j in range(4) for k in range(4))
    path.write_text(f"version: 1\ncapture: {{lattice: 4, oversample: 1}}\nsteps:\n  - move:\n{moves}\n")
    return path


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
