"""Voxelising an image-swept volume by adaptive subdivision (Winter & Chen §4.2, §4.3).

For each trajectory segment the parameter interval is bisected until
neighbouring templates are at most ``tau`` apart in world space (the largest
move of the template square's corners and centre; for a volume template also
at most one frame apart in ``f(u)``, so no frame is skipped). Each pair of
neighbouring templates A (at ``u_a``) and B (at ``u_b``) bounds a sub-segment.
For every voxel ``p`` between them, the voxel is projected onto each template
along its sweeping direction, both templates are sampled bilinearly there,
and the two values are interpolated linearly in ``t`` (``u = u_a + t (u_b - u_a)``).

*Which voxels lie between two templates, and at which t.* With the signed
plane distances ``sA = (p - a_a) . d_a`` and ``sB = (p - a_b) . d_b``, the
plane interpolated linearly between the two, ``(1 - t) sA + t sB = 0``, passes
through ``p`` at ``t = sA / (sA - sB)``, which lies in [0, 1] exactly when
``sA`` and ``sB`` have opposite signs. ``sA >= 0 > sB`` is the ordinary slab
(a wedge on a bend); ``sA <= 0 < sB`` is the *split* region of the paper:
where the two templates intersect each other (the template sweeps back
across a tight bend, or across the axis of a rotational sweep), the space
between them falls into two disjoint parts on either side of the planes'
intersection line, and the second part is this one. A voxel is covered when
the interpolated template coordinate lies in [0, 1]^2. The sub-segments of a
segment are half-open (``t`` in [0, 1), the last one closed unless the
segment's last template is the next segment's first, or the first segment's
in a closed trajectory: :meth:`.model.Sweep.joined_ends`), so the
subdivision never counts a voxel twice; a point reached by genuinely
different instances (a self-intersection, another segment, another pass of
the same segment) is combined per field with the CVG operator of
:mod:`.cvg`.

*Departures from the paper.* The paper scan-converts each sub-segment with a
3-D boundary fill seeded once per split region; the sign test above finds the
same voxels without seeds (both regions at once, no holes where a seed would
be missed) and is exact for the linear interpolation it implies. Polyline
vertices get a rotational joint: the template turns about the vertex from the
incoming to the outgoing direction (subdivided to ``tau`` like any other
part), so no wedge is left open on the outer side of a corner.

The kernel works on z slices of the output, ranges of them over the threads:
each slice belongs to one thread and sees the sub-segments in trajectory
order, so the result does not depend on the number of threads. The same
holds for any block of the output (:func:`voxelize_block`, for
:mod:`.chunked`): the subdivision (:func:`plan_voxelize`) depends on the
sweep and ``tau`` alone, the kernel's loops run the whole grid's indices
clamped to the block, and every voxel's value comes from its own world point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import parallel
from ..box import Box
from ..errors import VolwarpError
from ..geometry import Geometry
from ..progress import log, progress, timed
from .cvg import OP_CODES, finish_fields
from .frames import Frames, compute_frames
from .trajectory import Polyline

#: upper bound on the number of templates per segment
MAX_KNOTS = 2_000_000


class TooManyTemplates(VolwarpError):
    """A segment that needs more than :data:`MAX_KNOTS` templates.

    ``cause``: ``"tau"`` (templates farther apart than tau) or ``"path"``
    (template ``template``'s slices jump by more than one), so that the
    caller can name the spec key or option that asked for it.
    """

    def __init__(self, message: str, cause: str, template: int | None = None):
        super().__init__(message)
        self.cause = cause
        self.template = template


def check_axis_aligned(grid: Geometry) -> None:
    """Refuse a grid with a direction other than the identity.

    The sweep's samplers (this one and :mod:`.direct`) place voxel ``(i, j, k)``
    at ``origin + spacing * (i, j, k)``: they ignore ``direction``.
    """
    if not grid.identity_direction:
        raise VolwarpError(f"a sweep is sampled on an axis-aligned grid (identity direction), "
                           f"got direction {[list(r) for r in grid.direction]}")


# -- subdivision --------------------------------------------------------------------
def _gaps(frames: Frames, slices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = frames.corners()
    move = np.linalg.norm(np.diff(c, axis=0), axis=2).max(axis=1)
    if slices.shape[1]:
        jump = np.abs(np.diff(slices, axis=0)).max(axis=1)
    else:
        jump = np.zeros(len(move))
    return move, jump


def _refine(evaluate, s0: np.ndarray, tau: float, slice_fn, what: str):
    """Bisect the parameter intervals of ``s0`` until templates are <= tau apart."""
    s = np.asarray(s0, dtype=np.float64)
    while True:
        fr = evaluate(s)
        sl = slice_fn(fr)
        move, jump = _gaps(fr, sl)
        split = ((move > tau) | (jump > 1.0)) & (np.diff(s) > 1e-12)
        if not np.any(split):
            return fr, sl
        if s.size + int(split.sum()) > MAX_KNOTS:
            if np.any(split & (move > tau)):
                raise TooManyTemplates(f"{what} needs more than {MAX_KNOTS} templates at "
                                       f"tau={tau:g}; raise tau or use a coarser grid", "tau")
            bad = int(np.argmax(np.abs(np.diff(sl, axis=0))[split].max(axis=0)))
            raise TooManyTemplates(f"{what}: the template's slices f(u) jump by more than one "
                                   f"slice in over {MAX_KNOTS} places", "path", bad)
        mids = 0.5 * (s[:-1][split] + s[1:][split])
        s = np.sort(np.concatenate([s, mids]))


def segment_knots(seg, fns, index: int, templates, tau: float):
    """Frames and slice coordinates of the templates of segment ``index`` (in order).

    Polyline vertices appear twice (incoming and outgoing direction) with the
    rotation between them subdivided as a joint.
    """
    breaks = seg.breaks()
    edges = np.concatenate([[0.0], breaks, [1.0]])
    what = f"{seg.kind} segment {index}"

    def slice_fn_for(s_of):
        def fn(fr):
            s = s_of(fr)
            if not templates:
                return np.zeros((len(s), 0))
            return np.stack([t.slice_coords(seg, s) for t in templates], axis=1)
        return fn

    slice_fn = slice_fn_for(lambda fr: fr.s)
    parts: list[Frames] = []
    part_slices = []
    for p in range(len(edges) - 1):
        lo, hi = edges[p], edges[p + 1]
        n0 = 9 if len(edges) == 2 else 3

        def evaluate(s, hi=hi):
            fr = compute_frames(seg, fns, s, index)
            if isinstance(seg, Polyline) and hi < 1.0:
                last = compute_frames(seg, fns, s[-1:], index, left=True)
                for f in ("EX", "EY", "EZ"):
                    getattr(fr, f)[-1] = getattr(last, f)[0]
            return fr

        fr, sl = _refine(evaluate, np.linspace(lo, hi, n0), tau, slice_fn, what)
        if parts:  # rotational joint from the previous piece's end to this start
            joint, jsl = _joint(parts[-1].take([-1]), fr.take([0]), part_slices[-1][-1:],
                                tau, what, fns)
            parts.append(joint)
            part_slices.append(jsl)
        parts.append(fr)
        part_slices.append(sl)
    return Frames.concat(parts), np.concatenate(part_slices)


def _joint(a: Frames, b: Frames, sl: np.ndarray, tau: float, what: str, fns):
    """Interior templates of the rotation about a polyline vertex (may be empty)."""
    def evaluate(w):
        w = np.asarray(w)[:, None]
        ang = np.arccos(np.clip(np.sum(a.EZ * b.EZ), -1, 1))
        if ang < 1e-9:
            return Frames(np.repeat(a.s, len(w)), np.repeat(a.u, len(w)), np.repeat(a.P, len(w), 0),
                          np.repeat(a.EX, len(w), 0), np.repeat(a.EY, len(w), 0),
                          np.repeat(a.EZ, len(w), 0), np.repeat(a.SX, len(w)), np.repeat(a.SY, len(w)))
        if ang > np.pi - 1e-6:
            raise VolwarpError(f"{what} turns back on itself (180 degrees) at a vertex")
        sa = np.sin((1 - w) * ang) / np.sin(ang)
        sb = np.sin(w * ang) / np.sin(ang)
        def slerp(x, y):
            v = sa * x + sb * y
            return v / np.linalg.norm(v, axis=1)[:, None]
        ez = slerp(a.EZ, b.EZ)
        ey = slerp(a.EY, b.EY)
        ey = ey - np.sum(ey * ez, axis=1)[:, None] * ez
        ey /= np.linalg.norm(ey, axis=1)[:, None]
        ex = np.cross(ey, ez)
        n = len(w)
        return Frames(np.repeat(a.s, n), np.repeat(a.u, n), np.repeat(a.P, n, 0), ex, ey, ez,
                      np.repeat(a.SX, n), np.repeat(a.SY, n))

    def slice_fn(fr):
        return np.repeat(sl, len(fr.s), axis=0)

    fr, jsl = _refine(evaluate, np.array([0.0, 1.0]), tau, slice_fn, what)
    inner = np.arange(1, len(fr.s) - 1)
    return fr.take(inner), jsl[inner]


# -- the kernel ---------------------------------------------------------------------
def _get_kernel():
    """The voxelising kernel (C, releases the GIL: z slices ``[zlo, zhi)`` per call)."""
    from ._sweepkernels import sweep_voxelize

    return sweep_voxelize


def pack_templates(templates):
    """Flatten templates for the kernel: (tex, offsets, heights, widths, slice counts)."""
    tex = np.concatenate([t.data.ravel() for t in templates]).astype(np.float32) \
        if templates else np.zeros(1, np.float32)
    sizes = [t.data.size for t in templates]
    off = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64) if templates \
        else np.zeros(0, np.int64)
    h = np.array([t.data.shape[1] for t in templates], dtype=np.int64)
    w = np.array([t.data.shape[2] for t in templates], dtype=np.int64)
    n = np.array([t.data.shape[0] for t in templates], dtype=np.int64)
    return tex, off, h, w, n


@dataclass
class VoxelPlan:
    """A sweep's subdivision, ready for the kernel: everything but the grid.

    The templates (frames ``P``, ``EX``, ``EY``, ``EZ``, scales ``SX``, ``SY``,
    slice coordinates ``SL``), the sub-segments (``sub_a``, ``sub_b``,
    ``closed``) with their world bounding boxes (``lo``, ``hi``), the packed
    template images and the per-field operators. It depends on the sweep and
    ``tau`` alone, so a blocked run makes it once and hands it to every block
    (:func:`voxelize_block`).
    """

    names: list
    ops: list
    tau: float
    P: np.ndarray
    EX: np.ndarray
    EY: np.ndarray
    EZ: np.ndarray
    SX: np.ndarray
    SY: np.ndarray
    SL: np.ndarray
    sub_a: np.ndarray
    sub_b: np.ndarray
    closed: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    tex: np.ndarray
    off: np.ndarray
    th: np.ndarray
    tw: np.ndarray
    tn: np.ndarray
    op_codes: np.ndarray
    opac: int

    @property
    def blend(self) -> bool:
        """True when a field blends (the kernel then keeps a weight sum)."""
        return "blend" in self.ops


def plan_voxelize(sweep, tau: float) -> VoxelPlan:
    """Subdivide ``sweep`` to ``tau`` (:func:`segment_knots`): the :class:`VoxelPlan`."""
    names = list(sweep.templates)
    templates = [sweep.templates[n] for n in names]
    ops = [sweep.ops[n] for n in names]
    F = len(names)
    knots, slices, sub_a, sub_b, closed = [], [], [], [], []
    base = 0
    with timed("sweep: subdivide"):
        for i, (seg, fns) in enumerate(zip(sweep.segments, sweep.functions, strict=True)):
            fr, sl = segment_knots(seg, fns, i, templates, tau)
            k = len(fr.s)
            knots.append(fr)
            slices.append(sl)
            a = np.arange(base, base + k - 1)
            sub_a.append(a)
            sub_b.append(a + 1)
            c = np.zeros(k - 1, dtype=np.uint8)
            c[0] |= 1  # first sub-segment of the segment
            c[-1] |= 2  # last
            closed.append(c)
            base += k
        joined = sweep.joined_ends()
        for i, join in enumerate(joined):
            if not join:
                continue
            j = (i + 1) % len(knots)
            closed[i][-1] &= ~np.uint8(2)  # half-open: the plane is the next start's
            closed[j][0] &= ~np.uint8(1)  # and met without the ends' tolerance
            for f in ("P", "EX", "EY", "EZ", "SX", "SY"):  # one plane, bit for bit
                getattr(knots[i], f)[-1] = getattr(knots[j], f)[0]
    fr = Frames.concat(knots)
    SL = np.ascontiguousarray(np.concatenate(slices), dtype=np.float64).reshape(len(fr.s), F)
    sub_a = np.concatenate(sub_a).astype(np.int64)
    sub_b = np.concatenate(sub_b).astype(np.int64)
    closed = np.concatenate(closed)
    log.info("sweep: %d templates, %d sub-segments, tau %.4g", len(fr.s), len(sub_a), tau)
    # world bounding boxes of the sub-segments
    corners = fr.corners()  # (K, 5, 3)
    lo = np.minimum(corners[sub_a].min(axis=1), corners[sub_b].min(axis=1))
    hi = np.maximum(corners[sub_a].max(axis=1), corners[sub_b].max(axis=1))
    tex, off, th, tw, tn = pack_templates(templates)
    op_codes = np.array([OP_CODES[o] for o in ops], dtype=np.int64)
    opac = names.index("opacity") if "opacity" in names else -1
    c64 = np.ascontiguousarray
    return VoxelPlan(names, ops, float(tau), c64(fr.P), c64(fr.EX), c64(fr.EY), c64(fr.EZ),
                     c64(fr.SX), c64(fr.SY), SL, sub_a, sub_b, closed, lo, hi,
                     tex, off, th, tw, tn, op_codes, opac)


def _kernel_args(plan: VoxelPlan, grid: Geometry, box: Box):
    """The kernel's arguments for the voxels of ``box`` (accumulators of its shape).

    The sub-segments' voxel-index boxes are the whole grid's, clamped to ``box``
    (the kernel tests every voxel of that range exactly; the clamp only skips
    voxels outside the block).
    """
    origin = np.ascontiguousarray(grid.origin_array, dtype=np.float64)
    spacing = np.ascontiguousarray(grid.spacing_array, dtype=np.float64)
    ilo = np.floor((plan.lo - origin) / spacing).astype(np.int64) - 1
    ihi = np.ceil((plan.hi - origin) / spacing).astype(np.int64) + 1
    blo_xyz, bhi_xyz = box.xyz()
    ilo = np.maximum(ilo, np.array(blo_xyz, dtype=np.int64))
    ihi = np.minimum(ihi, np.array(bhi_xyz, dtype=np.int64) - 1)
    keep = np.all(ilo <= ihi, axis=1)
    boxes = np.ascontiguousarray(np.stack([ilo[:, 0], ihi[:, 0], ilo[:, 1], ihi[:, 1],
                                           ilo[:, 2], ihi[:, 2]], axis=1)[keep])
    F = len(plan.names)
    shape = box.shape
    acc = np.zeros((F,) + shape, dtype=np.float32)
    covered = np.zeros(shape, dtype=np.uint8)
    wsum = np.zeros(shape if plan.blend else (1, 1, 1), dtype=np.float32)
    args = (plan.P, plan.EX, plan.EY, plan.EZ, plan.SX, plan.SY, plan.SL,
            plan.sub_a[keep], plan.sub_b[keep], plan.closed[keep], boxes, origin, spacing,
            plan.tex, plan.off, plan.th, plan.tw, plan.tn, plan.op_codes, plan.opac,
            1e-6 * float(spacing.min()), acc, wsum, covered)
    return args, acc, wsum, covered


def _finish(plan: VoxelPlan, acc, wsum, covered) -> dict:
    F = len(plan.names)
    shape = covered.shape
    fields = finish_fields(plan.names, plan.ops, acc.reshape(F, -1),
                           wsum.reshape(-1) if plan.blend else None,
                           covered.reshape(-1).astype(bool))
    return {n: fields[n].reshape(shape) for n in plan.names}


def voxelize_block(plan: VoxelPlan, grid: Geometry, box: Box, *, threads: int = 1) -> dict:
    """The fields of ``plan`` on the voxels ``box`` of ``grid``, ``{name: float32 [z, y, x]}``.

    The one evaluation, for the whole grid as for a block of it: each voxel's
    value comes from its own world point and the sub-segments in trajectory
    order, so any box gives the whole grid's values bit for bit. ``threads``:
    the box's z planes are split over that many threads (1: one call of the
    kernel in the calling thread, safe in any thread; more: the whole grid's
    run, in z slabs so that a progress bar moves).
    """
    check_axis_aligned(grid)
    args, acc, wsum, covered = _kernel_args(plan, grid, box)
    if box.empty:
        return _finish(plan, acc, wsum, covered)
    kernel = _get_kernel()
    (z_lo, y_lo, x_lo), (z_hi, _, _) = box.lo, box.hi
    if threads <= 1:
        kernel(*args, int(z_lo), int(z_hi), int(z_lo), int(y_lo), int(x_lo))
        return _finish(plan, acc, wsum, covered)
    nz = int(z_hi - z_lo)
    n_slabs = max(1, min(16, nz // 8))
    edges = np.linspace(0, nz, n_slabs + 1).astype(int)
    with timed("sweep: voxelise"), progress(n_slabs, "sweep") as bar:
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            z0 = int(z_lo + a)
            parallel.run_ranges(
                lambda p, q, z0=z0: kernel(*args, z0 + p, z0 + q, int(z_lo), int(y_lo),
                                           int(x_lo)), int(b - a), threads)
            bar.advance()
    return _finish(plan, acc, wsum, covered)
