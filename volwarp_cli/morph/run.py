"""The morph end to end: decided before any sample is read, run in memory or by blocks.

:func:`plan_morph` reads the inputs' headers, the frame grid's size and the
outputs', and decides by arithmetic, as :func:`volwarp_cli.execute.run` does
for every operation: the in-memory morph's memory against the budget
(``--chunked``/``--no-chunked`` as asked), what neither way can make refused
with both reasons. :func:`run_morph` runs it: the fields in memory
(:func:`morph_in_memory`) or on disk by blocks (:func:`morph_by_blocks`,
which strings together the steps of :mod:`.chunked`: the frame grid and what
the block path refuses, the alignment's matrices counted by blocks, the
resampling's blocks and the aligned inputs' coverage, the outputs' checks,
both fields on disk), then the same frames either way
(:func:`.frames.frames`: each frame an operation of the executor, one block
in memory, many by blocks). Nothing here parses options: the command
line passes the job, its outputs (:class:`.outputs.MorphOutputs`) and how to
run (:class:`volwarp_cli.execute.How`).
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import VolwarpError
from ..geometry import Geometry
from ..progress import timed
from .frames import Frame, RenderSettings
from .spec import MorphJob


class BlocksRefused(VolwarpError):
    """A morph the block path cannot run, and why (said before any work).

    ``usage``: the morph itself is one the block path does not run (a
    landmark warp, a frame grid the aligned inputs do not cover: the
    in-memory morph does); otherwise its outputs or its blocks cannot be
    made (a format written whole, a full disk, a resampling too big for a
    block).
    """

    def __init__(self, message: str, usage: bool = True):
        super().__init__(message)
        self.usage = usage


def morph_note(job: MorphJob, rules: dict) -> str:
    """The frames' ``volwarp_morph`` value: metric, output, band, and each shape's rule.

    ``rules``: :attr:`.pipeline.Prepared.rules`, what each shape's field is
    of (``distance``'s ``volwarp_distance`` words: a label map's voxels, or
    a level of intensities). The same in memory and by blocks (the frames
    are the same samples).
    """
    note = f"metric={job.metric} output={job.output}"
    if job.max_distance is not None:
        note += f" max_distance={job.max_distance:g} (each field clamped)"
    return note + "".join(f"; {name}: {rules[name].note()}" for name in ("source", "target"))


@dataclass(frozen=True)
class FrameWrite:
    """How the frames are written: their type and the writers' options.

    ``dtype``: None for float32, or the source's for a density ``range:
    source``; the attributes keep their own.
    """

    dtype: object = None
    compress: bool = False
    byte_order: str = "little"
    version: str = "0.5"
    pyramid: int = 0

    @classmethod
    def of(cls, write_kw: dict) -> FrameWrite:
        """From the command's write options (``dtype``, ``compress``, ``ome_zarr_version``...)."""
        return cls(write_kw.get("dtype"), bool(write_kw.get("compress")),
                   write_kw.get("byte_order", "little"),
                   write_kw.get("ome_zarr_version", "0.5"), int(write_kw.get("pyramid") or 0))

    def refusal(self, path, shape_zyx, dtype) -> str | None:
        """Why ``path`` cannot be written by blocks (its format, its folder's space), or None."""
        import math

        from ..execute import blocks_refusal

        nbytes = math.prod(int(n) for n in shape_zyx) * np.dtype(dtype).itemsize
        return blocks_refusal([(path, nbytes)], self.compress, self.pyramid)


@dataclass
class MorphPlan:
    """:func:`plan_morph`'s decision.

    ``by_blocks``; ``in_memory_refusal``: why the in-memory morph does not
    fit, when blocks run instead of it unasked; ``loaded``: inputs read whole
    to read their headers, by path; ``headers``: the source's and the
    target's :class:`~volwarp_cli.volume.Header`.
    """

    by_blocks: bool
    in_memory_refusal: str | None = None
    loaded: dict = field(default_factory=dict)
    headers: tuple = ()


