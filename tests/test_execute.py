"""The one executor (volwarp_cli.execute): the in-memory run is the one-block case.

A synthetic operation whose every sample is known (``100 z + 10 y + x`` in world-free
index arithmetic, and a second output of its squares) is run in memory and by blocks of
odd shapes on threads and synchronously: the files are the same bytes and hold the
analytic values. The decision is made by arithmetic before any work (a budget that the
whole exceeds runs blocks, with one warning; ``--no-chunked`` then refuses with the
sizes; an output format written whole refuses blocks), and a refusal or a failing block
leaves nothing behind.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli import execute, memory
from volwarp_cli.box import Box
from volwarp_cli.engine import open_engine
from volwarp_cli.errors import OutOfMemoryError, VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import read_volume
from volwarp_cli.io.nrrd import read_nrrd

SHAPE = (11, 13, 17)  # z, y, x: no block shape below divides them


class Ramp(execute.Operation):
    """``v = 100 z + 10 y + x`` (int32) and its square (float64): analytic samples."""

    def __init__(self, folder, *, fail_at=None, multi=False, suffix=".nrrd", bytes_per=12):
        self.grid = Geometry(SHAPE, (1.0, 2.0, 3.0), (5.0, 6.0, 7.0))
        self.what = "ramp 17x13x11"
        self.fail_at = fail_at
        self.bytes_per = bytes_per
        self.computed = []
        if multi:
            self.targets = {None: execute.Target(folder / f"both{suffix}", self.grid.header(
                np.int32, meta={"k": "v"}), np.dtype(np.float64), components=("v", "sq"))}
        else:
            self.targets = {
                "v": execute.Target(folder / f"v{suffix}", self.grid.header(
                    np.int32, meta={"k": "v"}), np.dtype(np.int32)),
                "sq": execute.Target(folder / f"sq{suffix}", self.grid.header(
                    np.int32, meta={"k": "sq"}), np.dtype(np.float64))}

    def memory(self, box):
        return int(box.size) * self.bytes_per

    def compute(self, box, *, threads):
        self.computed.append((box, threads))
        if self.fail_at is not None and box.contains(self.fail_at):
            raise VolwarpError("a block failed")
        z, y, x = np.meshgrid(*(np.arange(a, b) for a, b in zip(box.lo, box.hi, strict=True)),
                              indexing="ij")
        v = (100 * z + 10 * y + x).astype(np.int32)
        return {"v": v, "sq": v.astype(np.float64) ** 2}

    def output(self, results, key):
        if key is None:
            return np.stack([results["v"].astype(np.float64), results["sq"]], axis=-1)
        return results[key]


def _expected():
    z, y, x = np.meshgrid(*(np.arange(n) for n in SHAPE), indexing="ij")
    v = (100 * z + 10 * y + x).astype(np.int32)
    return v, v.astype(np.float64) ** 2


def _blocks(block=(4, 5, 6), scheduler="threads"):
    return execute.How(chunked=True, block=block,
                       open_engine=lambda: open_engine(scheduler, workers=2))


@pytest.mark.parametrize("scheduler", ["threads", "synchronous"])
@pytest.mark.parametrize("block", [(4, 5, 6), (11, 1, 17), (3, 13, 2)])
def test_by_blocks_writes_the_in_memory_bytes(tmp_path, scheduler, block):
    (tmp_path / "m").mkdir()
    (tmp_path / "b").mkdir()
    mem = execute.run(Ramp(tmp_path / "m"), execute.How(chunked=False))
    op = Ramp(tmp_path / "b")
    blk = execute.run(op, _blocks(block, scheduler))
    assert not mem.by_blocks and blk.by_blocks and blk.block == block
    v, sq = _expected()
    for name, want in (("v", v), ("sq", sq)):
        a, b = tmp_path / "m" / f"{name}.nrrd", tmp_path / "b" / f"{name}.nrrd"
        assert a.read_bytes() == b.read_bytes()
        vol = read_volume(b)
        assert np.array_equal(vol.data, want) and vol.meta["k"] == name
        assert tuple(vol.origin) == (5.0, 6.0, 7.0) and tuple(vol.spacing) == (1.0, 2.0, 3.0)
    if scheduler == "synchronous":  # (the tasks ran here: each block once, on one thread)
        boxes = [b for b, _ in op.computed]
        assert sorted(b.lo for b in boxes) == sorted(b.lo for b in Box.from_shape(SHAPE)
                                                     .blocks(block))
        assert {t for _, t in op.computed} == {1}


def test_in_memory_is_one_block_on_the_calling_threads(tmp_path):
    op = Ramp(tmp_path)
    ran = execute.run(op, execute.How(threads=3))
    assert not ran.by_blocks
    assert op.computed == [(Box.from_shape(SHAPE), 3)]
    assert np.array_equal(ran.results["v"], _expected()[0])


def test_a_multi_component_output_by_blocks_is_the_in_memory_file(tmp_path):
    (tmp_path / "m").mkdir()
    (tmp_path / "b").mkdir()
    execute.run(Ramp(tmp_path / "m", multi=True), execute.How(chunked=False))
    execute.run(Ramp(tmp_path / "b", multi=True), _blocks())
    assert (tmp_path / "m/both.nrrd").read_bytes() == (tmp_path / "b/both.nrrd").read_bytes()
    assert np.array_equal(read_nrrd(tmp_path / "b/both.nrrd", component=1).data, _expected()[1])


def test_the_whole_over_the_budget_runs_by_blocks_with_one_warning(tmp_path, caplog,
                                                                   monkeypatch):
    import logging

    from volwarp_cli.progress import log

    monkeypatch.setattr(memory, "process_rss", lambda: 0)  # (a budget of its own: 2 GiB)
    # (a command run earlier in this process keeps the volwarp logger to its own handler;
    # the logger itself: progress.log stands in for it)
    real = logging.getLogger("volwarp")
    monkeypatch.setattr(real, "level", logging.WARNING)
    monkeypatch.setattr(real, "propagate", False)
    log.addHandler(caplog.handler)
    op = Ramp(tmp_path, bytes_per=2 << 20)  # (the whole: 4.7 GiB; a 6x7x8 block 672 MiB)
    how = execute.How(block=(6, 7, 8), open_engine=lambda: open_engine("threads", workers=2))
    try:
        with memory.use_memory_limit(2 << 30):
            ran = execute.run(op, how)
    finally:
        log.removeHandler(caplog.handler)
    assert ran.by_blocks
    assert [r.getMessage() for r in caplog.records
            if "running by blocks" in r.getMessage()] == [
        "ramp 17x13x11 needs 4.7 GiB: running by blocks (--no-chunked to refuse instead)"]
    assert np.array_equal(read_volume(tmp_path / "v.nrrd").data, _expected()[0])


def test_a_user_block_over_a_task_s_budget_is_refused_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setattr(memory, "process_rss", lambda: 0)  # (a budget of its own: 2 GiB)
    old = tmp_path / "v.nrrd"
    old.write_bytes(b"an earlier output")
    op = Ramp(tmp_path, bytes_per=4 << 20)  # a 6x7x8 block: 1.3 GiB, a task has < 1 GiB
    how = execute.How(block=(6, 7, 8), open_engine=lambda: open_engine("threads", workers=2))
    with memory.use_memory_limit(2 << 30), pytest.raises(OutOfMemoryError) as err:
        execute.run(op, how)
    assert str(err.value).startswith("ramp 17x13x11: a block of 6x7x8 (z, y, x) needs 1.3 GiB")
    assert "each of 2 workers may use" in str(err.value) and "\n" not in str(err.value)
    assert op.computed == [] and old.read_bytes() == b"an earlier output"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.nrrd"]


def test_no_chunked_refuses_with_the_sizes_and_writes_nothing(tmp_path):
    op = Ramp(tmp_path, bytes_per=1 << 30)
    with memory.use_memory_limit(2 << 30), pytest.raises(OutOfMemoryError) as err:
        execute.run(op, execute.How(chunked=False))
    assert "ramp 17x13x11 needs 2.4 TiB but only" in str(err.value)
    assert op.computed == [] and list(tmp_path.iterdir()) == []


def test_an_output_written_whole_refuses_blocks_with_both_reasons(tmp_path):
    op = Ramp(tmp_path, bytes_per=1 << 30, suffix=".nii.gz")  # (NIfTI: written whole)
    how = execute.How(open_engine=lambda: open_engine("threads", workers=2))
    with memory.use_memory_limit(2 << 30), pytest.raises(OutOfMemoryError) as err:
        execute.run(op, how)
    message = str(err.value)
    assert message.startswith("ramp 17x13x11 needs 2.4 TiB") and ", and by blocks " in message
    assert "cannot be written block by block" in message
    assert op.computed == [] and list(tmp_path.iterdir()) == []


def test_a_failing_block_leaves_nothing_and_an_old_output_untouched(tmp_path):
    old = tmp_path / "v.nrrd"
    old.write_bytes(b"an earlier output")
    with pytest.raises(VolwarpError, match="a block failed"):
        execute.run(Ramp(tmp_path, fail_at=(7, 7, 7)), _blocks())
    assert old.read_bytes() == b"an earlier output"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.nrrd"]


def test_the_after_hook_reads_what_was_written(tmp_path):
    """In memory it gets the results; by blocks it reads the outputs back, before the commit."""
    box = Box((2, 3, 4), (9, 10, 11))

    def peek(ran):
        got = ran.results["v"][box.slices] if ran.results is not None else ran.read("v", box)
        assert not (tmp_path / "b" / "v.nrrd").exists()  # (by blocks: not committed yet)
        return np.array(got)

    (tmp_path / "m").mkdir()
    (tmp_path / "b").mkdir()
    a = execute.run(Ramp(tmp_path / "m"), execute.How(chunked=False), after=peek).after
    b = execute.run(Ramp(tmp_path / "b"), _blocks(), after=peek).after
    assert np.array_equal(a, b) and np.array_equal(a, _expected()[0][box.slices])


def test_the_default_blocks_fit_the_task_and_feed_every_worker():
    class Big(execute.Operation):
        grid = Geometry((40, 50, 60))
        what = "big"

        def memory(self, box):
            return int(box.size) * 36

    op = Big()
    for workers in (1, 2, 8, 64):
        block = op.block_shape(1 << 30, workers)
        count = np.prod([-(-n // b) for n, b in zip(op.grid.shape, block, strict=True)])
        assert count >= 2 * workers or min(block) <= 16
    for per_task in (36 * 9 ** 3, 36 * 23 ** 3 + 5, 36 * 30 ** 3):
        edge = op.block_shape(per_task, 1)[0]
        assert edge ** 3 * 36 <= per_task < (edge + 2) ** 3 * 36
    assert op.block_shape(1, 1) == (8, 8, 8)  # never below 8


def _block_that_warns(n):
    from volwarp_cli.progress import log

    log.warning("warning: block %d saw a NaN", n)
    return n


def _block_that_fails_later(n):
    import time

    time.sleep(1.5)  # (the other block has ended by then)
    raise VolwarpError(f"block {n} failed")


def test_a_worker_blocks_warning_is_said_when_a_later_block_fails(caplog):
    """Warnings of worker processes' blocks are said as each block ends, not lost to a failure."""
    from volwarp_cli.engine import block_delayed
    from volwarp_cli.runscope import run_scope

    tasks = [block_delayed(_block_that_warns, "warns", 1),
             block_delayed(_block_that_fails_later, "fails", 2)]
    with run_scope(), open_engine("processes", workers=2) as engine, \
            pytest.raises(VolwarpError, match="block 2 failed"):
        engine.run(tasks)
    assert caplog.text.count("block 1 saw a NaN") == 1


