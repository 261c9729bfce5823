"""Signed distance fields by passes, each pass's field in a scratch file between them.

**Exact** (:func:`signed_edt_staged`): the exact Euclidean transform of
:mod:`.exact` is three separable passes (x, y, z), and a pass sets each value
from the whole line through it along its axis and nothing else
(:func:`~volwarp_cli.regions.distance_pass_input`). So each pass runs on
blocks holding whole lines along its axis (x and y together on slabs of
whole planes), its float32 squared distances stored in a scratch file for
the next; the block kernels (:func:`.exact.x_pass`, :func:`.exact.y_pass`,
:func:`.exact.z_pass`) are the loop bodies of the in-memory parallel kernel,
and a line sees the same values at the same indices, so the arithmetic is
the same: equal to the in-memory field bit for bit.

**Line metrics** (:func:`line_metric_staged`): ``minnorm``, ``taxicab`` and
``chessboard`` are per-axis passes too, each pass elementwise along the lines
of its axis (:func:`.minnorm.axis_pass`, the in-memory passes' own function;
:func:`.minnorm.chessboard_axis_pass`), so they run on blocks of whole lines
with the outside and inside fields in two scratch files between passes;
equal bit for bit to the in-memory field, and with ``--max-distance`` the
same passes, clamped.

:func:`field_by_blocks` runs either, or, for a band (``--max-distance``, or
a sub-voxel surface with one), the blocks of :class:`.band.BandedDistance`
(each block from itself grown by its halo). A sub-voxel field without a band
has no form by blocks and is refused (:data:`_SUBVOXEL_NEEDS_BAND`).

Every kernel a block task calls is a serial ``nogil`` one, run in the task's
own thread: the engine's threads give the parallelism across blocks (volwarp
has no numba ``prange`` kernel, whose workqueue layer aborts when two threads
run one).
"""

from __future__ import annotations

import math

import numpy as np

from ..box import Box
from ..errors import VolwarpError
from .band import SUBVOXEL_NEEDS_BAND as _SUBVOXEL_NEEDS_BAND
from .exact import x_pass, y_pass, z_pass
from .field import check_method, finish_field, inside_mask
from .scan import block_stats, check_shape, merge_stats

#: Bytes per voxel a pass block holds: the float32 field in, a float32 copy out, the mask.
PASS_BYTES_PER_VOXEL = 9


