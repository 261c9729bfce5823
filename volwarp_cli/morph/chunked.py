"""The morph by blocks: frames from fields kept on disk, computed and written block by block.

For a morph whose fields do not fit in memory (``volwarp morph --chunked``,
or when the in-memory morph does not fit the budget). Each shape's signed
distance field is computed out of core, once
(:func:`volwarp_cli.distance.chunked.field_by_blocks`: the exact passes, or a
band with ``max_distance``), into a float32 scratch file. A frame is an
elementwise function of the two fields (:func:`.interpolate.blend`, then
:class:`.frames.FrameValues`), so an output block needs its own box of both
and nothing more (no halo); the frame's surface is the mesh by blocks
(:func:`volwarp_cli.surface.chunked.isosurface_blocks`) of the same field
read box by box (:class:`FrameField`). The frames equal the in-memory
frames bit for bit, their meshes after a canonical ordering.

What runs by blocks is the morph in which nothing moves: source, target
and attributes on the frame grid, no alignment and no landmark warp (those
resample whole fields; :func:`blocks_refusal` says why not).
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..box import Box
from ..errors import VolwarpError
from ..geometry import Geometry
from ..samples import cast_samples
from .frames import FrameValues, RenderSettings, box_corners
from .grid import choose_grid
from .interpolate import blend, check_time, lands_on_grid
from .spec import MorphJob

#: Bytes per voxel a frame block holds at most: both fields (8), their blend (4), the
#: occupancy and its float64 mapping to the source's range (about 40), the output
FRAME_BYTES_PER_VOXEL = 64
#: ... and a mesh block: the frame field (12 with both inputs) and the flying edges' arrays
MESH_BYTES_PER_VOXEL = 36


def block_grid(job: MorphJob, source: Geometry, target: Geometry,
               attributes: dict[str, tuple[Geometry, Geometry]] | None = None
               ) -> tuple[Geometry, str | None]:
    """``(frame grid, why the morph cannot run by blocks or None)``.

    The grid by the in-memory rules (:func:`.grid.choose_grid`: its GridError
    is the in-memory one); the morph runs by blocks when every input's samples
    land on that grid unmoved (:func:`.interpolate.lands_on_grid`).
    """
    eye = np.eye(4)
    grid = choose_grid(job.grid, source, target, eye, eye, moved=job.moved, margin=job.margin)
    if job.moved:
        return grid, "an alignment or a landmark warp (they resample whole fields)"
    if job.metric != "euclidean":
        return grid, f"the {job.metric} metric (its passes have no out-of-core form)"
    inputs = [("source", source), ("target", target)]
    for name, (a, b) in (attributes or {}).items():
        inputs += [(f"attribute {name}'s source", a), (f"attribute {name}'s target", b)]
    for what, geo in inputs:
        if not lands_on_grid(geo.shape, geo.index_to_world_matrix, eye, grid):
            return grid, (f"a frame grid that is not the {what}'s own (its samples would be "
                          "resampled)")
    return grid, None


class FrameField:
    """The field of frame ``t``, ``(1 - t) d_s + t d_t``, read box by box (picklable).

    ``source``, ``target``: the two float32 fields, sliceable ``[z, y, x]``
    (:class:`~volwarp_cli.io.filearray.FileArray`).
    """

    def __init__(self, source, target, t: float):
        check_time(t)
        self.source, self.target, self.t = source, target, float(t)
        self.shape = tuple(source.shape)
        self.dtype = np.dtype(np.float32)
        self.ndim = 3

    def __getitem__(self, key) -> np.ndarray:
        a = np.asarray(self.source[key], dtype=np.float32)
        b = np.asarray(self.target[key], dtype=np.float32)
        return blend(a, b, self.t)


@dataclass
class BlockMorph:
    """Both shapes' fields on disk (float32, the frame grid), ready for frames by blocks.

    ``info``: how the fields were computed (:func:`field_by_blocks`'s, e.g.
    ``chunked: passes``), for the frames' metadata.
    """

    source: object
    target: object
    grid: Geometry
    info: dict

    def frame(self, t: float) -> FrameField:
        """Frame ``t``'s field, read by boxes."""
        return FrameField(self.source, self.target, t)