def _input_header(path, loaded: dict):
    """The Header of ``path``: its samples unread where the format allows, else read whole.

    A volume read whole is kept in ``loaded`` (by path). A compressed file's
    header is read alone (its samples inflated only if the morph runs by
    blocks, by :func:`_lazy`).
    """
    from ..io import read_volume
    from ..io.lazy import open_volume_header

    try:
        return open_volume_header(path, require_lazy=True, samples=False)[0]
    except VolwarpError:  # (a file read whole, or not a volume: read_volume says so)
        loaded[str(path)] = read_volume(path)
        return loaded[str(path)].header


#: Bytes a frame-grid voxel holds in the in-memory morph, measured (256^3 binary shapes,
#: static: 23 bytes a voxel above the command's start): both fields on the grid, the
#: frame's buffer and values, a field being resampled onto the grid and the writer's copy
FRAME_BYTES = {"static": 24, "moving": 48}
#: ... and what a density mapped to the source's range adds: its float64 values and the
#: temporaries of the mapping (160^3 int16, measured: 415 MiB at the peak)
RANGE_BYTES = 56


def in_memory_bytes(job: MorphJob, source, target, frame_voxels: int) -> int:
    """What the in-memory morph holds at its peak, from the headers alone.

    Both inputs read whole, and the larger of two phases: the fields on the
    inputs' grids (the source's kept while the target's is computed, each as
    its operation counts it: :func:`volwarp_cli.distance.operation.field_memory`),
    and the frame grid's arrays (:data:`FRAME_BYTES` a voxel, twice as many
    with a moving landmark warp; each attribute's pair).
    """
    from ..distance.operation import field_memory

    def mem(v):
        return field_memory(v.shape, v.dtype, metric=job.metric, surface=job.surface,
                            max_distance=job.max_distance)

    inputs = sum(math.prod(v.shape) * np.dtype(v.dtype).itemsize
                 for v in (source, target))
    fields = max(mem(source), 4 * math.prod(source.shape) + mem(target))
    per_voxel = FRAME_BYTES["static" if job.warp_mode == "static" else "moving"]
    if job.output == "density" and job.density_range == "source":
        per_voxel += RANGE_BYTES
    frames = frame_voxels * (per_voxel + 8 * len(job.attributes))
    return inputs + max(fields, frames)


def plan_morph(job: MorphJob, outputs, write: FrameWrite, chunked: bool | None) -> MorphPlan:
    """In memory or by blocks, decided before any sample is read (module notes).

    Refuses, before any work, frames that fit neither the memory nor the disk
    (:func:`volwarp_cli.execute.refuse_unmakeable`); a
    :class:`~.grid.GridError` for a frame grid that cannot be made.
    """
    from .. import execute, memory
    from .grid import least_frame_shape

    plan = MorphPlan(False)
    with one_volume_inputs():
        source = _input_header(job.source.path, plan.loaded)
        target = _input_header(job.target.path, plan.loaded)
    plan.headers = (source, target)
    shape = least_frame_shape(job, Geometry.of(source), Geometry.of(target))
    n = math.prod(shape)
    frame_type = np.dtype(write.dtype or (
        source.dtype if job.output == "density" and job.density_range == "source"
        else np.float32))
    typed = [(p, frame_type) for p in outputs.frames]
    for a in job.attributes:  # (an attribute's own type: one byte at least)
        typed += [(p, np.dtype(a.dtype or np.uint8)) for p in outputs.attributes[a.name]]
    sizes = [(p, n * t.itemsize) for p, t in typed]
    what = f"a morph on a {'x'.join(map(str, shape))} grid"
    # (inputs read whole for their headers are held already: the budget left counts them;
    # and a frame's write beside the frames' arrays: an OME-Zarr store's encoding, a gzip
    # stream, counted, or the in-memory morph was refused at its first write, its work done)
    need = in_memory_bytes(job, source, target, n) - sum(
        v.data.nbytes for v in plan.loaded.values()) + _write_bytes(write, typed, shape)
    no_blocks = None
    if job.warp_source_points is not None and chunked is None:  # (--chunked: a usage error)
        no_blocks = "a morph with a landmark warp runs in memory only"
    def load():  # (what the work loads, counted where the budget is tight)
        import scipy.ndimage  # noqa: F401 - the fields' resampling onto the frame grid

        from ..io import load_writer

        if job.warp_source_points is not None:
            import scipy.interpolate  # noqa: F401 - the landmark warp's solver
        for path, _ in typed:  # (the writers: zarr's 17 MiB for a store's frames)
            load_writer(path, write.compress)

    if execute.decide(need, what, sizes, execute.How(chunked=chunked), load=load,
                      no_blocks=no_blocks, compress=write.compress, pyramid=write.pyramid):
        return plan
    plan.by_blocks = True
    plan.loaded.clear()  # (the block path opens its inputs itself)
    if chunked is None:
        try:
            memory.ensure_fits_in_memory(need, what)
        except VolwarpError as exc:
            plan.in_memory_refusal = str(exc)
    return plan