# -- chunk choice ---------------------------------------------------------------------
def line_chunks(shape, axis: int, block_bytes: int, *, bytes_per_voxel: int = PASS_BYTES_PER_VOXEL,
                min_blocks: int = 1) -> tuple[int, int, int]:
    """Block shape (z, y, x) holding whole lines along ``axis`` within ``block_bytes``.

    The other two axes are split, the faster one (the later array axis) kept
    as long as the budget allows, so a block is few long contiguous runs. A
    single line longer than the budget still makes a block (a pass needs it
    whole). With fewer than ``min_blocks`` blocks the slower axis is cut
    further so that the threads all have work.
    """
    shape = tuple(int(n) for n in shape)
    others = [a for a in range(3) if a != axis]
    slow, fast = others
    n_line = max(1, shape[axis])
    voxels = max(1, int(block_bytes) // (bytes_per_voxel * n_line))
    c = [0, 0, 0]
    c[axis] = shape[axis]
    c[fast] = max(1, min(shape[fast], voxels))
    c[slow] = max(1, min(shape[slow], voxels // c[fast]))
    n_fast = math.ceil(shape[fast] / c[fast]) if shape[fast] else 1
    n_slow = math.ceil(shape[slow] / c[slow]) if shape[slow] else 1
    if n_fast * n_slow < min_blocks and shape[slow] > 1:
        want = min(shape[slow], math.ceil(min_blocks / n_fast))
        c[slow] = max(1, math.ceil(shape[slow] / want))
    return tuple(max(1, v) for v in c)


# -- exact by passes, each pass's field on disk ------------------------------------------------
class MaskSource:
    """The shape's mask of any box of a sliceable source, for block tasks (picklable)."""

    def __init__(self, source, iso: float, inside: str):
        self.source, self.iso, self.inside = source, float(iso), inside
        self.shape = tuple(source.shape)

    def box(self, box) -> np.ndarray:
        """uint8 mask (1 inside) of ``box`` (z, y, x)."""
        data = np.asarray(self.source[box.slices])
        return inside_mask(data, self.iso, self.inside).view(np.uint8)

    def box_and_stats(self, box):
        """:meth:`box` and the block's :func:`.scan.block_stats` (the scan, in the first pass)."""
        data = np.asarray(self.source[box.slices])
        return (inside_mask(data, self.iso, self.inside).view(np.uint8),
                block_stats(data, self.iso, self.inside))


class LabelMaskSource(MaskSource):
    """A label map's shape of any box (:func:`.labels.label_mask`): its voxels, never its ids.

    ``label``: one label's voxels; None: every non-zero id's. The checks are
    made before the passes (:func:`.labels.choose_shape`), so a block's stats
    are None.
    """

    def __init__(self, source, label: int | None = None):
        self.source, self.label = source, label
        self.shape = tuple(source.shape)

    def box(self, box) -> np.ndarray:
        """uint8 mask (1 inside) of ``box`` (z, y, x)."""
        from .labels import label_mask

        return label_mask(np.asarray(self.source[box.slices]), self.label).view(np.uint8)

    def box_and_stats(self, box):
        """:meth:`box`, and None for the stats."""
        return self.box(box), None


def pass_blocks(shape, axis: int, block_bytes: int, min_blocks: int = 1, *,
                bytes_per_voxel: int = PASS_BYTES_PER_VOXEL):
    """The blocks (Boxes) of one pass: whole lines along ``axis`` (:func:`line_chunks`).

    The rows (x) are kept whole where the budget allows, so that each block
    reads and writes its scratch file in long contiguous runs.
    """
    return Box.from_shape(shape).blocks(line_chunks(shape, axis, block_bytes,
                                                    bytes_per_voxel=bytes_per_voxel,
                                                    min_blocks=min_blocks))


def _scratch_array(folder, name: str, shape):
    """A float32 scratch file of ``shape`` (sparse until written), read and written by box."""
    from ..io.filearray import FileArray

    path = folder / f"{name}.f32"
    with open(path, "wb") as fh:
        fh.truncate(int(np.prod(shape)) * 4)
    return FileArray(path, np.dtype(np.float32), 0, shape, writable=True)


def _pass_x(masks, box, hx, dest):
    mask, stats = masks.box_and_stats(box)
    out = np.empty(box.shape, np.float32)
    x_pass(mask, hx, out)
    dest[box.slices] = out
    return stats


def _pass_xy(masks, box, hx, hy, dest):
    # a slab of whole planes holds whole x lines and whole y lines: both passes at once
    mask, stats = masks.box_and_stats(box)
    out = np.empty(box.shape, np.float32)
    x_pass(mask, hx, out)
    y_pass(out, mask, hy)
    # the mask rides along as the sign: a squared distance to the other label is never 0
    # (at least one spacing) and negating is exact, so the z pass needs no second read
    np.negative(out, out=out, where=mask.view(bool))
    dest[box.slices] = out
    return stats


def _pass_z_signed(box, hz, src, write, finish):
    # the z pass of a field whose sign carries the mask (_pass_xy)
    field = np.ascontiguousarray(src[box.slices], dtype=np.float32)
    mask = np.signbit(field)
    np.abs(field, out=field)
    z_pass(field, mask.view(np.uint8), hz)
    write(box, finish(field) if finish is not None else field)


def _pass_y(masks, box, hy, src, dest):
    field = np.ascontiguousarray(src[box.slices], dtype=np.float32)
    y_pass(field, masks.box(box), hy)
    dest[box.slices] = field


def _pass_z(masks, box, hz, src, write, finish):
    field = np.ascontiguousarray(src[box.slices], dtype=np.float32)
    z_pass(field, masks.box(box), hz)
    write(box, finish(field) if finish is not None else field)


def _slabs(shape, block_bytes: int, min_blocks: int, bytes_per_voxel: int = PASS_BYTES_PER_VOXEL):
    """Slabs of whole planes within ``block_bytes``, at least ``min_blocks`` of them.

    None when one plane does not fit the budget.
    """
    nz, ny, nx = shape
    plane = bytes_per_voxel * ny * nx
    if plane > block_bytes:
        return None
    depth = max(1, min(block_bytes // plane, math.ceil(nz / max(1, min_blocks))))
    return Box.from_shape(shape).blocks((depth, ny, nx))


def staged_check(*, size: int, iso: float, inside: str, surface: str, is_bool: bool):
    """The ``check`` of :func:`signed_edt_staged`: the whole's scan from its blocks' stats.

    Refuses what :func:`.scan.scan_shape` refuses: an empty or full shape;
    and smooth samples under ``surface="auto"`` (their sub-voxel field needs
    a band).
    """
    def check(stats):
        nans, count, lo, hi, binary = merge_stats(stats, is_bool)
        check_shape(nans, count, size, lo, hi, iso, inside)
        if surface == "auto" and not binary:
            raise VolwarpError(_SUBVOXEL_NEEDS_BAND)

    return check


def signed_edt_staged(masks: MaskSource, spacing_zyx, engine, write, scratch, *,
                      block_bytes: int, finish=None, memory: int | None = None,
                      last_blocks=None, check=None, slab_depth: int | None = None) -> int:
    """The exact field by passes, the field stored in ``scratch`` between them.

    Memory is the blocks in flight, never the field. The x and y passes run
    together on slabs of whole planes (or, where a plane does not fit the
    budget, the x pass on blocks of whole x lines and the y pass on blocks of
    whole y lines, through a second scratch file) and write their squared
    distances to a float32 scratch file (read and written in whole rows,
    :mod:`volwarp_cli.io.filearray`); the z pass reads it by whole z lines
    and hands each finished block to ``write(box, field)`` (after
    ``finish(field)``: --unsigned, the output type). The same kernels on the
    same lines as the in-memory transform: equal
    bit for bit. ``last_blocks``: the z pass's blocks (the output's block
    grid), default whole z lines within ``block_bytes``; ``slab_depth``: the
    x and y passes' slabs, that many planes deep (default from
    ``block_bytes``). ``check``: called
    with the first pass's blocks' :func:`.scan.block_stats` (the scan of the
    samples, made as they are read) before the last pass, to refuse an
    empty shape or one that needs another method. Returns the number of
    block tasks run.
    """
    shape = masks.shape
    hz, hy, hx = (float(s) for s in spacing_zyx)
    n = 4 * max(1, engine.workers)  # blocks per pass: four a task, for balance
    field = _scratch_array(scratch, "xy", shape)
    slabs = (_slabs(shape, block_bytes, n) if slab_depth is None
             else Box.from_shape(shape).blocks((int(slab_depth), shape[1], shape[2])))
    if slabs is not None:
        tasks = [engine.block_delayed(_pass_xy, f"distance-xy-{'-'.join(map(str, b.lo))}",
                                      masks, b, hx, hy, field, memory=memory, keep=True)
                 for b in slabs]
        count = len(tasks)
        stats = engine.run(tasks, label="distance passes x, y")
    else:
        first = _scratch_array(scratch, "x", shape)
        tasks = [engine.block_delayed(_pass_x, f"distance-x-{'-'.join(map(str, b.lo))}", masks,
                                      b, hx, first, memory=memory, keep=True)
                 for b in pass_blocks(shape, 2, block_bytes, n)]
        stats = engine.run(tasks, label="distance pass x")
        count = len(tasks)
        tasks = [engine.block_delayed(_pass_y, f"distance-y-{'-'.join(map(str, b.lo))}", masks,
                                      b, hy, first, field, memory=memory)
                 for b in pass_blocks(shape, 1, block_bytes, n)]
        count += len(tasks)
        engine.run(tasks, label="distance pass y")
        first.close()
        (scratch / "x.f32").unlink(missing_ok=True)
    if check is not None:
        check([s.value for s in stats])
    blocks = last_blocks if last_blocks is not None else pass_blocks(shape, 0, block_bytes, n)
    if slabs is not None:
        tasks = [engine.block_delayed(_pass_z_signed, f"distance-z-{'-'.join(map(str, b.lo))}",
                                      b, hz, field, write, finish, memory=memory)
                 for b in blocks]
    else:
        tasks = [engine.block_delayed(_pass_z, f"distance-z-{'-'.join(map(str, b.lo))}", masks,
                                      b, hz, field, write, finish, memory=memory)
                 for b in blocks]
    engine.run(tasks, label="distance pass z")
    return count + len(tasks)


# -- minnorm, taxicab, chessboard by per-axis line passes -----------------------------------
#: Bytes per voxel a line-metric block holds: the mask, the outside and inside float32
#: fields, the shift scratch and a read copy.
LINE_BYTES_PER_VOXEL = 17


def _line_passes(metric, fields, axes, spacing_zyx):
    from .minnorm import line_metric_pass

    scratch = np.empty(fields[0].size, np.float32) if metric != "chessboard" else None
    for f in fields:
        for axis in axes:
            line_metric_pass(metric, f, axis, spacing_zyx[axis], scratch)


def _line_first(masks, box, metric, axes, spacing_zyx, out_f, in_f):
    # the outside field (0 on the shape, +inf off it) and the inside one, through the
    # passes along ``axes`` (the block holds whole lines along each)
    mask, stats = masks.box_and_stats(box)
    m = mask.view(bool)
    out = np.where(m, np.float32(0), np.float32(np.inf))
    inn = np.where(m, np.float32(np.inf), np.float32(0))
    del mask, m
    _line_passes(metric, (out, inn), axes, spacing_zyx)
    out_f[box.slices] = out
    in_f[box.slices] = inn
    return stats


def _line_middle(box, metric, axis, spacing_zyx, out_f, in_f):
    # in place: the blocks of one pass are disjoint, and each reads only its own box
    out = np.ascontiguousarray(out_f[box.slices], dtype=np.float32)
    inn = np.ascontiguousarray(in_f[box.slices], dtype=np.float32)
    _line_passes(metric, (out, inn), (axis,), spacing_zyx)
    out_f[box.slices] = out
    in_f[box.slices] = inn


def _line_last(box, metric, spacing_zyx, out_f, in_f, scale, max_distance, write, finish):
    out = np.ascontiguousarray(out_f[box.slices], dtype=np.float32)
    inn = np.ascontiguousarray(in_f[box.slices], dtype=np.float32)
    _line_passes(metric, (out, inn), (0,), spacing_zyx)
    # the shape is where the outside field is 0 (every other value is at least one step),
    # combined as minnorm_signed / signed_distance do: -inside on the shape
    mask = out == 0
    np.negative(inn, out=inn)
    np.copyto(out, inn, where=mask)
    del inn, mask
    if scale is not None:
        out *= np.float32(scale)
    if max_distance is not None:
        finish_field(out, max_distance=max_distance)
    write(box, finish(out) if finish is not None else out)


def line_metric_staged(masks: MaskSource, spacing_zyx, engine, write, scratch, *, metric: str,
                       block_bytes: int, finish=None, max_distance: float | None = None,
                       memory: int | None = None, last_blocks=None, check=None,
                       slab_depth: int | None = None) -> int:
    """The signed ``minnorm``, ``taxicab`` or ``chessboard`` field by per-axis line passes.

    :func:`signed_edt_staged`'s structure for the metrics of
    :func:`.field.signed_distance` that are separable per axis: the outside
    and inside fields go through the passes along x, y, z on blocks holding
    whole lines along each pass's axis, stored in two float32 scratch files
    between passes (x and y together on slabs of whole planes where a plane
    fits ``block_bytes``); the z pass combines them into the signed field,
    scales taxicab and chessboard by the (isotropic) spacing, clamps to
    ``±max_distance``, and hands each block to ``write(box, finish(field))``.

    Bit for bit the in-memory field: ``minnorm`` runs
    :func:`.minnorm.axis_pass` (the in-memory passes' own function) on whole
    lines, elementwise along them; ``taxicab`` is the same with unit spacing
    (integers, exact in float32: ``distance_transform_cdt``'s values);
    ``chessboard`` the L-infinity line passes of
    :func:`.minnorm.chessboard_axis_pass` (integers, equal to scipy's
    chessboard ``distance_transform_cdt``). Returns the number of block tasks.
    """
    from .field import check_isotropic

    if metric not in ("minnorm", "taxicab", "chessboard"):
        raise VolwarpError(f"no per-line passes for the {metric!r} metric")
    spacing_zyx = tuple(float(s) for s in spacing_zyx)
    check_isotropic(metric, spacing_zyx)
    scale = None if metric == "minnorm" or spacing_zyx[0] == 1.0 else spacing_zyx[0]
    shape = masks.shape
    bpv = LINE_BYTES_PER_VOXEL
    n = 4 * max(1, engine.workers)
    out_f = _scratch_array(scratch, "outside", shape)
    in_f = _scratch_array(scratch, "inside", shape)
    slabs = (_slabs(shape, block_bytes, n, bpv) if slab_depth is None
             else Box.from_shape(shape).blocks((int(slab_depth), shape[1], shape[2])))
    if slabs is not None:
        tasks = [engine.block_delayed(_line_first, f"distance-xy-{'-'.join(map(str, b.lo))}",
                                      masks, b, metric, (2, 1), spacing_zyx, out_f, in_f,
                                      memory=memory, keep=True)
                 for b in slabs]
        count = len(tasks)
        stats = engine.run(tasks, label="distance passes x, y")
    else:
        tasks = [engine.block_delayed(_line_first, f"distance-x-{'-'.join(map(str, b.lo))}",
                                      masks, b, metric, (2,), spacing_zyx, out_f, in_f,
                                      memory=memory, keep=True)
                 for b in pass_blocks(shape, 2, block_bytes, n, bytes_per_voxel=bpv)]
        count = len(tasks)
        stats = engine.run(tasks, label="distance pass x")
        tasks = [engine.block_delayed(_line_middle, f"distance-y-{'-'.join(map(str, b.lo))}",
                                      b, metric, 1, spacing_zyx, out_f, in_f, memory=memory)
                 for b in pass_blocks(shape, 1, block_bytes, n, bytes_per_voxel=bpv)]
        count += len(tasks)
        engine.run(tasks, label="distance pass y")
    if check is not None:
        check([s.value for s in stats])
    blocks = (last_blocks if last_blocks is not None
              else pass_blocks(shape, 0, block_bytes, n, bytes_per_voxel=bpv))
    tasks = [engine.block_delayed(_line_last, f"distance-z-{'-'.join(map(str, b.lo))}", b,
                                  metric, spacing_zyx, out_f, in_f, scale, max_distance, write,
                                  finish, memory=memory)
             for b in blocks]
    engine.run(tasks, label="distance pass z")
    out_f.close()
    in_f.close()
    return count + len(tasks)


# -- the whole operation ---------------------------------------------------------------
def field_by_blocks(source, spacing_zyx, engine, open_output, *, iso: float | None,
                    inside: str, metric: str, surface: str,
                    max_distance: float | None = None, finish=None,
                    block_bytes: int, block=None, scratch_near, rule=None) -> dict:
    """The signed field of ``source`` computed and written by blocks on ``engine``.

    ``source``: a sliceable input (a :class:`~volwarp_cli.io.lazy.LazySource`);
    ``open_output(block_zyx, info)``: a context manager giving the
    :class:`~volwarp_cli.io.blockwrite.BlockOutput` the field goes to, with
    that block grid (``info``: how the field was computed, for the
    metadata). ``minnorm``, ``taxicab`` and ``chessboard`` run as
    :func:`line_metric_staged`'s passes (with ``max_distance`` too: the
    passes, then clamped); the exact Euclidean field as :func:`signed_edt_staged`'s passes,
    their scratch files in a folder next to ``scratch_near``; with
    ``max_distance``, as the blocks of :class:`.band.BandedDistance` (the
    surface ``auto`` picks by a scan of the whole, :func:`.scan.field_surface`).
    ``finish(field)``: a block's last step (--unsigned, the output type).
    ``block_bytes``: one task's memory; ``block``: the
    user's block shape (for the passes: Z the x/y slabs' depth, Y,X the z
    pass's columns). ``rule``: a :class:`.labels.ShapeRule`; a label rule's
    voxels are the shape (:class:`LabelMaskSource`: ``iso`` and ``inside``
    unused, the voxel surface, its checks already made by
    :func:`.labels.choose_shape`); default: the samples ``inside`` ``iso``.
    Returns ``info``.
    """
    from ..io.atomic import scratch_folder

    shape = tuple(source.shape)
    spacing_zyx = tuple(float(s) for s in spacing_zyx)
    labels = rule is not None and rule.labels
    if labels:
        surface = "voxel"
    masks = LabelMaskSource(source, rule.label) if labels else MaskSource(source, iso, inside)
    if metric != "euclidean":
        return _line_metric_by_blocks(masks, spacing_zyx, engine, open_output, iso=iso,
                                      inside=inside, metric=metric, surface=surface,
                                      max_distance=max_distance, finish=finish,
                                      block_bytes=block_bytes, block=block,
                                      scratch_near=scratch_near, checked=labels,
                                      is_bool=source.dtype == bool)
    check_method(metric, surface)
    if max_distance is not None:
        return _band_by_blocks(source, spacing_zyx, engine, open_output, rule=rule, iso=iso,
                               inside=inside, surface=surface, max_distance=max_distance,
                               finish=finish, block_bytes=block_bytes, block=block)
    if surface == "subvoxel":
        raise VolwarpError(_SUBVOXEL_NEEDS_BAND)
    # the exact field by passes: the samples are scanned in the first pass (the
    # checks run before the last one), not in a pass of their own
    info = {"metric": metric, "surface": "voxel", "chunked": "passes", "max_distance": None}
    grid = _pass_grid(shape, block, block_bytes, engine.workers)
    with open_output(grid, info) as sink, scratch_folder(scratch_near) as scratch:
        check = None if labels else staged_check(
            size=int(np.prod(shape)), iso=iso, inside=inside, surface=surface,
            is_bool=source.dtype == bool)
        every = sink.blocks()
        signed_edt_staged(masks, spacing_zyx, engine,
                          sink.writer().write, scratch, block_bytes=block_bytes // 4,
                          finish=finish, memory=block_bytes, check=check,
                          last_blocks=every, slab_depth=block[0] if block else None)
        sink.mark_written(every)
    return info


def _band_by_blocks(source, spacing_zyx, engine, open_output, *, rule, iso, inside, surface,
                    max_distance, finish, block_bytes, block) -> dict:
    """:func:`field_by_blocks` within a band: :class:`.band.BandedDistance`'s blocks on ``engine``."""
    import dask

    from ..geometry import Geometry
    from ..volume import zyx_to_xyz
    from .band import BandedDistance
    from .labels import ShapeRule
    from .scan import field_surface, scan_box_voxels

    if rule is None:
        rule = ShapeRule("intensity", "given", iso=iso, inside=inside)
    surface = field_surface(source, rule, metric="euclidean", surface=surface,
                            max_distance=max_distance, box_voxels=scan_box_voxels())
    grid = Geometry(tuple(source.shape), zyx_to_xyz(spacing_zyx))
    op = BandedDistance(source, grid, rule, surface=surface, max_distance=max_distance)
    info = {"metric": "euclidean", "surface": surface, "chunked": "band",
            "max_distance": float(max_distance)}
    with open_output(block or op.block_shape(block_bytes, engine.workers), info) as sink:
        boxes = sink.blocks()
        op_node = dask.delayed(op, pure=False)
        writer = dask.delayed(sink.writer(), pure=False)
        tasks = [engine.block_delayed(_band_block, f"distance-{'-'.join(map(str, b.lo))}",
                                      op_node, b, writer, finish, memory=block_bytes)
                 for b in boxes]
        engine.run(tasks, label="distance")
        sink.mark_written(boxes)
    return info


def _band_block(op, box, writer, finish):
    field = op.compute(box, threads=1)["field"]
    writer.write(box, finish(field) if finish is not None else field)


def _pass_grid(shape, block, block_bytes, workers, bytes_per_voxel=PASS_BYTES_PER_VOXEL):
    # the output's block grid = the z pass's blocks: whole z lines
    if block is not None:  # the slabs' depth, the z pass's columns
        return (shape[0], *block[1:])
    last = pass_blocks(shape, 0, block_bytes // 4, 4 * workers, bytes_per_voxel=bytes_per_voxel)
    return last[0].shape if len(last) else shape


def _line_metric_by_blocks(masks, spacing_zyx, engine, open_output, *, iso, inside, metric,
                           surface, max_distance, finish, block_bytes, block,
                           scratch_near, checked=False, is_bool=False) -> dict:
    """:func:`field_by_blocks` for minnorm, taxicab, chessboard: :func:`line_metric_staged`.

    With ``max_distance`` the same passes, then clamped (as ``finish_field``
    clamps the in-memory field): no halo, the whole field is exact anyway.
    ``masks``: the shape's :class:`MaskSource`; ``checked``: its checks made
    already (a label map's), so the first pass's stats are not checked.
    """
    from ..io.atomic import scratch_folder
    from .field import check_isotropic
    from .minnorm import signed_pass_count

    check_method(metric, surface)
    check_isotropic(metric, spacing_zyx)
    if inside not in ("above", "below"):
        raise VolwarpError(f"inside must be 'above' or 'below', got {inside!r}")
    if max_distance is not None and not max_distance > 0:
        raise VolwarpError(f"max distance must be positive, got {max_distance:g}")
    shape = tuple(masks.shape)
    info = {"metric": metric, "surface": "voxel", "chunked": "passes",
            "max_distance": None if max_distance is None else float(max_distance),
            "passes": signed_pass_count(shape) if metric == "minnorm" else 0}
    grid = _pass_grid(shape, block, block_bytes, engine.workers, LINE_BYTES_PER_VOXEL)
    with open_output(grid, info) as sink, scratch_folder(scratch_near) as scratch:
        check = None if checked else staged_check(
            size=int(np.prod(shape)), iso=iso, inside=inside, surface="voxel", is_bool=is_bool)
        every = sink.blocks()
        line_metric_staged(masks, spacing_zyx, engine,
                           sink.writer().write, scratch, metric=metric,
                           block_bytes=block_bytes // 4, finish=finish,
                           max_distance=max_distance, memory=block_bytes, check=check,
                           last_blocks=every, slab_depth=block[0] if block else None)
        sink.mark_written(every)
    return info
