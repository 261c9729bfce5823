"""OME-Zarr outputs within the memory budget: the pyramid made by pieces, the shards' encoding counted.

A reviewer measured a 256^3 float32 warp to ``.ome.zarr`` at ``--memory-limit
120M`` peaking at 170 MiB (``--pyramid 2`` at 150M: 385 MiB): each level's
shard was made from the whole 2x region of the level above, read at once, and
no one counted zarr's encoding of a shard (kept whole, twice).
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli import execute
from volwarp_cli.errors import OutOfMemoryError
from volwarp_cli.io import blockwrite, omezarr


class Recording:
    """A zarr array's reads recorded (the largest region's samples), everything else passed on."""

    def __init__(self, array):
        self.array = array
        self.shape, self.chunks, self.shards = array.shape, array.chunks, array.shards
        self.dtype = array.dtype
        self.largest = 0

    def __getitem__(self, key):
        out = np.asarray(self.array[key])
        self.largest = max(self.largest, out.nbytes)
        return out

    def __setitem__(self, key, value):
        self.array[key] = value


def _store(tmp_path, name, data, version, levels):
    group = omezarr.open_group_for_writing(tmp_path / name, version)
    arrays = omezarr.create_arrays(group, omezarr.level_shapes(data.shape, levels), data.dtype,
                                   version, (8, 8, 8))
    arrays[0][...] = data
    return arrays


@pytest.mark.parametrize("version", ["0.5", "0.4"])
@pytest.mark.parametrize("labels", [False, True])
def test_levels_read_the_level_above_by_pieces_the_budget_holds(tmp_path, version, labels):
    """Each coarse shard is made piece by piece: no read of the level above is larger than
    its step's budget allows (the old code read the whole 2x region of a shard: here all
    of level 0), and the levels are the same samples whatever the budget."""
    rng = np.random.default_rng(3)
    data = (rng.random((64, 48, 40)) * (5 if labels else 1000)).astype(np.float32)
    wide = _store(tmp_path, "wide.zarr", data, version, 2)
    omezarr.write_levels(wide, None, labels, budget=1 << 40)
    arrays = _store(tmp_path, "tight.zarr", data, version, 2)
    level1 = arrays[1].shards or arrays[1].chunks
    budget = omezarr.level_step_bytes(level1, arrays[1].chunks, (2, 2, level1[2]),
                                      arrays[0].shape, arrays[0].chunks, 4)
    source = Recording(arrays[0])
    omezarr.write_levels([source, *arrays[1:]], None, labels, budget=budget)
    whole_region = min(data.nbytes, 8 * int(np.prod(level1)) * 4)
    shard = int(np.prod(level1)) * 4
    # (a read holds its region twice, beside the shard being made)
    assert 0 < source.largest and shard + 2 * source.largest <= budget
    assert source.largest * 8 <= whole_region
    for a, b in zip(wide[1:], arrays[1:], strict=True):
        assert np.array_equal(np.asarray(a[...]), np.asarray(b[...]))


def test_level_one_is_made_from_the_samples_in_memory(tmp_path):
    """Given level 0's samples, level 1 averages them (no read back from the store), in
    pieces, to the same samples as from the store."""
    data = np.random.default_rng(4).random((40, 36, 30)).astype(np.float32)
    arrays = _store(tmp_path, "a.zarr", data, "0.5", 1)
    source = Recording(arrays[0])
    omezarr.write_levels([source, arrays[1]], data, False, budget=8 << 20)
    assert source.largest == 0
    assert np.array_equal(np.asarray(arrays[1][...]), omezarr.downsample(data))


def test_a_level_whose_smallest_piece_does_not_fit_is_refused(tmp_path):
    """Below the least a level's shard needs (its samples and its encoding), one line with
    both sizes, before the level is written."""
    data = np.zeros((32, 32, 32), np.float32)
    arrays = _store(tmp_path, "a.zarr", data, "0.5", 1)
    need = omezarr.pyramid_bytes(data.shape, 4, "0.5", 1, chunks=(8, 8, 8))
    with pytest.raises(OutOfMemoryError, match="pyramid level's shard of 16x16x16 samples "
                                               "needs .* but only 1.0 KiB is left"):
        omezarr.write_levels(arrays, None, False, budget=1024)
    assert need > 3 * 16 ** 3 * 4  # (the shard, and twice it while zarr encodes it)
    omezarr.write_levels(arrays, None, False, budget=need)


def test_a_shards_encoding_is_counted_twice_its_samples():
    """zarr keeps a shard's zstd frames and then their join: a block of an NGFF 0.5 store
    weighs twice its samples beside them, 0.4 a few chunks' buffers; the in-memory write
    the largest of one shard's and the levels' (the whole 256^3 array is one shard)."""
    shape, block = (256, 256, 256), (256, 256, 256)
    nbytes = 256 ** 3 * 4
    assert blockwrite.zarr_block_bytes(shape, np.float32, "0.5", block) >= 2 * nbytes
    assert blockwrite.zarr_block_bytes(shape, np.float32, "0.4", block) < nbytes
    assert omezarr.memory_bytes(shape, np.float32, "0.5") >= 2 * nbytes
    assert omezarr.memory_bytes(shape, np.float32, "0.5", 2) >= omezarr.pyramid_bytes(
        shape, 4, "0.5", 2, held=True)
    assert blockwrite.zarr_commit_bytes(shape, np.float32, "0.5", 0, block) == 0


def test_the_in_memory_decision_counts_the_stores_encoding(tmp_path):
    """An OME-Zarr target's whole weighs its samples and its encoding: what fit as samples
    alone (the old count) runs by blocks, each block with its shard's encoding counted;
    blocks smaller than the store's shard go to a scratch file by offset (no encoding),
    and the store's commit weighs a shard and its encoding."""
    from volwarp_cli.geometry import Geometry

    grid = Geometry((32, 32, 32))
    target = execute.Target(tmp_path / "o.ome.zarr", grid.header(np.float32), np.dtype("f4"))
    nrrd = execute.Target(tmp_path / "o.nrrd", grid.header(np.float32), np.dtype("f4"))
    assert nrrd.write_bytes(grid.shape) == 0 and nrrd.block_bytes(grid.shape, (8, 32, 32)) == 0
    assert target.write_bytes(grid.shape) >= 2 * 32 ** 3 * 4
    assert target.block_bytes(grid.shape, (32, 32, 32)) >= 2 * 32 ** 3 * 4
    assert target.block_bytes(grid.shape, (8, 32, 32)) == 0
    assert target.commit_bytes(grid.shape, (32, 32, 32)) == 0
    assert target.commit_bytes(grid.shape, (8, 32, 32)) >= 3 * 32 ** 3 * 4


