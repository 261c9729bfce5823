"""The morph's frames: each frame's volume, attributes, surface and picture, one code.

After Dinh & Carvalho 2004, section 0.3.

A frame is an elementwise function of the two shapes' fields on the frame
grid (and of each attribute's pair): :class:`FrameOperation` states it as an
operation of the executor, whose block is a box of the frame. In memory the
fields are arrays and the frame is its one block (:func:`computed`, or the
command's run); by blocks the fields are scratch files and the executor runs
the same :meth:`FrameOperation.compute` block by block, so the frames are
the same bytes either way. :func:`frames` walks the job's times: each frame
made (computed or written, as its caller says), then, when asked, its
zero-level surface (:func:`volwarp_cli.surface.chunked.isosurface_blocks` of
the frame's field, one block or many) and its render, all frames seen by one
fixed camera.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from ..box import Box
from ..errors import VolwarpError
from ..execute import Operation
from ..progress import progress
from ..samples import cast_samples, expect_reached, note_reached
from ..volume import Header, Volume
from .interpolate import blend, check_time, density, occupancy_to_range, warp_on_grid
from .pipeline import Prepared
from .spec import MorphJob


@dataclass(frozen=True)
class RenderSettings:
    """How the frames' surfaces are rendered.

    A view (a name or (azimuth, elevation)) and a (width, height) in pixels; one
    camera, fitted to both shapes, for every frame, or ``camera`` (a
    :class:`volwarp_cli.render.camera.Camera`, e.g. one read back to compare with
    another run); ``orientation_labels``: the anatomical letters at the edges.
    """

    view: object = "iso"
    size: tuple[int, int] = (800, 600)
    camera: object = None
    orientation_labels: bool = False


@dataclass
class Frame:
    """One frame of a morph.

    ``volume``: the frame's field (float32 SDF, negative inside) or occupancy,
    with the frame's key/values (``volwarp_morph_t``); ``attributes``: name ->
    the attribute at ``t`` in its output type; ``mesh``: the zero-level surface
    (when meshes or renders were asked for); ``image``: its ``(H, W, 3)`` render,
    ``camera`` the camera of every frame's render. Where the frames were
    written by blocks, ``volume`` and the attributes are the files'
    :class:`~volwarp_cli.volume.Header` (their geometry and key/values), no samples.
    """

    index: int
    t: float
    volume: Volume | Header
    attributes: dict[str, Volume | Header] = field(default_factory=dict)
    mesh: object = None
    image: np.ndarray | None = None
    camera: object = None


def box_corners(occupied_zyx, grid) -> np.ndarray:
    """World corners ``(8, 3)`` of the index box spanned by per-axis occupancy.

    ``occupied_zyx``: three boolean arrays, along z, y and x, true where a
    plane holds a voxel inside either shape (the shapes' projections).
    """
    idx = [np.flatnonzero(a) for a in occupied_zyx]  # z, y, x
    if not all(len(i) for i in idx):
        raise VolwarpError("neither shape has any voxel inside on the frame grid")
    lo = np.array([idx[2][0], idx[1][0], idx[0][0]], dtype=np.float64)
    hi = np.array([idx[2][-1], idx[1][-1], idx[0][-1]], dtype=np.float64)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                        for c in (lo[2], hi[2])])
    m = grid.index_to_world_matrix
    return corners @ m[:3, :3].T + m[:3, 3]


@dataclass(frozen=True)
class FrameValues:
    """What a frame's field becomes in its volume: the SDF, an occupancy, or source values.

    Elementwise (a block of the field gives the block of the frame), so the
    in-memory frames and the frames by blocks share it. ``range_lo, range_hi``:
    the source's value range, for a density ``range: source``.
    """

    output: str = "sdf"
    width: float = 1.0
    range_source: bool = False
    range_lo: float = 0.0
    range_hi: float = 1.0
    iso: float = 0.0
    inside: str = "above"
    dtype: str = "float32"

    @staticmethod
    def of(job: MorphJob, grid, source_dtype, value_range=None) -> FrameValues:
        """The values of ``job``'s frames on ``grid``; ``value_range``: the source's (lo, hi)."""
        ranged = job.output == "density" and job.density_range == "source"
        lo, hi = value_range if ranged else (0.0, 1.0)
        iso = float(job.source.iso) if ranged else 0.0  # (a label map's shape may have none)
        return FrameValues(job.output, float(job.density_width or min(grid.spacing)), ranged,
                           float(lo), float(hi), iso, job.source.inside,
                           np.dtype(source_dtype).name)

    def __call__(self, sdf: np.ndarray) -> np.ndarray:
        """The frame's samples from its field ``sdf`` (``sdf`` itself for an SDF output)."""
        if self.output != "density":
            return sdf
        data = density(sdf, self.width)
        if self.range_source:
            data = occupancy_to_range(data, self.range_lo, self.iso, self.range_hi,
                                      self.inside, self.dtype)
        return data



#: Bytes per voxel a frame block holds at most: both fields (8), their blend (4), the
#: occupancy and its float64 mapping to the source's range (about 40), the output
FRAME_BYTES_PER_VOXEL = 64
#: ... and per attribute: its pair's box (8), their blend and the cast output
ATTRIBUTE_BYTES_PER_VOXEL = 16


@dataclass
class FrameFields:
    """Both shapes' fields and the attributes' pairs on the frame grid, read box by box.

    ``source``, ``target``: float32 fields sliceable ``[z, y, x]`` (arrays in
    memory, :class:`~volwarp_cli.io.filearray.FileArray` scratch by blocks),
    the static landmark warp already applied; ``attributes``: name ->
    ``(source samples, target samples, output type name)``, sliceable on the
    grid; ``back``, ``fwd``: a progressive landmark warp's displacements
    (:class:`.interpolate.Morph`'s), which move whole fields: such a morph has
    no form by blocks.
    """

    source: object
    target: object
    grid: object
    attributes: dict = field(default_factory=dict)
    back: np.ndarray | None = None
    fwd: np.ndarray | None = None

    @classmethod
    def of(cls, job: MorphJob, prep: Prepared) -> FrameFields:
        """The fields of an in-memory :class:`~.pipeline.Prepared` morph."""
        types = {a.name: a.dtype or np.dtype(prep.attribute_types[a.name]).name
                 for a in job.attributes}
        return cls(prep.morph.source, prep.morph.target, prep.grid,
                   {name: (a, b, types[name]) for name, (a, b) in prep.attributes.items()},
                   prep.morph.back, prep.morph.fwd)

    def pair(self, t: float, a, b, box: Box) -> tuple[np.ndarray, np.ndarray]:
        """``box`` of a pair at time ``t`` (float32): moved by a progressive warp (whole only)."""
        a = np.asarray(a[box.slices], dtype=np.float32)
        b = np.asarray(b[box.slices], dtype=np.float32)
        if self.back is None:
            return a, b
        return (warp_on_grid(a, self.grid, self.back, t),
                warp_on_grid(b, self.grid, self.fwd, 1 - t))

    def field(self, t: float):
        """Frame ``t``'s field ``(1 - t) d_s + t d_t``, sliceable (read box by box)."""
        check_time(t)
        if self.back is None:
            return FrameField(self.source, self.target, t)
        return blend(*self.pair(t, self.source, self.target, self.grid.box), t)

    def corners(self, run=None, block=None) -> np.ndarray:
        """World corners ``(8, 3)`` of the box holding both shapes (:func:`box_corners`).

        Counted over blocks of ``block`` (default one, the whole) by ``run``
        (``run(task, boxes)``: an engine's map; default here).
        """
        boxes = self.grid.box.blocks(block) if block is not None else [self.grid.box]
        task = functools.partial(_occupied, source=self.source, target=self.target)
        occ = [np.zeros(n, bool) for n in self.grid.shape]
        for box, parts in (run(task, boxes) if run is not None else map(task, boxes)):
            for axis in range(3):
                occ[axis][box.lo[axis]:box.hi[axis]] |= parts[axis]
        return box_corners(occ, self.grid)


def _occupied(box: Box, source, target):
    inside = (np.asarray(source[box.slices]) < 0) | (np.asarray(target[box.slices]) < 0)
    return box, [inside.any(axis=a) for a in ((1, 2), (0, 2), (0, 1))]


class FrameField:
    """The field of frame ``t``, ``(1 - t) d_s + t d_t``, read box by box (picklable).

    ``source``, ``target``: the two float32 fields, sliceable ``[z, y, x]``.
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


class FrameOperation(Operation):
    """One frame of a morph as an operation of the executor: a block is a box of the frame.

    A frame is an elementwise function of the two fields (:func:`.interpolate.blend`,
    then :class:`FrameValues`) and each attribute's pair, so a block needs its
    own box of them and nothing more: the in-memory frame is the one block,
    the frames by blocks the same :meth:`compute` on each. Its results:
    ``"frame"`` and each attribute's name. ``targets`` (set by the caller
    that writes them: key -> :class:`~volwarp_cli.execute.Target`); the frame's
    ``cast``: the type it is written in (``--dtype``), if not its own;
    ``space``: the world frame its file names (:func:`frame_space`).
    """

    def __init__(self, fields: FrameFields, values: FrameValues, t: float, *,
                 meta: dict, cast=None, space: str | None = None):
        check_time(t)
        self.fields, self.values, self.t = fields, values, float(t)
        self.grid, self.space = fields.grid, space
        self.meta = dict(meta, volwarp_morph_t=f"{t:.9g}")
        self.dtype = np.dtype(values.dtype if values.range_source else np.float32)
        self.cast = None if cast is None else np.dtype(cast)
        self.targets = {}
        self._inside = None  # (the note of whether a block holds an inside voxel: expect_shape)
        self.what = (f"the morph's frame at t = {t:g} on a "
                     f"{'x'.join(map(str, self.grid.shape_xyz))} grid")
        if fields.back is not None:
            self.no_blocks = "a morph with a landmark warp runs in memory only"

    def types(self) -> dict:
        """Each result's type: the frame's (its cast, if any) and each attribute's."""
        out = {"frame": self.cast or self.dtype}
        out.update({name: np.dtype(kind) for name, (_, _, kind)
                    in self.fields.attributes.items()})
        return out

    def memory(self, box: Box) -> int:
        """A block's bytes: its fields' boxes, blend and values, its attributes'."""
        return box.size * (FRAME_BYTES_PER_VOXEL
                           + ATTRIBUTE_BYTES_PER_VOXEL * len(self.fields.attributes))

    def expect_shape(self, i: int) -> None:
        """In a run, say at its end if frame ``i``'s field is negative nowhere: no shape.

        Two shapes that do not overlap (no alignment) blend into nothing
        between them, and a shape beside the frame grid (``--grid source``
        or ``target``) is none on it: frames of only the outside, exit 0.
        Each block notes whether it holds an inside voxel (:meth:`compute`).
        """
        self._inside = f"morph frame {i}: inside"
        expect_reached(self._inside, (
            f"frame {i} (t = {self.t:g}) is empty: no voxel lies inside its surface (its "
            "field is positive everywhere): the source's and target's shapes do not overlap "
            "on the frame grid, or one lies beside it; align them (a spec's align) or choose "
            "another grid (--grid union)"))

    def compute(self, box: Box, *, threads: int) -> dict:
        """``box`` of the frame and of each attribute (elementwise: ``threads`` unused)."""
        f, t = self.fields, self.t
        sdf = blend(*f.pair(t, f.source, f.target, box), t)
        if self._inside is not None:
            note_reached(self._inside, lambda: bool(np.any(sdf < 0)))
        out = {"frame": self.values(sdf)}
        for name, (a, b, kind) in f.attributes.items():
            out[name] = cast_samples(blend(*f.pair(t, a, b, box), t), kind,
                                     what=f"attribute {name} at t = {t:g}")
        return out

    def output(self, results: dict, key) -> np.ndarray:
        """Result ``key`` in its output type (the frame cast to ``--dtype``)."""
        data = results[key]
        if key == "frame" and self.cast is not None:
            data = cast_samples(data, self.cast, what=str(self.targets[key].path))
        return data

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """Whole rows within ``per_task``, two blocks a worker at least."""
        from ..passes import pass_boxes

        return pass_boxes(self.grid.shape, (2,), block_bytes=per_task,
                          bytes_per_voxel=self.memory(Box((0, 0, 0), (1, 1, 1))),
                          min_blocks=workers)[0].shape

    def volume(self, data, key="frame"):
        """A Volume of result ``key``'s ``data`` with the frame's key/values."""
        return self.grid.volume(data, meta=dict(self.meta), space=self.space)

    def header(self, key="frame"):
        """The Header of result ``key``: its type on the grid, the frame's key/values."""
        return self.grid.header(self.types()[key], meta=dict(self.meta), space=self.space)


