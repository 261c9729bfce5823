"""The sweep's outputs: fields as output volumes, their render, and the whole sweep by blocks.

``volwarp sweep`` parses its options, loads the spec, fits the grid, calls
these and writes what it gets. :func:`sweep_by_blocks` runs the sweep by
output blocks on an engine (:func:`.chunked.sweep_block` per block, every
field's block written into the block outputs the caller opens), then
ray-casts the written fields slab by slab: the in-memory render's picture,
bit for bit. Nothing here parses options or names files.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import VolwarpError
from ..geometry import Geometry
from ..progress import timed
from ..samples import cast_samples
from ..volume import Volume


@dataclass(frozen=True)
class VolumeRender:
    """How the sweep's fields are ray-cast.

    A view (a name or (azimuth, elevation)), a (width, height) in pixels, a
    camera (default: fitted to the grid) and the anatomical letters at the
    edges; ``what``: the render's name in the timings (its file).
    """

    view: object = "iso"
    size: tuple[int, int] = (512, 512)
    camera: object = None
    orientation_labels: bool = False
    what: str = "render"


def scale_to_dtype(data, dtype):
    """Float fields in [0, 1] scaled to an integer type's full range (floats unchanged)."""
    if dtype is None or np.dtype(dtype).kind == "f":
        return data
    return data.astype(np.float64) * np.iinfo(np.dtype(dtype)).max


def sweep_volume(data: np.ndarray, grid: Geometry, dtype, meta: dict,
                 name: str | None = None) -> Volume:
    """Field ``name`` as the volume the sweep writes: of type ``dtype``, with ``meta``.

    ``meta`` gets ``volwarp_sweep_field``: ``name`` (unless None: the fields of
    one multi-component file).
    """
    data = cast_samples(scale_to_dtype(data, dtype), dtype, what=str(name))
    meta = dict(meta, volwarp_sweep_field=name) if name else dict(meta)
    return grid.volume(data, meta=meta)


def render_fields(fields: dict, grid: Geometry, render: VolumeRender):
    """``(image, camera)``: the ray-cast of the swept ``fields`` (``opacity`` at least)."""
    from ..render.raycast import render_volume

    colour = None
    if all(c in fields for c in ("red", "green", "blue")):
        colour = [fields["red"], fields["green"], fields["blue"]]
    return render_volume(fields["opacity"], colour=colour, geometry=fields.get("geometry"),
                         spacing=grid.spacing_array, origin=grid.origin_array, view=render.view,
                         size=render.size, camera=render.camera,
                         orientation_labels=render.orientation_labels, return_camera=True)


def _render_by_slabs(render: VolumeRender, grid, outs, names, dtype, plan, slab):
    """Ray-cast the fields written by blocks, slab by slab of z planes (the in-memory picture).

    Float32/float64 outputs hold the sweep's float32 fields exactly: their planes
    are read back. Other types (scaled, rounded) do not: the planes' fields are
    computed again (:func:`~volwarp_cli.sweep.chunked.sweep_block`, the in-memory
    sweep's samples), so that the picture is the in-memory render's either way.
    """
    from ..box import Box
    from ..render.raycast import render_volume_slabs
    from .chunked import sweep_block

    nz, ny, nx = grid.shape
    exact = np.dtype(dtype) in (np.dtype(np.float32), np.dtype(np.float64))

    def read_slab(z0, z1, wanted):
        box = Box((z0, 0, 0), (z1, ny, nx))
        if not exact:
            fields = sweep_block(plan.root, plan.geometry, box, plan=plan)
            return [fields[names.index(n)] for n in wanted]
        if None in outs:  # --multi: the fields are the components of one output
            both = outs[None].read(box)
            return [np.asarray(both[..., names.index(n)], dtype=np.float32) for n in wanted]
        return [np.asarray(outs[n].read(box), dtype=np.float32) for n in wanted]

    colour = all(c in names for c in ("red", "green", "blue"))
    with timed(f"render {render.what} by slabs of {slab} z cells"):
        return render_volume_slabs(
            read_slab, (nz, ny, nx), colour=colour, geometry="geometry" in names, slab=slab,
            spacing=grid.spacing_array, origin=grid.origin_array, view=render.view,
            size=render.size, camera=render.camera,
            orientation_labels=render.orientation_labels, return_camera=True)


def _sweep_block_task(plan, box, writers, names, dtype):
    """One output block of every field, each written to its own output (a block task).

    ``writers``: name -> writer, or ``{None: writer}`` for one output holding
    every field as its components (--multi).
    """
    from .chunked import sweep_block

    fields = sweep_block(plan.root, plan.geometry, box, plan=plan)
    blocks = [cast_samples(scale_to_dtype(fields[i], dtype), dtype, what=str(name))
              for i, name in enumerate(names)]
    if None in writers:
        writers[None].write(box, np.stack(blocks, axis=-1))
        return
    for name, data in zip(names, blocks, strict=True):
        writers[name].write(box, data)