_MAPPED_PROBE = r"""
import ctypes, sys
import numpy as np
from volwarp_cli import api
from volwarp_cli.memory import large_allocations_mapped
from volwarp_cli.volume import Volume

libc = ctypes.CDLL("libc.so.6")
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]
libc.mallinfo2.restype = Info
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]

def mapped(size):
    # whether glibc serves an allocation of ``size`` with a mapping of its own (the
    # threshold decides only where the arena has no free room that size: each probe's
    # size is larger than the last's)
    before = libc.mallinfo2().hblkhd
    p = libc.malloc(size)
    grew = libc.mallinfo2().hblkhd - before
    libc.free(p)
    return grew >= size

with large_allocations_mapped():
    inside = mapped(1 << 20)
after_scope = mapped(2 << 20)
with large_allocations_mapped():
    with large_allocations_mapped():  # (nested: the threshold stays until the outer one leaves)
        pass
    after_nested = mapped(4 << 20)
api.write(Volume(np.arange(4096, dtype=np.float32).reshape(16, 16, 16)), sys.argv[1])
after_write = mapped(16 << 20)
print(inside, after_scope, after_nested, after_write)
"""


def test_a_store_write_maps_large_allocations_only_while_it_lasts(tmp_path):
    """glibc's fixed mmap threshold is the writes' own, not the process's for ever after.

    Kept after one ``api.write`` of a store, every later allocation from
    128 KiB to 32 MiB was a fresh mapping and its page faults (a script's
    200 KB numpy temporaries 1.4x slower). Measured in a fresh process
    (glibc's state is the process's): inside the scope a 1 MiB allocation is
    a mapping of its own; after it (and after a store's write) it comes from
    the arena (up to 32 MiB).
    """
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _MAPPED_PROBE, str(tmp_path / "o.ome.zarr")],
                         capture_output=True, text=True, check=True).stdout.split()
    assert out == ["True", "False", "True", "False"]
    assert (tmp_path / "o.ome.zarr").is_dir()