def _write_bytes(write: FrameWrite, typed, shape) -> int:
    """The most one output's write holds beyond its samples (:func:`~volwarp_cli.io.write_memory`).

    ``typed``: ``[(path, dtype)]`` of the frames and attributes.
    """
    from ..io import write_memory

    return max((write_memory(path, shape, dtype, compress=write.compress,
                             byte_order=write.byte_order, ome_zarr_version=write.version,
                             pyramid=write.pyramid) for path, dtype in typed), default=0)


@contextlib.contextmanager
def one_volume_inputs():
    """A morph input that holds several volumes is the input's fault (exit 1).

    Morph has no ``--volume-index`` nor ``--series`` to choose one with: the
    reader's usage error becomes a file error saying how to extract one.
    """
    from ..errors import ChoiceNeeded, FormatError

    try:
        yield
    except ChoiceNeeded as exc:
        raise FormatError(f"{exc} (morph takes one volume per input: extract it first, e.g. "
                          "volwarp convert IN --volume-index N -o one.nrrd)") from None


def frame_targets(op, i: int, outputs, write: FrameWrite) -> None:
    """Frame ``i``'s outputs as ``op``'s targets (the frame cast to ``--dtype``)."""
    from .. import execute

    op.cast = None if write.dtype is None else np.dtype(write.dtype)
    types = op.types()
    paths = {"frame": outputs.frames[i],
             **{name: outputs.attributes[name][i] for name in op.fields.attributes}}
    op.targets = {key: execute.Target(Path(path), op.header(key), types[key],
                                      compress=write.compress, byte_order=write.byte_order,
                                      version=write.version, pyramid=write.pyramid)
                  for key, path in paths.items()}


def frame_writer(outputs, write: FrameWrite, how, *, by_blocks: bool):
    """``make(i, op)`` for :func:`.frames.frames`: frame ``i`` written where ``outputs`` says.

    The frame and its attributes are ``op``'s targets, run by the executor as
    the morph's plan decided (``by_blocks``; ``how``: the engine the blocks
    run on). Returns their Headers (no samples held).
    """
    from .. import execute

    def make(i, op):
        frame_targets(op, i, outputs, write)
        execute.run(op, how, by_blocks=by_blocks)
        return op.targets["frame"].header, {
            name: op.targets[name].header for name in op.fields.attributes}
    return make


def morph_in_memory(job: MorphJob, source, target, attributes: dict | None = None, *,
                    outputs, meta: dict | None = None, write: FrameWrite = FrameWrite(),
                    meshes: bool = False, render: RenderSettings | None = None,
                    space: str | None = None) -> Iterator[Frame]:
    """The frames of ``job`` computed in memory and written, yielded in order once written.

    ``source``, ``target``: the shapes' Volumes; ``attributes``: name ->
    (source Volume, target Volume); the rest as :func:`morph_by_blocks`'.
    The frames are :func:`.frames.frames` of the in-memory fields
    (:func:`.pipeline.prepare`), each the one block of its operation.
    """
    from ..execute import How
    from .frames import FrameFields, MeshBlocks, frame_values, frames
    from .pipeline import prepare

    prep = prepare(job, source, target, attributes)
    fields = FrameFields.of(job, prep)
    yield from frames(job, fields, frame_values(job, fields, source.data),
                      frame_writer(outputs, write, How(), by_blocks=False),
                      meta={"volwarp_morph": morph_note(job, prep.rules), **(meta or {})},
                      meshes=MeshBlocks() if meshes else None, render=render, space=space)


