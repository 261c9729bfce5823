"""One executor: an operation is written once, against a block; the whole output is one block.

ITK's streaming pipeline is the model (``itkStreamingImageFilter``: the
splitter cuts the output region and the same filter runs on each piece; the
whole image is one piece), and rasterio's ``merge`` for the decision (the
library, not the command line, decides ``[whole] if it fits else
subdivide``). An :class:`Operation` states, before any sample is read:

- its output grid and its outputs (:class:`Target`: where each goes, its
  type, key/values and write options);
- the memory computing a block of them takes (:meth:`Operation.memory`);
- how to compute a block (:meth:`Operation.compute`), from the block's
  :class:`~volwarp_cli.box.Box` alone (inputs it reads, it reads for that
  block: :mod:`volwarp_cli.regions` says which region).

:func:`run` then decides by arithmetic, before any work: when the whole
output's memory fits the budget (and ``--chunked`` did not ask otherwise),
the whole output is computed as one block on the calling threads and written
with :func:`~volwarp_cli.io.write_volume` (any format); otherwise it is
computed as many blocks on an engine (threads, processes or a Dask cluster),
each written straight into the outputs
(:class:`~volwarp_cli.io.blockwrite.BlockOutput`). The same
:meth:`Operation.compute` runs either way, so the outputs are the same bytes.

An output that is not a volume (a mesh) is a :class:`Reduction`: its blocks
make parts and the operation reduces them to its output (the weld of a
mesh's blocks), written once at the end; :func:`run` decides the same way,
and hands the operation the :class:`Blocks` it runs on (the whole as one
block on the calling threads, or blocks of one shape on the engine).

No click here: the command line says how it wants to run (:class:`How`) and
gets back what ran (:class:`Ran`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .box import Box
from .errors import BadUsage, OutOfMemoryError, VolwarpError
from .progress import log, timed

#: the least memory worth running blocks in (below it, refuse: tiny blocks take forever)
MIN_BLOCK_BUDGET = 32 << 20
#: the outputs' bytes from which an in-memory run that can writes them as it computes
#: them; below, the whole is an array written after the work (a 16^3 warp, a batch's
#: step: its pages and its copy are a fraction of a millisecond either way)
STREAMED_FROM = 1 << 20


@dataclass(frozen=True)
class Target:
    """One output of an operation: its file, its samples' type, and how it is written.

    ``header``: the output's :class:`~volwarp_cli.volume.Header` (its shape,
    geometry, frame and key/values); ``components``: the names of the components
    of a multi-component output (NRRD; a block's samples then have them on
    their last axis), else None. The rest are
    :func:`~volwarp_cli.io.write_volume`'s options.
    """

    path: Path
    header: object
    dtype: np.dtype
    compress: bool = False
    byte_order: str = "little"
    version: str = "0.5"
    pyramid: int = 0
    components: tuple[str, ...] | None = None
    #: the samples are a label map (True), not one (False), or the writer's rule
    #: decides ("auto"): an OME-Zarr pyramid's levels take the mode of a label map
    labels: object = "auto"

    def write_whole(self, data: np.ndarray) -> None:
        """Write the whole output's ``data`` (the in-memory run), in any format."""
        from .io import write_volume

        if self.components is not None:
            from .io.nrrd import write_nrrd

            # (the components on the last axis are the file's order: written as they are,
            # not split and stacked again, two more copies of the whole output)
            write_nrrd(self.header.with_data(data[..., 0]), self.path, compress=self.compress,
                       byte_order=self.byte_order, components=data,
                       component_names=list(self.components))
            return
        write_volume(self.header.with_data(data), self.path, compress=self.compress,
                     byte_order=self.byte_order, ome_zarr_version=self.version,
                     pyramid=self.pyramid, labels=self.labels)

    def open_blocks(self, block):
        """The :class:`~volwarp_cli.io.blockwrite.BlockOutput` written block by block.

        A context manager: committed (renamed into place) on a clean exit,
        aborted (nothing left, an existing file untouched) on an error.
        """
        from .io.blockwrite import committed, open_block_output

        out = open_block_output(self.path, self.header, dtype=self.dtype, chunks_zyx=block,
                                version=self.version, compress=self.compress,
                                byte_order=self.byte_order, pyramid=self.pyramid,
                                components=list(self.components) if self.components else None,
                                labels=self.labels)
        return committed(out)

    def nbytes(self, shape) -> int:
        """The bytes of the whole output (its components included)."""
        n = math.prod(int(v) for v in shape) * np.dtype(self.dtype).itemsize
        return n * (len(self.components) if self.components else 1)

    def _zarr(self) -> bool:
        from .io import volume_format

        return self.components is None and volume_format(self.path) == "omezarr"

    def write_bytes(self, shape) -> int:
        """What writing the whole output of ``shape`` holds beyond its samples (in memory).

        An OME-Zarr store's shard encoding, label-map count and pyramid
        (:func:`~volwarp_cli.io.omezarr.memory_bytes`); 0 for the other formats.
        """
        if not self._zarr():
            return 0
        from .io.omezarr import memory_bytes

        return memory_bytes(shape, self.dtype, self.version, self.pyramid)

    def block_bytes(self, shape, block) -> int:
        """What writing one block of ``block`` of an output of ``shape`` adds to its samples.

        An OME-Zarr store's encoding of the block's shards
        (:func:`~volwarp_cli.io.blockwrite.zarr_block_bytes`); 0 for the
        formats written by offset, a staged store's blocks among them
        (:func:`~volwarp_cli.io.blockwrite.zarr_staged`).
        """
        if not self._zarr():
            return 0
        from .io.blockwrite import zarr_block_bytes, zarr_staged

        if zarr_staged(self.path, shape, self.dtype, self.version, block, self.header.direction):
            return 0
        return zarr_block_bytes(shape, self.dtype, self.version, block)

    def commit_bytes(self, shape, block) -> int:
        """The least memory committing the output written in blocks of ``block`` takes.

        An OME-Zarr store's pyramid levels and a staged store's shards
        (:func:`~volwarp_cli.io.blockwrite.zarr_commit_bytes`); else 0.
        """
        if not self._zarr():
            return 0
        from .io.blockwrite import zarr_commit_bytes, zarr_staged

        staged = zarr_staged(self.path, shape, self.dtype, self.version, block,
                             self.header.direction)
        return zarr_commit_bytes(shape, self.dtype, self.version, self.pyramid, block, staged)


