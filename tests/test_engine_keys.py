"""Block tasks' keys are unique to each task made, not to the block.

A Dask scheduler hands back the result it holds for a key without running the
task again. Named by the block alone (``volwarp-block-block-(0, 0, 0)``), the
tasks of a morph's second frame were its first frame's on a LocalCluster (frames
of zeros, exit 0) and a mesh's pieces were its counting pass's results (an
internal error), in about half the runs.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.engine import _key_name, block_delayed
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

pytest.importorskip("dask")


def _double(x):
    return 2 * x


def test_the_same_block_twice_makes_two_keys_and_one_name():
    ident = "block-(0, 0, 0)"
    a, b = block_delayed(_double, ident, 1), block_delayed(_double, ident, 2)
    assert a.key != b.key
    assert _key_name(a.key) == _key_name(b.key) == ident  # (the progress lines' id)


def _mask(shape, centre, radius):
    z, y, x = np.indices(shape, dtype=np.float64)
    r = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2)
    return Volume((r <= radius).astype(np.float32))


def test_morph_frames_by_a_local_cluster_are_the_in_memory_ones(run, tmp_path):
    pytest.importorskip("distributed")
    a, b = tmp_path / "a.nrrd", tmp_path / "b.nrrd"
    write_volume(_mask((24, 26, 28), (12, 13, 11), 6), a)
    write_volume(_mask((24, 26, 28), (15, 12, 12), 8), b)
    assert run("morph", a, b, "--frames", "5", "--iso", "0.5", "-o",
               tmp_path / "m_{i}.nrrd").code == 0
    res = run("morph", a, b, "--frames", "5", "--iso", "0.5", "-o", tmp_path / "c_{i}.nrrd",
              "--chunked", "--scheduler", "local", "--workers", "2")
    assert res.code == 0, res.stderr
    for i in range(5):
        mem, blk = read_volume(tmp_path / f"m_{i}.nrrd"), read_volume(tmp_path / f"c_{i}.nrrd")
        assert np.ptp(blk.data) > 0, i  # (a frame of zeros before)
        np.testing.assert_array_equal(blk.data, mem.data)
    res = run("mesh", a, "--iso", "0.5", "--stats", "--json", "--chunked", "--scheduler",
              "local", "--workers", "2")
    assert res.code == 0, res.stderr  # ("'Facts' object has no attribute 'faces'" before)
    assert res.stdout == run("mesh", a, "--iso", "0.5", "--stats", "--json").stdout