@dataclass(frozen=True)
class MeshBlocks:
    """How the frames' surfaces are meshed: ``block`` None for one block, the whole.

    ``run``, ``threads``: who runs the blocks
    (:func:`volwarp_cli.surface.chunked.isosurface_blocks`' ``run`` and ``threads``).
    """

    block: tuple | None = None
    run: object = None
    threads: int | None = None

    def check(self, what: str):
        """``check(vertices)`` for :func:`isosurface_blocks`: refuse a surface that won't fit.

        As the mesh command's: about 2.25 triangles a vertex, the weld's bytes a
        triangle by blocks, the extraction's in one block, against what the budget
        leaves once the frame is written (the mesh's blocks are sized to their own
        share). Unchecked, a morph's surfaces took a run under 250M to 273 MiB.
        """
        from ..memory import ensure_fits_in_memory
        from ..surface.run import EXTRACT_BYTES_PER_TRIANGLE, WELD_BYTES_PER_TRIANGLE

        per = EXTRACT_BYTES_PER_TRIANGLE if self.block is None else WELD_BYTES_PER_TRIANGLE

        def check(vertices: int) -> None:
            triangles = (9 * int(vertices)) // 4 + 8
            ensure_fits_in_memory(triangles * per,
                                  f"the surface of {what} ({vertices} vertices)")
        return check


