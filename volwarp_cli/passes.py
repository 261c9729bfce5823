"""Operations in passes: each pass runs on blocks of whole lines, scratch arrays between them.

Some operations are separable but not local: the exact distance transform
sets a voxel from the whole line through it along one axis, then along the
next (:func:`volwarp_cli.regions.distance_pass_input`). No halo makes a block
of such a field from a box of its input; they run in passes instead, each
pass on blocks holding whole lines along its axes, the values between passes
kept in scratch arrays of the grid's shape.

A :class:`Passes` operation states its scratch arrays and its :class:`Pass`
es; :func:`volwarp_cli.execute.run` decides how it runs, as for any
operation (its whole's memory against the budget, before any work), and
:func:`run_whole` or :func:`run_by_blocks` runs it:

- in memory: the scratch and the outputs are arrays; each pass's blocks run
  on the calling threads, a block a view of the arrays (the kernels work in
  place: :class:`ArrayStore`);
- by blocks: the scratch are files next to the first output
  (:class:`FileStore`), each pass's blocks are block tasks on the engine,
  the last pass's blocks are the outputs' blocks, written into them.

The same pass functions on the same lines either way: the same bytes.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .box import Box
from .execute import Operation
from .progress import timed


# -- where a pass's blocks read and write ----------------------------------------------
class ArrayStore:
    """An array in memory: a block is a view of it, so a pass can work in place."""

    def __init__(self, array: np.ndarray):
        self.array = array

    def read(self, box: Box) -> np.ndarray:
        """The samples of ``box``: a view (writing it writes the store)."""
        return self.array[box.slices]

    def empty(self, box: Box) -> np.ndarray:
        """Where a block's values for ``box`` go: the view itself."""
        return self.array[box.slices]

    def write(self, box: Box, data: np.ndarray) -> None:
        """Store ``data`` in ``box`` (nothing to do when it is the store's own view)."""
        view = self.array[box.slices]
        if view.__array_interface__ != getattr(data, "__array_interface__", None):
            view[...] = data


class FileStore:
    """A scratch file of the grid's shape, read and written by box (:mod:`.io.filearray`)."""

    def __init__(self, folder, name: str, shape, dtype):
        from .io.filearray import FileArray

        path = folder / f"{name}.scratch"
        dtype = np.dtype(dtype)
        with open(path, "wb") as fh:
            fh.truncate(math.prod(int(n) for n in shape) * dtype.itemsize)
        self.file = FileArray(path, dtype, 0, tuple(shape), writable=True)

    def read(self, box: Box) -> np.ndarray:
        """A contiguous copy of ``box``'s samples."""
        return np.ascontiguousarray(self.file[box.slices])

    def empty(self, box: Box) -> np.ndarray:
        """A new array for ``box``'s values (nothing is read)."""
        return np.empty(box.shape, self.file.dtype)

    def write(self, box: Box, data: np.ndarray) -> None:
        """Write ``data`` into ``box``."""
        self.file[box.slices] = data

    def close(self) -> None:
        """Close the file (the scratch folder removes it)."""
        self.file.close()


class OutputStore:
    """An output written block by block: the last pass writes into it, nothing reads it."""

    def __init__(self, writer):
        self.writer = writer

    def empty(self, box: Box) -> np.ndarray:
        """Not for an output: its blocks are written whole (the last pass's)."""
        raise TypeError("an output's blocks are written, not filled in place")

    read = empty

    def write(self, box: Box, data: np.ndarray) -> None:
        """Write ``data`` into ``box`` of the output."""
        self.writer.write(box, data)


# -- the operation -------------------------------------------------------------------------
@dataclass(frozen=True)
class Pass:
    """One pass: ``block(box, stores)`` on blocks holding whole lines along ``whole``.

    ``whole``: the axes (0 z, 1 y, 2 x) a block holds whole (``(1, 2)``:
    slabs of whole planes); ``bytes_per_voxel``: what a block holds at its
    peak, per voxel of its box; ``block(box, stores)`` reads and writes the
    stores (scratch names and target keys) for its box and returns a value
    (a block's statistics, or None); ``after(values)``: the pass's values in
    block order, called before the next pass (a check of the whole).
    """

    name: str
    whole: tuple[int, ...]
    bytes_per_voxel: int
    block: Callable
    after: Callable | None = None


