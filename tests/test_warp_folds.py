"""The plan's fold check (volwarp_cli/bspline/folds.py) against scipy's B-spline, and its warning.

A review found a folding lattice (one control point moved 30 voxels) warped
with exit 0 and nothing said; only a displacement export mentioned it.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.bspline import folds
from volwarp_cli.bspline.evaluate import LatticeSpline
from volwarp_cli.bspline.lattice import Lattice
from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume


def test_jacobian_dets_are_scipy_s_at_their_parameters():
    grid = Lattice.create((30, 26, 22), (7, 6, 8), 1.0)
    positions = grid.uniform_positions() + np.random.default_rng(2).normal(0, 2.5, (8, 6, 7, 3))
    per = 3
    regions = np.argwhere(np.ones(grid.regions[::-1], bool))  # (z, y, x)
    dets = folds.jacobian_dets(positions, regions, per)
    params = [(c + i / per, b + j / per, a + k / per) for a, b, c in regions
              for k, j, i in itertools.product(range(per), repeat=3)]
    jac = LatticeSpline(positions, grid.regions).jacobian(np.array(params))  # [n, comp, axis]
    np.testing.assert_allclose(dets.ravel(), np.linalg.det(jac), rtol=1e-9, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), amplitude=st.floats(0.1, 6.0))
def test_a_region_the_bound_clears_never_folds(seed, amplitude):
    """Where the bound clears a region, a dense sampling finds its determinants positive."""
    grid = Lattice.create((40, 40, 40), (7, 7, 7), 1.0)
    positions = grid.uniform_positions() + np.random.default_rng(seed).normal(
        0, amplitude, (7, 7, 7, 3))
    cleared = np.argwhere(~folds.suspect_regions(positions))
    if len(cleared):
        assert (folds.jacobian_dets(positions, cleared, 8) > 0).all()


def test_a_mirror_is_no_fold_and_a_fold_in_a_mirror_is():
    grid = Lattice.create((40, 40, 40), (9, 9, 9), 1.0)
    positions = grid.uniform_positions()
    mirror = positions * [-1, 1, 1]
    assert folds.fold_count(mirror)[0] == 0
    folded = mirror.copy()
    folded[4, 4, 4, 0] -= 40.0
    assert folds.fold_count(folded)[0] > 0
    assert folds.fold_count(positions) == (0, 0)  # (the bound: no sampling)


@pytest.fixture
def ball(tmp_path):
    z, y, x = np.mgrid[:40, :40, :40]
    path = tmp_path / "ball.nrrd"
    write_volume(Volume((((x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 < 150) * 100.0)
                        .astype(np.float32)), path)
    return path


@pytest.mark.parametrize("by, folds_", [(30, True), (3, False)])
def test_a_folding_spec_is_said(run, tmp_path, ball, by, folds_):
    spec = tmp_path / "s.yaml"
    spec.write_text(f"version: 1\ncapture: {{lattice: 9}}\nsteps:\n  - move:\n"
                    f"      - {{index: [4, 4, 4], by: [{by}, 0, 0]}}\n")
    res = run("warp", ball, "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 0, res.stderr
    assert ("steps[0]: the lattice folds the map" in res.stderr) == folds_, res.stderr


def test_a_fold_is_said_once_by_the_step_that_makes_it(run, tmp_path, ball):
    """Later steps carry the fold: they are not told to make smaller moves."""
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 9}\nsteps:\n  - move:\n"
                    "      - {index: [4, 4, 4], by: [3, 0, 0]}\n  - move:\n"
                    "      - {index: [4, 4, 4], by: [27, 0, 0]}\n  - move:\n"
                    "      - {index: [2, 2, 2], by: [0.5, 0, 0]}\n")
    res = run("warp", ball, "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 0, res.stderr
    assert res.stderr.count("the lattice folds the map") == 1
    assert "steps[1]: the lattice folds the map" in res.stderr


def test_a_large_lattice_is_sampled_within_the_budget():
    grid = Lattice.create((256, 256, 256), (60, 60, 60), 1.0)
    positions = grid.uniform_positions()
    positions[30, 30, 30, 0] += 40.0  # (ten spacings: a fold)
    folded, samples = folds.fold_count(positions)
    assert 0 < samples <= folds.SAMPLES and folded > 0


def test_a_strong_mirror_is_no_fold_and_its_fold_is():
    """A mirrored lattice with a strong but one-to-one move (a suspect region, every
    determinant negative) is no fold; the cleared regions' sign is the mirror's."""
    grid = Lattice.create((40, 40, 40), (9, 9, 9), 1.0)
    mirror = grid.uniform_positions() * [-1, 1, 1]
    strong = mirror.copy()
    strong[4, 4, 4, 1] += 4.0  # (across the axis: a shear of 0.6 spacing, no fold)
    assert folds.suspect_regions(strong).any() and not folds.suspect_regions(strong).all()
    assert (folds.jacobian_dets(strong, None, 4) < 0).all()
    assert folds.fold_count(strong)[0] == 0
    folded = mirror.copy()
    folded[4, 4, 4, 0] -= 40.0
    assert folds.fold_count(folded)[0] > 0
