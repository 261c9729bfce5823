"""Operations in passes (:mod:`volwarp_cli.passes`): in memory = by blocks, and right.

An analytic operation: the running sums along x, then along z, of a ramp (a
pass needs whole lines: a sum cut at a block's edge is wrong), checked
against numpy's ``cumsum``; the same bytes in memory, by blocks of any shape,
on threads or processes, and with a budget that splits the first pass in two.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli import execute
from volwarp_cli.box import Box
from volwarp_cli.engine import open_engine
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import read_volume
from volwarp_cli.passes import Pass, Passes, pass_boxes
from volwarp_cli.volume import Header

SHAPE = (13, 11, 17)


def ramp(shape):
    z, y, x = np.indices(shape, dtype=np.float64)
    return (1 + x + 7 * y + 3 * (z % 5)).astype(np.float64)


def reference(shape):
    return np.cumsum(np.cumsum(ramp(shape), axis=2), axis=0)


class RunningSums(Passes):
    """x running sums on slabs (or on x lines, then nothing, where a plane does not fit), then z."""

    scratch = {"x": np.float64}
    aliases = {"sum": "x"}

    def __init__(self, shape, target, *, record=None):
        self.grid = Geometry(shape, (1.0, 1.0, 1.0))
        self.targets = {"sum": target}
        self.what = "running sums"
        self.record = record if record is not None else []

    def passes(self, block_bytes):
        plane = self.grid.shape[1] * self.grid.shape[2] * 24
        whole = (1, 2) if block_bytes is None or plane <= block_bytes else (2,)
        return [Pass("x", whole, 24, self._x, self._after),
                Pass("z", (0,), 24, self._z)]

    def _x(self, box, stores):
        out = stores["x"].empty(box)
        z, y, x = np.indices(box.shape)
        z, y, x = z + box.lo[0], y + box.lo[1], x + box.lo[2]
        np.cumsum((1 + x + 7 * y + 3 * (z % 5)).astype(np.float64), axis=2, out=out)
        stores["x"].write(box, out)
        return box.size

    def _after(self, values):
        self.record.append(values)

    def _z(self, box, stores):
        field = stores["x"].read(box)
        np.cumsum(field, axis=0, out=field)
        stores["sum"].write(box, field)


def _target(path, shape, dtype=np.float64):
    return execute.Target(path, Header(shape, dtype), np.dtype(dtype))


def _run(tmp_path, name, *, chunked, block=None, scheduler="threads", workers=3,
         dtype=np.float64):
    path = tmp_path / f"{name}.nrrd"
    record = []
    op = RunningSums(SHAPE, _target(path, SHAPE, dtype), record=record)

    @contextlib.contextmanager
    def engine():
        with open_engine(scheduler, workers=workers) as eng:
            yield eng

    ran = execute.run(op, execute.How(chunked=chunked, block=block, open_engine=engine))
    return np.asarray(read_volume(path).data), ran, record


def test_in_memory_is_the_reference(tmp_path):
    got, ran, record = _run(tmp_path, "m", chunked=False)
    assert not ran.by_blocks
    assert np.array_equal(got, reference(SHAPE))
    assert sum(record[0]) == math.prod(SHAPE)  # every voxel in one block of the first pass


@pytest.mark.parametrize("block", [None, (4, 3, 5), (1, 11, 1), (13, 2, 17)])
def test_by_blocks_is_the_in_memory_bytes(tmp_path, block):
    mem, _, _ = _run(tmp_path, "m", chunked=False)
    blk, ran, record = _run(tmp_path, "b", chunked=True, block=block)
    assert ran.by_blocks and ran.blocks > 2
    assert mem.tobytes() == blk.tobytes()
    assert sum(record[0]) == math.prod(SHAPE)  # the after hook saw every block's value
    if block is not None:  # the outputs' blocks: the user's, whole along z
        assert ran.block == (SHAPE[0], *block[1:])


def test_by_blocks_in_processes(tmp_path):
    mem, _, _ = _run(tmp_path, "m", chunked=False)
    blk, ran, _ = _run(tmp_path, "b", chunked=True, block=(5, 4, 6), scheduler="processes",
                       workers=2)
    assert mem.tobytes() == blk.tobytes()


def test_a_plane_over_the_budget_splits_the_first_pass(tmp_path):
    """Blocks of a few x lines: the x pass's blocks are lines, still right."""
    from volwarp_cli.passes import last_pass_block, run_by_blocks

    path = tmp_path / "s.nrrd"
    op = RunningSums(SHAPE, _target(path, SHAPE))
    budget = 24 * SHAPE[2] * 3  # three x lines
    assert op.passes(budget)[0].whole == (2,)
    block = last_pass_block(op, block_bytes=budget, workers=2)
    with open_engine("threads", workers=2) as eng, \
            op.targets["sum"].open_blocks(block) as out:
        count = run_by_blocks(op, eng, {"sum": out}, block_bytes=budget)
    assert count > 10
    assert np.array_equal(read_volume(path).data, reference(SHAPE))


def test_a_pass_that_cuts_its_lines_is_wrong():
    """The tests above can fail: running sums over blocks that cut x lines differ."""
    data = ramp(SHAPE)
    cut = np.empty(SHAPE)
    for box in Box.from_shape(SHAPE).blocks((SHAPE[0], SHAPE[1], 6)):
        cut[box.slices] = np.cumsum(data[box.slices], axis=2)
    assert not np.array_equal(np.cumsum(cut, axis=0), reference(SHAPE))


def test_a_failing_pass_leaves_no_output_and_an_old_one_untouched(tmp_path):
    path = tmp_path / "o.nrrd"
    path.write_bytes(b"old")

    class Failing(RunningSums):
        def _z(self, box, stores):
            if box.lo[1] > 0:
                raise RuntimeError("block failed")
            super()._z(box, stores)

    op = Failing(SHAPE, _target(path, SHAPE))
    with pytest.raises(RuntimeError, match="block failed"):
        execute.run(op, execute.How(chunked=True, block=(4, 3, 5),
                                    open_engine=lambda: open_engine("threads", workers=2)))
    assert path.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.nrrd"]  # no scratch left


@settings(max_examples=40, deadline=None)
@given(shape=st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 9)),
       whole=st.sampled_from([(0,), (1,), (2,), (1, 2)]),
       budget=st.integers(1, 4000), min_blocks=st.integers(1, 9))
def test_pass_boxes_tile_the_grid_with_whole_lines(shape, whole, budget, min_blocks):
    boxes = pass_boxes(shape, whole, block_bytes=budget, bytes_per_voxel=8,
                       min_blocks=min_blocks)
    seen = np.zeros(shape, np.int8)
    for b in boxes:
        seen[b.slices] += 1
        assert all(b.shape[a] == shape[a] for a in whole)
    assert np.all(seen == 1)  # a tiling: every voxel once
    line = 8 * math.prod(shape[a] for a in whole)
    if line <= budget:  # a block within the budget wherever one line is
        assert all(8 * b.size <= budget for b in boxes)
    free = math.prod(shape[a] for a in range(3) if a not in whole)
    assert len(boxes) >= min(min_blocks, free)
