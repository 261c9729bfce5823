"""OME-Zarr writes hold the memory ceiling: NGFF 0.4's chunks in flight, reindexed grids.

A reviewer measured two writes over ``--memory-limit`` (256^3 float32):

- NGFF 0.4 (Zarr v2, no shards): ``convert`` at 120M peaked at 137 MiB.
  Level 0 went to zarr in one write, and zarr encodes ten of a write's
  chunks at once (each with its copy, its zstd frame and a context), where
  the estimate counted one.
- A grid whose direction flips or permutes axes (a NIfTI in RAS): the
  writer made the store's identity-direction samples as a whole contiguous
  copy that nothing counted (0.4 at 120M: 200 MiB; a warp at 230M: 247 MiB).

Now level 0 of a 0.4 store is written in as many whole chunks at once as
the budget holds, and a reindexed grid is written from a flipped and
transposed view, the same bytes. (And ``convert --dtype``'s cast of the
whole, made before the store is written, is counted with it.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.errors import OutOfMemoryError
from volwarp_cli.io import omezarr, read_volume
from volwarp_cli.volume import Volume

RAS = np.diag([-1.0, -1.0, 1.0])
LAS = np.diag([1.0, -1.0, 1.0])
# index x runs along world +y, y along world -z, z along world -x
PERMUTED = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def stored_reference(data: np.ndarray, name: str) -> np.ndarray:
    """The samples a store of identity direction holds, by hand (not omezarr's own code)."""
    if name == "RAS":  # x and y reversed
        return data[:, ::-1, ::-1]
    if name == "LAS":  # y reversed
        return data[:, ::-1, :]
    # stored [z, y, x] = world z (old y, reversed), world y (old x), world x (old z, reversed)
    return data[::-1, ::-1, :].transpose(1, 2, 0)


DIRECTIONS = {"RAS": RAS, "LAS": LAS, "PERMUTED": PERMUTED}


class Recording:
    """A zarr array whose writes are recorded (the shape of each), everything else passed on."""

    def __init__(self, array):
        self.array = array
        self.shape, self.chunks, self.shards = array.shape, array.chunks, array.shards
        self.dtype = array.dtype
        self.writes: list[tuple[int, int, int]] = []

    def __getitem__(self, key):
        return np.asarray(self.array[key])

    def __setitem__(self, key, value):
        self.writes.append(tuple(np.shape(value)))
        self.array[key] = value


def _level0(tmp_path: Path, name: str, shape, chunks=(8, 8, 8)):
    group = omezarr.open_group_for_writing(tmp_path / name, "0.4")
    return omezarr.create_arrays(group, [shape], np.dtype("f4"), "0.4", chunks)[0]


def _chunk_files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and p.name[0].isdigit()}


