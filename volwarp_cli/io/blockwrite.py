"""Outputs written block by block, for results that do not fit in memory.

:func:`open_block_output` makes a :class:`BlockOutput` for an output's
:class:`~volwarp_cli.volume.Header` (grid, sample type, frame, key/values) and
path; the engine (Dask, threads) computes blocks and hands each to
:meth:`BlockOutput.write`, then calls :meth:`BlockOutput.commit` (or
:meth:`BlockOutput.abort`). The output appears at its path only on
commit, atomically, as every volwarp output (:mod:`.atomic`); an error, an
abort or a stop leaves no temporary behind and an existing output untouched.

Blocks must lie on the output's block grid, :attr:`BlockOutput.chunks`:
a write covers whole blocks (the last block of an axis may be cut short at
the grid's end), so that two writes never share a block. For OME-Zarr that is
the shard shape (0.5) or the chunk shape (0.4) where the blocks are made of
them: zarr-python reads, modifies and writes back a whole shard for a partial
write, and two threads doing so at once lose one's data silently. Other
blocks are staged (:func:`zarr_staged`): placed in a raw scratch file, the
store written from it shard by shard on commit. :func:`aligned_chunks` gives
the chunk sizes a Dask array should be rechunked to.

Formats:

- **OME-Zarr** (``.ome.zarr``, ``.zarr``): zarr writes into the temporary
  store (or a raw scratch file beside it, :func:`zarr_staged`, written into
  the store on commit); commit builds the pyramid (``pyramid`` levels, block
  by block from the level above), writes the metadata and renames the store
  into place. The store is the one :func:`~.omezarr.write_omezarr` writes for
  the same volume, byte for byte (but where a shard's write would not fit the
  memory budget, or its samples the disk, for staging: then one shard per
  block, the same samples).
- **NRRD** (``.nrrd``, raw encoding), **MetaImage** (``.mha``) and **raw**:
  the header goes into the temporary file and the samples into its data
  region with ``pwrite`` (:mod:`.filearray`; a memory map's pages would count
  in the writer's memory); the file is byte for byte the one
  :func:`~volwarp_cli.io.write_volume` writes for the same volume.
- Compressed NRRD/NIfTI/MetaImage, TIFF and detached headers (``.nhdr``,
  ``.mhd``) are refused: their bytes cannot be placed block by block.

Computing is left to the engine: this module only places blocks.
"""

from __future__ import annotations

import collections
import contextlib
import functools
import itertools
import math
import os
import threading
from pathlib import Path

import numpy as np

from ..box import Box
from ..errors import BadUsage, VolwarpError
from ..geometry import Geometry
from ..samples import check_dtype
from . import writeback
from .atomic import write_error

__all__ = ["BlockOutput", "BlockWriter", "aligned_chunks", "block_indices", "open_block_output"]


class _Aborted(Exception):
    """Thrown into the atomic-output context to make it remove its temporary."""


def open_block_output(path: str | os.PathLike, header, *, dtype=None, chunks_zyx=None,
                      version: str = "0.5", compress: bool = False, byte_order: str = "little",
                      pyramid: int = 0, labels="auto",
                      components: list[str] | None = None) -> BlockOutput:
    """A :class:`BlockOutput` writing the volume of ``header`` to ``path``.

    ``header``: the output's :class:`~volwarp_cli.volume.Header`, what
    :func:`~volwarp_cli.io.write_volume` is given with the samples: its grid,
    its frame (``space`` and the input's ``file_space``) and key/values
    (provenance), so that the file is the one written in memory.
    ``dtype``: the samples' type, default ``header.dtype``.
    ``chunks_zyx``: the block shape the engine writes (OME-Zarr: the store's
    own layout, the blocks staged in a scratch file where they are not made of
    its shards, :func:`zarr_staged`, else one shard per block,
    :func:`block_layout`; others: the block grid, default 64 planes of the
    whole y, x extent). ``version``, ``pyramid``,
    ``labels``: OME-Zarr (see :mod:`.omezarr`; ``labels="auto"``, as
    :func:`~volwarp_cli.io.write_volume`'s: an integer output's levels are
    decided on commit from the samples written, read shard by shard).
    ``compress``: refused except for OME-Zarr (always compressed).
    ``components``: names of the components each voxel holds (a
    multi-component NRRD, components interleaved, as :func:`.nrrd.write_nrrd`
    writes it); each block is then written with them last, ``box.shape + (C,)``.
    """
    from . import say_unused_writer_options

    path = Path(path)
    fmt = check_block_format(path, compress, pyramid)
    say_unused_writer_options(path, fmt, compress, version)
    dtype = check_dtype(header.dtype if dtype is None else dtype, str(path))
    if dtype != header.dtype:
        header = header.replace(dtype=dtype)
    if components and fmt != "nrrd":
        raise VolwarpError(f"{path}: samples with several components are written by blocks "
                           "to an uncompressed .nrrd only")
    if fmt == "omezarr":
        return _ZarrOutput(path, header, chunks_zyx, version, byte_order, pyramid, labels)
    return _MappedOutput(path, header, chunks_zyx, fmt, byte_order, components)