def fields_by_blocks(job: MorphJob, inputs: dict, engine, scratch: Path, *, block_bytes: int,
                     block=None) -> BlockMorph:
    """Both shapes' signed fields computed by blocks on ``engine`` into ``scratch``.

    ``inputs``: ``{"source": (template, samples), "target": ...}``, each a
    template Volume (the geometry) and a sliceable, picklable reader of its
    samples (:class:`~volwarp_cli.bspline.blocks.LazySource`); ``block_bytes``:
    one task's memory; ``block``: the user's block shape.
    """
    from ..distance.chunked import field_by_blocks
    from ..io.blockwrite import committed, open_block_output
    from ..io.lazy import open_volume_lazy
    from ..volume import xyz_to_zyx

    fields, info = {}, {}
    for name, ref in (("source", job.source), ("target", job.target)):
        template, samples = inputs[name]
        path = Path(scratch) / f"{name}.nrrd"
        geometry = Geometry.of(template)

        def open_output(grid, _info, path=path, geometry=geometry):
            return committed(open_block_output(path, geometry, np.float32, chunks_zyx=grid))

        finish = None
        if job.max_distance is not None:
            finish = functools.partial(_clamp, max_distance=float(job.max_distance))
        try:
            info[name] = field_by_blocks(samples, xyz_to_zyx(template.spacing), engine,
                                         open_output, iso=ref.iso, inside=ref.inside,
                                         metric=job.metric, surface=job.surface,
                                         max_distance=job.max_distance, finish=finish,
                                         block_bytes=block_bytes, block=block,
                                         scratch_near=path)
        except VolwarpError as exc:
            raise VolwarpError(f"{ref.path}: {exc}") from None
        _, fields[name] = open_volume_lazy(path)
    grid = Geometry.of(inputs["source"][0])
    return BlockMorph(fields["source"], fields["target"], grid, info["source"])


def _clamp(field: np.ndarray, *, max_distance: float) -> np.ndarray:
    # the band is clamped already; the in-memory morph clamps with finish_field too
    from ..distance.field import finish_field

    return finish_field(field, max_distance=max_distance)


@dataclass
class BlockFrame:
    """One frame by blocks: its samples as a Dask array, to be written block by block.

    ``template``: a Volume of the frame's geometry and key/values (its samples a
    placeholder); ``data``: the frame's samples (chunked as the output's
    blocks); ``attributes``: name -> (template, Dask array); ``mesh``,
    ``image``, ``camera`` as :class:`.frames.Frame`'s.
    """

    index: int
    t: float
    template: object
    data: object
    attributes: dict = field(default_factory=dict)
    mesh: object = None
    image: np.ndarray | None = None
    camera: object = None


def _placeholder(dtype, shape) -> np.ndarray:
    # the samples a block output's template stands for (zero-strided: no memory)
    return np.broadcast_to(np.zeros((), dtype), shape)


def _frame_block(a: np.ndarray, b: np.ndarray, *, t: float, values: FrameValues) -> np.ndarray:
    return values(blend(np.asarray(a, np.float32), np.asarray(b, np.float32), t))


def _attribute_block(a, b, *, t: float, out_type: str, what: str) -> np.ndarray:
    return cast_samples(blend(np.asarray(a, np.float32), np.asarray(b, np.float32), t),
                        out_type, what=what)


def frame_chunks(shape, block_bytes: int, workers: int, block=None):
    """The frames' output blocks: ``block``, else whole rows within ``block_bytes``."""
    from ..distance.chunked import line_chunks

    if block is not None:
        return tuple(block)
    return line_chunks(shape, 2, block_bytes, bytes_per_voxel=FRAME_BYTES_PER_VOXEL,
                       min_blocks=workers)


def mesh_block_shape(shape, block_bytes: int, block=None) -> tuple[int, int, int]:
    """The frames' mesh blocks: ``block``, else slabs of whole planes within ``block_bytes``."""
    if block is not None:
        return tuple(block)
    nz, ny, nx = shape
    depth = block_bytes // max(1, MESH_BYTES_PER_VOXEL * ny * nx)
    return max(8, min(nz, depth, 256)), ny, nx


def _occupied(box: Box, source, target):
    inside = (np.asarray(source[box.slices]) < 0) | (np.asarray(target[box.slices]) < 0)
    return box, [inside.any(axis=a) for a in ((1, 2), (0, 2), (0, 1))]