def frames(job: MorphJob, fields: FrameFields, values: FrameValues, make, *,
           meta: dict | None = None, meshes: MeshBlocks | None = None,
           render: RenderSettings | None = None, corners=None,
           space: str | None = None) -> Iterator[Frame]:
    """The frames of ``job`` at its times, in order (a progress bar counts them).

    Each frame's :class:`FrameOperation` is given to ``make(i, op)``, which
    returns the frame's volume and its attributes' (``(Volume, {name:
    Volume})``: computed in memory by :func:`computed`; or written by the
    command, then their Headers). ``meta``: what every frame
    carries (the source's own, :func:`source_keys`, then the morph's note and
    provenance; each adds ``volwarp_morph_t``); ``space``: the
    world frame the frames' files name (:func:`frame_space`). ``meshes``: each
    frame's surface made so (default none, but for a render); ``render``:
    each surface rendered, every frame by one camera (``render.camera``, or
    fitted to both shapes: ``corners()`` gives their box, default
    :meth:`FrameFields.corners` in one block).
    """
    meta = dict(meta or {})
    camera = None if render is None else render.camera
    if meshes is None and render is not None:
        meshes = MeshBlocks()
    with progress(len(job.times), "morph frames") as bar:
        for i, t in enumerate(job.times):
            op = FrameOperation(fields, values, t, meta=meta, space=space)
            op.expect_shape(i)
            volume, attributes = make(i, op)
            frame = Frame(i, t, volume, attributes)
            if meshes is not None:
                from ..surface.chunked import isosurface_blocks

                frame.mesh = isosurface_blocks(fields.field(t), fields.grid, 0.0,
                                               inside="below", normals=True,
                                               block_shape=meshes.block, run=meshes.run,
                                               threads=meshes.threads,
                                               check=meshes.check(f"frame {i}"))
            if render is not None:
                from ..render.surface import fit_camera, render_mesh

                if camera is None:
                    camera = fit_camera((corners or fields.corners)(), render.view,
                                        render.size)
                frame.image = render_mesh(frame.mesh, camera=camera,
                                          orientation_labels=render.orientation_labels)
                frame.camera = camera
            yield frame
            bar.advance()