def _block_that_warns_then_fails(n):
    from volwarp_cli.progress import log

    log.warning("warning: block %d saw a NaN before it failed", n)
    raise VolwarpError(f"block {n} failed")


def test_a_failing_worker_blocks_own_warning_is_said_with_its_error(caplog):
    """A worker process's block that warns and then fails: its warning goes back with the error."""
    from volwarp_cli.engine import block_delayed
    from volwarp_cli.runscope import run_scope

    with run_scope(), open_engine("processes", workers=2) as engine, \
            pytest.raises(VolwarpError, match="block 3 failed"):
        engine.run([block_delayed(_block_that_warns_then_fails, "fails", 3)])
    assert caplog.text.count("block 3 saw a NaN before it failed") == 1


@pytest.fixture
def placed_small(monkeypatch):
    """Outputs of any size written as computed (SHAPE's are below STREAMED_FROM)."""
    monkeypatch.setattr(execute, "STREAMED_FROM", 0)


class PlacedRamp(Ramp):
    """Ramp whose in-memory run places its samples a plane at a time (compute_into),
    from two threads, the planes in a scrambled order; ``fail_at``: a plane whose
    placing fails, after others were placed."""

    streams = True

    def compute_into(self, box, *, threads, place):
        from volwarp_cli import parallel

        self.computed.append(("placed", threads))

        def plane(z):
            if self.fail_at is not None and z == self.fail_at[0]:
                raise VolwarpError("a plane failed")
            one = Box((z, box.lo[1], box.lo[2]), (z + 1, box.hi[1], box.hi[2]))
            for key, samples in Ramp.compute(self, one, threads=1).items():
                if key in place:
                    place[key](one, samples)

        order = list(range(box.lo[0], box.hi[0]))
        parallel.run_blocks(plane, order[1::2] + order[::2], 2)