def morph_by_blocks(job: MorphJob, source, target, attributes: dict | None = None, *,
                    outputs, meta: dict | None = None, write: FrameWrite = FrameWrite(),
                    meshes: bool = False, render: RenderSettings | None = None,
                    how, space: str | None = None) -> Iterator[Frame]:
    """The frames of ``job`` computed and written by blocks, yielded in order once written.

    Parameters
    ----------
    job : MorphJob
        The morph (no landmark warp).
    source, target : (header, samples)
        Each shape opened lazily: its :class:`~volwarp_cli.volume.Header`
        (its geometry) and a sliceable, picklable reader of its samples.
    attributes : dict, optional
        name -> ((header, samples), (header, samples)) of each attribute.
    outputs : MorphOutputs
        Each frame's path (``frames``) and each attribute's (``attributes``).
    meta : dict, optional
        Key/values every frame carries after ``volwarp_morph`` (provenance).
    write : FrameWrite
        The frames' type and the writers' options.
    meshes, render
        Each frame's surface and its render (the caller writes them).
    how : volwarp_cli.execute.How
        The engine the blocks run on (``open_engine``), the user's ``block``
        shape, and the ``scheduler`` named (the meshes run on it when one is;
        threads otherwise).

    Yields
    ------
    Frame
        Each frame once its volume and attributes are written (their
        Headers), with its mesh and render when asked for. The same
        :func:`.frames.frames` as in memory, on the fields by blocks.

    Raises
    ------
    BlocksRefused
        Before any work: a morph the block path does not run (a landmark
        warp, a frame grid the aligned inputs do not cover), an output that
        cannot be written by blocks, a resampling too big for a block.
    GridError
        The frame grid's error (the in-memory morph's).
    VolwarpError
        The work's errors.
    """
    from .. import execute, parallel
    from ..execute import block_budget
    from ..io.atomic import scratch_folder
    from .chunked import (
        block_grid,
        check_covered,
        frame_chunks,
        mesh_block_shape,
        resample_chunks,
    )
    from .fields import StepsOnEngine
    from .frames import FrameFields, FrameOperation, MeshBlocks, frame_values, frames
    from .grid import GridError
    from .interpolate import index_map, lands_on_grid
    from .pipeline import prepare_on

    attrs = attributes or {}
    block = how.block

    def refuse_why(why, advice=None):
        raise BlocksRefused(f"--chunked does not run this morph by blocks: {why} (without "
                            "--chunked it runs in memory)" + (f"; {advice}" if advice else ""))

    try:
        _, why = block_grid(job, Geometry.of(source[0]), Geometry.of(target[0]))
    except GridError:  # (the unaligned grid's error: the aligned one's is below)
        if not job.moved:
            raise
        why = None
    if why:
        refuse_why(why)
    inputs = {"source": source, "target": target}
    frame_type = (np.dtype(source[1].dtype) if job.output == "density"
                  and job.density_range == "source" else np.dtype(np.float32))
    types = {a.name: np.dtype(a.dtype or attrs[a.name][0][1].dtype) for a in job.attributes}

    def check(grid, matrices):
        """What the block path refuses, before any field: coverage, outputs, blocks."""
        a_s, a_t = matrices["source"], matrices["target"]
        maps = []
        for (header, _), mat in ((source, a_s), (target, a_t), *(
                (pair, m) for a, b in attrs.values() for pair, m in ((a, a_s), (b, a_t)))):
            geo = Geometry.of(header)
            if not lands_on_grid(geo.shape, geo.index_to_world_matrix, mat, grid):
                maps.append((index_map(geo.index_to_world_matrix, mat, grid), geo.shape))
        if maps:
            chunks = steps.chunks(grid.shape)
            try:
                chunks = resample_chunks(grid.shape, chunks, maps, steps.per_task)
            except VolwarpError as exc:
                raise BlocksRefused(str(exc), usage=False) from None
            uncovered = check_covered(job, {name: Geometry.of(inputs[name][0])
                                            for name in inputs}, matrices, grid, steps.map,
                                      chunks)
            if uncovered:
                refuse_why(*uncovered)
        checks = [(p, np.dtype(write.dtype or frame_type)) for p in outputs.frames]
        for a in job.attributes:
            checks += [(p, types[a.name]) for p in outputs.attributes[a.name]]
        for path, out_type in checks:
            why = write.refusal(path, grid.shape, out_type)
            if why is not None:
                raise BlocksRefused(why, usage=False)

    with how.open_engine() as engine, scratch_folder(outputs.frames[0]) as scratch:
        per_task = block_budget() // max(1, engine.workers)
        steps = StepsOnEngine(engine, scratch, per_task, block)
        with timed("morph by blocks: both fields"):
            prep = prepare_on(job, inputs, attrs, steps, check=check)
        fields = FrameFields.of(job, prep)
        grid = prep.grid
        # the frames' budget: what is left now that the fields' kernels are loaded (taken once)
        per_task = block_budget() // max(1, engine.workers)
        surfaces = None
        if meshes or render is not None:
            mesh_run = None
            if how.scheduler is not None:  # (VTK holds the GIL: threads otherwise)
                mesh_run = functools.partial(engine.map, label="mesh", memory=per_task)
            surfaces = MeshBlocks(mesh_block_shape(grid.shape, per_task, block), mesh_run,
                                  parallel.threads())
        values = frame_values(job, fields, source[1])
        if block is None:  # every frame in the same blocks, chosen once (identical runs:
            probe = FrameOperation(fields, values, 0.0, meta={})  # identical stores)
            frame_targets(probe, 0, outputs, write)
            block = execute.auto_block(probe, per_task, engine.workers)
        on_engine = execute.How(chunked=True, block=block, scheduler=how.scheduler,
                                open_engine=lambda: contextlib.nullcontext(engine),
                                planned=how.block is None)
        yield from frames(job, fields, values,
                          frame_writer(outputs, write, on_engine, by_blocks=True),
                          meta={"volwarp_morph": morph_note(job, prep.rules), **(meta or {})},
                          meshes=surfaces, render=render,
                          corners=functools.partial(fields.corners, steps.map,
                                                    frame_chunks(grid.shape, per_task,
                                                                 engine.workers, block)),
                          space=space)


