"""Both shapes' fields on the frame grid, made by one code in memory and by blocks.

Dinh & Carvalho 2004, section 0.4, as :mod:`.interpolate` describes it: the
alignment's matrices (a shape's centroid counted box by box, in integers, so
that blocks sum to the whole's bit for bit), the frame grid, each shape's
signed field on its own grid (:func:`volwarp_cli.distance.operation.field_operation`),
resampled onto the frame grid through its alignment (:class:`ResampleOperation`:
a block reads the input box its voxels reach), then, in memory only, the
voxels no input covers filled and a landmark warp applied (both move whole
fields); each attribute's pair is resampled as its shape is.

Where each step runs is a :class:`Steps`: in memory every operation's whole
is computed on the calling threads and kept as an array; by blocks
(:class:`StepsOnEngine`) the executor runs it on the morph's engine into a
scratch file, read back box by box. The operations are the same, so the
fields are the same bits either way.
"""

from __future__ import annotations

import contextlib
import functools
from pathlib import Path

import numpy as np

from ..box import Box
from ..errors import OutOfMemoryError, VolwarpError
from ..execute import Operation
from ..geometry import Geometry
from ..progress import log, timed
from .interpolate import index_map, lands_on_grid, needed_box, resample_box
from .spec import MorphJob

#: Bytes per voxel a resampling block holds: its coordinates (24), the output (4), slack
#: for the interpolation
RESAMPLE_BYTES_PER_VOXEL = 32
#: ... and per input sample it reads: the stored samples and their float32 copy
INPUT_BYTES_PER_VOXEL = 12
#: Voxels one resampling computes at once (its coordinates: 24 bytes a voxel)
_PART_VOXELS = 1 << 20


class Steps:
    """Where a morph's steps run: in memory, each operation's whole on the calling threads."""

    whole = True

    def map(self, task, boxes, *, label: str = "morph") -> list:
        """``[task(box) for box in boxes]``."""
        return [task(box) for box in boxes]

    def chunks(self, shape) -> tuple[int, int, int]:
        """The blocks a pass over a grid of ``shape`` reads: one, the whole."""
        return tuple(int(n) for n in shape)

    def run(self, op, name: str, *, user_block: bool = True):
        """``op``'s one output, computed whole: an array (refused where it cannot fit)."""
        from ..execute import compute_whole
        from ..memory import ensure_fits_once_loaded

        ensure_fits_once_loaded(op.memory(op.grid.box), op.what, op.load)
        results = compute_whole(op)
        (key,) = op.targets
        return op.output(results, key)

    def target(self, name: str, header):
        """A float32 output named ``name`` on ``header``'s grid (in memory, not written)."""
        from ..execute import Target

        return Target(Path(f"{name}.nrrd"), header, np.dtype(np.float32))

    def on_grid(self, samples):
        """Samples already on the frame grid, as the frames read them (float32 in memory)."""
        return np.asarray(samples, dtype=np.float32)


class StepsOnEngine(Steps):
    """By blocks: each operation run by the executor on ``engine`` into ``scratch``.

    ``per_task``: one task's memory; ``block``: the user's block shape.
    """

    whole = False

    def __init__(self, engine, scratch: Path, per_task: int, block=None):
        self.engine, self.scratch, self.per_task, self.block = engine, Path(scratch), per_task, block

    def map(self, task, boxes, *, label: str = "morph") -> list:
        """The tasks on the engine, their results in order."""
        return self.engine.map(task, list(boxes), label=label, memory=self.per_task)

    def chunks(self, shape) -> tuple[int, int, int]:
        """Whole rows within a task's memory (the user's block, if given)."""
        from .chunked import frame_chunks

        return frame_chunks(shape, self.per_task, self.engine.workers, self.block)

    def run(self, op, name: str, *, user_block: bool = True):
        """``op`` by blocks into its scratch file, opened to be read box by box.

        ``user_block``: in blocks of the user's shape, if given (else ``op``'s own).
        """
        from .. import execute
        from ..io.lazy import open_volume_lazy

        how = execute.How(chunked=True, block=self.block if user_block else None,
                          open_engine=lambda: contextlib.nullcontext(self.engine))
        execute.run(op, how, by_blocks=True)
        (target,) = op.targets.values()
        return open_volume_lazy(target.path)[1]

    def target(self, name: str, header):
        """A float32 scratch file named ``name`` on ``header``'s grid."""
        from ..execute import Target

        return Target(self.scratch / f"{name}.nrrd", header, np.dtype(np.float32))

    def on_grid(self, samples):
        """Samples already on the frame grid, read box by box as they are."""
        return samples


