"""An OME-Zarr input replaced while it is read: refused, never a mix (volwarp_cli.io.mapped).

A store is a folder whose chunks are read by path as the work goes; one put
in its place meanwhile (`volwarp convert B.ome.zarr -o S.ome.zarr` swaps the
whole store in by renames) had the rest of the read take the new store's
chunks: a distance by blocks wrote a field that was neither A's nor B's, exit
0, or failed with "chunk data is damaged" (the old shard index, the new
shard), and a store of another layout read as zeros (its chunk keys missing).
Each test swaps the store at a chosen point of the read, by the renames
volwarp's own writer makes (:func:`volwarp_cli.io.atomic._exchange`).
"""

from __future__ import annotations

import os
import pickle
import shutil

import numpy as np
import pytest

from volwarp_cli.errors import FormatError
from volwarp_cli.io import atomic, omezarr, read_volume
from volwarp_cli.volume import Volume

N, CHUNK = 32, 8


def _volume(seed: int) -> Volume:
    z, y, x = np.mgrid[:N, :N, :N]
    return Volume((((x - 15) ** 2 + (y - 16) ** 2 + (z - 14 - seed) ** 2) * (1 + seed))
                  .astype(np.int16))


def _store(path, seed: int, version: str = "0.5", chunks=CHUNK):
    omezarr.write_omezarr(_volume(seed), path, version=version, chunks=(chunks,) * 3)
    return path


def _swap(new, path) -> None:
    """Put the store ``new`` at ``path`` as volwarp's store writer does, the old one removed.

    One exchange of the two names, or two renames where the system has none.
    """
    aside = f"{path}.old"
    if atomic._exchange(new, path):
        os.rename(new, aside)
    else:
        os.rename(path, aside)
        os.rename(new, path)
    shutil.rmtree(aside)


@pytest.fixture
def stores(tmp_path):
    """``(S, other)``: the input store S (A's samples); ``other(version, chunks)`` writes
    B now (outside any run: a run's own writes are renamed at its end) and gives the call
    that puts it in S's place, once."""
    src = _store(tmp_path / "S.ome.zarr", 0)

    def other(version="0.5", chunks=CHUNK):
        new = _store(tmp_path / "B.ome.zarr", 1, version, chunks)
        swapped = []

        def replace():
            if not swapped:
                swapped.append(_swap(new, src))
        return replace

    return src, other


def _listing(folder) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


def _swapped_after(monkeypatch, reads: int, replace) -> list:
    """Call ``replace`` once ``reads`` reads of level 0 (regions larger than one voxel) are done."""
    real = omezarr.read_region
    done = []

    def read(opened, region):
        if any(r.stop - r.start > 1 for r in region):
            done.append(region)
        out = real(opened, region)
        if len(done) == reads:
            replace()
        return out

    monkeypatch.setattr(omezarr, "read_region", read)
    return done


@pytest.mark.parametrize("how", [{}, {"version": "0.4"}, {"chunks": 16}],
                         ids=["same-layout", "v0.4", "other-chunks"])
def test_a_store_replaced_while_read_by_blocks_writes_nothing(run, stores, tmp_path,
                                                              monkeypatch, how):
    """The bug hunt's case: distance by blocks, the store swapped after the first block.
    Before: exit 0 and a field mixing A's and B's (or of zeros for the missing keys of
    a store of another layout), or "chunk data is damaged"."""
    _read_by_box(monkeypatch)
    src, other = stores
    out = tmp_path / "d.nrrd"
    out.write_bytes(b"old output")
    done = _swapped_after(monkeypatch, 1, other(**how))
    r = run("distance", src, "--iso", "400", "--values", "intensity", "--surface", "voxel",
            "-o", out, "--chunked", "--block", "8", "--scheduler", "synchronous")
    assert len(done) > 1, "the input was not read by blocks"
    assert r.code == 1, r
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "S.ome.zarr: the store changed while it was being read" \
        in lines[0], r.stderr
    assert "damaged" not in r.stderr
    assert out.read_bytes() == b"old output"
    assert _listing(tmp_path) == ["S.ome.zarr", "d.nrrd"]  # (no temporary left)


def _read_by_box(monkeypatch) -> None:
    """Stores read by box whatever their size (as those too big for their budget share are:
    one that fits is read whole, its chunks decoded once)."""
    from volwarp_cli.io import lazy

    monkeypatch.setattr(lazy, "_fits_whole", lambda nbytes: False)