@pytest.mark.parametrize("suffix", [".nrrd", ".mha", ".raw"])
def test_an_output_placed_as_computed_is_the_file_written_whole(placed_small, tmp_path, suffix):
    (tmp_path / "m").mkdir()
    (tmp_path / "p").mkdir()
    execute.run(Ramp(tmp_path / "m", suffix=suffix), execute.How(chunked=False))
    op = PlacedRamp(tmp_path / "p", suffix=suffix)
    ran = execute.run(op, execute.How(chunked=False, threads=2))
    assert not ran.by_blocks and ran.results is None
    assert op.computed[0] == ("placed", 2) and all(t == 1 for _, t in op.computed[1:])
    for name in ("v", "sq"):
        assert ((tmp_path / "p" / f"{name}{suffix}").read_bytes()
                == (tmp_path / "m" / f"{name}{suffix}").read_bytes())
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == [f"sq{suffix}", f"v{suffix}"]


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz", ".nhdr", ".tif", ".ome.zarr"])
def test_outputs_not_written_by_offset_are_computed_whole(placed_small, tmp_path, suffix):
    op = PlacedRamp(tmp_path, suffix=suffix)
    ran = execute.run(op, execute.How(chunked=False, threads=2))
    assert ran.results is not None and op.computed == [(Box.from_shape(SHAPE), 2)]
    assert np.array_equal(read_volume(tmp_path / f"v{suffix}").data, _expected()[0])