def open_volume_blocks(path, header, dtype=None, *, block=None, compress=False,
                       byte_order="little", pyramid=0, version="0.5", labels="auto",
                       components=None):
    """The :class:`BlockOutput` of the volume of ``header`` (its geometry, frame, key/values).

    ``header``: the output's :class:`~volwarp_cli.volume.Header`. A context
    manager: committed when it exits without an error, aborted (nothing left
    at ``path``, an existing file untouched) otherwise. The options are
    :func:`open_block_output`'s.
    """
    return committed(open_block_output(path, header, dtype=dtype, chunks_zyx=block,
                                       version=version, compress=compress,
                                       byte_order=byte_order, pyramid=pyramid, labels=labels,
                                       components=components))


def check_block_format(path: str | os.PathLike, compress: bool = False, pyramid: int = 0) -> str:
    """The format of ``path`` if it is written block by block, else a VolwarpError saying why.

    OME-Zarr (compressed, and ``pyramid`` levels), or uncompressed NRRD,
    MetaImage and raw with attached headers (written in place by offset).
    """
    from . import volume_format

    path = Path(path)
    fmt = volume_format(path)
    if pyramid and fmt != "omezarr":
        raise BadUsage(f"{path}: --pyramid writes extra levels of OME-Zarr outputs only")
    if fmt == "omezarr":
        return fmt
    name = path.name.lower()
    hint = "write .ome.zarr or uncompressed .nrrd for block-wise outputs"
    # (a raw file is never compressed: --compress is said and ignored, as in memory)
    if (compress and fmt != "raw") or fmt in ("tiff", "nifti"):
        what = "a compressed" if compress and fmt not in ("tiff", "nifti") else f"a {fmt}"
        raise VolwarpError(f"{path}: {what} output cannot be written block by block; {hint}")
    if name.endswith((".nhdr", ".mhd")):
        raise VolwarpError(f"{path}: detached headers are not written block by block; {hint}")
    if fmt not in ("nrrd", "metaimage", "raw"):
        raise VolwarpError(f"{path}: {fmt} outputs cannot be written block by block; {hint}")
    return fmt


def _edges(n: int, c: int, phase: int) -> list[int]:
    """Block boundaries of an axis of ``n`` samples: ``0, phase + k c, n`` (phase < c)."""
    n, c, phase = int(n), int(c), int(phase) % int(c)
    inner = range(phase if phase else c, n, c)
    return [0, *inner, n] if n else [0]


def grid_boxes(shape_zyx, chunks, phase=(0, 0, 0)) -> list[Box]:
    """The blocks of a block grid (``chunks``, shifted by ``phase``) over ``shape_zyx``."""
    edges = [_edges(n, c, p) for n, c, p in zip(shape_zyx, chunks, phase, strict=True)]
    return [Box((z0, y0, x0), (z1, y1, x1))
            for z0, z1 in itertools.pairwise(edges[0])
            for y0, y1 in itertools.pairwise(edges[1])
            for x0, x1 in itertools.pairwise(edges[2])]


def aligned_chunks(shape_zyx, out: BlockOutput) -> tuple[tuple[int, ...], ...]:
    """Dask-style chunks (per axis, the block lengths) of ``shape_zyx`` on ``out``'s block grid.

    ``darr.rechunk(aligned_chunks(darr.shape, out))`` makes every Dask block one
    aligned write.
    """
    out_chunks = []
    for n, c, p in zip(shape_zyx, out.chunks, out.phase, strict=True):
        edges = _edges(n, c, p)
        sizes = tuple(b - a for a, b in itertools.pairwise(edges))
        out_chunks.append(sizes if sizes else (0,))
    return tuple(out_chunks)