@pytest.mark.parametrize("by_box", [True, False], ids=["by-box", "read-whole"])
def test_a_worker_process_reading_the_new_store_cannot_hide_it(stores, tmp_path, monkeypatch,
                                                               by_box):
    """Worker processes (`--scheduler processes`) get the input pickled and reopen the store
    by its path: swapped between the command's opening and a worker's, the worker reads B
    whole, under A's opening. The command's watch refuses the output. (A worker's own
    pickled copy here: a run with processes takes longer than a test may.)"""
    from volwarp_cli.cli.chunked import lazy_input
    from volwarp_cli.io import write_volume
    from volwarp_cli.runscope import run_scope

    if by_box:  # (else the store, which fits, is read whole: the worker reopens it all the same)
        _read_by_box(monkeypatch)
    src, other = stores
    replace = other()
    out = tmp_path / "d.nrrd"
    with run_scope():
        header, source = lazy_input(src)
        replace()
        worker = pickle.loads(pickle.dumps(source))
        assert worker._array is None  # (reopened by path where it is read)
        samples = worker[:, :, :]
        assert np.array_equal(samples, _volume(1).data)  # (B's, whole)
        with pytest.raises(FormatError, match=r"S\.ome\.zarr: the store changed while it "
                                              r"was being read"):
            write_volume(Volume(samples, spacing=header.spacing, origin=header.origin), out)
    assert not out.exists() and _listing(tmp_path) == ["S.ome.zarr"]


class Rows(list):
    """The rows of chunks read (not a one-voxel read); ``hook`` called after the first one."""

    hook = None


@pytest.fixture
def by_rows(monkeypatch):
    """A whole read in rows of chunks (zarr reads each row's chunks at once)."""
    import zarr

    monkeypatch.setattr(omezarr, "ROW_BYTES", 1)
    real = zarr.Array.__getitem__
    rows = Rows()

    def row(self, key):
        got = real(self, key)
        if got.size > 1:
            rows.append(key)
            if len(rows) == 1 and rows.hook:
                rows.hook()
        return got

    monkeypatch.setattr(zarr.Array, "__getitem__", row)
    return rows


@pytest.mark.parametrize("how", [{}, {"version": "0.4"}], ids=["same-layout", "v0.4"])
def test_a_store_replaced_during_an_in_memory_read_is_refused(stores, by_rows, how):
    """An in-memory read is not one step either: it reads row after row of chunks, by
    path. Swapped after the first row, it gave A's first rows and B's others (or zeros)."""
    src, other = stores
    by_rows.hook = other(**how)
    with pytest.raises(FormatError, match=r"S\.ome\.zarr: the store changed while it was "
                                          r"being read"):
        read_volume(src)
    assert len(by_rows) > 1, "not read in rows"


@pytest.mark.parametrize("how", [{}, {"version": "0.4"}], ids=["same-layout", "v0.4"])
def test_an_in_memory_run_of_a_replaced_store_writes_nothing(run, stores, tmp_path, by_rows,
                                                             how):
    """A command run in memory (one block) reads the store whole, row by row, first to see
    whether it is a label map: swapped after the first row, the mix was taken for one
    ("looks like a label map", exit 2) or its field written, exit 0."""
    src, other = stores
    out = tmp_path / "d.nrrd"
    out.write_bytes(b"old output")
    by_rows.hook = other(**how)
    r = run("distance", src, "--iso", "400", "--surface", "voxel", "-o", out)
    assert len(by_rows) > 1, "not read in rows"
    assert r.code == 1 and "S.ome.zarr: the store changed while it was being read" \
        in r.stderr, r
    assert out.read_bytes() == b"old output"
    assert _listing(tmp_path) == ["S.ome.zarr", "d.nrrd"]


def test_a_level_0_rewritten_by_zarr_while_read_by_blocks_writes_nothing(run, stores, tmp_path,
                                                                         monkeypatch):
    """Not a new store: chunks of its level 0 written over by another program (zarr writes
    a chunk to a temporary and renames it into place)."""
    import zarr

    _read_by_box(monkeypatch)
    src = stores[0]
    out = tmp_path / "d.nrrd"

    def rewrite():
        arr = zarr.open_array(str(src / "0"), mode="r+")
        arr[24:] = 7

    _swapped_after(monkeypatch, 1, rewrite)
    r = run("distance", src, "--iso", "400", "--values", "intensity", "--surface", "voxel",
            "-o", out, "--chunked", "--block", "8", "--scheduler", "synchronous")
    assert r.code == 1 and "S.ome.zarr: the store changed while it was being read" \
        in r.stderr, r
    assert not out.exists()


def test_a_decode_error_of_a_replaced_store_names_the_change(stores):
    """The opening's array (A's chunk grid) reads B's shards: their indexes do not decode.
    That is a store that changed, not a damaged one."""
    src, other = stores
    replace = other(chunks=16)
    opened = omezarr.open_omezarr(src)
    replace()
    with pytest.raises(FormatError, match=r"the store changed while it was being read") as err:
        omezarr.read_region(opened, (slice(0, N),) * 3)
    assert "damaged" not in str(err.value)


def test_a_damaged_store_that_did_not_change_is_still_damaged(stores):
    """(The check on a failed read says "changed" only where the store did.)"""
    src = stores[0]
    shard = next(p for p in (src / "0").rglob("*") if p.is_file() and p.name != "zarr.json")
    data = bytearray(shard.read_bytes())
    data[40] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="chunk data is damaged"):
        read_volume(src)