def block_shape(shape, per_task: int, workers: int, fields: int, dtype) -> tuple[int, int, int]:
    """The sweep's output blocks: cubes within ``per_task`` bytes, at least two per worker.

    Each voxel of a block holds every field as float32 and its cast to
    ``dtype``; the cubes shrink (to 16 at least) until the grid has
    ``2 * workers`` of them.
    """
    import math

    per_voxel = fields * (4 + np.dtype(dtype).itemsize) + 16
    edge = max(8, int((per_task // per_voxel) ** (1 / 3)))
    want = 2 * workers
    while edge > 16 and math.prod(math.ceil(n / min(edge, n)) for n in shape) < want:
        edge = edge * 3 // 4
    return tuple(min(edge, n) for n in shape)


def sweep_by_blocks(model, grid: Geometry, *, paths: dict, names: list[str], dtype, meta: dict,
                    open_output: Callable, open_engine: Callable, budget: Callable[[], int],
                    block=None, method: str | None = None, tau: float | None = None,
                    render: VolumeRender | None = None):
    """The sweep computed and written by output blocks on an engine (:mod:`.chunked`).

    Each block task computes every field's block once and writes it to that
    field's output, or (``paths`` keyed by None) all of them as the
    components of one multi-component output.

    Parameters
    ----------
    model : SweepSpec
        The sweep (its method and tau are the defaults), as
        :func:`.chunked.prepare_sweep` takes it.
    grid : Geometry
        The output grid.
    paths : dict
        Field name -> output path, or ``{None: path}`` for one file of every
        field.
    names : list of str
        The fields, in the spec's order.
    dtype
        The outputs' type (floats as they are, integers scaled from [0, 1]).
    meta : dict
        Key/values of every output (each adds ``volwarp_sweep_field``).
    open_output : callable
        ``open_output(path, template, dtype, block, components)``: a context
        manager giving the :class:`~volwarp_cli.io.blockwrite.BlockOutput` of
        ``template``'s geometry and key/values (``components``: the field
        names of a multi-component output, else None), committed on a clean
        exit.
    open_engine : callable
        ``open_engine()``: a context manager giving the engine the blocks run on.
    budget : callable
        ``budget()``: the memory the blocks may use, bytes (asked once the
        engine is open).
    block : (z, y, x) ints, optional
        The user's block shape (default :func:`block_shape`'s); with
        ``render``, also the depth of its slabs.
    method, tau : optional
        As :func:`volwarp_cli.sweep.evaluate`'s.
    render : VolumeRender, optional
        Ray-cast the written fields (they need ``opacity``).

    Returns
    -------
    (image, camera) or None
        The render, once every output is committed (None without ``render``).
    """
    import contextlib

    import dask

    from .chunked import prepare_sweep

    plan = prepare_sweep(model, grid, method=method, tau=tau)
    shape = grid.shape
    picture = None
    with open_engine() as engine, contextlib.ExitStack() as stack:
        total = budget()
        per_task = total // max(1, engine.workers)
        blocks = block or block_shape(shape, per_task, engine.workers, len(names), dtype)
        outs = {}
        placeholder = np.broadcast_to(np.zeros((), dtype), shape)
        if None in paths:  # (the in-memory file's key/values: the first field's, without its name)
            outs[None] = stack.enter_context(open_output(
                paths[None], grid.volume(placeholder, meta=dict(meta)), dtype, blocks,
                list(names)))
        for name in [] if None in paths else names:
            template = grid.volume(placeholder, meta=dict(meta, volwarp_sweep_field=name))
            outs[name] = stack.enter_context(open_output(paths[name], template, dtype, blocks,
                                                         None))
        boxes = next(iter(outs.values())).blocks()
        if any(o.blocks() != boxes for o in outs.values()):  # pragma: no cover - one layout
            raise VolwarpError("--chunked fields of different output formats: give one "
                               "extension for every field")
        plan_node = dask.delayed(plan, pure=False)
        writers = dask.delayed({n: o.writer() for n, o in outs.items()}, pure=False)
        tasks = [engine.block_delayed(_sweep_block_task, f"sweep-{'-'.join(map(str, b.lo))}",
                                      plan_node, b, writers, names, np.dtype(dtype),
                                      memory=per_task)
                 for b in boxes]
        engine.run(tasks, label="sweep blocks")
        for out in outs.values():
            out.mark_written(boxes)
        if render is not None:
            from ..render.raycast import slab_depth

            slab = block[0] if block else slab_depth(shape, total // 2)
            picture = _render_by_slabs(render, grid, outs, names, dtype, plan, slab)
    return picture
