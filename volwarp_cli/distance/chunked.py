"""Signed distance fields out of core, on Dask arrays.

Two ways, both equal to the in-memory field bit for bit:

**Passes** (:func:`signed_edt_dask`): the exact Euclidean transform of
:mod:`.exact` is three separable passes (x, y, z), and a pass sets each value
from the whole line through it along its axis and nothing else
(:func:`~volwarp_cli.regions.distance_pass_input`). So each pass is a
``map_blocks`` over blocks holding whole lines along its axis, with a Dask
rechunk between passes; the block kernels (:func:`.exact.x_pass`,
:func:`.exact.y_pass`, :func:`.exact.z_pass`) are the loop bodies of the
in-memory parallel kernel, and a line sees the same values at the same
indices, so the arithmetic is the same. The float32 squared distances of a
pass are what the in-memory kernel stores between its passes too.

**Band** (:func:`banded_signed_distance_dask`): clipped to ``±D``
(``--max-distance``), a voxel's value depends only on the samples within a
halo of it (:func:`~volwarp_cli.regions.distance_band_input`), so the field
is a ``map_overlap``: the in-memory kernel on each block grown by the halo,
clipped, cropped. Exact inside the band ``|d| <= D``, ``±D`` outside, as
``finish_field(field, max_distance=D)`` of the whole. The sub-voxel field
(smooth inputs) bands the same way with its own, wider halo.

**Line metrics** (:func:`line_metric_staged`, through :func:`field_by_blocks`):
``minnorm``, ``taxicab`` and ``chessboard`` are per-axis passes too, each
pass elementwise along the lines of its axis (:func:`.minnorm.axis_pass`, the
in-memory passes' own function; :func:`.minnorm.chessboard_axis_pass`), so
they run on blocks of whole lines with the outside and inside fields in two
scratch files between passes; equal bit for bit to the in-memory field, and
with ``--max-distance`` the same passes, clamped. They have no Dask-array
form (:func:`signed_distance_dask` refuses them).

What cannot be done out of core is refused (:func:`signed_distance_dask`):
a sub-voxel field without a band (its nearest-seed transform carries seed ids
and foot points through the passes, which the block kernels here do not).

Every kernel a block task calls is a serial ``nogil`` one, run in the task's
own thread: Dask's threads give the parallelism across blocks (volwarp has no
numba ``prange`` kernel, whose workqueue layer aborts when two threads run one).
"""

from __future__ import annotations

import functools
import math

import dask
import dask.array as da
import numpy as np

from ..box import Box
from ..errors import VolwarpError
from .exact import x_pass, y_pass, z_pass
from .field import check_method, finish_field, inside_mask

#: Bytes per voxel a pass block holds: the float32 field in, a float32 copy out, the mask.
PASS_BYTES_PER_VOXEL = 9

_F32 = np.empty((0, 0, 0), np.float32)
_U8 = np.empty((0, 0, 0), np.uint8)


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


def _default_block_bytes(block_bytes):
    if block_bytes is not None:
        return int(block_bytes)
    from ..memory import block_bytes as budget

    return budget()


def _threads() -> int:
    from ..parallel import threads

    return threads()


# -- block tasks -------------------------------------------------------------------------
def _as_u8(block):
    if block.dtype == bool:
        return np.ascontiguousarray(block).view(np.uint8)
    return (block != 0).view(np.uint8)


def _x_block(mask, hx):
    out = np.empty(mask.shape, np.float32)
    x_pass(np.ascontiguousarray(mask), hx, out)
    return out


def _y_block(field, mask, hy):
    field = np.array(field, dtype=np.float32, order="C")  # a copy: Dask's blocks are shared
    y_pass(field, np.ascontiguousarray(mask), hy)
    return field


def _z_block(field, mask, hz):
    field = np.array(field, dtype=np.float32, order="C")
    z_pass(field, np.ascontiguousarray(mask), hz)
    return field


def _edt_block(mask, hz, hy, hx, max_distance):
    # the in-memory transform, serial, on one overlapped block; then --max-distance
    mask = np.ascontiguousarray(mask)
    out = np.empty(mask.shape, np.float32)
    x_pass(mask, hx, out)
    y_pass(out, mask, hy)
    z_pass(out, mask, hz)
    return finish_field(out, max_distance=max_distance)


# -- exact by passes ---------------------------------------------------------------------
def _mask_u8(mask) -> da.Array:
    mask = da.asarray(mask)
    if mask.ndim != 3:
        raise VolwarpError(f"signed_edt needs a 3-D mask, got shape {mask.shape}")
    if mask.dtype == np.uint8 or mask.dtype == bool:
        return mask.map_blocks(_as_u8, dtype=np.uint8, meta=_U8)
    return (mask != 0).map_blocks(_as_u8, dtype=np.uint8, meta=_U8)


