"""A warp that moves nothing changes nothing; one that moves a point changes only what it reaches.

At an integer oversample k (the default 2; uniform placement) the domain is an
exact subdivision of the input's voxels: domain voxel e lies inside input voxel
(e - lead) // k and takes its value (the box model of a voxel), the affine base
map has slope exactly 1/k, and the domain voxels outside the input carry
nothing. An unmoved region's box pushforward is then an exact area-weighted
copy: every input voxel's k^3 sub-voxels land exactly on its own target voxel.

Bounds (the fixed-point sums resolve 2^-40 of the largest magnitude M): an
integer output is the input bit for bit (the error is below 2^-37 M, far below
the half unit the conversion rounds away, for every integer type); a float one
is within 2 k^3 2^-40 M of it (k^3 sub-voxels, each rounding its weight and
weighted value by at most half a unit, and the final rounding to float32 at
most doubling that), so it is bit for bit wherever |value| >= 2^-12 M (and at 0),
i.e. on every ordinary scan.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.bspline.lattice import Lattice
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

DATA = Path(__file__).parent / "data"
BRAIN = DATA / "mri_colin27_brain_1mm.nrrd"  # 181 x 217 x 181 uint8, 1 mm, values 0..133


def _spec(tmp_path, text, name="w.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _warp(run, tmp_path, src, spec_text, *extra):
    out = tmp_path / "out.nrrd"
    res = run("warp", src, "--spec", _spec(tmp_path, spec_text), "-o", out, *extra)
    assert res.code == 0, res.stderr
    return read_volume(out)


def _float_bound(k: int, data: np.ndarray) -> float:
    return 2 * k ** 3 * 2.0 ** -40 * float(np.abs(data).max())


@pytest.mark.parametrize("oversample", [1, 2])
@pytest.mark.parametrize("steps", ["[]", "\n  - move:\n      - {index: [4, 4, 4], by: [0, 0, 0]}"])
def test_unmoved_warp_of_the_brain_scan_returns_it(run, tmp_path, oversample, steps):
    """The bundled 181 x 217 x 181 scan, default 9^3 lattice, nothing moved: the cropped
    output is the input bit for bit (it was 19% of the voxels off, by up to 74 of 133)."""
    capture = "" if oversample == 2 else f"capture: {{oversample: {oversample}}}\n"
    got = _warp(run, tmp_path, BRAIN, f"version: 1\n{capture}steps: {steps}\n", "--crop")
    vin = read_volume(BRAIN)
    assert got.dtype == vin.dtype and got.same_grid(vin)
    assert np.array_equal(got.data, vin.data)


def test_unmoved_warp_without_crop_pads_with_the_background(run, tmp_path):
    """Without --crop the padded target holds the input at the pad's offset and the
    background around it (a pad asked for, nothing moved)."""
    vin = read_volume(BRAIN)
    got = _warp(run, tmp_path, BRAIN, "version: 1\nbackground: 7\ncapture: {pad: 3}\n"
                "steps: []\n")
    assert got.data.shape == tuple(n + 6 for n in vin.data.shape)
    inner = got.data[3:-3, 3:-3, 3:-3]
    assert np.array_equal(inner, vin.data)
    mask = np.ones(got.data.shape, bool)
    mask[3:-3, 3:-3, 3:-3] = False
    assert np.all(got.data[mask] == 7)


def _smooth_random(shape_zyx, seed):
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    field = gaussian_filter(rng.normal(size=shape_zyx), 2.0)
    return (1000.0 * field / np.abs(field).max() + 30.0).astype(np.float32)


@pytest.mark.parametrize("oversample", [1, 2])
def test_unmoved_warp_of_float32_is_within_the_sums_resolution(run, tmp_path, oversample):
    """Random smooth float32 values of both signs: within 2 k^3 2^-40 of the largest
    magnitude everywhere, and bit for bit wherever |value| >= 2^-12 of it."""
    data = _smooth_random((23, 29, 31), 1)
    src = tmp_path / "in.nrrd"
    write_volume(Volume(data, spacing=(0.7, 1.1, 1.3)), src)
    got = _warp(run, tmp_path, src, f"version: 1\ncapture: {{oversample: {oversample}}}\n"
                "steps: []\n", "--crop").data
    assert got.dtype == np.float32
    err = np.abs(got.astype(np.float64) - data)
    assert err.max() <= _float_bound(oversample, data)
    big = np.abs(data) >= 2.0 ** -12 * np.abs(data).max()
    assert big.mean() > 0.99 and np.array_equal(got[big], data[big])


DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64"]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("oversample", [1, 2, 3])
def test_unmoved_warp_is_exact_for_every_dtype(run, tmp_path, dtype, oversample):
    """Every sample type, full-range random values, the default box pushforward and
    linear sampling: integers bit for bit, floats within the bound (see the module)."""
    rng = np.random.default_rng(7)
    shape = (9, 11, 13)
    if np.dtype(dtype).kind in "iu":
        info = np.iinfo(dtype)
        data = rng.integers(info.min, info.max, size=shape, dtype=dtype, endpoint=True)
        data.flat[:2] = info.min, info.max
    else:
        data = rng.uniform(-1e6, 1e6, size=shape).astype(dtype)
    src = tmp_path / "in.nrrd"
    write_volume(Volume(data, spacing=(1, 2, 3)), src)
    got = _warp(run, tmp_path, src, f"version: 1\ncapture: {{lattice: [5, 6, 4], "
                f"oversample: {oversample}}}\nsteps: []\n", "--crop").data
    assert got.dtype == np.dtype(dtype)
    if np.dtype(dtype).kind in "iu":
        assert np.array_equal(got, data)
    else:
        err = np.abs(got.astype(np.float64) - data.astype(np.float64))
        assert err.max() <= _float_bound(oversample, data)
        if dtype == "float32":
            big = np.abs(data) >= 2.0 ** -12 * np.abs(data).max()
            assert np.array_equal(got[big], data[big])


def _support_box(grid: Lattice, index, move, margin):
    """Per axis (x, y, z), the input-index interval outside which no output voxel can
    be reached by the moved point's regions: the regions i - 3..i (clipped), widened
    by the move and by ``margin``."""
    uniform = grid.uniform_positions()  # [k, j, i, (x, y, z)]: uniform[.., 1] is parameter 0
    axes = [uniform[0, 0, :, 0], uniform[0, :, 0, 1], uniform[:, 0, 0, 2]]
    lo, hi = [], []
    for axis in range(3):
        r = grid.regions[axis]
        a0, a1 = max(index[axis] - 3, 0), min(index[axis], r - 1) + 1
        # region a spans the uniform points a + 1 .. a + 2 (the B-spline of an affine
        # lattice is that affine map)
        x0, x1 = axes[axis][a0 + 1], axes[axis][a1 + 1]
        reach = abs(move[axis]) + margin
        lo.append(x0 - reach)
        hi.append(x1 + reach)
    return np.array(lo), np.array(hi)


@pytest.mark.parametrize("oversample", [1, 2])
@pytest.mark.parametrize("index, move", [((2, 3, 4), (2.5, -1.5, 1.0)),
                                         ((6, 5, 2), (-3.0, 2.0, -2.5))])
def test_one_moved_point_leaves_everything_else_exact(run, tmp_path, oversample, index, move):
    """One control point moved (voxel units): every output voxel outside its support's
    image equals the input voxel exactly; inside, the scan changes.

    The support: the point's regions (i - 3..i per axis) map within ``move`` of
    their base image (an offset is a convex combination of control-point
    offsets). A still voxel next to a moved one (within 1/k of the support) has
    its box's face centre on that side shifted by half its neighbour's offset,
    so it reaches at most ``|move| / 2 + 1/k`` beyond the support too; the
    margin of one voxel, with ``|move|``, covers both.
    """
    vin = read_volume(BRAIN)
    capture = f"capture: {{oversample: {oversample}}}\n"
    text = (f"version: 1\nunits: voxel\n{capture}steps:\n  - move:\n"
            f"      - {{index: [{index[0]}, {index[1]}, {index[2]}], "
            f"by: [{move[0]}, {move[1]}, {move[2]}]}}\n")
    got = _warp(run, tmp_path, BRAIN, text, "--crop").data
    grid = Lattice.create(vin.shape_xyz, (9, 9, 9), oversample)
    lo, hi = _support_box(grid, index, move, margin=1.0)
    nz, ny, nx = vin.data.shape
    x, y, z = np.arange(nx), np.arange(ny), np.arange(nz)
    # target voxel t's box [t - 0.5, t + 0.5] misses (lo, hi) on some axis
    out_x = (x + 0.5 <= lo[0]) | (x - 0.5 >= hi[0])
    out_y = (y + 0.5 <= lo[1]) | (y - 0.5 >= hi[1])
    out_z = (z + 0.5 <= lo[2]) | (z - 0.5 >= hi[2])
    outside = out_z[:, None, None] | out_y[None, :, None] | out_x[None, None, :]
    assert 0.2 < outside.mean() < 0.95
    assert np.array_equal(got[outside], vin.data[outside])
    changed = got != vin.data
    assert changed[~outside].sum() > 1000  # the moved part of the scan did move
    assert not changed[outside].any()
