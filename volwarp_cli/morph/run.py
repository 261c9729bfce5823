"""The morph by blocks, end to end: the checks, then the fields on disk and the frames by blocks.

:func:`morph_by_blocks` strings together the steps of :mod:`.chunked` as
``volwarp morph --chunked`` runs them (and the in-memory morph's fallback
when it does not fit the memory budget): the frame grid and what the block
path refuses, the alignment's matrices counted by blocks, the resampling's
blocks and the aligned inputs' coverage, the outputs' checks, then both
fields computed on disk and every frame written block by block. Nothing
here parses options, opens inputs or names files: the caller passes the
inputs opened lazily, the output paths, the engine and the block outputs.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator

import numpy as np

from ..errors import VolwarpError
from ..geometry import Geometry
from ..progress import log, timed
from .chunked import BlockFrame
from .frames import RenderSettings
from .spec import MorphJob


class BlocksRefused(VolwarpError):
    """A morph the block path does not run (the in-memory morph does): a usage error."""


def morph_note(job: MorphJob) -> str:
    """The frames' ``volwarp_morph`` value: metric, output, band.

    The same in memory and by blocks (the frames are the same samples).
    """
    note = f"metric={job.metric} output={job.output}"
    if job.max_distance is not None:
        note += f" max_distance={job.max_distance:g} (each field clamped)"
    return note


def _cast_block(block, *, dtype, what):
    from ..samples import cast_samples

    return cast_samples(block, dtype, what=what)


def morph_by_blocks(job: MorphJob, source, target, attributes: dict | None = None, *,
                    frame_paths: list[str], attribute_paths: dict[str, list[str]] | None = None,
                    meta: dict | None = None, dtype=None, meshes: bool = False,
                    render: RenderSettings | None = None, open_engine: Callable,
                    budget: Callable[[], int], block=None, scheduler: str | None = None,
                    open_output: Callable, check_output: Callable,
                    fallback: VolwarpError | None = None,
                    confirm: Callable[[str], bool] | None = None) -> Iterator[BlockFrame]:
    """The frames of ``job`` computed and written by blocks, yielded in order once written.

    Parameters
    ----------
    job : MorphJob
        The morph (no landmark warp).
    source, target : (template, samples)
        Each shape opened lazily: a template Volume (its geometry) and a
        sliceable, picklable reader of its samples.
    attributes : dict, optional
        name -> ((template, samples), (template, samples)) of each attribute.
    frame_paths, attribute_paths
        Each frame's output path; name -> each frame's path of that attribute.
    meta : dict, optional
        Key/values every frame carries after ``volwarp_morph`` (provenance).
    dtype : optional
        The frames' output type (default float32, or the source's for a
        density ``range: source``); the attributes keep their own.
    meshes, render
        As :func:`.frames.morph_frames`' (the caller writes them).
    open_engine : callable
        ``open_engine()``: a context manager giving the engine the blocks run on.
    budget : callable
        ``budget()``: the memory the blocks may use, bytes (asked once the
        engine is open).
    block : (z, y, x) ints, optional
        The user's block shape.
    scheduler : str, optional
        The engine's scheduler; the meshes run on it when one is named
        (threads otherwise).
    open_output : callable
        ``open_output(path, template, dtype, block)``: a context manager giving
        the :class:`~volwarp_cli.io.blockwrite.BlockOutput` of ``template``'s
        geometry and key/values, committed on a clean exit.
    check_output : callable
        ``check_output(path, shape_zyx, dtype)``: a VolwarpError when that
        output cannot be written by blocks (its format, its folder's space).
    fallback : VolwarpError, optional
        The in-memory morph's refusal, when this runs instead of it: raised
        in place of every refusal here.
    confirm : callable, optional
        With ``fallback``: ``confirm(message)``, once every check has passed,
        whether to run by blocks after all (False raises ``fallback``).

    Yields
    ------
    BlockFrame
        Each frame once its volume and attributes are written (their mesh and
        render, when asked for, are the caller's to write).

    Raises
    ------
    BlocksRefused
        A morph the block path does not run (a landmark warp, a frame grid the
        aligned inputs do not cover), unless ``fallback``.
    GridError
        The frame grid's error (the in-memory morph's).
    VolwarpError
        An output that cannot be written by blocks, a resampling too big for a
        block, or the work's errors.
    """
    from .. import parallel
    from ..engine import write_blocks
    from ..io.atomic import scratch_folder
    from .chunked import (
        attributes_by_blocks,
        block_frames,
        block_grid,
        block_matrices,
        check_covered,
        fields_by_blocks,
        frame_chunks,
        mesh_block_shape,
        resample_chunks,
    )
    from .grid import GridError
    from .interpolate import index_map, lands_on_grid

    attrs = attributes or {}
    attribute_paths = attribute_paths or {}

    def refuse(message, usage=True):
        if fallback is not None:
            raise fallback
        raise (BlocksRefused if usage else VolwarpError)(message)

    def refuse_why(why):
        refuse(f"--chunked does not run a morph with {why} by blocks (that morph runs in memory)")

    geometry = {name: (Geometry.of(a[0]), Geometry.of(b[0])) for name, (a, b) in attrs.items()}
    try:
        grid, why = block_grid(job, Geometry.of(source[0]), Geometry.of(target[0]), geometry)
    except GridError:  # (the unaligned grid's error: the aligned one's is below)
        if not job.moved:
            raise
        why = None
    if why:
        refuse_why(why)
    source_type = np.dtype(source[1].dtype)
    frame_type = (source_type if job.output == "density" and job.density_range == "source"
                  else np.dtype(np.float32))
    types = {a.name: np.dtype(a.dtype or attrs[a.name][0][1].dtype) for a in job.attributes}
    with open_engine() as engine:
        per_task = budget() // max(1, engine.workers)
        run = functools.partial(engine.map, label="morph", memory=per_task)
        inputs = {"source": source, "target": target}
        if job.moved:
            a_s, a_t = block_matrices(job, inputs, run, frame_chunks(
                Geometry.of(source[0]).shape, per_task, engine.workers, block))
            grid, why = block_grid(job, Geometry.of(source[0]), Geometry.of(target[0]),
                                   geometry, a_s, a_t)
            if why:
                refuse_why(why)
        else:
            a_s = a_t = np.eye(4)
        matrices = {"source": a_s, "target": a_t}
        chunks = frame_chunks(grid.shape, per_task, engine.workers, block)
        maps = []
        for (template, _), mat in ((source, a_s), (target, a_t), *(
                (pair, m) for a, b in attrs.values() for pair, m in ((a, a_s), (b, a_t)))):
            geo = Geometry.of(template)
            if not lands_on_grid(geo.shape, geo.index_to_world_matrix, mat, grid):
                maps.append((index_map(geo.index_to_world_matrix, mat, grid), geo.shape))
        rchunks = chunks
        if maps:
            try:
                rchunks = resample_chunks(grid.shape, chunks, maps, per_task)
            except VolwarpError as exc:
                refuse(str(exc), usage=False)
            why = check_covered(job, {"source": Geometry.of(source[0]),
                                      "target": Geometry.of(target[0])}, matrices, grid, run,
                                rchunks)
            if why:
                refuse_why(why)
        checks = [(p, np.dtype(dtype or frame_type)) for p in frame_paths]
        for a in job.attributes:
            checks += [(p, types[a.name]) for p in attribute_paths[a.name]]
        for path, out_type in checks:
            try:
                check_output(path, grid.shape, out_type)
            except VolwarpError:
                if fallback is not None:
                    raise fallback from None
                raise
        if fallback is not None and confirm is not None and not confirm(str(fallback)):
            raise fallback
        with scratch_folder(frame_paths[0]) as scratch:
            with timed("morph by blocks: both fields"):
                bm = fields_by_blocks(job, inputs, engine, scratch, block_bytes=per_task,
                                      block=block, grid=grid, matrices=matrices, chunks=rchunks)
            log.info("morph fields by blocks: %s", bm.info["chunked"])
            frame_meta = {"volwarp_morph": morph_note(job), **(meta or {})}
            mesh_run = None
            if scheduler is not None:  # (VTK holds the GIL: threads otherwise)
                mesh_run = functools.partial(engine.map, label="mesh", memory=per_task)
            attr_samples = attributes_by_blocks(
                {a.name: (attrs[a.name][0], attrs[a.name][1], types[a.name].name)
                 for a in job.attributes}, matrices, grid, engine, scratch,
                block_bytes=per_task, chunks=rchunks)
            for frame in block_frames(job, bm, source[1], attr_samples, meta=frame_meta,
                                      chunks=chunks, run=run,
                                      mesh_block=mesh_block_shape(grid.shape, per_task, block),
                                      meshes=meshes, render=render, mesh_run=mesh_run,
                                      mesh_threads=parallel.threads()):
                i = frame.index
                path = frame_paths[i]
                data = frame.data
                if dtype is not None:
                    data = data.map_blocks(functools.partial(_cast_block, dtype=dtype,
                                                             what=str(path)),
                                           dtype=np.dtype(dtype))
                with open_output(path, frame.template, data.dtype, chunks) as sink:
                    write_blocks(data, sink, engine, label=f"frame-{i}", memory=per_task)
                for name, (template, values) in frame.attributes.items():
                    with open_output(attribute_paths[name][i], template, values.dtype,
                                     chunks) as sink:
                        write_blocks(values, sink, engine, label=f"{name}-{i}",
                                     memory=per_task)
                yield frame
