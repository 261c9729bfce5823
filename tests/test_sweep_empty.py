"""A sweep that reaches no voxel is said, not written silently as zeros.

Three slips gave an all-zero output with exit 0 and no word: a direction that
moves the template within its own plane (a flat set, no volume), a spec's grid
beside the sweep, and a template thinner than the voxels that passes between
their centres. The first is a spec error (it can never sweep a volume); the
others are warned once the run ends, by blocks and in worker processes too.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume

LINE_ACROSS = """\
version: 1
fields:
  opacity: 1
trajectory:
  - line: {from: [0, 0, 0], to: [10, 0, 0]}
direction: [0, 0, 1]
scale: [4, 4]
"""

ARC_IN_ITS_PLANE = """\
version: 1
fields:
  opacity: 1
trajectory:
  - arc: {center: [0, 0, 0], radius: 5, axis: [0, 0, 1], start: 0, end: 180}
direction: [0, 0, 1]
scale: [2, 2]
"""

BESIDE = """\
version: 1
grid: {shape: [10, 10, 10], origin: [100, 100, 100], spacing: 1}
fields:
  opacity: 1
trajectory:
  - line: {from: [0, 0, 0], to: [10, 0, 0]}
scale: [4, 4]
"""

THIN = """\
version: 1
grid: {spacing: 1}
fields:
  opacity: 1
trajectory:
  - line: {from: [0, 0, 0], to: [0.3, 0, 0]}
scale: [0.4, 0.4]
"""

GOOD = """\
version: 1
grid: {spacing: 0.5, margin: 3}
fields:
  opacity: 1
trajectory:
  - line: {from: [0, 0, 0], to: [6, 0, 0]}
scale: [3, 3]
"""


@pytest.mark.parametrize("spec, line", [(LINE_ACROSS, 6), (ARC_IN_ITS_PLANE, 6)])
def test_a_template_moving_in_its_own_plane_is_a_spec_error(tmp_path, run, spec, line):
    (tmp_path / "s.yaml").write_text(spec)
    out = tmp_path / "o.nrrd"
    res = run("sweep", tmp_path / "s.yaml", "-o", out)
    assert res.code == 2, res
    assert f"s.yaml:{line}: direction:" in res.stderr and "sweeps no volume" in res.stderr
    assert not out.exists()


def test_a_direction_slightly_across_the_path_still_sweeps(tmp_path, run):
    """Not flat: tilted by 0.1 rad, the thin slab it sweeps is a volume (no error)."""
    spec = LINE_ACROSS.replace("direction: [0, 0, 1]", "direction: [0.1, 0, 1]")
    (tmp_path / "s.yaml").write_text(spec + "grid: {spacing: 0.1}\n")
    out = tmp_path / "o.nrrd"
    res = run("sweep", tmp_path / "s.yaml", "-o", out)
    assert res.code == 0, res.stderr
    assert read_volume(out).data.max() == 1.0 and "warning" not in res.stderr


def test_a_template_kept_tangent_to_a_circle_is_not_flat(tmp_path, run):
    """Normals that turn sweep volume where the path is perpendicular to them: a ring.

    The direction from the circle of radius 5 to the one of radius 10 is radial: each
    template lies in the circle's tangent plane, perpendicular to the path all along it,
    yet the templates together fill a ring between radius 5 and sqrt(5^2 + 1^2).
    """
    spec = ARC_IN_ITS_PLANE.replace(
        "direction: [0, 0, 1]",
        "direction: {trajectory: [{arc: {center: [0, 0, 0], radius: 10, axis: [0, 0, 1], "
        "start: 0, end: 180}}]}\ngrid: {spacing: 0.25}")
    (tmp_path / "s.yaml").write_text(spec)
    out = tmp_path / "o.nrrd"
    res = run("sweep", tmp_path / "s.yaml", "-o", out)
    assert res.code == 0, res.stderr
    vol = read_volume(out)
    assert vol.data.sum() > 100 and "warning" not in res.stderr


@pytest.mark.parametrize("chunked", [[], ["--chunked", "--block", "4"],
                                     ["--chunked", "--block", "4", "--scheduler", "processes"]])
@pytest.mark.parametrize("spec, words", [(BESIDE, "does not meet the sweep"),
                                         (THIN, "reached no voxel centre")])
def test_an_all_zero_sweep_is_said(tmp_path, run, spec, words, chunked):
    (tmp_path / "s.yaml").write_text(spec)
    out = tmp_path / "o.nrrd"
    res = run("sweep", tmp_path / "s.yaml", "-o", out, *chunked)
    assert res.code == 0, res.stderr
    assert not read_volume(out).data.any()
    assert res.stderr.count("warning: every field of the sweep is 0") == 1, res.stderr
    assert words in res.stderr


@pytest.mark.parametrize("chunked", [[], ["--chunked", "--block", "4"],
                                     ["--chunked", "--block", "4", "--scheduler", "processes"]])
def test_a_sweep_with_samples_is_not_warned(tmp_path, run, chunked):
    """Blocks of zeros beside the sweep's blocks say nothing: any block's samples count."""
    (tmp_path / "s.yaml").write_text(GOOD)
    out = tmp_path / "o_{field}.nrrd"
    res = run("sweep", tmp_path / "s.yaml", "-o", out, *chunked)
    assert res.code == 0, res.stderr
    data = read_volume(tmp_path / "o_opacity.nrrd").data
    assert data.any() and not data[:4, :4, :4].any()  # (a block of zeros among them)
    assert "warning" not in res.stderr


def test_an_integer_output_of_a_sweep_beside_its_grid_is_said(tmp_path, run):
    (tmp_path / "s.yaml").write_text(BESIDE)
    out = tmp_path / "o.nrrd"
    res = run("sweep", tmp_path / "s.yaml", "-o", out, "--dtype", "uint8")
    assert res.code == 0 and "does not meet the sweep" in res.stderr
    assert read_volume(out).data.dtype == np.uint8