class Passes(Operation):
    """An operation computed in :class:`Pass` es (module notes).

    Subclasses set ``grid``, ``targets`` and ``what`` as every operation,
    ``scratch`` (name -> dtype: arrays of the grid's shape kept between
    passes) and ``aliases`` (target key -> scratch name: in memory the
    target's samples are that scratch array, where the types agree, so the
    last pass finishes in place), and define :meth:`passes`. The last pass
    writes every target.
    """

    scratch: dict = {}
    aliases: dict = {}
    #: the first word of the block tasks' ids in progress lines (``distance-xy-0-0-0``)
    label: str = "pass"

    def passes(self, block_bytes: int | None) -> list[Pass]:
        """The passes, for blocks of ``block_bytes`` (None: in memory, no limit)."""
        raise NotImplementedError

    def memory(self, box: Box) -> int:
        """The whole's arrays (scratch, outputs not aliased) and the passes' block temporaries."""
        voxels = box.size
        held = sum(np.dtype(d).itemsize for d in self.scratch.values())
        for key, target in self.targets.items():
            if not self._aliased(key):
                held += target.nbytes((1, 1, 1))
        return voxels * (held + max(p.bytes_per_voxel for p in self.passes(None)))

    def scratch_files(self) -> list:
        """``[(path, nbytes)]`` of the scratch files by blocks (beside the first output)."""
        first = next(iter(self.targets.values()))
        size = self.grid.size * sum(np.dtype(d).itemsize for d in self.scratch.values())
        return [(first.path, size)] if size else []

    def _aliased(self, key) -> bool:
        name = self.aliases.get(key)
        return name is not None and np.dtype(self.scratch[name]) == np.dtype(self.targets[key].dtype)

    def compute(self, box: Box, *, threads: int) -> dict:
        """The whole's results (``box`` the whole grid): the passes in memory."""
        if box != self.grid.box:
            raise ValueError("an operation in passes computes the whole grid only")
        return run_whole(self, threads)


