"""`volwarp apply` on files ANTs and elastix wrote, against their own resamplers.

antspyx and itk-elastix live in their own environment (`make test` installs .venv-peers:
antspyx pins numpy < 2.4 and scipy < 1.16, which volwarp's environment is past). The
registrations and the tools' own results come from `tests/peers/registrations.py` run
there as a process; volwarp then applies the files those tools wrote, here. Without that
environment these tests skip, unless VOLWARP_REQUIRE_PEERS=1 (make test sets it): then a
missing peer is a failure, so CI cannot pass them by skipping.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import read_volume

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "peers" / "registrations.py"


def peers_python() -> str:
    exe = os.environ.get("VOLWARP_PEERS_PYTHON") or str(ROOT / ".venv-peers" / "bin" / "python")
    if not Path(exe).exists():
        if os.environ.get("VOLWARP_REQUIRE_PEERS") == "1":
            pytest.fail(f"the peers' environment is missing ({exe}): make install-peers")
        pytest.skip("ANTs and elastix are not installed (make install-peers)")
    return exe


def peer(*args) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    res = subprocess.run([peers_python(), str(SCRIPT), *map(str, args)], env=env,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]


def test_ants_warp_and_affine(run, tmp_path):
    peer("ants", tmp_path)
    t = json.loads((tmp_path / "transforms.json").read_text())
    warp, aff = t["warp"], t["affine"]
    assert warp.endswith("1Warp.nii.gz") and aff.endswith("0GenericAffine.mat")
    theirs = np.load(tmp_path / "ants_linear.npy")
    m = read_volume(tmp_path / "moving.nii.gz").data
    span = float(m.max() - m.min())
    for order, close in (((warp, aff), True), ((aff, warp), False)):
        res = run("apply", tmp_path / "moving.nii.gz", "-o", tmp_path / "out.nii.gz",
                  "--reference", tmp_path / "fixed.nii.gz", "-t", order[0], "-t", order[1],
                  "--background-value", "0")
        if not close and res.code == 1:  # the field's extent check caught the order
            assert "wrong order" in res.stderr
            continue
        assert res.code == 0, res
        err = np.abs(read_volume(tmp_path / "out.nii.gz").data - theirs).max()
        assert (err <= 1e-3 * span) if close else (err > 1e-2 * span)
    # points of the moving image into the fixed space, by the chain's inverse; ANTs maps
    # them back by the chain itself
    pts = np.array([[-1.0, 12.0, 18.0], [2.0, 15.0, 20.0], [5.0, 18.0, 22.0]])
    (tmp_path / "p.csv").write_text("x,y,z,t\n" + "".join(f"{a},{b},{c},0\n" for a, b, c in pts))
    res = run("apply", "-t", warp, "-t", aff, "--points-in", tmp_path / "p.csv",
              "--points-to", tmp_path / "q.csv")
    assert res.code == 0, res
    q = np.loadtxt(tmp_path / "q.csv", delimiter=",", skiprows=1)[:, :3]
    assert np.abs(q - pts).max() > 0.5  # (the chain moves them: the check below can fail)
    peer("ants-points", tmp_path, tmp_path / "q.csv", tmp_path / "back.csv", warp, aff)
    back = np.loadtxt(tmp_path / "back.csv", delimiter=",", skiprows=1)
    assert np.abs(back - pts).max() < 1e-3


@pytest.mark.slow  # (an elastix registration in one thread: about 10 s)
def test_elastix_chain(run, tmp_path):
    peer("elastix", tmp_path)
    grid = json.loads((tmp_path / "fixed_grid.json").read_text())
    m = read_volume(tmp_path / "moving.nrrd").data
    span = float(m.max() - m.min())
    last = tmp_path / "TransformParameters.2.txt"
    for order, interp in ((3, "bspline"), (1, "linear")):
        theirs = np.load(tmp_path / f"transformix_order{order}.npy")
        res = run("apply", tmp_path / "moving.nrrd", "-o", tmp_path / "out.nrrd", "-t", last,
                  "--interpolation", interp, "--background-value", "0")
        assert res.code == 0, res
        out = read_volume(tmp_path / "out.nrrd")  # on the fixed grid the file states
        assert np.allclose(out.direction, grid["direction"])
        assert np.allclose(out.origin, grid["origin"])
        err = np.abs(out.data - theirs)
        if order == 1:  # transformix's order-1 spline mirrors at the edges, ITK's linear clamps
            err = err[2:-2, 2:-2, 2:-2]
        assert err.max() <= 1e-3 * span
    # a chain whose last step is taken alone is another mapping: it must not pass
    res = run("apply", tmp_path / "moving.nrrd", "-o", tmp_path / "alone.nrrd",
              "-t", tmp_path / "TransformParameters.0.txt", "--reference", tmp_path / "out.nrrd",
              "--interpolation", "bspline", "--background-value", "0")
    assert res.code == 0, res
    assert np.abs(read_volume(tmp_path / "alone.nrrd").data
                  - np.load(tmp_path / "transformix_order3.npy")).max() > 1e-2 * span