def computed(i: int, op: FrameOperation):
    """A frame computed in memory, the whole as one block: ``(Volume, {name: Volume})``."""
    from ..execute import compute_whole

    results = compute_whole(op)
    return (op.volume(op.output(results, "frame")),
            {name: op.volume(results[name], name) for name in op.fields.attributes})


def frame_values(job: MorphJob, fields: FrameFields, source) -> FrameValues:
    """What ``job``'s frames hold; ``source``: the source's samples (sliceable: their type, range)."""
    value_range = None
    if job.output == "density" and job.density_range == "source":
        value_range = finite_range(source, str(job.source.path))
    return FrameValues.of(job, fields.grid, source.dtype, value_range)


def finite_range(source, name: str, *, slab_bytes: int = 64 << 20) -> tuple[float, float]:
    """(min, max) of ``source``'s finite samples, read slab by slab (sliceable ``[z, y, x]``).

    NaN samples count as outside the shape (the distance says so), so the
    range is the other samples'; none at all is an error naming ``name``.
    """
    nz, ny, nx = source.shape
    step = max(1, slab_bytes // max(1, ny * nx * np.dtype(source.dtype).itemsize))
    lo, hi = np.inf, -np.inf
    for z0 in range(0, nz, step):
        part = np.asarray(source[z0:min(z0 + step, nz)])
        if part.dtype.kind == "f":
            part = part[np.isfinite(part)]
        if part.size:
            lo, hi = min(lo, float(part.min())), max(hi, float(part.max()))
    if lo > hi:
        raise VolwarpError(f"{name}: no finite sample: the source has no value range for "
                           "density: {range: source}")
    return lo, hi


def morph_frames(job: MorphJob, prep: Prepared, source: Volume,
                 attributes: dict[str, tuple[Volume, Volume]] | None = None, *,
                 meta: dict | None = None, meshes: bool = False,
                 render: RenderSettings | None = None,
                 space: str | None = None) -> Iterator[Frame]:
    """The frames of an in-memory morph, computed (nothing written): :func:`frames`.

    ``prep``: :func:`.pipeline.prepare` of ``job`` with ``source``, the
    target and ``attributes`` (their volumes: the output types' defaults);
    ``meshes``: make each frame's surface.
    """
    fields = FrameFields.of(job, prep)
    return frames(job, fields, frame_values(job, fields, source.data), computed, meta=meta,
                  meshes=MeshBlocks() if meshes else None, render=render, space=space)


#: the source's keys a frame does not keep: what describes the source's own samples, not
#: the subject (a SEG's segments and identity: a frame written back as a SEG named its
#: morphed shape after the source's segment 1), and volwarp's notes of earlier commands
_NOT_THE_FRAMES = ("volwarp_", "DICOM_Segment", "DICOM_ROI_", "DICOM_Structure",
                   "DICOM_Modality", "DICOM_SOPClassUID", "DICOM_SOPInstanceUID",
                   "DICOM_SeriesInstanceUID", "DICOM_SeriesNumber", "DICOM_ContentLabel")


def source_keys(source) -> dict:
    """The source's own key/values that every frame keeps (as every command keeps its input's).

    What is the subject's (custom keys, the study, the frame of reference),
    not what describes the source's samples (:data:`_NOT_THE_FRAMES`, and a
    label map's marks: a NIfTI's intent made frames of distances pyramids of
    modes): a frame is a new shape, its provenance and the morph's notes its own.
    """
    from ..labelmap import without_label_keys

    return {k: v for k, v in without_label_keys(source.meta).items()
            if not k.startswith(_NOT_THE_FRAMES)}


def frame_space(source, target) -> str | None:
    """The world frame the frames' files name: LPS where an input names one, else None.

    The frame grid is in volwarp's LPS world; inputs that name no frame (TIFF,
    raw) give frames that name none either.
    """
    return "left-posterior-superior" if (source.space or target.space) else None


def shape_box(prep: Prepared) -> np.ndarray:
    """World corners ``(8, 3)`` of the box holding source and target shapes on the frame grid."""
    return FrameFields(prep.morph.source, prep.morph.target, prep.grid).corners()
