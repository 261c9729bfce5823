"""The examples/morph-topology pipeline, run at reduced size through its Makefile."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

from volwarp_cli.io import read_volume
from volwarp_cli.io.images import read_image

EXAMPLE = Path(__file__).parent.parent / "examples" / "morph-topology"


@pytest.mark.examples
@pytest.mark.skipif(shutil.which("make") is None, reason="GNU make is not installed")
def test_ball_to_torus_example(tmp_path):
    volwarp = Path(sys.executable).parent / "volwarp"
    out = tmp_path / "out"
    res = subprocess.run(["make", "-C", str(EXAMPLE), f"OUT={out}", "SIZE=small",
                          f"VOLWARP={volwarp}", f"PYTHON={sys.executable}"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    frames = sorted(out.glob("frame_*.nrrd"))
    assert len(frames) == 5
    holes = []
    for f in frames:
        inside = read_volume(f).data < 0
        assert ndi.label(inside)[1] == 1
        mid = inside[inside.shape[0] // 2]
        holes.append(ndi.label(~mid)[1] - 1)
    assert holes[0] == 0 and holes[-1] == 1
    assert len(list(out.glob("frame_*.ply"))) == 5
    sheet = read_image(out / "sheet.png")
    assert sheet.shape[1] > 3 * 320 and sheet.std() > 0.02
    sdf = read_volume(out / "ball.sdf.nrrd").data
    assert sdf.min() < 0 < sdf.max()
    # nothing to do the second time: real file dependencies
    again = subprocess.run(["make", "-C", str(EXAMPLE), f"OUT={out}", "SIZE=small",
                            f"VOLWARP={volwarp}", f"PYTHON={sys.executable}", "-q"])
    assert again.returncode == 0
    assert np.isfinite(sdf).all()