class ResampleOperation(Operation):
    """Samples on their own grid brought onto ``grid`` through an alignment ``matrix``.

    An operation of the executor: a block of the frame grid is :func:`.interpolate.resample_box`
    of the input box its voxels reach (:func:`.interpolate.needed_box`), so
    any blocks give the whole's values bit for bit. ``outside``: ``"nan"``
    (uncovered voxels NaN: a field) or ``"nearest"`` (an attribute's border
    sample); ``scale``: the field's alignment scale, multiplied in.
    """

    def __init__(self, values, values_i2w: np.ndarray, matrix: np.ndarray, grid: Geometry, *,
                 outside: str, scale: float = 1.0, target=None, what: str = "a field",
                 chunks=None):
        self.values, self.values_shape = values, tuple(values.shape)
        self.m = index_map(values_i2w, matrix, grid)
        self.grid, self.outside, self.scale = grid, outside, float(scale)
        self.targets = {"values": target}
        self.chunks = chunks
        self.what = f"{what} resampled onto the {'x'.join(map(str, grid.shape_xyz))} frame grid"

    def memory(self, box: Box) -> int:
        """A block's output, and its largest part's coordinates and the input box that part reads.

        :meth:`compute` goes part by part (:meth:`_parts`): counted whole, the
        coordinates of a 164^3 frame grid were 135 MiB where its parts hold 24,
        and an in-memory morph chosen by its measured need was refused halfway.
        """
        worst = max(needed_box(self.m, part, self.values_shape).size * INPUT_BYTES_PER_VOXEL
                    + part.size * (RESAMPLE_BYTES_PER_VOXEL - 4) for part in self._parts(box))
        return box.size * 4 + worst

    def _parts(self, box: Box):
        """``box`` in parts of whole planes, about :data:`_PART_VOXELS` each (bounded coordinates)."""
        depth = max(1, _PART_VOXELS // max(1, box.shape[1] * box.shape[2]))
        for z0 in range(box.lo[0], box.hi[0], depth):
            yield Box((z0, box.lo[1], box.lo[2]), (min(box.hi[0], z0 + depth), *box.hi[1:]))

    def compute(self, box: Box, *, threads: int) -> dict:
        """``box`` of the resampled values, part by part (:meth:`_parts`)."""
        out = np.empty(box.shape, np.float32)
        for part in self._parts(box):
            need = needed_box(self.m, part, self.values_shape)
            out[part.lo[0] - box.lo[0]:part.hi[0] - box.lo[0]] = resample_box(
                self.values[need.slices], need, self.m, part, values_shape=self.values_shape,
                outside=self.outside)
        if self.scale != 1.0:
            out *= np.float32(self.scale)
        return {"values": out}

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """``chunks`` (default whole rows within ``per_task``), halved until blocks fit.

        A block holds the input box it reads (:func:`.chunked.resample_chunks`);
        a VolwarpError when not even single voxels fit (a strong scaling: one
        frame voxel reaching a huge input box).
        """
        from .chunked import frame_chunks, resample_chunks

        chunks = self.chunks or frame_chunks(self.grid.shape, per_task, workers)
        return resample_chunks(self.grid.shape, chunks, [(self.m, self.values_shape)],
                               per_task)


def alignment_matrices(job: MorphJob, inputs: dict, steps: Steps, rules: dict) -> dict:
    """The alignment matrix of each shape (``{"source": 4x4, "target": 4x4}``).

    ``inputs``: ``{"source": (header, samples), ...}``; ``rules``: each
    shape's :class:`~volwarp_cli.distance.labels.ShapeRule` (:func:`shape_rule`).
    A shape's default centre (the centroid of the rule's voxels) is counted
    box by box in integers over ``steps``' blocks (:func:`.align.axis_counts`):
    the same bits for any blocks.
    """
    from .align import affine_from_params, centroid_from_counts

    out = {}
    for name, ref in (("source", job.source), ("target", job.target)):
        params = getattr(job, f"align_{name}")
        if not params:
            out[name] = np.eye(4)
            continue
        header, samples = inputs[name]
        geo = Geometry.of(header)
        center = None
        if "center" not in params and "matrix" not in params:
            shape = geo.shape
            counts = [np.zeros(n, np.int64) for n in (shape[2], shape[1], shape[0])]
            task = functools.partial(_counts, samples=samples, rule=rules[name])
            for box, parts in steps.map(task, Box.from_shape(shape).blocks(steps.chunks(shape))):
                for k, axis in enumerate((2, 1, 0)):
                    counts[k][box.lo[axis]:box.hi[axis]] += parts[k]
            try:
                center = centroid_from_counts(counts, geo.index_to_world_matrix)
            except VolwarpError as exc:
                raise VolwarpError(f"{ref.path}: {exc}") from None
        out[name] = affine_from_params(params, default_center=center)
    return out


def _counts(box: Box, samples, rule):
    from .align import axis_counts

    return box, axis_counts(rule.mask(np.asarray(samples[box.slices])))


def shape_rule(job: MorphJob, name: str, header, samples):
    """What shape ``name``'s field is of: ``distance``'s choice (:func:`~volwarp_cli.distance.labels.choose_shape`).

    A label map's shape is its labels' voxels, never a level of its ids (a
    level between ids 1 and 2 moved a frame's surface by 0.83 mm when id 2
    was renamed 1000, and dropped negative ids); its refusals are
    ``distance``'s, in the spec's keys for a spec (:func:`.spec.spec_terms`).
    Read once, box by box: the same choice in memory and by blocks.
    """
    from ..distance.labels import LabelAbsent, choose_shape
    from ..distance.scan import scan_box_voxels
    from ..errors import BadUsage
    from .spec import spec_terms

    ref = getattr(job, name)
    try:
        with timed(f"{name} label rule"):
            rule = choose_shape(samples, values=ref.values, label=ref.label, iso=ref.iso,
                                inside=ref.inside, surface=job.surface, name=str(ref.path),
                                box_voxels=scan_box_voxels(), meta=header.meta)
    except (BadUsage, LabelAbsent) as exc:
        if job.doc is None:
            raise
        # (the file by its name: the spec's line says which, and a long path clipped the hint;
        # a label the volume lacks is the spec's label: key, a spec error as a warp's index
        # outside its lattice is)
        message = spec_terms(str(exc)).replace(str(ref.path), ref.path.name)
        key = (name, "label") if isinstance(exc, LabelAbsent) else (name,)
        raise job.doc.error(key, message) from None
    log.info("%s: %s", name, rule.describe())
    return rule


def attribute_values(job: MorphJob, name: str, side: str, header, samples) -> None:
    """Refuse attribute ``name``'s ``side`` if it is a label map (:func:`~volwarp_cli.warp.defaults.choose_values`).

    An attribute is blended, ``(1 - t) a + t b``: ids 10 and 30 gave 20, an
    id neither map has. Its ``values: intensity`` blends them as asked.
    """
    from ..errors import BadUsage
    from ..warp.defaults import choose_values

    index, ref = next(((i, a) for i, a in enumerate(job.attributes) if a.name == name),
                      (None, None))
    path = getattr(ref, side) if ref is not None else None
    choice = choose_values(samples, ref.values if ref is not None else None,
                           name=str(path or f"attribute {name}'s {side}"), meta=header.meta)
    log.info("attribute %s (%s): %s", name, side, choice.describe())
    if choice.values != "labels":
        return
    message = (f"attribute {name}: its {side}{f', {path.name},' if path else ''} is a label "
               f"map ({choice.why}): blending it, (1 - t) a + t b, writes ids neither map has "
               "(10 and 30 give 20); set values: intensity on the attribute to blend its ids "
               "anyway, or morph a label as the shapes (label: N)")
    if job.doc is None or index is None:
        raise BadUsage(message)
    raise job.doc.error(("attributes", index), message)


def shape_field(job: MorphJob, name: str, header, samples, steps: Steps, rule):
    """The signed field of shape ``name`` on its own grid: the distance's operation of ``rule``."""
    from ..distance.operation import field_operation
    from ..distance.scan import field_surface, scan_box_voxels
    from ..passes import Passes
    from .chunked import in_morph_terms

    ref = getattr(job, name)
    try:
        surface = field_surface(samples, rule, metric=job.metric, surface=job.surface,
                                max_distance=job.max_distance, box_voxels=scan_box_voxels())
        op = field_operation(samples, Geometry.of(header), rule, metric=job.metric,
                             surface=surface, max_distance=job.max_distance,
                             target=steps.target(name, header))
        with timed(f"{name} distance ({job.metric})"):
            field = steps.run(op, name)
    except VolwarpError as exc:  # (named after its input, once; a refusal stays one)
        kind = OutOfMemoryError if isinstance(exc, OutOfMemoryError) else VolwarpError
        text = in_morph_terms(job, exc)
        raise kind(text if text.startswith(f"{ref.path}: ") else f"{ref.path}: {text}") from None
    log.info("%s field: %s, %s surface", name,
             "passes" if isinstance(op, Passes) else "band", surface)
    return field


def onto_grid(samples, header, matrix: np.ndarray, grid: Geometry, steps: Steps, name: str,
              *, outside: str, scale: float = 1.0):
    """``samples`` (on ``header``'s grid) on the frame grid: as they are, or resampled."""
    geo = Geometry.of(header)
    if lands_on_grid(geo.shape, geo.index_to_world_matrix, matrix, grid):
        return steps.on_grid(samples)
    op = ResampleOperation(samples, geo.index_to_world_matrix, matrix, grid, outside=outside,
                           scale=scale,
                           target=steps.target(f"{name}-on-grid", grid.header(np.float32)),
                           what=name, chunks=steps.chunks(grid.shape))
    with timed(f"{name} onto the frame grid"):
        return steps.run(op, f"{name}-on-grid", user_block=False)