def occupied_box(bm: BlockMorph, run, chunks) -> np.ndarray:
    """:func:`.frames.shape_box` by blocks: world corners of both shapes' box."""
    shape = bm.grid.shape
    occ = [np.zeros(n, bool) for n in shape]
    task = functools.partial(_occupied, source=bm.source, target=bm.target)
    for box, parts in run(task, Box.from_shape(shape).blocks(chunks)):
        for axis in range(3):
            occ[axis][box.lo[axis]:box.hi[axis]] |= parts[axis]
    return box_corners(occ, bm.grid)


def block_frames(job: MorphJob, bm: BlockMorph, source, attributes: dict | None = None, *,
                 meta: dict | None = None, chunks, run, mesh_block, meshes: bool = False,
                 render: RenderSettings | None = None, mesh_run=None,
                 mesh_threads: int | None = 1) -> Iterator[BlockFrame]:
    """The frames of ``job`` by blocks, in order: :func:`.frames.morph_frames`' counterpart.

    Parameters
    ----------
    job, bm
        The morph and its fields (:func:`fields_by_blocks`).
    source : sliceable
        The source shape's samples (their type, and their value range for a
        density ``range: source``, read in one pass).
    attributes : dict, optional
        name -> (source samples, target samples, output type name), each
        sliceable on the frame grid.
    meta : dict, optional
        Key/values of every frame (provenance); each adds ``volwarp_morph_t``.
    chunks : (z, y, x) ints or Dask chunks
        The frames' blocks.
    run : callable
        ``run(task, items)`` -> results in order (an engine's ``map``): the
        small passes over the fields (the render's box).
    mesh_block, mesh_run, mesh_threads
        The meshes' blocks and who runs them
        (:func:`volwarp_cli.surface.chunked.isosurface_blocks`' ``run`` and
        ``threads``).
    meshes, render
        As :func:`.frames.morph_frames`.
    """
    import dask.array as da

    from ..engine import dask_input
    from ..progress import log

    value_range = None
    if job.output == "density" and job.density_range == "source":
        from ..bspline.capture import source_range

        value_range = source_range(source)
    values = FrameValues.of(job, bm.grid, source.dtype, value_range)
    out_dtype = np.dtype(values.dtype if values.range_source else np.float32)
    fs, ft = dask_input(bm.source, chunks), dask_input(bm.target, chunks)
    attrs = {name: (dask_input(a, fs.chunks), dask_input(b, fs.chunks), dtype)
             for name, (a, b, dtype) in (attributes or {}).items()}
    meta = dict(meta or {})
    camera = None if render is None else render.camera
    for i, t in enumerate(job.times):
        check_time(t)
        frame_meta = dict(meta, volwarp_morph_t=f"{t:.9g}")
        placeholder = bm.grid.volume(_placeholder(out_dtype, bm.grid.shape), meta=frame_meta)
        data = da.map_blocks(_frame_block, fs, ft, t=t, values=values, dtype=out_dtype,
                             meta=np.empty((0, 0, 0), out_dtype))
        frame = BlockFrame(i, t, placeholder, data)
        for name, (a, b, dtype) in attrs.items():
            adtype = np.dtype(dtype)
            attr_template = bm.grid.volume(_placeholder(adtype, bm.grid.shape),
                                           meta=dict(frame_meta))
            frame.attributes[name] = (attr_template, da.map_blocks(
                _attribute_block, a, b, t=t, out_type=adtype.name,
                what=f"attribute {name} at t = {t:g}", dtype=adtype,
                meta=np.empty((0, 0, 0), adtype)))
        if meshes or render is not None:
            from ..surface.chunked import isosurface_blocks

            frame.mesh = isosurface_blocks(bm.frame(t), bm.grid, 0.0, inside="below",
                                           normals=True, block_shape=mesh_block, run=mesh_run,
                                           threads=mesh_threads)
            if render is not None:
                from ..render.surface import fit_camera, render_mesh

                if camera is None:
                    camera = fit_camera(occupied_box(bm, run, chunks), render.view,
                                        render.size)
                frame.image = render_mesh(frame.mesh, camera=camera,
                                          orientation_labels=render.orientation_labels)
                frame.camera = camera
        log.debug("morph by blocks: frame %d (t = %g)", i, t)
        yield frame