@pytest.mark.parametrize("chunks_held", [1, 4])
def test_level_zero_of_a_v2_store_is_written_in_the_chunks_the_budget_holds(tmp_path,
                                                                           chunks_held):
    """No write of level 0 holds more chunks in flight than the budget (the old code gave
    zarr the whole array at once: ten chunks encoded together where one was counted), and
    the chunks are the same bytes as those of one write of the whole."""
    data = np.random.default_rng(5).random((40, 36, 30)).astype(np.float32)
    chunks = (8, 8, 8)
    budget = omezarr.write_bytes((8, 8, 8 * chunks_held), 4, chunks)
    wide = _level0(tmp_path, "wide.zarr", data.shape)
    omezarr.write_levels([wide], data, False, budget=1 << 40)
    target = Recording(_level0(tmp_path, "tight.zarr", data.shape))
    omezarr.write_levels([target], data, False, budget=budget)
    assert target.writes
    assert all(omezarr.write_bytes(w, 4, chunks) <= budget for w in target.writes)
    largest = max(np.prod([-(-n // c) for n, c in zip(w, chunks, strict=True)])
                  for w in target.writes)
    assert largest == chunks_held  # (as many as it holds, not fewer)
    assert np.array_equal(np.asarray(target.array[...]), data)
    assert _chunk_files(tmp_path / "tight.zarr") == _chunk_files(tmp_path / "wide.zarr")


def test_the_v2_estimate_counts_a_writes_chunks_in_flight():
    """One write of a Zarr v2 region weighs the chunks zarr encodes at once (its
    concurrency's, whatever the region), each with its copy, frame and zstd context; the
    in-memory estimate is one chunk's, which write_levels then holds to."""
    chunk = 64 ** 3 * 4
    whole = omezarr.write_bytes((256, 256, 256), 4, (64, 64, 64))
    one = omezarr.write_bytes((64, 64, 64), 4, (64, 64, 64))
    assert whole >= 10 * 2 * chunk  # (the old count: 22 MiB; measured 22-24 MiB)
    assert whole == omezarr.write_bytes((128, 256, 256), 4, (64, 64, 64))
    assert one >= 2 * chunk + (4 << 20)  # (measured 4.8-6.6 MiB in convert)
    assert omezarr.memory_bytes((256, 256, 256), np.float32, "0.4") == one


def test_a_chunk_that_does_not_fit_is_refused_before_level_zero_is_written(tmp_path):
    """Below one chunk's write, one line with both sizes, and nothing written (the old code
    wrote the whole array whatever the budget)."""
    data = np.zeros((16, 16, 16), np.float32)
    target = Recording(_level0(tmp_path, "a.zarr", data.shape))
    with pytest.raises(OutOfMemoryError, match=r"writing a chunk of 8x8x8 samples needs "
                                               r".* but only 1.0 KiB is left"):
        omezarr.write_levels([target], data, False, budget=1024)
    assert target.writes == []


@pytest.mark.parametrize("name", ["RAS", "LAS", "PERMUTED"])
@pytest.mark.parametrize("version", ["0.4", "0.5"])
@pytest.mark.parametrize("pyramid", [0, 1])
def test_a_reindexed_grid_is_written_from_a_view_to_the_same_samples(tmp_path, name, version,
                                                                     pyramid, monkeypatch):
    """A flipped or permuted grid's store holds the flipped/transposed samples (read back
    with zarr, levels by an independent mean), at the world points the input gave them, in
    the very chunk bytes of the same samples written with the identity direction; and the
    levels are written from a view of the input's own samples (the old code held a
    contiguous copy of the whole volume beside it, which no estimate counted). (A first
    version compared tracemalloc peaks: zarr's chunks in flight made that flaky under load.)"""
    import zarr

    data = (np.random.default_rng(7).random((48, 40, 64)) * 1000).astype(np.float32)
    spacing, origin = np.array([0.7, 1.1, 1.9]), np.array([-10.0, 20.0, 5.0])
    vol = Volume(data, spacing=spacing, origin=origin, direction=DIRECTIONS[name],
                 space="LPS")
    expected = stored_reference(data, name)
    same = read_volume(_write(tmp_path / "warm.ome.zarr", vol, version, pyramid))
    plain = Volume(np.ascontiguousarray(expected), spacing=same.spacing, origin=same.origin,
                   space="LPS")
    _write(tmp_path / "plain.ome.zarr", plain, version, pyramid)
    written = []
    levels = omezarr.write_levels

    def spy(arrays, first, *args, **kwargs):
        written.append(first)
        return levels(arrays, first, *args, **kwargs)

    monkeypatch.setattr(omezarr, "write_levels", spy)
    _write(tmp_path / "v.ome.zarr", vol, version, pyramid)
    (first,) = written
    assert np.shares_memory(first, data) and np.array_equal(first, expected)

    store = tmp_path / "v.ome.zarr"
    level0 = np.asarray(zarr.open_array(str(store / "0"), mode="r")[...])
    assert level0.dtype == np.float32 and np.array_equal(level0, expected)
    if pyramid:
        z, y, x = expected.shape
        mean = expected.astype(np.float64).reshape(z // 2, 2, y // 2, 2, x // 2, 2)
        level1 = np.asarray(zarr.open_array(str(store / "1"), mode="r")[...])
        assert np.array_equal(level1, mean.mean(axis=(1, 3, 5)).astype(np.float32))
    # the chunks are those of the same samples stored as they lie
    assert _chunk_files(store) == _chunk_files(tmp_path / "plain.ome.zarr")
    # every stored voxel lies where its input voxel lay: the corners, by hand
    back = read_volume(store)
    assert np.array_equal(back.direction, np.eye(3))
    assert np.array_equal(back.data, expected)
    nz, ny, nx = data.shape
    for k in (0, nz - 1):
        for j in (0, ny - 1):
            for i in (0, nx - 1):
                value = data[k, j, i]
                where = vol.index_to_world(np.array([i, j, k], dtype=np.float64))
                stored_index = np.rint((where - back.origin) / back.spacing).astype(int)
                np.testing.assert_allclose(back.index_to_world(stored_index), where,
                                           atol=1e-9)
                assert back.data[tuple(stored_index[::-1])] == value


def _write(path: Path, vol: Volume, version: str, pyramid: int) -> Path:
    # (chunks of 16: each chunk zarr copies out of the view is small beside the volume)
    omezarr.write_omezarr(vol, path, version=version, pyramid=pyramid, labels=False,
                          chunks=(16, 16, 16))
    return path


def test_a_cast_to_an_ome_zarr_output_is_counted_before_it_is_made():
    """``convert --dtype`` casts the whole before the store is written and holds the cast
    while it is: counted with the store's write (it was not counted at all: a 256^3
    float32 convert to int16 at 125M peaked at 191 MiB before the store's own check
    refused it)."""
    from volwarp_cli.io import write_memory

    shape = (64, 64, 64)
    store = omezarr.memory_bytes(shape, np.int16, "0.4")
    need = write_memory("o.ome.zarr", shape, np.float32, dtype="int16", ome_zarr_version="0.4")
    assert need >= 64 ** 3 * 2 + store
    assert need >= 64 ** 3 * (2 + 4)  # (the cast beside np.rint's floats)
    # (no cast: the store's write, checked before zarr is loaded, and by write_omezarr again)
    assert write_memory("o.ome.zarr", shape, np.float32) == omezarr.memory_bytes(shape,
                                                                                 np.float32)
    levels = write_memory("o.ome.zarr", shape, np.float32, dtype="int16", pyramid=1)
    assert levels >= 64 ** 3 * 2 + omezarr.memory_bytes(shape, np.int16, "0.5", 1)


def test_convert_refuses_a_cast_store_that_does_not_fit_before_any_output(run, tmp_path,
                                                                         monkeypatch):
    """Between the store's own write and the cast with it: one line, exit 1, nothing made
    (the old check counted no cast for OME-Zarr: the cast was made and the store written)."""
    from volwarp_cli import memory
    from volwarp_cli.io import write_volume

    data = (np.random.default_rng(3).random((64, 64, 64)) * 1000).astype(np.float32)
    write_volume(Volume(data, direction=RAS, space="LPS"), tmp_path / "in.nrrd")
    store = omezarr.memory_bytes(data.shape, np.int16, "0.4")
    budget = store + data.size * 2 // 2  # (the store's write, not its cast beside it)
    monkeypatch.setattr(memory, "_limit", lambda: (budget, "the memory limit (a test's)"))
    out = tmp_path / "o.ome.zarr"
    res = run("convert", tmp_path / "in.nrrd", "-o", out, "--dtype", "int16",
              "--ome-zarr-version", "0.4")
    assert res.code == 1, res.stderr
    assert res.stderr.startswith("volwarp: error: writing ") and res.stderr.count("\n") == 1
    assert "needs" in res.stderr and "int16" in res.stderr
    assert not out.exists() and list(tmp_path.iterdir()) == [tmp_path / "in.nrrd"]
    roomy = store + data.size * (2 + 4)
    monkeypatch.setattr(memory, "_limit", lambda: (roomy, "the memory limit (a test's)"))
    res = run("convert", tmp_path / "in.nrrd", "-o", out, "--dtype", "int16",
              "--ome-zarr-version", "0.4")
    assert res.code == 0, res.stderr
    monkeypatch.undo()  # (the test's budget was the convert's: the read back has its own)
    assert np.array_equal(read_volume(out).data, np.rint(data[:, ::-1, ::-1]).astype(np.int16))