def test_an_after_hook_gets_the_whole_in_memory(placed_small, tmp_path):
    """(It may read any part of the results: they are computed whole, not placed.)"""
    op = PlacedRamp(tmp_path)
    ran = execute.run(op, execute.How(chunked=False), after=lambda r: r.results["v"][1, 2, 3])
    assert ran.after == 123 and op.computed[0][0] == Box.from_shape(SHAPE)
    assert np.array_equal(read_volume(tmp_path / "v.nrrd").data, _expected()[0])


def test_a_failure_while_placing_leaves_nothing_and_an_old_output_untouched(placed_small, tmp_path):
    old = tmp_path / "v.nrrd"
    old.write_bytes(b"an earlier output")
    op = PlacedRamp(tmp_path, fail_at=(4, 0, 0))
    with pytest.raises(VolwarpError, match="a plane failed"):
        execute.run(op, execute.How(chunked=False, threads=2))
    assert len(op.computed) > 2  # (other planes were placed first)
    assert old.read_bytes() == b"an earlier output"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.nrrd"]


@pytest.mark.parametrize("how", ["placed", "blocks"])
def test_a_full_disk_while_writing_names_the_output_and_leaves_nothing(placed_small, tmp_path,
                                                                       monkeypatch, how):
    import errno

    from volwarp_cli.io import filearray

    def full(self, key, value):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(filearray.FileArray, "__setitem__", full)
    old = tmp_path / "v.nrrd"
    old.write_bytes(b"an earlier output")
    with pytest.raises(VolwarpError, match=r"v\.nrrd: cannot write \(No space left on device\)"):
        if how == "placed":
            execute.run(PlacedRamp(tmp_path), execute.How(chunked=False, threads=2))
        else:
            execute.run(Ramp(tmp_path), _blocks(scheduler="synchronous"))
    assert old.read_bytes() == b"an earlier output"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.nrrd"]


