"""A sweep under --memory-limit peaks below it: in memory (--multi) and by blocks.

A review measured `sweep --multi` at 1561 MiB under 800M: the model left out the
stacked output (and the writer split it and stacked it again, two more copies), and
the blend's finish copied each field. By blocks the peaks were 1-3 MiB over the limit.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from peaks import volwarp_peak

from volwarp_cli import memory

ROOT = Path(__file__).resolve().parents[1]
M = 1 << 20

@pytest.mark.parametrize("options, limit", [(["--multi", "-o", "m.nrrd"], 300),
                                            (["--dtype", "uint8", "--multi", "-o", "m.nrrd"], 300),
                                            (["-o", "s_{field}.nrrd"], 140)],
                         ids=["multi", "multi-uint8", "fields-by-blocks"])
def test_a_sweep_peaks_below_its_memory_limit(tmp_path, options, limit):
    spec = ROOT / "specs" / "sweep-bottle.yaml"
    code, err, peak = volwarp_peak("sweep", spec, "--shape", "160", "160", "160",
                                   *options[:-1], tmp_path / options[-1], "--memory-limit",
                                   f"{limit}M")
    assert code == 0, err
    assert peak < limit * M, f"peak RSS {peak / M:.0f} MiB under --memory-limit {limit}M"


def test_a_render_whose_kernels_do_not_fit_is_refused_before_the_fields(tmp_path):
    """`sweep --render` under 150M computed every field (3 s) and then refused to load the
    ray caster's numba; it is refused first now, nothing written."""
    env = {k: v for k, v in os.environ.items() if k != memory.MEMORY_ENV}
    spec = ROOT / "specs" / "sweep-bottle.yaml"
    proc = subprocess.run([sys.executable, "-m", "volwarp_cli", "sweep", str(spec), "--shape",
                           "96", "96", "96", "-o", str(tmp_path / "s_{field}.nrrd"), "--render",
                           str(tmp_path / "r.png"), "--memory-limit", "150M", "-v"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 1, proc.stderr
    assert "loading numba" in proc.stderr and "voxelise" not in proc.stderr, proc.stderr
    assert not list(tmp_path.iterdir())


def test_template_images_that_do_not_fit_are_the_budget_s_refusal_not_the_spec_s(tmp_path):
    """Loading OpenImageIO for a spec's template images, refused by the budget, was worded
    as the spec's error, exit 2 (a hunt): it is the budget's, exit 1, nothing written."""
    env = {k: v for k, v in os.environ.items() if k != memory.MEMORY_ENV}
    spec = ROOT / "specs" / "sweep-ring-of-fire.yaml"
    proc = subprocess.run([sys.executable, "-m", "volwarp_cli", "sweep", str(spec), "--shape",
                           "64", "64", "64", "-o", str(tmp_path / "s_{field}.nrrd"),
                           "--memory-limit", "60M"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 1, proc.stderr
    assert "loading OpenImageIO" in proc.stderr and "memory limit" in proc.stderr
    assert "fields.opacity" not in proc.stderr
    assert not list(tmp_path.iterdir())