def block_indices(box: Box, shape, chunks, phase=(0, 0, 0)) -> list[tuple[int, int, int]]:
    """The indices of the blocks of grid ``chunks`` that ``box`` covers (whole blocks only).

    The grid's boundaries lie at ``phase + k * chunks`` along each axis (and
    at 0 and the grid's end: the first and last block of an axis may be
    short). ValueError when ``box`` is not aligned to the grid or reaches
    outside ``shape``.
    """
    shift = [(c - p % c) % c for c, p in zip(chunks, phase, strict=True)]
    for lo, hi, n, c, s, axis in zip(box.lo, box.hi, shape, chunks, shift, "zyx", strict=True):
        if lo < 0 or hi > n:
            raise ValueError(f"block {box} reaches outside the grid of shape {shape}")
        if ((lo + s) % c and lo != 0) or ((hi + s) % c and hi != n):
            raise ValueError(f"block {box} is not aligned to the output's blocks of "
                             f"{tuple(chunks)} (axis {axis}: {lo}..{hi}); rechunk with "
                             "aligned_chunks()")
    if box.empty:
        return []
    ranges = [range((lo + s) // c, math.ceil((hi + s) / c))
              for lo, hi, c, s in zip(box.lo, box.hi, chunks, shift, strict=True)]
    return [(a, b, d) for a in ranges[0] for b in ranges[1] for d in ranges[2]]


class _Reindex:
    """Blocks of the volume's index grid -> blocks of a store reindexed to it (picklable).

    The store holds the samples flipped along the array axes ``flips`` and then
    transposed by ``order`` (:func:`.omezarr.reindex_axes`), so that its
    direction is the identity.
    """

    def __init__(self, shape_zyx, flips, order):
        self.shape = tuple(int(n) for n in shape_zyx)
        self.flips, self.order = tuple(flips), tuple(order)

    @property
    def stored_shape(self) -> tuple[int, int, int]:
        """The store's array shape."""
        return tuple(self.shape[o] for o in self.order)

    def volume_axes(self, stored) -> tuple[int, int, int]:
        """A stored per-axis triple (chunks) in the volume's array axes."""
        out = [0, 0, 0]
        for c, o in enumerate(self.order):
            out[o] = int(stored[c])
        return tuple(out)

    def stored_axes(self, values) -> tuple[int, int, int]:
        """A per-axis triple of the volume's array axes in the store's."""
        return tuple(int(values[o]) for o in self.order)

    def box(self, box: Box) -> Box:
        """Where the volume's ``box`` lies in the store."""
        lo, hi = list(box.lo), list(box.hi)
        for a in self.flips:
            lo[a], hi[a] = self.shape[a] - hi[a], self.shape[a] - lo[a]
        return Box(self.stored_axes(lo), self.stored_axes(hi))

    def volume_box(self, stored: Box) -> Box:
        """Where the store's box ``stored`` lies in the volume (:meth:`box` undone)."""
        lo, hi = list(self.volume_axes(stored.lo)), list(self.volume_axes(stored.hi))
        for a in self.flips:
            lo[a], hi[a] = self.shape[a] - hi[a], self.shape[a] - lo[a]
        return Box(tuple(lo), tuple(hi))

    def array(self, array: np.ndarray) -> np.ndarray:
        """A block's samples in the store's orientation."""
        if self.flips:
            array = np.flip(array, axis=self.flips)
        return array.transpose(self.order)

    def unarray(self, stored: np.ndarray) -> np.ndarray:
        """A block of the store in the volume's orientation (:meth:`array` undone)."""
        array = stored.transpose(np.argsort(self.order))
        return np.flip(array, axis=self.flips) if self.flips else array


class BlockWriter:
    """Writes aligned blocks into an output's temporary: picklable, usable in any process.

    Made by :meth:`BlockOutput.writer`. What a write opens it closes before it
    returns, and an error closing it (a quota or an NFS server reporting
    then) fails the write naming the output: no descriptor is left for a
    finaliser to close, where such an error would be lost.
    """

    def __init__(self, shape, chunks, dtype, where: str, phase=(0, 0, 0), components: int = 0):
        self.shape = tuple(shape)
        self.chunks = tuple(chunks)
        self.phase = tuple(phase)
        self.dtype = np.dtype(dtype)
        self.where = where
        self.components = int(components)

    def write(self, box: Box, array) -> None:
        """Write ``array`` at ``box`` (whole blocks of the grid)."""
        array = np.asarray(array)
        if tuple(array.shape) != _block_shape(box, self.components):
            raise ValueError(f"block of shape {array.shape} written at {box}")
        block_indices(box, self.shape, self.chunks, self.phase)
        if box.empty:
            return
        self._write(box, array)

    def _write(self, box: Box, array: np.ndarray) -> None:  # pragma: no cover - per format
        raise NotImplementedError

    @contextlib.contextmanager
    def placing(self):
        """A task's ``place(box, array)``: samples at any box of its block, as they are made.

        Outputs written by offset only (:func:`volwarp_cli.execute.places_blocks`):
        one descriptor for the task, closed when it leaves (an error closing it
        raised naming the output, unless the task failed: its own error is the
        one to tell); the executor marks the block written once the task returned.
        """
        raise VolwarpError(f"{self.where}: this format is written by whole blocks")
        yield  # pragma: no cover - (a context manager)


class _ZarrWriter(BlockWriter):
    def __init__(self, array, shape, chunks, dtype, where, phase, reindex):
        super().__init__(shape, chunks, dtype, where, phase)
        self.array = array  # a zarr array pickles as its store and path
        self.reindex = reindex

    def _write(self, box, array):
        try:
            if self.reindex is None:
                self.array[box.slices] = array
            else:
                self.array[self.reindex.box(box).slices] = self.reindex.array(array)
        except OSError as exc:  # (a full disk: the store named, as the other writers do)
            raise write_error(self.where, exc) from exc


class _MappedWriter(BlockWriter):
    """A writer by offset: ``pwrite`` into the temporary.

    Through a descriptor of the write's (or the placing task's) own, closed by
    it (not a memory map: mapped pages would count in the task's memory).
    ``write_back``: an output replacing a file (:mod:`.writeback`).
    """

    def __init__(self, file, file_dtype, offset, shape, chunks, dtype, where, components=0,
                 write_back=False):
        super().__init__(shape, chunks, dtype, where, components=components)
        self.file, self.file_dtype, self.offset = str(file), np.dtype(file_dtype), int(offset)
        self.write_back = write_back

    @contextlib.contextmanager
    def _opened(self):
        from .filearray import FileArray

        file = FileArray(self.file, self.file_dtype, self.offset,
                         _file_shape(self.shape, self.components), writable=True,
                         write_back=self.write_back)
        try:
            file._file()  # (now: not by two of a task's threads at once)
        except OSError as exc:
            raise write_error(self.where, exc) from exc
        try:
            yield file
        except BaseException:
            with contextlib.suppress(OSError):
                file.close()
            raise
        try:
            file.close()
        except OSError as exc:  # (a quota or NFS error reported when the file is closed)
            raise write_error(self.where, exc) from exc

    def _put(self, file, box, array):
        key, flat = _flat(box, array, self.components)
        try:
            file[key] = flat
        except OSError as exc:  # (a full disk, a file size limit: the output named)
            raise write_error(self.where, exc) from exc

    def _write(self, box, array):
        with self._opened() as file:
            self._put(file, box, array)

    def _place(self, file, box, array):
        array = np.asarray(array)
        if tuple(array.shape) != _block_shape(box, self.components):
            raise ValueError(f"samples of shape {array.shape} placed at {box}")
        if not box.empty:
            self._put(file, box, array)

    @contextlib.contextmanager
    def placing(self):
        with self._opened() as file:
            yield functools.partial(self._place, file)


def _block_shape(box: Box, components: int) -> tuple:
    """The shape of a block's samples: the box's, and the components last (if any)."""
    return box.shape + ((components,) if components else ())


def _file_shape(shape, components: int) -> tuple:
    """A file of interleaved components read as (z, y, x * components) samples."""
    nz, ny, nx = shape
    return (nz, ny, nx * max(1, components))


def _flat(box: Box, array: np.ndarray, components: int):
    """``(slices, samples)`` of a block in a file of interleaved components."""
    if not components:
        return box.slices, array
    (z0, y0, x0), (z1, y1, x1) = box.lo, box.hi
    key = (slice(z0, z1), slice(y0, y1), slice(x0 * components, x1 * components))
    return key, np.ascontiguousarray(array).reshape(z1 - z0, y1 - y0, -1)


class BlockOutput:
    """An output volume being written block by block (made by :func:`open_block_output`).

    Attributes
    ----------
    path : Path
        Where the output appears on :meth:`commit`.
    geometry : Geometry
        The output grid.
    dtype : numpy.dtype
        The sample type (native order; writes are converted to it).
    chunks : tuple of 3 ints
        The block grid (z, y, x): every write covers whole blocks.
    phase : tuple of 3 ints
        Where the grid's boundaries start along each axis (``phase + k *
        chunks``): 0, but for a store whose axes run reversed, where the grid
        is the store's own, counted from the other end. :meth:`blocks` lists
        the grid's blocks.
    """

    def __init__(self, path: Path, geometry: Geometry, dtype: np.dtype, chunks,
                 phase=(0, 0, 0), components: int = 0):
        self.path = path
        self.geometry = geometry
        self.dtype = np.dtype(dtype)
        self.chunks = tuple(int(c) for c in chunks)
        self.phase = tuple(int(p) for p in phase)
        self.components = int(components)
        self._lock = threading.Lock()
        self._written: set[tuple[int, int, int]] = set()
        self._state = "open"
        self._stack = contextlib.ExitStack()

    # -- blocks -----------------------------------------------------------------------
    def _blocks_of(self, box: Box) -> list[tuple[int, int, int]]:
        """The block indices ``box`` covers; ValueError unless it covers whole blocks."""
        return block_indices(box, self.geometry.shape, self.chunks, self.phase)

    def blocks(self) -> list[Box]:
        """Every block of the output's block grid, in order."""
        return grid_boxes(self.geometry.shape, self.chunks, self.phase)

    def writer(self) -> BlockWriter:
        """A picklable handle that writes blocks into this output's temporary, in any process.

        For tasks in other processes (Dask's process and distributed
        schedulers): their writes are not counted here; :meth:`mark_written`
        the blocks whose tasks succeeded before :meth:`commit`.
        """
        raise NotImplementedError  # pragma: no cover - every format has one

    def place(self, box: Box, array) -> None:
        """Write ``array`` at any ``box`` of the output (thread-safe; not counted as written).

        For a run that writes the whole as one block, a few planes at a time
        as they are finished (:func:`volwarp_cli.execute.run`): it marks the
        whole written once every part is placed. Files written by offset only.
        """
        raise VolwarpError(f"{self.path}: this format is written by whole blocks")

    def mark_written(self, boxes) -> None:
        """Count the blocks of ``boxes`` as written (by :meth:`writer` handles)."""
        with self._lock:
            for box in boxes:
                self._written.update(self._blocks_of(box))

    def write(self, box: Box, array) -> None:
        """Write ``array`` (shape ``box.shape``) at ``box`` (whole blocks; thread-safe)."""
        if not isinstance(box, Box):
            box = Box(*box)
        array = np.asarray(array)
        if tuple(array.shape) != _block_shape(box, self.components):
            raise ValueError(f"block of shape {array.shape} written at {box} "
                             f"(shape {_block_shape(box, self.components)})")
        blocks = self._blocks_of(box)
        with self._lock:
            if self._state != "open":
                raise ValueError(f"{self.path}: the output is {self._state}: no more writes")
        self._write(box, array)
        with self._lock:
            self._written.update(blocks)

    def _write(self, box: Box, array: np.ndarray) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def read(self, box: Box) -> np.ndarray:
        """The samples written at ``box`` so far (to change a few voxels before commit).

        Call it with no writes in flight: a block read while another process
        writes it may be torn.
        """
        with self._lock:
            if self._state != "open":
                raise ValueError(f"{self.path}: the output is {self._state}: nothing to read")
        return self._read(box)

    def _read(self, box: Box) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def missing(self) -> int:
        """How many blocks have not been written yet."""
        total = 1
        for n, c, p in zip(self.geometry.shape, self.chunks, self.phase, strict=True):
            total *= len(_edges(n, c, p)) - 1
        return total - len(self._written)

    # -- ending -----------------------------------------------------------------------
    def commit(self) -> None:
        """Finish (pyramid, header) and rename the output into place.

        Every block must have been written (else a VolwarpError, and the
        output is abandoned).
        """
        with self._lock:
            if self._state != "open":
                raise VolwarpError(f"{self.path}: the output is {self._state} already")
            self._state = "committing"
        try:
            left = self.missing()
            if left:
                raise VolwarpError(f"{self.path}: {left} block{'s' if left != 1 else ''} of "
                                   f"{self.chunks} not written; the output is not made")
            self._finish()
            stack, self._stack = self._stack, contextlib.ExitStack()
            stack.close()  # the atomic rename
        except BaseException:
            self._state = "committing"
            self.abort()
            raise
        self._state = "committed"

    def _finish(self) -> None:
        """Hook: complete the temporary before the rename."""

    def _release(self) -> None:
        """Hook: close maps and files before the temporary is removed or renamed."""

    def abort(self) -> None:
        """Remove the temporary output (an existing output at ``path`` is kept)."""
        if self._state in ("committed", "aborted"):
            return
        self._state = "aborted"
        try:
            with contextlib.suppress(Exception):
                self._release()
        finally:  # (a second stop while the release waits: the temporary still goes)
            stack, self._stack = self._stack, contextlib.ExitStack()
            stack.__exit__(_Aborted, _Aborted(), None)

    def __enter__(self) -> BlockOutput:
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is not None:
            self.abort()
        return False


@contextlib.contextmanager
def committed(out: BlockOutput):
    """``out`` as a context: committed when the block exits cleanly, aborted otherwise.

    (Aborted: nothing left at its path, an existing file there untouched.)
    """
    try:
        yield out
    except BaseException:
        out.abort()
        raise
    out.commit()


def clip_block(block, shape_zyx) -> tuple[int, int, int]:
    """``block`` (z, y, x) within ``shape_zyx``: each side 1 sample at least, the grid's at most."""
    return tuple(max(1, min(int(b), max(int(n), 1))) for b, n in zip(block, shape_zyx,
                                                                     strict=True))


def block_layout(shape_zyx, version: str, block=None):
    """``(chunks, shards)`` of a store written in blocks of ``block`` (z, y, x).

    The in-memory writer's own layout (:func:`.omezarr.store_layout`) where
    the blocks are made of its write units (shards in 0.5, chunks in 0.4:
    :func:`store_unit`), so that the store is the one written in memory, byte
    for byte; else NGFF 0.5: one shard per block (the unit of a write), inner
    chunks of 64 along an axis whose block is a multiple of 64, else of the
    whole block; 0.4: the blocks are the chunks.
    """
    from . import omezarr

    standard = omezarr.store_layout(shape_zyx, version, None)
    if block is None:
        return standard
    block = clip_block(block, shape_zyx)
    if all(b >= n or b % u == 0 for b, u, n in zip(block, store_unit(shape_zyx, version),
                                                    shape_zyx, strict=True)):
        return standard
    if version == "0.4":
        return block, None
    inner = tuple(omezarr.CHUNK if b % omezarr.CHUNK == 0 else b for b in block)
    return inner, block


def store_unit(shape_zyx, version: str) -> tuple[int, int, int]:
    """The unit a write of the in-memory OME-Zarr layout covers: its shards (0.5), chunks (0.4).

    The same edge on every axis, clipped to it: in the grid's own axes as in
    the store's (permuted or reversed to the identity direction).
    """
    from . import omezarr

    chunks, shards = omezarr.store_layout(shape_zyx, omezarr.check_version(version), None)
    return tuple(shards or chunks)


def zarr_staged(path, shape_zyx, dtype, version: str, block, direction=None) -> bool:
    """Whether an OME-Zarr output written in blocks of ``block`` is staged in a raw scratch file.

    Blocks not made of the in-memory layout's write units (:func:`store_unit`)
    would give the store a layout of their own (one shard per block): the
    same samples, not the same bytes, and a layout that changed with the
    blocks, so with ``--threads``. Staged, the blocks are placed by offset
    in a raw file beside the output, and the commit writes the store shard
    by shard in the in-memory layout: the bytes the in-memory write gives.
    Not staged where a shard's write does not fit the memory budget (the
    in-memory write would not fit either: it writes the same shards) or the
    samples do not fit the disk beside the output. ``direction``: the grid's,
    whose store may be reindexed (:func:`.omezarr.reindex_axes`): its write
    units are the store's. The run decides once per output and block
    (``RunFiles.decided``, :mod:`volwarp_cli.runscope`): the blocks' memory
    is weighed by the decision before the output is opened.
    """
    from ..runscope import run_files
    from . import omezarr

    if block is None:
        return False
    shape = tuple(int(n) for n in shape_zyx)
    found = None if direction is None else omezarr.reindex_axes(direction)
    if found is not None:  # (the store's axes)
        shape = tuple(shape[o] for o in found[1])
        block = tuple(int(block[o]) for o in found[1])
    standard = omezarr.store_layout(shape, version, None)
    if block_layout(shape, version, block) == standard:
        return False
    key = ("zarr staged", os.path.abspath(path), shape, np.dtype(dtype).str, version,
           tuple(int(b) for b in block))
    decided = run_files().decided
    if key not in decided:
        decided[key] = _stage_fits(path, shape, dtype, version, decided)
    return decided[key]


def _stage_fits(path, shape_zyx, dtype, version: str, decided: dict) -> bool:
    """Whether a staged store's commit fits the memory budget, and its scratch file the disk.

    The disk holds the raw samples and, while the commit writes it, the
    store (counted as large: zstd may gain nothing), beside what the run's
    other staged stores not yet finished reserve there (``decided``: by
    output path, each one's until it commits or is abandoned,
    :func:`_release_stage`; what finished stores wrote, the free space
    shows). Counted as the raw samples alone, a 64 MiB warp failed on a 100
    MiB disk after its blocks, where one shard per block fits (a review).
    """
    import shutil

    from ..memory import memory_limit

    if staged_commit_bytes(shape_zyx, dtype, version) > memory_limit():
        return False
    folder = Path(path).resolve().parent
    try:
        free = shutil.disk_usage(folder).free
        reserved = decided.setdefault(("zarr staged disk", os.stat(folder).st_dev), {})
    except OSError:
        return False
    mine = os.path.abspath(path)
    need = 2 * math.prod(shape_zyx) * np.dtype(dtype).itemsize
    if sum(n for p, n in reserved.items() if p != mine) + need > free:
        reserved.pop(mine, None)
        return False
    reserved[mine] = need
    return True


def _release_stage(path) -> None:
    """The disk a staged store reserved (:func:`_stage_fits`), given back once it is done."""
    from ..runscope import run_files

    mine = os.path.abspath(path)
    for key, reserved in run_files().decided.items():
        if isinstance(key, tuple) and key[:1] == ("zarr staged disk",):
            reserved.pop(mine, None)


def staged_commit_bytes(shape_zyx, dtype, version: str) -> int:
    """The memory a staged store's commit holds: one write unit's samples and zarr's encoding.

    The unit within the grid (a shard of 256 planes over a grid of 200 is
    200 planes of samples): counted whole, it was up to twice what was
    measured, and stores fell back to blocks of their own without need.
    """
    from . import omezarr

    unit = clip_block(store_unit(shape_zyx, version), shape_zyx)
    chunks, shards = omezarr.store_layout(shape_zyx, version, None)
    item = np.dtype(dtype).itemsize
    return math.prod(unit) * item + omezarr.write_bytes(unit, item, chunks, shards)


def zarr_block_bytes(shape_zyx, dtype, version: str, block) -> int:
    """What writing a block of ``block`` (z, y, x) into an OME-Zarr output adds to its samples.

    zarr's encoding of the shards (0.5; the chunks in 0.4) the block is
    made of (:func:`.omezarr.write_bytes`), in the store's layout for blocks
    of ``block`` (:func:`block_layout`).
    """
    from . import omezarr

    block = clip_block(block, shape_zyx)
    chunks, shards = block_layout(shape_zyx, version, block)
    return omezarr.write_bytes(block, np.dtype(dtype).itemsize, chunks, shards)


def zarr_commit_bytes(shape_zyx, dtype, version: str, pyramid: int, block,
                      staged: bool = False) -> int:
    """The least memory committing an OME-Zarr output written in blocks of ``block`` takes.

    Its pyramid's levels, each made in its smallest pieces
    (:func:`.omezarr.pyramid_bytes`), and a ``staged`` store's shards
    (:func:`zarr_staged`); 0 for neither. (The label-map rule's count reads
    boxes as small as it must.)
    """
    from . import omezarr

    copy = staged_commit_bytes(shape_zyx, dtype, version) if staged else 0
    if not pyramid:
        return copy
    standard = omezarr.store_layout(shape_zyx, version, None)
    layout = (standard if block is None or staged
              else block_layout(shape_zyx, version, block))
    chunks = None if layout == standard else clip_block(block, shape_zyx)
    return max(copy, omezarr.pyramid_bytes(shape_zyx, np.dtype(dtype).itemsize, version,
                                           pyramid, chunks=chunks, layout0=layout))


class _ZarrOutput(BlockOutput):
    def __init__(self, path, header, chunks_zyx, version, byte_order, pyramid, labels):
        from . import omezarr
        from .atomic import atomic_folder

        version = omezarr.check_version(version)
        geometry, dtype = Geometry.of(header), header.dtype
        # a grid whose axes are flipped or permuted is stored reindexed to the identity
        # direction, as write_omezarr stores it: each block is moved into place, on the
        # store's own block grid (counted from the far end along a reversed axis)
        stored = omezarr.reindexed_header(header)
        omezarr.warn_if_oblique(stored, path)
        found = omezarr.reindex_axes(header.direction)
        reindex = None
        if found is not None and (found[0] or found[1] != (0, 1, 2)):
            reindex = _Reindex(geometry.shape, *found)
        block = chunks_zyx
        if reindex is not None and block is not None:
            block = reindex.stored_axes(block)
        # blocks not made of the store's write units: placed in a raw scratch file, the
        # store written in its in-memory layout on commit (zarr_staged)
        staged = zarr_staged(path, header.shape, dtype, version, chunks_zyx, header.direction)
        layout = (omezarr.store_layout(stored.shape, version, None) if staged
                  else block_layout(stored.shape, version, block))
        phase = (0, 0, 0)
        if staged:  # (the scratch file: the volume's own axes)
            grid = clip_block(chunks_zyx, geometry.shape)
        else:
            # the caller's blocks: each one whole write units in the in-memory layout, or
            # one shard of its own (the units as the grid cut a distance's last pass, whole
            # along z, at a shard's edge: 1,144,000 voxels were left inf, exit 0); without
            # blocks, the store's write units
            grid = (clip_block(block, stored.shape) if block is not None
                    else layout[1] or layout[0])
            if reindex is not None:
                grid = reindex.volume_axes(grid)
                phase = tuple(int(n) % c if a in reindex.flips else 0
                              for a, (n, c) in enumerate(zip(geometry.shape, grid,
                                                             strict=True)))
        super().__init__(path, geometry, dtype, grid, phase)
        self._reindex = reindex
        self._staged = None
        self._stored, self._header, self._version, self._pyramid = (stored, header, version,
                                                                     pyramid)
        # labels "auto" (write_volume's default): a map its key/values say is one (a SEG's)
        # is; of an integer output, or a float one (a float map of integer ids is one
        # too), decided on commit, from the samples written (their pyramid levels take the
        # mode or the mean), as in memory
        # (an integer one without levels too: its image-label says it, as in memory)
        self._segmentation = False  # (a float map its keys call labels: ids if integers)
        if labels == "auto" or labels is None:
            from ..labelmap import segmentation_of

            integer = self.dtype.kind in "iu"
            self._segmentation = bool((pyramid or integer)
                                      and segmentation_of(getattr(header, "meta", None)))
            labels = (True if self._segmentation and integer
                      else None if integer or (pyramid and self.dtype.kind == "f") else False)
        self._labels = labels if labels is None else bool(labels)
        try:
            from ..memory import large_allocations_mapped

            # (zarr's threads' freed frames given back until the store is renamed: see there)
            self._stack.enter_context(large_allocations_mapped())
            tmp = self._stack.enter_context(atomic_folder(path))
            if staged:
                self._stage(path)
            group = omezarr.open_group_for_writing(tmp, version)
            # (the in-memory layout at level 0: the pyramid's levels take theirs too)
            standard = layout == omezarr.store_layout(stored.shape, version, None)
            self._arrays = omezarr.create_arrays(group, omezarr.level_shapes(stored.shape,
                                                                             pyramid),
                                                 dtype, version, None if standard else block,
                                                 byte_order, layout0=layout)
            self._group = group
        except BaseException:
            self.abort()
            raise

    def _stage(self, path):
        """The raw scratch file the blocks go to (the volume's own axes), removed with the store's temporary."""
        from .atomic import make_scratch_folder, remove_scratch_folder
        from .filearray import FileArray

        folder = make_scratch_folder(path)
        self._stack.callback(remove_scratch_folder, folder)
        file = folder / "level0.raw"
        try:
            with open(file, "wb") as fh:
                fh.truncate(self.geometry.size * self.dtype.itemsize)
        except OSError as exc:
            raise write_error(path, exc) from exc
        self._staged = FileArray(file, self.dtype, 0, self.geometry.shape, writable=True)

    def _write(self, box, array):
        if self._staged is not None:
            try:
                self._staged[box.slices] = array
            except OSError as exc:
                raise write_error(self.path, exc) from exc
        elif self._reindex is None:
            self._arrays[0][box.slices] = array
        else:
            self._arrays[0][self._reindex.box(box).slices] = self._reindex.array(array)

    def _read(self, box):
        if self._staged is not None:
            return np.asarray(self._staged[box.slices])
        if self._reindex is None:
            return np.asarray(self._arrays[0][box.slices])
        return np.ascontiguousarray(self._reindex.unarray(
            np.asarray(self._arrays[0][self._reindex.box(box).slices])))

    def writer(self):
        if self._staged is not None:
            return _MappedWriter(self._staged.path, self.dtype, 0, self.geometry.shape,
                                 self.chunks, self.dtype, str(self.path))
        return _ZarrWriter(self._arrays[0], self.geometry.shape, self.chunks, self.dtype,
                           str(self.path), self.phase, self._reindex)

    def _unstage(self):
        """Level 0 from the scratch file, one write unit at a time, as the in-memory write does."""
        level0 = self._arrays[0]
        for stored in grid_boxes(level0.shape, level0.shards or level0.chunks):
            box = stored if self._reindex is None else self._reindex.volume_box(stored)
            samples = self._staged[box.slices]
            if self._reindex is not None:
                samples = self._reindex.array(samples)
            try:
                level0[stored.slices] = samples
            except OSError as exc:
                raise write_error(self.path, exc) from exc
            del samples
        self._release()

    def _release(self):
        if self._staged is not None:
            self._staged.close()
            _release_stage(self.path)

    def _finish(self):
        from ..memory import memory_limit, release_freed
        from . import omezarr

        release_freed()  # (what the blocks' tasks freed: the levels are weighed against the rest)
        if self._staged is not None:
            self._unstage()
        if self._labels is None:  # (the whole array's rule, read box by box)
            from ..labelmap import integer_samples, looks_like_labels_by_blocks

            level0 = self._arrays[0]
            pieces = omezarr.scan_pieces(level0, memory_limit())
            if self._segmentation:  # (as resolve_labels: its keys, if its samples are ids)
                self._labels = all(integer_samples(level0[box.slices]) is not None
                                   for box in pieces)
            else:
                self._labels = looks_like_labels_by_blocks(level0, pieces)
        method = ("mode" if self._labels else "mean") if self._pyramid else None
        if self._pyramid:  # (the label choice said at -v, as in memory)
            from ..progress import log

            log.info("%s: %d pyramid level(s) by the %s (%s)", self.path, self._pyramid,
                     method, "a label map" if self._labels else "intensities")
        omezarr.write_levels(self._arrays, None, self._labels, memory_limit())
        self._group.attrs.update(omezarr.group_attributes(
            omezarr.multiscales_metadata(self._stored, self._pyramid, self._version, method),
            omezarr.volwarp_attribute(self._stored, self._header, method), self._version,
            omezarr.tags_image_label(self._labels, self.dtype)))


class _MappedOutput(BlockOutput):
    def __init__(self, path, vol_header, chunks_zyx, fmt, byte_order, components=None):
        from .atomic import atomic_output
        from .common import with_byte_order

        geometry, dtype = Geometry.of(vol_header), vol_header.dtype
        chunks = chunks_zyx or (64, geometry.shape[1], geometry.shape[2])
        chunks = clip_block(chunks, geometry.shape)
        super().__init__(path, geometry, dtype, chunks, components=len(components or ()))
        with_byte_order(np.zeros(0, dtype), byte_order)  # checks the name
        if fmt == "nrrd":
            from .nrrd import nrrd_header

            header = nrrd_header(vol_header, self.dtype, encoding="raw", byte_order=byte_order,
                                 components=list(components) if components else None)
        elif fmt == "metaimage":
            from .metaimage import metaimage_header

            header = metaimage_header(vol_header, self.dtype, byte_order=byte_order,
                                      data_file="LOCAL")
        else:
            header = b""
        file_dtype = self.dtype.newbyteorder("<" if byte_order == "little" else ">")
        nbytes = geometry.size * self.dtype.itemsize * max(1, self.components)
        self._map = None
        self._placing = collections.Counter()  # (place calls under way by thread, their end)
        self._placed = threading.Condition(self._lock)
        self._file_dtype, self._offset = file_dtype, len(header)
        try:
            tmp = self._tmp = self._stack.enter_context(atomic_output(path))
            # a rename replacing a file waits for the samples' writing out: begun as they come
            self._write_back = writeback.replaces(tmp)
            with open(tmp, "r+b") as fh:
                fh.write(header)
                fh.truncate(len(header) + nbytes)
            if nbytes:
                from .filearray import FileArray

                self._map = FileArray(tmp, file_dtype, len(header),
                                      _file_shape(geometry.shape, self.components),
                                      writable=True, write_back=self._write_back)
        except BaseException as exc:
            self.abort()
            if isinstance(exc, OSError):
                raise write_error(path, exc) from exc
            raise

    def _write(self, box, array):
        if self._map is not None:
            self._put(box, array)

    def _put(self, box, array):
        key, flat = _flat(box, array, self.components)
        try:
            self._map[key] = flat
        except OSError as exc:  # (a full disk, a file size limit: the output named)
            raise write_error(self.path, exc) from exc

    def place(self, box, array):
        array = np.asarray(array)
        if tuple(array.shape) != _block_shape(box, self.components):
            raise ValueError(f"samples of shape {array.shape} placed at {box}")
        me = threading.get_ident()
        try:
            with self._lock:
                if self._state != "open":
                    raise ValueError(f"{self.path}: the output is {self._state}: no more writes")
                if self._map is None:
                    return
                self._map._file()  # (opened once, not by two threads at once)
                self._placing[me] += 1
            self._put(box, array)
        finally:
            with self._lock:
                if self._placing[me]:
                    self._placing[me] -= 1
                self._placed.notify_all()

    def _read(self, box):
        shape = _block_shape(box, self.components)
        if self._map is None:
            return np.zeros(shape, self.dtype)
        key, _ = _flat(box, np.zeros(shape, self.dtype), self.components)
        return np.asarray(self._map[key]).astype(self.dtype, copy=False).reshape(shape)

    def writer(self):
        return _MappedWriter(self._tmp, self._file_dtype, self._offset, self.geometry.shape,
                             self.chunks, self.dtype, str(self.path), self.components,
                             write_back=self._write_back)

    def _finish(self):
        try:
            self._release()
        except OSError as exc:  # (a quota or NFS error reported when the file is closed)
            raise write_error(self.path, exc) from exc

    def _release(self):
        # A stop while the threads place their planes aborts from the main thread: the
        # file is closed once the other threads' writes under way end (later ones are
        # refused), never under them (its descriptor's number could be another file's
        # by then); a place of this thread's own that a stop cut short is not waited for
        me = threading.get_ident()
        with self._lock:
            self._placed.wait_for(lambda: not any(
                n for thread, n in self._placing.items() if thread != me))
        if self._map is not None:
            self._map.close()
            self._map = None