def test_a_full_disk_while_a_store_is_written_by_blocks_names_it(tmp_path, monkeypatch):
    """zarr let a bare OSError through: 'volwarp: error: No space left on device', no
    file named, where every other writer names its output (a review)."""
    import errno

    from volwarp_cli.io import blockwrite

    real = blockwrite._ZarrWriter._write  # (its own handling tested: the store's write fails)

    class Full:
        def __setitem__(self, key, value):
            raise OSError(errno.ENOSPC, "No space left on device")

    def failing(self, box, array):
        self.array = Full()
        return real(self, box, array)

    monkeypatch.setattr(blockwrite._ZarrWriter, "_write", failing)
    with pytest.raises(VolwarpError, match=r"v\.ome\.zarr: cannot write \(No space left"):
        # (one block, the store's one shard: written by zarr from the task)
        execute.run(Ramp(tmp_path, suffix=".ome.zarr"), _blocks(SHAPE, "synchronous"))
    assert not list(tmp_path.iterdir())


def test_a_full_disk_while_a_staged_store_is_committed_names_it(tmp_path, monkeypatch):
    """Blocks not made of the store's shards go to a scratch file first; the store's
    write on commit names the output too, and neither the scratch nor the store is left."""
    import errno

    from volwarp_cli.io import blockwrite

    real = blockwrite._ZarrOutput._unstage

    class Full:
        def __init__(self, array):
            self.shape, self.shards, self.chunks = array.shape, array.shards, array.chunks

        def __setitem__(self, key, value):
            raise OSError(errno.ENOSPC, "No space left on device")

    def failing(self):
        self._arrays[0] = Full(self._arrays[0])
        return real(self)

    monkeypatch.setattr(blockwrite._ZarrOutput, "_unstage", failing)
    with pytest.raises(VolwarpError, match=r"(v|sq)\.ome\.zarr: cannot write \(No space left"):
        execute.run(Ramp(tmp_path, suffix=".ome.zarr"), _blocks(scheduler="synchronous"))
    assert not list(tmp_path.iterdir())


@pytest.fixture
def quota_on_close(monkeypatch):
    """Files closed by the block tasks' threads report a full quota (as an NFS server may:
    the data reach it only then); the output's own file, closed by the main thread on
    commit, does not."""
    import errno
    import threading

    from volwarp_cli.io import filearray

    made = []

    class QuotaOnClose(filearray.FileArray):
        def _file(self):
            made.append(self)
            return super()._file()

        def close(self):
            had = self._fd is not None
            super().close()
            if had and threading.current_thread() is not threading.main_thread():
                raise OSError(errno.EDQUOT, "Disk quota exceeded")

    monkeypatch.setattr(filearray, "FileArray", QuotaOnClose)
    return made


@pytest.mark.parametrize("how", ["written", "placed"])
def test_an_error_closing_a_blocks_file_names_the_output_and_leaves_nothing(quota_on_close,
                                                                            tmp_path, how):
    """The descriptors a block task writes through are closed by the task, their errors
    reported (not left to a finaliser that drops them): the run fails, nothing is left."""
    old = tmp_path / "v.nrrd"
    old.write_bytes(b"an earlier output")
    op = Ramp(tmp_path) if how == "written" else PlacedRamp(tmp_path)
    with pytest.raises(VolwarpError, match=r"(v|sq)\.nrrd: cannot write \(Disk quota exceeded\)"):
        execute.run(op, _blocks(scheduler="threads"))
    assert old.read_bytes() == b"an earlier output"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.nrrd"]
    assert quota_on_close and all(f._fd is None for f in quota_on_close)  # none left open


def test_a_block_that_fails_while_placing_tells_its_own_error_not_the_close(quota_on_close,
                                                                            tmp_path):
    with pytest.raises(VolwarpError, match="a plane failed"):
        execute.run(PlacedRamp(tmp_path, fail_at=(4, 0, 0)), _blocks(SHAPE, "threads"))
    assert list(tmp_path.iterdir()) == []
    assert quota_on_close and all(f._fd is None for f in quota_on_close)  # none left open