class Operation:
    """What an operation states before any sample is read (see the module notes).

    Subclasses set ``grid`` (the output :class:`~volwarp_cli.geometry.Geometry`),
    ``targets`` (key -> :class:`Target`) and ``what`` (the work and its sizes,
    for messages), and define :meth:`memory` and :meth:`compute`.
    """

    grid = None
    targets: dict = {}
    what: str = "the work"
    #: why the operation has no form by blocks (it then runs in memory or not at all), or None
    no_blocks: str | None = None
    #: whether it has :meth:`compute_into` (the in-memory run then writes as it computes)
    streams: bool = False

    def memory(self, box: Box) -> int:
        """The bytes computing ``box`` holds at its peak (its results included)."""
        raise NotImplementedError

    def compute(self, box: Box, *, threads: int) -> dict:
        """The results of ``box``: key -> array (at least one per target's key).

        ``threads``: how many threads the computation may use (1 in a block
        task: the engine's tasks are the parallelism).
        """
        raise NotImplementedError

    def compute_into(self, box: Box, *, threads: int, place: dict) -> None:
        """:meth:`compute`, each target's samples handed over as they are finished.

        ``place[key](sub_box, samples)``: where they go (any boxes, together
        ``box``; called from the computing threads, each box once). For
        operations whose parts finish their output a few planes at a time:
        the in-memory run then holds no array of the whole output, and the
        output's file is written while the work goes on. Only where
        :attr:`streams`.
        """
        raise NotImplementedError

    def scratch_files(self) -> list:
        """``[(path, nbytes)]`` of the files it writes by blocks besides its targets (none)."""
        return []

    def output(self, results: dict, key) -> np.ndarray:
        """Target ``key``'s samples (its type) from a block's results (default: ``results[key]``)."""
        return results[key]

    def prepare(self) -> None:  # noqa: B027 - optional
        """What every block shares, made once the run is decided (before any block runs)."""

    def load(self) -> None:  # noqa: B027 - optional: most operations load nothing
        """Run the kernels once on something small, so the budget counts what they load."""

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """The blocks' shape (z, y, x): cubes within ``per_task`` bytes, two per worker at least."""
        shape = self.grid.shape
        per_voxel = max(1, self.memory(Box((0, 0, 0), (1, 1, 1))))
        edge = max(8, int((per_task // per_voxel) ** (1 / 3)))
        want = 2 * workers
        while edge > 16 and math.prod(math.ceil(n / min(edge, n)) for n in shape) < want:
            edge = edge * 3 // 4
        return tuple(min(edge, n) for n in shape)


@dataclass(frozen=True)
class How:
    """How the command asked to run.

    ``chunked``: True (by blocks), False (in memory or refused) or None (by
    blocks only when the whole does not fit); ``block``: the user's block
    shape (z, y, x); ``open_engine()``: a context manager giving the engine
    the blocks run on; ``threads``: the in-memory run's threads (None:
    :func:`volwarp_cli.parallel.threads`); ``scheduler``: the scheduler the
    user named, if any; ``planned``: ``block`` was chosen by a caller that
    planned a larger job once for all its steps (:func:`auto_block`; a morph's
    frames), not weighed again.
    """

    chunked: bool | None = None
    block: tuple[int, int, int] | None = None
    open_engine: Callable | None = None
    threads: int | None = None
    scheduler: str | None = None
    planned: bool = False


@dataclass
class Ran:
    """What :func:`run` did.

    ``by_blocks``; ``results``: the in-memory run's results (the whole's
    :meth:`Operation.compute`; None by blocks, and where the outputs were
    written as they were computed, :meth:`Operation.compute_into`); ``block``: the blocks' shape
    and ``blocks`` their count (by blocks); ``after``: what the ``after`` hook
    returned; ``output``: a :class:`Reduction`'s output (either way).
    """

    by_blocks: bool
    results: dict | None = None
    block: tuple[int, int, int] | None = None
    blocks: int = 0
    after: object = None
    output: object = None
    _outs: dict = field(default_factory=dict, repr=False)

    def read(self, key, box: Box) -> np.ndarray:
        """Target ``key``'s samples in ``box`` as written (by blocks: before the commit).

        For ``after`` hooks that read the outputs back (a render of them):
        in memory the whole's results are at hand, by blocks the outputs are
        read in whole blocks of the written file.
        """
        if self.results is not None:
            raise VolwarpError("in memory, the results are at hand")
        return self._outs[key].read(box)


def fits(nbytes: int, load=None) -> bool:
    """Whether ``nbytes`` fits the memory budget, what the work loads counted.

    Where the budget leaves :data:`~volwarp_cli.memory.LOAD_MARGIN` beyond
    ``nbytes``, yes at once; otherwise ``load()`` (the kernels on something
    small) runs first, so that the answer counts what the process then holds.
    """
    from . import memory

    limit = memory.memory_limit()
    if nbytes + memory.LOAD_MARGIN <= limit:
        return True
    if nbytes > limit:
        return False
    if load is not None:
        load()
    return nbytes <= memory.memory_limit()


def block_budget() -> int:
    """The memory blocks may use; an OutOfMemoryError below :data:`MIN_BLOCK_BUDGET`."""
    from . import memory

    left, where = memory.limit_and_source()
    if left < MIN_BLOCK_BUDGET:
        raise OutOfMemoryError(f"{memory.human_bytes(left)} is left for blocks under {where}; "
                               f"they need {memory.human_bytes(MIN_BLOCK_BUDGET)} at least "
                               "(raise --memory-limit)")
    return left


def blocks_refusal(outputs, compress: bool = False, pyramid: int = 0, *,
                   scratch=()) -> str | None:
    """Why ``outputs`` (``[(path, nbytes)]``) cannot be written by blocks, or None.

    Their formats (:func:`~volwarp_cli.io.blockwrite.check_block_format`), and
    their sizes against the free space of their folders (outputs sharing a
    folder add up). A compressed output (:func:`~volwarp_cli.io.compressed_output`: OME-Zarr's
    zstd chunks) is not weighed by its samples' size, which its file may be a
    thousandth of (a disk that fills while it is written fails it, with one
    line and nothing left); ``scratch``: ``[(path, nbytes)]`` of uncompressed
    scratch files beside those paths, weighed in full.
    """
    import shutil

    from .io import compressed_output
    from .io.blockwrite import check_block_format
    from .memory import human_bytes

    need: dict[Path, list[int]] = {}
    for path, nbytes in outputs:
        try:
            fmt = check_block_format(path, bool(compress), int(pyramid or 0))
        except BadUsage:  # (an option the output cannot take at all: a usage error either way)
            raise
        except VolwarpError as exc:
            return str(exc)
        if not compressed_output(path, fmt, compress):
            need.setdefault(Path(path).resolve().parent, []).append(int(nbytes))
    for path, nbytes in scratch:
        need.setdefault(Path(path).resolve().parent, []).append(int(nbytes))
    for folder, sizes in need.items():
        try:
            free = shutil.disk_usage(folder).free
        except OSError as exc:
            return f"{folder}: {exc.strerror}"
        if sum(sizes) > free:
            each = "" if len(sizes) == 1 else f" ({len(sizes)} files)"
            return (f"the outputs need {human_bytes(sum(sizes))}{each} where {folder} has "
                    f"{human_bytes(free)} free")
    return None


def refuse_unmakeable(what: str, memory_bytes: int, outputs, *, chunked: bool | None = None,
                      compress: bool = False, pyramid: int = 0, scratch=()) -> None:
    """Refuse, before any work, what fits neither the memory nor, by blocks, the disk.

    ``what``: the work and its sizes, for the message; ``memory_bytes``: what
    the work holds in memory at the least; ``outputs``: ``[(path, nbytes)]``.
    One line with the sizes of both ways (an absurd grid was otherwise
    allocated, or tiled into blocks, until killed). ``chunked``: as
    :class:`How`'s (False: memory only; True: blocks only); ``scratch``: as
    :func:`blocks_refusal`'s.
    """
    from .memory import ensure_fits_in_memory

    in_memory = None
    if not chunked:
        try:
            ensure_fits_in_memory(memory_bytes, what)
            return
        except OutOfMemoryError as exc:
            if chunked is False:
                raise
            in_memory = exc
    if chunked:  # (asked for blocks, an output format written whole: a usage error, as an
        # export's is; a disk too small stays a failure of the run, below)
        from .io.blockwrite import check_block_format

        for path, _ in outputs:
            try:
                check_block_format(path, bool(compress), int(pyramid or 0))
            except BadUsage:
                raise
            except VolwarpError as exc:
                raise BadUsage(f"--chunked: {exc}") from None
    by_blocks = blocks_refusal(outputs, compress, pyramid, scratch=scratch)
    if by_blocks is None:
        return
    raise OutOfMemoryError(f"{in_memory}, and by blocks {by_blocks}" if in_memory
                           else f"{what}, by blocks: {by_blocks}")


def run(op: Operation, how: How = How(), after: Callable | None = None, *,
        by_blocks: bool | None = None) -> Ran:
    """Run ``op``: in memory as one block when it fits, else by blocks (module notes).

    ``after(ran)``: called once the outputs are written (by blocks: before they
    are committed, so that it can read them back with :meth:`Ran.read`); what
    it returns is ``Ran.after``. An error in it leaves no output by blocks.
    ``by_blocks``: decided already, by a caller that planned a larger job
    whose step ``op`` is (a morph's frames: :func:`decide` on the whole job).

    Raises the in-memory refusal (:class:`~volwarp_cli.errors.OutOfMemoryError`,
    with the sizes) where the whole does not fit and blocks may not or cannot
    run (``--no-chunked``, an output format written whole, a full disk).
    """
    if isinstance(op, Reduction):
        return _reduce(op, how, after)
    streamed = written_as_computed(op, after)
    if by_blocks is None:
        first = next(iter(op.targets.values()))
        outputs = [(t.path, t.nbytes(op.grid.shape)) for t in op.targets.values()]
        by_blocks = not _in_memory(op, how, outputs, compress=first.compress,
                                   pyramid=first.pyramid, streamed=streamed,
                                   scratch=op.scratch_files())
    if by_blocks:
        if op.no_blocks is not None:
            raise VolwarpError(op.no_blocks)
        return _run_blocks(op, how, after)
    if streamed:
        _compute_written(op, how.threads)
        return Ran(False)
    results = compute_whole(op, how.threads)
    for key, target in op.targets.items():
        with timed(f"write {target.path}"):
            target.write_whole(op.output(results, key))
    ran = Ran(False, results=results)
    if after is not None:
        ran.after = after(ran)
    return ran


def compute_whole(op: Operation, threads: int | None = None) -> dict:
    """``op``'s whole output as one block on the calling threads: its results by key.

    The in-memory run's computation (:func:`run` decides that it fits and
    writes the targets; a Python caller, :mod:`volwarp_cli.api`, keeps the
    arrays). ``threads``: default :func:`volwarp_cli.parallel.threads`.
    """
    from . import parallel

    op.prepare()
    with timed(op.what):
        return op.compute(op.grid.box, threads=threads or parallel.threads())


def written_as_computed(op: Operation, after: Callable | None = None) -> bool:
    """Whether ``op``'s in-memory run writes its outputs as it computes them (no whole array).

    Not with an ``after`` hook (:func:`run`'s: it gets the results whole).
    Where its blocks would be placed (:func:`places_blocks`: every target a
    file of samples at an offset, written in place, the bytes
    :meth:`Target.write_whole` writes), the outputs are not small
    (:data:`STREAMED_FROM`) and their disks have room for them.
    """
    if after is not None or not places_blocks(op):
        return False
    outputs = [(t.path, t.nbytes(op.grid.shape)) for t in op.targets.values()]
    if sum(n for _, n in outputs) < STREAMED_FROM:
        return False
    return blocks_refusal(outputs) is None  # (and room for them on their disks)


def _compute_written(op: Operation, threads: int | None) -> None:
    """The whole output as one block on the calling threads, written as it is computed.

    Each target opened as one block of its file
    (:class:`~volwarp_cli.io.blockwrite.BlockOutput`: an existing output
    untouched and nothing left behind on an error or a stop) and committed
    once every part has been placed. The same bytes as :func:`compute_whole`
    and :meth:`Target.write_whole`, without the whole's array: its memory,
    its pages' first touch and the write's copy of them after the work.
    """
    from . import parallel

    box = op.grid.box
    with contextlib.ExitStack() as stack:
        outs = {key: stack.enter_context(t.open_blocks(box.shape))
                for key, t in op.targets.items()}
        op.prepare()
        names = ", ".join(str(t.path) for t in op.targets.values())
        with timed(f"{op.what}, written to {names} as it was computed"):
            op.compute_into(box, threads=threads or parallel.threads(),
                            place={key: out.place for key, out in outs.items()})
        for out in outs.values():
            out.mark_written([box])


def _in_memory(op: Operation, how: How, outputs, *, compress: bool = False,
               pyramid: int = 0, streamed: bool = False, scratch=()) -> bool:
    """Whether ``op`` runs as one block: its whole's memory against the budget, before any work.

    :func:`decide` with the operation's own sizes; ``streamed``: its outputs
    written as they are computed, so their arrays (in its memory) never held.
    """
    need = op.memory(op.grid.box)
    if streamed:
        need -= sum(t.nbytes(op.grid.shape) for t in op.targets.values())
    else:  # (written after the work: the writers' own buffers, one target at a time)
        need += max((t.write_bytes(op.grid.shape) for t in op.targets.values()), default=0)
    return decide(max(need, 0), op.what, outputs, how, load=op.load,
                  no_blocks=op.no_blocks, compress=compress, pyramid=pyramid, scratch=scratch)


def decide(need: int, what: str, outputs, how: How, *, load=None, no_blocks: str | None = None,
           compress: bool = False, pyramid: int = 0, scratch=()) -> bool:
    """In memory (True) or by blocks (False), by arithmetic, before any work.

    ``need``: the whole's memory in one block; ``what``: the work and its
    sizes, for messages; ``outputs``: ``[(path, nbytes)]`` written by blocks
    (the disk's check); ``load()``: what the work loads (kernels), run before
    a tight answer and before the blocks' budget is weighed (so that it counts
    them); ``no_blocks``: why the work has no form by blocks, if it has none;
    ``scratch``: the scratch files by blocks (:func:`blocks_refusal`).
    By blocks where the whole does not fit (said on stderr where the command
    did not ask for them); one refusal with both reasons where neither way can
    run (:func:`refuse_unmakeable`).
    """
    from . import memory

    if how.chunked is not True and fits(need, load):
        return True
    if no_blocks is not None:
        if how.chunked:
            raise VolwarpError(no_blocks)
        try:
            memory.ensure_fits_in_memory(need, what)
        except OutOfMemoryError as exc:
            raise OutOfMemoryError(f"{exc}, and by blocks: {no_blocks}") from None
        return True
    refuse_unmakeable(what, need, outputs, chunked=how.chunked, compress=compress,
                      pyramid=pyramid, scratch=scratch)
    if how.chunked is None:
        if load is not None:
            load()  # (the blocks' budget is what is left once the kernels are loaded)
        try:
            block_budget()
        except OutOfMemoryError:
            memory.ensure_fits_in_memory(need, what)  # no room for blocks either
            raise
        log.warning("%s needs %s: running by blocks (--no-chunked to refuse instead)",
                    what, memory.human_bytes(need))
    return False


def _run_blocks(op: Operation, how: How, after: Callable | None) -> Ran:
    """``op`` by blocks on the engine, every block written into the outputs, then committed."""
    import dask

    if how.open_engine is None:
        raise VolwarpError(f"{op.what}: no engine to run blocks on")
    op.prepare()  # (once, here: the blocks' tasks get it made)
    op.load()  # (the blocks' budget is what is left once the kernels are loaded)
    from .passes import Passes, heaviest_pass_block, last_pass_block, run_by_blocks

    with how.open_engine() as engine, contextlib.ExitStack() as stack:
        per_task = block_budget() // max(1, engine.workers)
        if isinstance(op, Passes):  # the outputs' blocks are the last pass's
            if how.block is not None and not how.planned:
                refuse_block_over_budget(op.what, *heaviest_pass_block(op, how.block, per_task),
                                         per_task, engine.workers)
            block = last_pass_block(op, block_bytes=per_task, workers=engine.workers,
                                    block=how.block)
        elif how.block is not None:
            block = how.block
            if not how.planned:
                _check_user_block(op, block, per_task, engine.workers)
        else:
            block = auto_block(op, per_task, engine.workers)
        _check_commit(op, block)
        outs = {key: stack.enter_context(t.open_blocks(block)) for key, t in op.targets.items()}
        boxes = next(iter(outs.values())).blocks()
        if any(o.blocks() != boxes for o in outs.values()):
            raise VolwarpError(f"{op.what}: outputs of different formats split into different "
                               "blocks: give them one format")
        if isinstance(op, Passes):
            with timed(f"{op.what} by passes"):
                count = run_by_blocks(op, engine, outs, block_bytes=per_task, block=how.block)
        else:
            op_node = dask.delayed(op, pure=False)
            writers = dask.delayed({k: o.writer() for k, o in outs.items()}, pure=False)
            placed = places_blocks(op)  # (decided here, as the blocks were weighed)
            tasks = [engine.block_delayed(_block_task, f"block-{'-'.join(map(str, b.lo))}",
                                          op_node, b, writers, placed, memory=per_task)
                     for b in boxes]
            with timed(f"{op.what} by {len(boxes)} blocks"):
                engine.run(tasks, label="blocks")
            count = len(boxes)
            for out in outs.values():
                out.mark_written(boxes)
        ran = Ran(True, block=tuple(block), blocks=count, _outs=outs)
        if after is not None:
            ran.after = after(ran)
    return ran


def _check_commit(op: Operation, block) -> None:
    """Refuse, before any work, outputs whose commit (an OME-Zarr pyramid) cannot fit the budget.

    Each target is committed alone, once the blocks are done, with the whole
    budget (its levels made in pieces of what is left: its least need,
    :meth:`Target.commit_bytes`, is weighed here).
    """
    from . import memory

    need = max((t.commit_bytes(op.grid.shape, block) for t in op.targets.values()), default=0)
    if need:
        memory.ensure_fits_in_memory(need, f"{op.what}: the --pyramid levels of its output")


def auto_block(op: Operation, per_task: int, workers: int) -> tuple[int, int, int]:
    """The blocks ``op`` runs in when the user gave none: its own, or its stores' shards.

    Where the outputs' writes add to a block's memory (OME-Zarr shards are
    encoded whole, :func:`writes_bytes`), the operation is asked for smaller
    blocks until its heaviest block with them fits ``per_task``; where none
    does, an :class:`~volwarp_cli.errors.OutOfMemoryError` before any work.
    """
    block = op.block_shape(per_task, workers)
    if writes_bytes(op, block):
        share = per_task
        while _heaviest(op, block) > per_task:
            share = share * 3 // 4
            if share < MIN_BLOCK_BUDGET // 8:  # (refused: the smallest it makes)
                _check_user_block(op, block, per_task, workers, chosen=True)
            smaller = op.block_shape(share, workers)
            if math.prod(smaller) < math.prod(block):
                block = smaller
    return _store_aligned(op, block, per_task, workers)


def _store_aligned(op: Operation, block, per_task: int, workers: int):
    """OME-Zarr outputs' own write units as the blocks, where they fit: else ``block``.

    Blocks made of the in-memory writer's shards (chunks in NGFF 0.4) give
    its store byte for byte (:func:`~volwarp_cli.io.blockwrite.block_layout`);
    taken when one fits a task's memory and they are about as many as the
    blocks chosen (two a worker at least), so that the work still spreads.
    """
    from .io import volume_format
    from .io.blockwrite import store_unit

    targets = list(op.targets.values())
    if not targets or any(volume_format(t.path) != "omezarr" for t in targets):
        return block
    versions = {t.version for t in targets}
    if len(versions) != 1:
        return block
    shape = op.grid.shape
    unit = store_unit(shape, versions.pop())
    count = math.prod(-(-n // min(b, n)) for n, b in zip(shape, block, strict=True))
    units = math.prod(-(-n // u) for n, u in zip(shape, unit, strict=True))
    if units < min(count, 2 * workers) or _heaviest(op, unit) > per_task:
        return block
    return unit


def _heaviest(op: Operation, block) -> int:
    """The most memory of the first, middle and last blocks of ``block`` (where they lie counts).

    Less the targets' samples where the blocks' tasks place them as they are
    computed (:func:`places_blocks`).
    """
    from . import parallel

    boxes = op.grid.box.blocks(block)
    placed = places_blocks(op)
    with parallel.use_threads(1):  # (as a block task runs)
        need = max(op.memory(b) - (sum(t.nbytes(b.shape) for t in op.targets.values())
                                   if placed else 0)
                   for b in {boxes[0], boxes[len(boxes) // 2], boxes[-1]})
    return need + writes_bytes(op, block)


def writes_bytes(op: Operation, block) -> int:
    """What a block task's writes of its block of ``block`` add to its samples (all targets).

    OME-Zarr outputs: zarr's encoding of the block's shards
    (:meth:`Target.block_bytes`); nothing for the outputs written by offset.
    """
    return sum(t.block_bytes(op.grid.shape, block) for t in op.targets.values())


def places_blocks(op: Operation) -> bool:
    """Whether ``op``'s block tasks place their samples as they compute them (no block array).

    Where it can (:attr:`Operation.streams`) and every target is written by
    offset (uncompressed NRRD, MetaImage or raw of one component: the
    writers of :mod:`~volwarp_cli.io.blockwrite` that place any box).
    """
    from .io.blockwrite import check_block_format

    def by_offset(t) -> bool:
        try:  # (the formats written by blocks, less OME-Zarr: its shards are written whole)
            return check_block_format(t.path, t.compress, t.pyramid) != "omezarr"
        except VolwarpError:
            return False

    return op.streams and bool(op.targets) and all(
        t.components is None and by_offset(t) for t in op.targets.values())


def _check_user_block(op: Operation, block, per_task: int, workers: int, *,
                      chosen: bool = False) -> None:
    """Refuse, before any work, a ``--block`` whose blocks need more than a task's budget.

    The first, middle and last blocks are weighed (an operation's block memory
    may depend on where the block lies: a warp's reach). ``chosen``: the
    smallest block the operation makes, not the user's.
    """
    refuse_block_over_budget(op.what, block, _heaviest(op, block), per_task, workers,
                             chosen=chosen)


def refuse_block_over_budget(what: str, block, need: int, per_task: int, workers: int, *,
                             chosen: bool = False) -> None:
    """Refuse a block of shape ``block`` (z, y, x) needing ``need`` bytes over ``per_task``.

    The one refusal of a ``--block`` too large for a task's share of the
    budget, whichever operation weighed it (:func:`_check_user_block`; an
    operation in passes, :func:`~volwarp_cli.passes.heaviest_pass_block`).
    ``chosen``: the block is the smallest the operation makes, not the user's.
    """
    from .memory import human_bytes

    if need > per_task:
        which = "the smallest block" if chosen else "a block"
        advice = "" if chosen else "give a smaller --block, "
        raise OutOfMemoryError(
            f"{what}: {which} of {'x'.join(map(str, block))} (z, y, x) needs "
            f"{human_bytes(need)}, more than the {human_bytes(per_task)} each of "
            f"{workers} workers may use ({advice}fewer --workers or a larger "
            "--memory-limit)")


def _block_task(op: Operation, box: Box, writers: dict, placed: bool = False) -> None:
    """One block: computed on this task's thread, each target's samples written.

    ``placed`` (:func:`places_blocks`, decided by the run): placed as they
    are computed, the block's array not made.
    """
    if placed:
        with contextlib.ExitStack() as stack:
            place = {k: stack.enter_context(w.placing()) for k, w in writers.items()}
            op.compute_into(box, threads=1, place=place)
        return
    results = op.compute(box, threads=1)
    for key, writer in writers.items():
        writer.write(box, op.output(results, key))


# -- reductions: outputs that are not volumes ------------------------------------------
@dataclass(frozen=True)
class Blocks:
    """Where a :class:`Reduction`'s blocks run, as :func:`run` decided.

    ``shape``: the blocks' shape (z, y, x), None in memory (one block, the
    whole); ``threads``: the threads one block's computation may use (the
    calling threads in memory, 1 in a block task); by blocks, the
    ``engine`` and each task's ``memory``.
    """

    shape: tuple[int, int, int] | None = None
    threads: int = 1
    engine: object = None
    memory: int | None = None

    @property
    def whole(self) -> bool:
        """True in memory: the whole is the one block."""
        return self.shape is None

    @property
    def in_flight(self) -> int:
        """The bytes the blocks running at once may hold (in memory 0: the caller counts its one)."""
        return 0 if self.engine is None else int(self.memory or 0) * self.engine.workers

    def split(self, box: Box) -> list[Box]:
        """``box`` cut into the blocks (in memory: ``[box]``)."""
        return [box] if self.shape is None else box.blocks(self.shape)

    def map(self, task: Callable, items, *, label: str = "blocks") -> list:
        """``[task(item) for item in items]``: here in memory, as block tasks on the engine."""
        items = list(items)
        if self.engine is None:
            return [task(item) for item in items]
        return self.engine.map(task, items, label=label, memory=self.memory)


class Reduction(Operation):
    """An operation whose output is not a volume: its blocks make parts that it reduces.

    A mesh is the example: each block's triangles are a part, their weld is
    the output, written once at the end. No ``targets``; :meth:`reduce` runs
    the operation's passes over the :class:`Blocks` :func:`run` gives it and
    returns the output (:attr:`Ran.output`). :meth:`memory` is a block's, as
    for every operation; ``blocks_share``: by blocks, the share of what is
    left of the budget that the blocks in flight may take (the rest holds
    the parts they return and their reduction).
    """

    targets: dict = {}
    blocks_share: float = 0.5

    def reduce(self, blocks: Blocks):
        """The output, its passes' blocks run where ``blocks`` says."""
        raise NotImplementedError

    def outputs(self) -> list:
        """``[(path, nbytes)]`` of the files the operation writes by blocks (the disk's check)."""
        return []


def _reduce(op: Reduction, how: How, after: Callable | None) -> Ran:
    """``op`` in memory (one block on the calling threads) or by blocks on the engine."""
    from . import parallel

    if _in_memory(op, how, op.outputs()):
        op.prepare()
        with timed(op.what):
            ran = Ran(False, output=op.reduce(Blocks(threads=how.threads or parallel.threads())))
    else:
        if how.open_engine is None:
            raise VolwarpError(f"{op.what}: no engine to run blocks on")
        op.prepare()
        with how.open_engine() as engine:
            per_task = int(block_budget() * op.blocks_share) // max(1, engine.workers)
            block = tuple(how.block or op.block_shape(per_task, engine.workers))
            with timed(f"{op.what} by blocks of {'x'.join(map(str, block))}"):
                ran = Ran(True, block=block,
                          output=op.reduce(Blocks(block, 1, engine, per_task)))
    if after is not None:
        ran.after = after(ran)
    return ran