def test_the_environments_malloc_thresholds_are_what_a_write_leaves(tmp_path):
    """A user's (or Dask's nanny's) MALLOC_MMAP_THRESHOLD_ is back after a store's write:
    the write left 32 MiB whatever the environment said (a review found it)."""
    import os
    import subprocess
    import sys

    probe = _MAPPED_PROBE.split("with large_allocations_mapped():")[0] + (
        "with large_allocations_mapped():\n    pass\n"
        "print(mapped(1 << 20))\n")
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536", MALLOC_TRIM_THRESHOLD_="65536")
    out = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "o.ome.zarr")],
                         capture_output=True, text=True, check=True, env=env).stdout.split()
    assert out == ["True"]  # (64 KiB again: a 1 MiB allocation is a mapping of its own)
    out = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "o.ome.zarr")],
                         capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False"]  # (without them: 32 MiB, from the arena)


def test_a_staged_stores_commit_counts_its_unit_within_the_grid():
    """A 256-sample shard over a 200-sample grid holds 200 planes: counted whole, the
    commit's estimate was up to twice what was measured (a review: 213 MiB counted, 96 MiB
    measured, for 200^3 float32), and stores fell back to blocks of their own."""
    samples = 200 ** 3 * 4
    need = blockwrite.staged_commit_bytes((200, 200, 200), np.float32, "0.5")
    assert 3 * samples <= need < 4 * samples  # (the samples, zarr's frames and their join)
    whole_unit = blockwrite.staged_commit_bytes((256, 256, 256), np.float32, "0.5")
    assert need < 0.6 * whole_unit
    assert need < omezarr.memory_bytes((200, 200, 200), np.float32, "0.5")  # (in memory)


def test_staging_needs_the_disk_for_the_samples_and_the_store_of_every_staged_output(
        tmp_path, monkeypatch):
    """The scratch file stays while the commit writes the store, and a run's stores share
    their disk: counted as the raw samples of one output alone, a warp failed on a full
    disk after its blocks where one shard per block fits (a review)."""
    import shutil
    from collections import namedtuple

    from volwarp_cli.runscope import run_scope

    shape, block = (40, 64, 64), (8, 64, 64)
    raw = 40 * 64 * 64 * 4
    usage = namedtuple("usage", "total used free")
    for free, expected in ((int(1.5 * raw), [False, False]), (int(2.5 * raw), [True, False]),
                           (int(4.5 * raw), [True, True])):
        monkeypatch.setattr(shutil, "disk_usage", lambda _, f=free: usage(f, 0, f))
        with run_scope():
            got = [blockwrite.zarr_staged(tmp_path / f"{n}.ome.zarr", shape, np.float32, "0.5",
                                          block) for n in ("a", "b")]
            # (decided once per output: asked again, the same answer, nothing counted twice)
            again = blockwrite.zarr_staged(tmp_path / "a.ome.zarr", shape, np.float32, "0.5",
                                           block)
            # (a store done gives its reservation back: what it wrote, the free space
            # shows; the frames of a morph, written one after another, are not summed)
            blockwrite._release_stage(tmp_path / "a.ome.zarr")
            later = blockwrite.zarr_staged(tmp_path / "c.ome.zarr", shape, np.float32, "0.5",
                                           block)
        assert got == expected and again == expected[0], (free / raw, got)
        assert later == expected[0]


def test_an_omezarr_region_is_read_holding_a_row_of_chunks_beside_it(tmp_path):
    """Read at once, a region held every chunk it touched beside the samples (a review:
    `convert` of a 256^3 store peaked at 190 MiB under 150M); read a row of chunks at a
    time, what the read holds beyond its result is a few rows' decoded chunks."""
    import tracemalloc

    from volwarp_cli.io import write_volume
    from volwarp_cli.io.lazy import open_volume_header
    from volwarp_cli.volume import Volume

    rng = np.random.default_rng(1)
    store = tmp_path / "r.ome.zarr"
    write_volume(Volume(rng.random((192, 192, 192), dtype=np.float32)), store)
    _, lazy = open_volume_header(store, inflate=False)
    region = np.asarray(lazy[0:96])  # (zarr's machinery loaded; the samples to compare)
    tracemalloc.start()
    try:
        got = np.asarray(lazy[0:96])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    np.testing.assert_array_equal(got, region)
    extra = peak - got.nbytes
    assert extra < 12 << 20, f"{extra >> 20} MiB held beside {got.nbytes >> 20} MiB"  # (3 rows)