def test_outputs_written_as_computed_are_not_counted_in_the_whole_s_memory(placed_small,
                                                                         tmp_path, monkeypatch):
    """Ramp's memory counts its results; placed as they are computed, the targets' arrays
    are never held: the decision weighs the rest (and an after hook, which gets them
    whole, weighs them again)."""
    weighed = []

    def decide(need, *args, **kwargs):
        weighed.append(need)
        return True

    monkeypatch.setattr(execute, "decide", decide)
    voxels = SHAPE[0] * SHAPE[1] * SHAPE[2]
    for kind, after, need in ((Ramp, None, 60), (PlacedRamp, None, 60 - 12),
                              (PlacedRamp, lambda ran: None, 60)):
        folder = tmp_path / f"{kind.__name__}{len(weighed)}"
        folder.mkdir()
        execute.run(kind(folder, bytes_per=60), execute.How(), after=after)
        assert weighed[-1] == voxels * need, kind
        assert np.array_equal(read_volume(folder / "v.nrrd").data, _expected()[0])


def test_small_outputs_are_computed_whole(tmp_path, monkeypatch):
    """Below STREAMED_FROM (a small command's fixed cost) the whole is an array."""
    nbytes = SHAPE[0] * SHAPE[1] * SHAPE[2] * 4
    for threshold, streamed in ((nbytes * 3 + 1, False), (nbytes * 3, True)):  # (v and sq)
        monkeypatch.setattr(execute, "STREAMED_FROM", threshold)
        folder = tmp_path / str(threshold)
        folder.mkdir()
        op = PlacedRamp(folder)
        ran = execute.run(op, execute.How(chunked=False, threads=2))
        assert (ran.results is None) == streamed and (op.computed[0][0] == "placed") == streamed
        assert np.array_equal(read_volume(folder / "v.nrrd").data, _expected()[0])