def signed_edt_dask(mask, spacing_zyx=(1.0, 1.0, 1.0), *, block_bytes: int | None = None,
                    min_blocks: int | None = None) -> da.Array:
    """Exact signed Euclidean distance of a Dask mask, by passes: :func:`.exact.signed_edt`.

    Parameters
    ----------
    mask : (Z, Y, X) dask (or numpy) array, bool or integer
        The shape (nonzero inside), in any chunks.
    spacing_zyx : 3 floats
        Sample spacing along the array axes.
    block_bytes : int, optional
        One pass block's working memory (:data:`PASS_BYTES_PER_VOXEL` a voxel);
        default :func:`volwarp_cli.memory.block_bytes`. Each pass rechunks to
        whole lines along its axis (:func:`line_chunks`).
    min_blocks : int, optional
        Cut each pass into at least this many blocks where the lines allow
        (default: the thread count, :func:`volwarp_cli.parallel.threads`).

    Returns
    -------
    (Z, Y, X) float32 dask array
        Equal to ``signed_edt(mask.compute(), spacing_zyx)`` bit for bit,
        ``±inf`` included for an empty or full mask (callers check first).
    """
    m = _mask_u8(mask)
    budget = _default_block_bytes(block_bytes)
    nb_min = _threads() if min_blocks is None else int(min_blocks)
    hz, hy, hx = (float(s) for s in spacing_zyx)
    c_x, c_y, c_z = (line_chunks(m.shape, a, budget, min_blocks=nb_min) for a in (2, 1, 0))
    d = m.rechunk(c_x).map_blocks(_x_block, hx, dtype=np.float32, meta=_F32)
    d = da.map_blocks(_y_block, d.rechunk(c_y), m.rechunk(c_y), hy, dtype=np.float32,
                      meta=_F32)
    return da.map_blocks(_z_block, d.rechunk(c_z), m.rechunk(c_z), hz, dtype=np.float32,
                         meta=_F32)


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
        """:meth:`box` and the block's :func:`_block_stats` (the scan, in the first pass)."""
        data = np.asarray(self.source[box.slices])
        return (inside_mask(data, self.iso, self.inside).view(np.uint8),
                _block_stats(data, self.iso, self.inside))


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

    Refuses what :func:`signed_distance_dask` refuses after its own scan: an
    empty or full shape, and smooth samples under ``surface="auto"`` (their
    sub-voxel field needs a band).
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
    same lines as :func:`signed_edt_dask` and the in-memory transform: equal
    bit for bit. ``last_blocks``: the z pass's blocks (the output's block
    grid), default whole z lines within ``block_bytes``; ``slab_depth``: the
    x and y passes' slabs, that many planes deep (default from
    ``block_bytes``). ``check``: called
    with the first pass's blocks' :func:`_block_stats` (the scan of the
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


# -- band by overlapping blocks --------------------------------------------------------------
def band_halo(spacing_zyx, max_distance: float, surface: str = "voxel") -> tuple[int, int, int]:
    """The halo (z, y, x voxels) a block of the field clipped to ``±max_distance`` needs.

    :func:`volwarp_cli.regions.distance_band_input`'s rule, and for voxel
    surfaces at least ``ceil(D / h)`` per axis: the rule takes ``floor(D / h)``
    (a site farther along an axis is farther than ``D`` in exact arithmetic),
    the one voxel more keeps a site just past ``D`` out of reach of float32
    rounding too.
    """
    from ..regions import distance_band_input
    from ..volume import zyx_to_xyz

    h = [float(s) for s in spacing_zyx]
    d = float(max_distance)
    if not d > 0:
        raise VolwarpError(f"max distance must be positive, got {max_distance:g}")
    big = [10**9] * 3  # a volume large enough that the rule's box is not clamped
    out = Box((big[0] // 2,) * 3, (big[0] // 2 + 1,) * 3)
    region = distance_band_input(out, big, zyx_to_xyz(tuple(h)), d, surface=surface)
    halo = [out.lo[a] - region.lo[a] for a in range(3)]
    if surface == "voxel":
        halo = [max(k, math.ceil(d / v)) for k, v in zip(halo, h, strict=True)]
    return tuple(int(k) for k in halo)


def _subvoxel_block(values, iso, above, hz, hy, hx, max_distance):
    # subvoxel.subvoxel_signed_distance in this thread alone, on one overlapped block;
    # a block without a crossing is farther than the band from the surface: ±D by side
    from .subvoxel import subvoxel_field

    vals = np.ascontiguousarray(values)
    if vals.dtype.kind not in "f":
        vals = vals.astype(np.float32)
    dist = subvoxel_field(vals, iso, above, (hz, hy, hx), threads=1)
    if dist is None:
        inside = (vals >= iso) if above else (vals < iso)
        return np.where(inside, np.float32(-max_distance), np.float32(max_distance))
    return finish_field(dist, max_distance=max_distance)


def banded_signed_distance_dask(data_or_mask, spacing_zyx, max_distance: float, *,
                                iso: float | None = None, inside: str = "above",
                                surface: str = "voxel") -> da.Array:
    """The signed distance clipped to ``±max_distance``, as overlapping blocks.

    Parameters
    ----------
    data_or_mask : (Z, Y, X) dask (or numpy) array
        The shape (nonzero inside) when ``iso`` is None; else samples, the shape
        being those {above|below} ``iso`` (:func:`.field.inside_mask`).
    spacing_zyx : 3 floats
    max_distance : float
        The band ``D``.
    iso, inside : the shape's definition; ``surface="subvoxel"`` needs ``iso``.
    surface : {"voxel", "subvoxel"}
        ``voxel``: the exact field between voxel centres (:mod:`.exact`);
        ``subvoxel``: the distance to the samples' iso-surface (:mod:`.subvoxel`).

    Returns
    -------
    (Z, Y, X) float32 dask array
        In the input's chunks; each block computed from itself grown by
        :func:`band_halo` (``map_overlap``, no padding at the volume's faces).
        Equal bit for bit to ``finish_field(field_of_whole, max_distance=D)``:
        exact where ``|d| <= D``, ``±D`` beyond. For ``subvoxel`` this rests on
        :func:`~volwarp_cli.regions.distance_band_input`'s bound (a bound
        checked on smooth data by ``tests/test_regions.py``).
    """
    if surface not in ("voxel", "subvoxel"):
        raise VolwarpError(f"unknown surface mode {surface!r} (known: voxel, subvoxel)")
    data = da.asarray(data_or_mask)
    if data.ndim != 3:
        raise VolwarpError(f"the distance needs a 3-D volume, got shape {data.shape}")
    d = float(max_distance)
    halo = band_halo(spacing_zyx, d, surface)
    hz, hy, hx = (float(s) for s in spacing_zyx)
    depth = {a: min(k, max(0, n - 1)) for a, (k, n) in enumerate(zip(halo, data.shape,
                                                                       strict=True))}
    if surface == "subvoxel":
        if iso is None:
            raise VolwarpError("sub-voxel distances need the iso level of the samples")
        if inside not in ("above", "below"):
            raise VolwarpError(f"inside must be 'above' or 'below', got {inside!r}")
        task = functools.partial(_subvoxel_block, iso=float(iso), above=inside == "above",
                                 hz=hz, hy=hy, hx=hx, max_distance=d)
        return data.map_overlap(task, depth=depth, boundary="none", trim=True, dtype=np.float32,
                                meta=_F32)
    mask = data if iso is None else inside_mask(data, iso, inside)
    m = _mask_u8(mask)
    task = functools.partial(_edt_block, hz=hz, hy=hy, hx=hx, max_distance=d)
    return m.map_overlap(task, depth=depth, boundary="none", trim=True,
                         dtype=np.float32, meta=_F32)


_SUBVOXEL_NEEDS_BAND = ("sub-voxel distances (smooth samples) out of core need --max-distance "
                        "(overlapping blocks); give one, or use --surface voxel for the exact "
                        "field between voxel centres")


# -- the chunked signed_distance --------------------------------------------------------------
def _block_stats(block, iso, inside):
    # (NaNs, inside count, nanmin, nanmax, binary, lo, hi) of one block
    b = np.asarray(block)
    if b.size == 0:
        return 0, 0, np.nan, np.nan, True, None, None
    nans = int(np.count_nonzero(np.isnan(b))) if b.dtype.kind == "f" else 0
    count = int(np.count_nonzero(inside_mask(b, iso, inside)))
    if b.dtype == bool:
        return nans, count, float(b.min()), float(b.max()), True, bool(b.min()), bool(b.max())
    lo, hi = b.min(), b.max()
    if nans == b.size:
        fmin = fmax = np.nan
    elif nans:
        fmin, fmax = float(np.nanmin(b)), float(np.nanmax(b))
    else:
        fmin, fmax = float(lo), float(hi)
    binary = bool(lo == hi) or int(np.count_nonzero((b == lo) | (b == hi))) == b.size
    return nans, count, fmin, fmax, binary, lo.item(), hi.item()


def _scan(data, iso, inside):
    """One pass over the samples: NaN count, inside count, range, and whether binary."""
    blocks = data.to_delayed().ravel()
    stats = dask.compute(*[dask.delayed(_block_stats)(b, iso, inside) for b in blocks])
    return merge_stats(stats, data.dtype == bool)


def merge_stats(stats, is_bool: bool = False):
    """The blocks' :func:`_block_stats` as the whole's ``(nans, count, lo, hi, binary)``."""
    nans = sum(s[0] for s in stats)
    count = sum(s[1] for s in stats)
    mins = [s[2] for s in stats if not np.isnan(s[2])]
    maxs = [s[3] for s in stats if not np.isnan(s[3])]
    values = {v for s in stats for v in s[5:] if v is not None}
    binary = is_bool or (all(s[4] for s in stats) and len(values) <= 2)
    return (nans, count, min(mins) if mins else np.nan, max(maxs) if maxs else np.nan,
            binary)


def check_shape(nans: int, count: int, size: int, lo, hi, iso: float, inside: str) -> None:
    """The refusals and the warning of the whole's scan (:func:`.field.signed_distance`'s words).

    NaN samples are warned about; an empty shape, or one filling the grid, refused.
    """
    if nans:
        from ..progress import log

        log.warning("%d NaN samples (%.2g%%) count as outside the shape", nans,
                    100.0 * nans / size)
    if count == 0:
        raise VolwarpError(f"the shape is empty: no sample is {inside} the iso level {iso:g} "
                           f"(samples range {float(lo):g} to {float(hi):g})")
    if count == size:
        raise VolwarpError(f"the shape fills the whole grid: every sample is {inside} the iso "
                           f"level {iso:g}, so there is no surface")


def check_out_of_core(metric: str, surface: str) -> None:
    """Refuse a metric or surface mode with no form as one Dask array (before any pass).

    The minnorm, taxicab and chessboard metrics run out of core by staged
    passes (:func:`line_metric_staged`, through :func:`field_by_blocks`), not
    as a Dask graph.
    """
    check_method(metric, surface)
    if metric != "euclidean":
        raise VolwarpError(f"the {metric} metric has no out-of-core form as a Dask array: "
                           "its passes run by blocks through field_by_blocks "
                           "(volwarp distance --chunked)")


def signed_distance_dask(data, spacing_zyx=(1.0, 1.0, 1.0), *, iso: float,
                         inside: str = "above", metric: str = "euclidean",
                         surface: str = "auto", max_distance: float | None = None,
                         block_bytes: int | None = None) -> tuple[da.Array, dict]:
    """The chunked counterpart of :func:`.field.signed_distance`, for what runs out of core.

    Parameters
    ----------
    data : (Z, Y, X) dask (or numpy) array
    spacing_zyx : 3 floats
    iso, inside, metric, surface : as :func:`.field.signed_distance`.
    max_distance : float, optional
        ``--max-distance``: the field clipped to ``±D``, computed as overlapping
        blocks (:func:`banded_signed_distance_dask`); else the exact field by
        passes (:func:`signed_edt_dask`).
    block_bytes : int, optional
        The passes' block budget (:func:`signed_edt_dask`).

    Returns
    -------
    field : (Z, Y, X) float32 dask array
        Equal bit for bit to the in-memory ``signed_distance`` (and, with
        ``max_distance``, to ``finish_field(field, max_distance=D)``).
    info : dict
        ``{"metric", "surface", "chunked", "max_distance"}``: ``chunked`` is
        ``"passes"`` or ``"band"``, for the output's metadata.

    Raises
    ------
    VolwarpError
        The shape is empty or fills the grid (the messages of
        ``signed_distance``); or the field has no form as a Dask array: the
        ``minnorm``, ``taxicab`` and ``chessboard`` metrics (they run by blocks
        through :func:`field_by_blocks`), a sub-voxel surface without
        ``max_distance``.
    """
    check_out_of_core(metric, surface)
    if inside not in ("above", "below"):
        raise VolwarpError(f"inside must be 'above' or 'below', got {inside!r}")
    if max_distance is not None and not max_distance > 0:
        raise VolwarpError(f"max distance must be positive, got {max_distance:g}")
    data = da.asarray(data)
    if data.dtype.kind == "c" or data.dtype.kind not in "biuf":
        raise VolwarpError(f"cannot take the distance of samples of type {data.dtype}")
    if data.ndim != 3:
        raise VolwarpError(f"the distance needs a 3-D volume, got shape {data.shape}")
    if surface == "subvoxel" and max_distance is None:
        raise VolwarpError(_SUBVOXEL_NEEDS_BAND)
    nans, count, lo, hi, binary = _scan(data, iso, inside)
    check_shape(nans, count, data.size, lo, hi, iso, inside)
    spacing_zyx = tuple(float(s) for s in spacing_zyx)
    sub = surface == "subvoxel" or (surface == "auto" and not binary)
    info = {"metric": metric, "surface": "subvoxel" if sub else "voxel",
            "chunked": "band" if max_distance is not None else "passes",
            "max_distance": None if max_distance is None else float(max_distance)}
    if sub:
        if max_distance is None:
            raise VolwarpError(_SUBVOXEL_NEEDS_BAND)
        return banded_signed_distance_dask(data, spacing_zyx, max_distance, iso=iso,
                                           inside=inside, surface="subvoxel"), info
    if max_distance is not None:
        return banded_signed_distance_dask(data, spacing_zyx, max_distance, iso=iso,
                                           inside=inside), info
    return signed_edt_dask(inside_mask(data, iso, inside), spacing_zyx,
                           block_bytes=block_bytes), info


# -- the whole operation ---------------------------------------------------------------
def field_by_blocks(source, spacing_zyx, engine, open_output, *, iso: float | None,
                    inside: str, metric: str, surface: str,
                    max_distance: float | None = None, finish=None, out_dtype=np.float32,
                    block_bytes: int, block=None, scratch_near, rule=None) -> dict:
    """The signed field of ``source`` computed and written by blocks on ``engine``.

    ``source``: a sliceable input (a :class:`~volwarp_cli.bspline.blocks.LazySource`);
    ``open_output(block_zyx, info)``: a context manager giving the
    :class:`~volwarp_cli.io.blockwrite.BlockOutput` the field goes to, with
    that block grid (``info``: :func:`signed_distance_dask`'s, for the
    metadata). ``minnorm``, ``taxicab`` and ``chessboard`` run as
    :func:`line_metric_staged`'s passes (with ``max_distance`` too: the
    passes, then clamped); the exact Euclidean field as :func:`signed_edt_staged`'s passes,
    their scratch files in a folder next to ``scratch_near``; with
    ``max_distance``, or a sub-voxel surface, as overlapping blocks.
    ``finish(field)``: a block's last step (--unsigned, the output type,
    ``out_dtype``). ``block_bytes``: one task's memory; ``block``: the
    user's block shape (for the passes: Z the x/y slabs' depth, Y,X the z
    pass's columns). ``rule``: a :class:`.labels.ShapeRule`; a label rule's
    voxels are the shape (:class:`LabelMaskSource`: ``iso`` and ``inside``
    unused, the voxel surface, its checks already made by
    :func:`.labels.choose_shape`). Returns ``info``.
    """
    from ..engine import dask_input, write_blocks
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
    if max_distance is None and surface != "subvoxel":
        # the exact field by passes: the samples are scanned in the first pass (the
        # checks run before the last one), not in a pass of their own
        check_out_of_core(metric, surface)
        info = {"metric": metric, "surface": "voxel", "chunked": "passes",
                "max_distance": None}
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
    chunks = block or line_chunks(shape, 2, block_bytes // 4, min_blocks=engine.workers)
    if labels:  # the band of the labels' voxels (checked): no scan of its own
        check_method(metric, surface)
        if not max_distance > 0:
            raise VolwarpError(f"max distance must be positive, got {max_distance:g}")
        mask = dask_input(source, chunks).map_blocks(_label_block, rule.label, dtype=bool,
                                                      meta=np.empty((0, 0, 0), bool))
        field = banded_signed_distance_dask(mask, spacing_zyx, max_distance)
        info = {"metric": metric, "surface": "voxel", "chunked": "band",
                "max_distance": float(max_distance)}
    else:
        field, info = signed_distance_dask(dask_input(source, chunks), spacing_zyx, iso=iso,
                                           inside=inside, metric=metric, surface=surface,
                                           max_distance=max_distance,
                                           block_bytes=block_bytes // 4)
    if finish is not None:
        field = field.map_blocks(finish, dtype=np.dtype(out_dtype))
    with open_output(block or chunks, info) as sink:
        write_blocks(field, sink, engine, label="distance", memory=block_bytes)
    return info


def _label_block(block, label):
    from .labels import label_mask

    return label_mask(block, label)


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
