"""An apply whose every output point maps outside its input is said, not written silently.

A translation by 5 m (metres taken for millimetres, an inverse forgotten, a
transform for another subject) resampled nothing of the scan: every voxel the
background, exit 0, no word. Each block knows, before reading a sample,
whether its points can reach the input (exact for linear chains); the run's
end says it once, in memory, by blocks and from worker processes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import read_volume

DATA = Path(__file__).parent / "data"
SCAN = DATA / "mri_t1_head_coronal_2x2x3mm.nrrd"
WORDS = "no output point maps inside"


def translation(path: Path, x_mm: float) -> Path:
    path.write_text("#Insight Transform File V1.0\n#Transform 0\n"
                    "Transform: AffineTransform_double_3_3\n"
                    f"Parameters: 1 0 0 0 1 0 0 0 1 {x_mm} 0 0\nFixedParameters: 0 0 0\n")
    return path


BLOCKS = [[], ["--chunked", "--block", "16"],
          ["--chunked", "--block", "16", "--scheduler", "processes"]]


@pytest.mark.parametrize("blocks", BLOCKS)
def test_a_chain_that_maps_every_point_outside_is_said_once(tmp_path, run, blocks):
    out = tmp_path / "o.nrrd"
    res = run("apply", SCAN, "-t", translation(tmp_path / "t.tfm", 5000), "-o", out, *blocks)
    assert res.code == 0, res.stderr
    assert not read_volume(out).data.any()
    assert res.stderr.count(WORDS) == 1 and "warning: every voxel of" in res.stderr


@pytest.mark.parametrize("blocks", BLOCKS)
def test_a_chain_that_keeps_part_of_the_scan_says_nothing(tmp_path, run, blocks):
    """Half the output outside the scan: some blocks reach nothing, the others count."""
    out = tmp_path / "o.nrrd"
    width = float(np.ptp(read_volume(SCAN).world_bounds(), axis=0)[0])
    res = run("apply", SCAN, "-t", translation(tmp_path / "t.tfm", width / 2), "-o", out,
              *blocks)
    assert res.code == 0, res.stderr
    assert read_volume(out).data.any() and "warning" not in res.stderr


def test_a_label_map_outside_is_said_by_its_ids_alone(tmp_path, run):
    out = tmp_path / "o.nrrd"
    res = run("apply", DATA / "ball_30_uint8.nrrd", "-t", translation(tmp_path / "t.tfm", 5000),
              "-o", out)
    assert res.code == 0 and "labels are in no output voxel" in res.stderr
    assert WORDS not in res.stderr
