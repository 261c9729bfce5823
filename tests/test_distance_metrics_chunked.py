"""minnorm, taxicab and chessboard by blocks = in memory, bit for bit (issue 19).

The per-axis line passes (:func:`volwarp_cli.distance.minnorm.line_metric_pass`)
against scipy's ``distance_transform_cdt`` on random masks; ``volwarp distance
--chunked`` against the in-memory field on odd shapes cut into several blocks
per axis (the operations themselves: ``test_distance_passes.py``); the refusals.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy import ndimage as ndi

from volwarp_cli.distance import minnorm
from volwarp_cli.distance.field import signed_distance
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

SHAPE = (23, 17, 19)  # z, y, x: odd, and no block size below divides them
ANISO = (1.7, 0.6, 1.1)


def blobs(shape, seed, sigma=1.5, level=0.52):
    return ndi.gaussian_filter(np.random.default_rng(seed).random(shape), sigma) > level


def same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


# -- the line passes against scipy -----------------------------------------------------------
masks3d = hnp.arrays(bool, hnp.array_shapes(min_dims=3, max_dims=3, min_side=1, max_side=9))


def _unsigned(metric, sites):
    f = np.where(sites, np.float32(0), np.float32(np.inf))
    for axis in (2, 1, 0):
        minnorm.line_metric_pass(metric, f, axis, 1.0)
    return f


@pytest.mark.parametrize("metric", ["chessboard", "taxicab"])
@settings(max_examples=100, deadline=None)
@given(mask=masks3d)
def test_line_passes_equal_scipy_cdt(metric, mask):
    if not mask.any():
        return  # cdt has no finite answer without a site
    ref = ndi.distance_transform_cdt(~mask, metric=metric).astype(np.float32)
    assert same(_unsigned(metric, mask), ref)


@settings(max_examples=60, deadline=None)
@given(line=hnp.arrays(np.float32, st.integers(1, 30),
                       elements=st.one_of(st.integers(0, 40).map(float), st.just(np.inf))))
def test_chessboard_line_is_the_min_max_formula(line):
    f = line.reshape(1, 1, -1).copy()
    minnorm.chessboard_axis_pass(f, 2)
    i = np.arange(line.size)
    ref = np.min(np.maximum(np.abs(i[:, None] - i[None, :]).astype(np.float32), line[None, :]),
                 axis=1)
    assert same(f.ravel(), ref.astype(np.float32))


def test_minnorm_pass_count_is_the_in_memory_one():
    mask = blobs(SHAPE, 0)
    _, info = signed_distance(mask.astype(np.uint8), ANISO, iso=0.5, metric="minnorm")
    assert info["passes"] == minnorm.signed_pass_count(SHAPE) == 2 * (5 + 5 + 5)


# -- the command ----------------------------------------------------------------------------
@pytest.fixture
def vol(tmp_path):
    def make(spacing_xyz, name="in.nrrd"):
        data = (blobs(SHAPE, 3) * 1000).astype(np.int16)
        path = tmp_path / name
        write_volume(Volume(data, spacing=np.array(spacing_xyz)), path)
        return path

    return make


@pytest.mark.parametrize("metric,spacing,extra", [
    ("minnorm", (1.1, 0.6, 1.7), []),
    ("minnorm", (1.1, 0.6, 1.7), ["--max-distance", "2.2", "--block", "23,4,4"]),
    ("taxicab", (0.8, 0.8, 0.8), ["--unsigned"]),
    ("taxicab", (0.8, 0.8, 0.8), ["--max-distance", "1.7"]),
    ("chessboard", (1.0, 1.0, 1.0), []),
    ("chessboard", (2.0, 2.0, 2.0), ["--max-distance", "3", "--dtype", "int16"]),
    ("minnorm", (1.1, 0.6, 1.7), ["--scheduler", "processes", "--workers", "2",
                                  "--block", "12,9,10"]),
])
def test_command_by_blocks_equals_in_memory(run, vol, tmp_path, metric, spacing, extra):
    src = vol(spacing)
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    common = ["--iso", "500", "--metric", metric]
    plain = list(extra)
    for flag in ("--block", "--scheduler", "--workers"):
        if flag in plain:
            i = plain.index(flag)
            del plain[i:i + 2]
    assert run("distance", src, "-o", mem, *common, *plain).code == 0
    block = [] if "--block" in extra else ["--block", "5,6,7"]
    res = run("distance", src, "-o", blk, *common, "--chunked", *block, *extra)
    assert res.code == 0, res.stderr
    a, b = read_volume(mem), read_volume(blk)
    assert a.data.dtype == b.data.dtype and np.array_equal(a.data, b.data)
    assert same(np.asarray(a.data), np.asarray(b.data))
    note = b.meta["volwarp_distance"]
    assert f"metric={metric}" in note and note == a.meta["volwarp_distance"]
    assert not any("part" in p.name or p.name.startswith(".") for p in tmp_path.iterdir())


def test_command_refusals(run, vol, tmp_path):
    src = vol((1.0, 2.0, 1.0))
    out = tmp_path / "o.nrrd"
    for metric in ("taxicab", "chessboard"):
        mem = run("distance", src, "-o", out, "--iso", "500", "--metric", metric)
        blk = run("distance", src, "-o", out, "--iso", "500", "--metric", metric, "--chunked")
        assert mem.code == blk.code == 1
        assert "needs isotropic spacing" in blk.stderr
        assert blk.stderr.strip().splitlines()[-1] == mem.stderr.strip().splitlines()[-1]
    # (the input, 0/1000 int16 blobs, is a label map: --iso 5000 selects other voxels)
    res = run("distance", src, "-o", out, "--iso", "5000", "--metric", "minnorm", "--chunked")
    assert res.code == 2 and "looks like a label map" in res.stderr
    res = run("distance", src, "-o", out, "--iso", "5000", "--metric", "minnorm", "--chunked",
              "--values", "intensity")
    assert res.code == 1 and f"{src}: the shape is empty" in res.stderr  # (the file named)
    res = run("distance", src, "-o", out, "--iso", "500", "--metric", "minnorm", "--chunked",
              "--surface", "subvoxel")
    assert res.code == 2 and "need the euclidean metric" in res.stderr  # (options clash)
    assert not out.exists()