def test_an_abort_waits_for_the_planes_being_placed_and_refuses_later_ones(tmp_path,
                                                                           monkeypatch):
    """A stop aborts from the main thread while the threads place planes: the file is
    closed only once the write under way returns (its descriptor is never closed under
    it), later places are refused, and nothing is left."""
    import threading
    import time

    from volwarp_cli.io import filearray
    from volwarp_cli.io.blockwrite import open_block_output

    entered, go = threading.Event(), threading.Event()
    real = filearray.FileArray.__setitem__

    def slow(self, key, value):
        entered.set()
        assert go.wait(10)
        real(self, key, value)

    monkeypatch.setattr(filearray.FileArray, "__setitem__", slow)
    geometry = Geometry(SHAPE, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    out = open_block_output(tmp_path / "v.nrrd", geometry.header(np.float32), chunks_zyx=SHAPE)
    plane = Box((0, 0, 0), (1, SHAPE[1], SHAPE[2]))
    placing = threading.Thread(target=out.place, args=(plane, np.ones(plane.shape, np.float32)))
    placing.start()
    assert entered.wait(10)
    aborting = threading.Thread(target=out.abort)
    aborting.start()
    time.sleep(0.2)
    assert aborting.is_alive() and out._map is not None  # (waiting: the file still open)
    go.set()
    placing.join(10)
    aborting.join(10)
    assert not aborting.is_alive() and out._map is None
    with pytest.raises(ValueError, match="aborted: no more writes"):
        out.place(plane, np.ones(plane.shape, np.float32))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("scheduler", ["threads", "synchronous"])
@pytest.mark.parametrize("suffix", [".nrrd", ".ome.zarr"])
def test_block_tasks_place_their_planes_into_outputs_written_by_offset(tmp_path, scheduler,
                                                                        suffix):
    """By blocks, an operation that can place its planes does so into an NRRD (no block
    array; the file is the in-memory one), and computes its blocks whole for a store; the
    blocks' weighing leaves out what is placed. Blocks not made of the store's shards go
    to a raw scratch file by offset (no encoding), the store written on commit in its
    in-memory layout: the same files."""
    (tmp_path / "m").mkdir()
    (tmp_path / "b").mkdir()
    execute.run(Ramp(tmp_path / "m", suffix=suffix), execute.How(chunked=False))
    op = PlacedRamp(tmp_path / "b", suffix=suffix)
    block = (4, 13, 17) if suffix == ".nrrd" else (4, 5, 6)
    ran = execute.run(op, _blocks(block, scheduler))
    assert ran.by_blocks
    placed = [c for c in op.computed if c[0] == "placed"]
    assert bool(placed) == (suffix == ".nrrd") and all(t == 1 for _, t in placed)
    assert execute.places_blocks(op) == (suffix == ".nrrd")
    voxels = 4 * 13 * 17
    weighed = execute._heaviest(op, (4, 13, 17))
    # (a store's blocks made of its shards add zarr's encoding of them, for each target;
    # staged ones, none)
    for block, staged in (((4, 13, 17), True), (SHAPE, False)):
        encoding = sum(t.block_bytes(op.grid.shape, block) for t in op.targets.values())
        assert (encoding == 0) == (suffix == ".nrrd" or staged)
    assert weighed == voxels * 12 - (voxels * 12 if suffix == ".nrrd" else 0)
    for name in ("v", "sq"):
        a, b = tmp_path / "m" / f"{name}{suffix}", tmp_path / "b" / f"{name}{suffix}"
        if suffix == ".nrrd":
            assert a.read_bytes() == b.read_bytes()
        else:
            assert _tree(a) == _tree(b)
        assert np.array_equal(read_volume(b).data, read_volume(a).data)
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == [f"sq{suffix}", f"v{suffix}"]


def _tree(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_an_abort_does_not_wait_for_its_own_thread_and_always_removes_the_temporary(tmp_path):
    """A stop can cut a place short on the thread that then aborts (the main thread places
    too when the run has one thread): that place is not waited for (it would never end),
    and a second stop while the release waits still leaves no temporary."""
    import threading

    from volwarp_cli.io.blockwrite import open_block_output
    from volwarp_cli.signals import Interrupted

    geometry = Geometry(SHAPE, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    out = open_block_output(tmp_path / "v.nrrd", geometry.header(np.float32), chunks_zyx=SHAPE)
    out._placing[threading.get_ident()] += 1  # (this thread's place, cut short by a stop)
    done = threading.Event()
    aborting = threading.Thread(target=lambda: (out.abort(), done.set()))
    aborting.start()  # (another thread: it must wait for this one's place)
    assert not done.wait(0.2)
    out._placing.clear()
    with out._lock:
        out._placed.notify_all()
    assert done.wait(10) and list(tmp_path.iterdir()) == []

    second = open_block_output(tmp_path / "w.nrrd", geometry.header(np.float32),
                               chunks_zyx=SHAPE)
    second._placing[threading.get_ident()] += 1
    second.abort()  # (this thread's own: returns at once)
    assert list(tmp_path.iterdir()) == []

    third = open_block_output(tmp_path / "x.nrrd", geometry.header(np.float32),
                              chunks_zyx=SHAPE)

    def stopped():
        raise Interrupted(2)

    third._release = stopped
    with pytest.raises(Interrupted):
        third.abort()
    assert list(tmp_path.iterdir()) == []


def test_a_compressed_output_is_not_refused_on_its_uncompressed_size(tmp_path, monkeypatch):
    """The free-disk check counts what will be written: an OME-Zarr output's chunks are
    compressed (a warp's 16 MiB output was 52 KB), so too little room for its samples
    uncompressed does not refuse it (a disk that fills still fails it, with one line); an
    uncompressed NRRD's, or a scratch file's, size is what it takes, and is refused."""
    import collections
    import shutil

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(1 << 30, 1 << 30, 1000))
    (tmp_path / "z").mkdir()
    ran = execute.run(Ramp(tmp_path / "z", suffix=".ome.zarr"), _blocks())
    assert ran.by_blocks
    assert np.array_equal(read_volume(tmp_path / "z" / "v.ome.zarr").data, _expected()[0])
    assert execute.blocks_refusal([(tmp_path / "z" / "w.ome.zarr", 1 << 20)]) is None
    (tmp_path / "n").mkdir()
    with pytest.raises(OutOfMemoryError, match=r"the outputs need .* \(2 files\) where .* has "
                                               r"1000 B free"):
        execute.run(Ramp(tmp_path / "n"), _blocks())
    assert list((tmp_path / "n").iterdir()) == []
    # a scratch file beside a compressed output takes its size
    why = execute.blocks_refusal([(tmp_path / "z" / "w.ome.zarr", 1 << 20)],
                                 scratch=[(tmp_path / "z" / "w.ome.zarr", 4000)])
    assert why is not None and "need 3.9 KiB" in why