def run_morph(job: MorphJob, outputs, plan: MorphPlan, *, meta: dict, write_kw: dict,
              render: RenderSettings | None = None, camera_to=None, how) -> Geometry:
    """Every frame of ``job`` and its surfaces written, as ``plan`` decided; the frame grid.

    ``meta``: each frame's provenance; ``write_kw``: the write options;
    ``render``, ``camera_to``: the renders' settings and the camera file.
    By blocks where the in-memory morph did not fit (unasked), what the
    block path refuses is that refusal's second half.
    """
    from ..errors import OutOfMemoryError
    from ..io import read_volume

    write = FrameWrite.of(write_kw)
    if not plan.by_blocks:
        def read(path):  # (taken out: the caller keeps none of them)
            vol = plan.loaded.pop(str(path), None)
            return read_volume(path) if vol is None else vol
        with timed("read inputs"), one_volume_inputs():
            source, target = read(job.source.path), read(job.target.path)
            attrs = {a.name: (read_volume(a.source), read_volume(a.target))
                     for a in job.attributes}
    else:
        with one_volume_inputs():
            source, target = _lazy(job.source.path), _lazy(job.target.path)
            attrs = {a.name: (_lazy(a.source), _lazy(a.target)) for a in job.attributes}
    from .frames import frame_space, source_keys

    # (the inputs' headers: the plan's; by blocks an input is its (header, samples))
    headers = plan.headers or ((source[0], target[0]) if plan.by_blocks else (source, target))
    kw = dict(outputs=outputs, meta={**source_keys(headers[0]), **meta}, write=write,
              meshes=bool(outputs.meshes), render=render, space=frame_space(*headers))
    frames = (morph_by_blocks(job, source, target, attrs, how=how, **kw) if plan.by_blocks
              else morph_in_memory(job, source, target, attrs, **kw))
    renders = []
    frame = None
    try:
        with contextlib.closing(frames):
            for frame in frames:
                outputs.write_surface(frame, frame.volume.meta, renders)
    except BlocksRefused as exc:
        if plan.in_memory_refusal is None:
            raise
        raise OutOfMemoryError(f"{plan.in_memory_refusal}, and by blocks: {exc}") from None
    outputs.finish(job, frame, render, camera_to, renders)
    return Geometry.of(frame.volume)


def _lazy(path):
    from ..io.lazy import LazySource, open_volume_header

    header, array = open_volume_header(path)
    return header, LazySource(path, array=array)