def pass_boxes(shape, whole, *, block_bytes: int | None, bytes_per_voxel: int,
               min_blocks: int = 1, block=None) -> list[Box]:
    """The blocks of a pass over ``shape``: whole along ``whole``, within ``block_bytes``.

    The other axes are cut, the faster one (the later array axis) kept as long
    as the budget allows, so that a block is few long contiguous runs; a
    single line longer than the budget still makes a block (a pass needs it
    whole). With fewer than ``min_blocks`` blocks the slowest cut axis is
    cut further, so that every thread has work. ``block``: the user's block
    shape (z, y, x), its ``whole`` axes made whole.
    """
    shape = tuple(int(n) for n in shape)
    free = [a for a in range(3) if a not in whole]
    if block is not None:
        size = [shape[a] if a in whole else max(1, min(int(block[a]), shape[a]))
                for a in range(3)]
        return Box.from_shape(shape).blocks(tuple(size))
    size = list(shape)
    room = (math.prod(shape) if block_bytes is None
            else max(1, int(block_bytes) // max(1, bytes_per_voxel)))
    room = max(1, room // max(1, math.prod(shape[a] for a in whole)))
    for a in reversed(free):
        size[a] = max(1, min(shape[a], room))
        room = max(1, room // size[a])
    def count():
        return math.prod(math.ceil(shape[a] / size[a]) for a in free)

    for a in free:  # slowest first, until there are blocks enough
        if count() >= min_blocks:
            break
        others = count() // math.ceil(shape[a] / size[a])
        want = min(shape[a], math.ceil(min_blocks / max(1, others)))
        size[a] = max(1, min(size[a], shape[a] // want))
    return Box.from_shape(shape).blocks(tuple(size))


def run_whole(op: Passes, threads: int) -> dict:
    """``op`` in memory: its passes over arrays, on ``threads`` threads; the targets' arrays."""
    from . import parallel

    shape = op.grid.shape
    stores = {name: ArrayStore(np.empty(shape, dtype)) for name, dtype in op.scratch.items()}
    for key, target in op.targets.items():
        stores[key] = (stores[op.aliases[key]] if op._aliased(key)
                       else ArrayStore(np.empty(shape, target.dtype)))
    for p in op.passes(None):
        boxes = pass_boxes(shape, p.whole, block_bytes=None, bytes_per_voxel=p.bytes_per_voxel,
                           min_blocks=threads)
        with timed(f"{op.what}: pass {p.name}"):
            values = parallel.run_blocks(lambda b, p=p: p.block(b, stores), boxes, threads)
        if p.after is not None:
            p.after(values)
    return {key: stores[key].array for key in op.targets}


def run_by_blocks(op: Passes, engine, outputs: dict, *, block_bytes: int, block=None) -> int:
    """``op`` by blocks on ``engine``: scratch files, the last pass into ``outputs``.

    ``outputs``: target key -> an opened
    :class:`~volwarp_cli.io.blockwrite.BlockOutput` whose blocks are the
    last pass's (:func:`last_pass_block`); ``block_bytes``: one task's
    memory; ``block``: the user's block shape. Returns the number of block
    tasks run.
    """
    from .io.atomic import scratch_folder

    passes = op.passes(block_bytes)
    first = next(iter(op.targets.values()))
    count = 0
    with scratch_folder(first.path) as folder, contextlib.ExitStack() as stack:
        stores = {}
        for name, dtype in op.scratch.items():
            stores[name] = FileStore(folder, name, op.grid.shape, dtype)
            stack.callback(stores[name].close)
        for key, out in outputs.items():
            stores[key] = OutputStore(out.writer())
        for i, p in enumerate(passes):
            if i == len(passes) - 1:
                boxes = next(iter(outputs.values())).blocks()
            else:
                boxes = pass_boxes(op.grid.shape, p.whole, block_bytes=block_bytes,
                                   bytes_per_voxel=p.bytes_per_voxel,
                                   min_blocks=4 * max(1, engine.workers), block=block)
            tasks = [engine.block_delayed(_pass_task, f"{op.label}-{p.name}-{'-'.join(map(str, b.lo))}",
                                          p.block, b, stores, memory=block_bytes,
                                          keep=p.after is not None)
                     for b in boxes]
            stats = engine.run(tasks, label=f"{op.what}: pass {p.name}")
            if p.after is not None:
                p.after([s.value for s in stats])
            count += len(tasks)
        for out in outputs.values():
            out.mark_written(boxes)
    return count


def heaviest_pass_block(op: Passes, block, block_bytes: int) -> tuple[tuple[int, ...], int]:
    """The largest block the user's ``block`` gives any pass, and the bytes it holds.

    Each pass makes ``block`` whole along its axes (:func:`pass_boxes`), so
    its blocks are larger than ``block``; the passes are those for blocks of
    ``block_bytes``. For :func:`volwarp_cli.execute.refuse_block_over_budget`,
    before any work.
    """
    heaviest: tuple[tuple[int, ...], int] = (tuple(block), 0)
    for p in op.passes(block_bytes):
        boxes = pass_boxes(op.grid.shape, p.whole, block_bytes=block_bytes,
                           bytes_per_voxel=p.bytes_per_voxel, block=block)
        box = max(boxes, key=lambda b: b.size)
        if box.size * p.bytes_per_voxel > heaviest[1]:
            heaviest = (tuple(box.shape), box.size * p.bytes_per_voxel)
    return heaviest


def _pass_task(block: Callable, box: Box, stores: dict):
    return block(box, stores)


def last_pass_block(op: Passes, *, block_bytes: int, workers: int, block=None
                    ) -> tuple[int, int, int]:
    """The outputs' block shape by blocks: the last pass's blocks (whole along its axes)."""
    last = op.passes(block_bytes)[-1]
    boxes = pass_boxes(op.grid.shape, last.whole, block_bytes=block_bytes,
                       bytes_per_voxel=last.bytes_per_voxel, min_blocks=4 * max(1, workers),
                       block=block)
    return boxes[0].shape if boxes else tuple(op.grid.shape)
