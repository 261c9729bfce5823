"""Where the write map can send domain voxels: reach bounds from the lattice alone.

Every bound here follows from the convex-hull property of the B-spline: a
domain voxel's offset is a convex combination of its region's 4^3 control-point
offsets, so the image of a region lies within the hull of those points, widened
by the box filter's half voxel (and, at the domain's faces, by the linear
extrapolation of the deformation's halo). They decide which target planes a
domain block can touch and which domain voxels a target block needs: the
one-shot warp's stream (its rolling window), the threads' parts, the local updates'
blocks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..box import Box
from .lattice import Lattice, window_reduce

#: Slack for float32 deformation offsets in bounds derived from the lattice.
OFFSET_SLACK = 0.01

#: about the most refined net values :meth:`Reach.tight_planes` computes (fewer
#: refinements beyond), and held at once
TIGHT_WORK = 1 << 24
TIGHT_BATCH = 1 << 20


@dataclass(frozen=True, eq=False)  # (arrays: compared by identity, as numpy cannot)
class Reach:
    """The write map's affine base ``A(g) = offset + scale * g`` on ``grid``.

    ``A(g)`` is the target index of domain voxel g (x y z) in a target of
    ``target_shape`` (x, y, z).
    """

    grid: Lattice
    offset: np.ndarray
    scale: np.ndarray
    target_shape: tuple[int, int, int]

    def z_reach(self, dq) -> tuple[float, float]:
        """``(below, above)``: domain voxel g's box lies in target z ``[A(g) - below, A(g) + above]``.

        From the lattice alone: a voxel's offset is a convex combination of
        control-point offsets, and its box (face centres, halo extrapolation)
        stays within that range widened by the range itself.
        """
        dz = dq[..., 2]
        top, bottom = float(dz.max()), float(dz.min())
        spread = top - bottom
        half = 0.5 * float(self.scale[2])
        return (half - bottom + spread + OFFSET_SLACK, half + top + spread + OFFSET_SLACK)

    def target_z_reach(self, dq, g0: int, g1: int) -> tuple[int, int]:
        """Target z planes [t0, t1) that domain z planes [g0, g1) can reach."""
        below, above = self.z_reach(dq)
        s, o = float(self.scale[2]), float(self.offset[2])
        t0 = int(np.floor(o + s * g0 - below - 0.5))
        t1 = int(np.ceil(o + s * (g1 - 1) + above + 0.5)) + 1
        return t0, t1

    def domain_z_window(self, dq, t0: int, t1: int) -> tuple[int, int]:
        """Domain z range [g0, g1) holding every voxel that can reach target z planes [t0, t1)."""
        below, above = self.z_reach(dq)
        s, o = float(self.scale[2]), float(self.offset[2])
        dz = self.grid.domain_shape[2]
        g0 = int(np.floor((t0 - 0.5 - o - above) / s))
        g1 = int(np.ceil((t1 - 0.5 - o + below) / s)) + 1
        return max(g0, 0), min(g1, dz)

    def planes(self, bounds) -> PlaneReach:
        """The target z planes each domain z plane can reach, from :func:`offset_bounds`.

        Tighter than :meth:`target_z_reach` (one bound for the whole lattice,
        widened everywhere by the halo's extrapolation): each plane takes the
        bounds of its own layer of regions, whose faces alone are widened.
        The threads' parts of an update (:func:`.work.thread_parts`) are
        sized from it, and the memory the label warp's rings may take
        (:meth:`tight_planes` narrows the one-shot warp's and the label
        warp's rings themselves).
        """
        lo_u, hi_u = bounds
        gz = self.grid.granularity[2]
        dz = self.grid.domain_shape[2]
        layer = np.minimum(np.arange(dz) // gz, lo_u.shape[0] - 1)
        lo_z = lo_u[..., 2].min(axis=(1, 2))[layer]
        hi_z = hi_u[..., 2].max(axis=(1, 2))[layer]
        s, o = float(self.scale[2]), float(self.offset[2])
        base = o + s * np.arange(dz)
        half = 0.5 * s
        t_lo = np.floor(base + lo_z - half - 0.5).astype(np.int64)
        t_hi = np.ceil(base + hi_z + half + 0.5).astype(np.int64) + 1
        return PlaneReach(t_lo, t_hi)

    def tight_planes(self, dq, hull: PlaneReach | None = None,
                     refinements: int = 3) -> PlaneReach:
        """:meth:`planes` from the deformation of ``dq`` itself, not its control points' hull.

        The hull of the control points is loose where a drag moved them: the
        minimum-norm solution moves a handle's 4^3 points by up to 2.4 times
        the drag, so a plane's reach bound was 21 target planes where the
        deformation moves 8. Here each domain plane's z offsets are the
        surface of a 2-D control net, exact (the z basis applied to the
        lattice), bounded by the hull of that net refined ``refinements``
        times (each halves its spacing; the hull closes in on the surface
        by 4x a step); the halo the scatter extrapolates at the domain's
        faces (``2 U[0] - U[1]``, :func:`.pushforward.fill_halo`) is a net of
        its own. A voxel's box reads its own and its six neighbours' offsets:
        plane g's bound is that of planes g - 1..g + 1 and of plane g's halo
        columns and rows. Strict (:data:`OFFSET_SLACK` for float32), as
        :meth:`planes`; for the warp's blocks and parts and the label warp's
        shares, whose halos it shrinks.

        ``hull``: :meth:`planes`'s bound, which the result never exceeds
        (both hold: their intersection does), and the result where ``dq`` is
        not finite. Fewer refinements on large lattices: the nets' work stays
        about :data:`TIGHT_WORK` values, held a batch of planes at a time.
        """
        from .basis import region_weights

        dz = np.asarray(dq[..., 2], np.float64)  # (cz, cy, cx)
        if not np.isfinite(dz).all():
            return hull if hull is not None else self.planes(offset_bounds(dq))
        (gx, gy, gz), (rx, ry, rz) = self.grid.granularity, self.grid.regions
        wz = region_weights(gz)  # (gz, 4): plane p's layers p // gz .. + 3

        def plane_nets(p0, p1):
            # planes [p0, p1)'s nets: each a convex blend of its 4 control layers (the z
            # basis's nonzero weights; a dense (planes x layers) product cost 1.2 G
            # multiply-adds for a 129^3 lattice on 512^3)
            rows = np.arange(p0, p1)
            out = np.zeros((p1 - p0,) + dz.shape[1:])
            for m in range(4):
                out += wz[rows % gz, m][:, None, None] * dz[rows // gz + m]
            return out

        def face_weights(g, r, end):
            # the halo an x or y face's extrapolation (2 U[0] - U[1], at the far end too)
            # makes: the weights of the lattice's columns or rows in it
            w = np.zeros(r + 3)
            first, second = (0, 1) if end == 0 else (g * r - 1, g * r - 2)
            for sign, v in ((2.0, first), (-1.0, second)):
                w[v // g:v // g + 4] += sign * region_weights(g)[v % g]
            return w

        n_planes = gz * rz
        cy, cx = dz.shape[1:]
        while refinements > 0 and n_planes * (cy << refinements) * (cx << refinements) > \
                TIGHT_WORK:
            refinements -= 1
        faces = [(face_weights(g, r, end), axis) for g, r, axis in ((gx, rx, 2), (gy, ry, 1))
                 if g * r >= 2 for end in (0, -1)]
        lo_p, hi_p = np.empty(n_planes), np.empty(n_planes)
        halo_lo = np.full(n_planes, np.inf)
        halo_hi = np.full(n_planes, -np.inf)
        step = max(1, TIGHT_BATCH // ((cy << refinements) * (cx << refinements)))
        for p0 in range(0, n_planes, step):  # (a batch of planes' nets held at a time)
            p1 = min(p0 + step, n_planes)
            nets = plane_nets(p0, p1)
            lo_p[p0:p1], hi_p[p0:p1] = _net_range(nets, (1, 2), refinements)
            for face, axis in faces:  # the x and y faces' halos on each plane (1-D nets)
                net = nets @ face if axis == 2 else np.einsum("j,gji->gi", face, nets)
                a, b = _net_range(net, (1,), refinements)
                halo_lo[p0:p1] = np.minimum(halo_lo[p0:p1], a)
                halo_hi[p0:p1] = np.maximum(halo_hi[p0:p1], b)
        if n_planes >= 2:  # the z faces' halo planes, below the first and above the last
            ends = plane_nets(0, 2), plane_nets(n_planes - 2, n_planes)
            below = _net_range((2 * ends[0][0] - ends[0][1])[None], (1, 2), refinements)
            above = _net_range((2 * ends[1][1] - ends[1][0])[None], (1, 2), refinements)
        else:
            below = above = (lo_p[:1], hi_p[:1])
        ext_lo = np.concatenate([below[0], lo_p, above[0]])
        ext_hi = np.concatenate([below[1], hi_p, above[1]])
        lo_z = np.minimum.reduce([ext_lo[:-2], ext_lo[1:-1], ext_lo[2:], halo_lo]) - OFFSET_SLACK
        hi_z = np.maximum.reduce([ext_hi[:-2], ext_hi[1:-1], ext_hi[2:], halo_hi]) + OFFSET_SLACK
        if not (np.isfinite(lo_z).all() and np.isfinite(hi_z).all()):  # (blends overflowed)
            return hull if hull is not None else self.planes(offset_bounds(dq))
        s, o = float(self.scale[2]), float(self.offset[2])
        base = o + s * np.arange(n_planes)
        half = 0.5 * s
        t_lo = np.floor(base + lo_z - half - 0.5).astype(np.int64)
        t_hi = np.ceil(base + hi_z + half + 0.5).astype(np.int64) + 1
        if hull is not None:
            t_lo, t_hi = np.maximum(t_lo, hull.t_lo), np.minimum(t_hi, hull.t_hi)
        return PlaneReach(t_lo, t_hi)

    def region_range(self, axis: int, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Per region along ``axis`` (0 = x): its voxels within [lo, hi), as [a, b).

        A region's range is empty where b <= a.
        """
        g = self.grid.granularity[axis]
        r = np.arange(self.grid.regions[axis])
        return np.maximum(r * g, lo), np.minimum((r + 1) * g, hi)

    def rebuild_block(self, old_bounds, new_bounds, voxels: Box) -> TargetBlock | None:
        """The blocks an update of the domain voxels ``voxels`` (a Box, z y x) rebuilds.

        ``old_bounds``, ``new_bounds``: :func:`offset_bounds` of the lattice
        before and after. The target block: every target voxel the old or new
        image of those voxels can reach; the domain block: every voxel whose
        new image can reach that target block (none when the new images all
        miss it: a lattice that carries the model off the target), region by
        region. None when the old and new images miss the target.
        """
        grid = self.grid
        vlo, vhi = voxels.xyz()
        tshape = np.array(self.target_shape)
        half = 0.5 * self.scale

        def along(v, axis):  # a per-region vector of x (0), y or z, broadcast on [Rz, Ry, Rx]
            shape = [1, 1, 1]
            shape[2 - axis] = -1
            return v.reshape(shape)

        def image_cells(bounds, wlo, whi):
            # per axis: the target cells [t0, t1) that the images of the regions'
            # voxels within [wlo, whi) can overlap, and which regions have such voxels
            lo_u, hi_u = bounds
            t0, t1, inside = [], [], np.ones(lo_u.shape[:3], bool)
            for axis in range(3):
                a, b = self.region_range(axis, wlo[axis], whi[axis])
                inside &= along(a < b, axis)
                a_img = self.offset[axis] + self.scale[axis] * along(a, axis)
                b_img = self.offset[axis] + self.scale[axis] * (along(b, axis) - 1)
                t0.append(np.floor(a_img + lo_u[..., axis] - half[axis] - 0.5))
                t1.append(np.ceil(b_img + hi_u[..., axis] + half[axis] + 0.5) + 1)
            return t0, t1, inside

        t_lo, t_hi = np.full(3, np.inf), np.full(3, -np.inf)
        for bounds in (old_bounds, new_bounds):
            t0, t1, inside = image_cells(bounds, vlo, vhi)
            if inside.any():
                for axis in range(3):
                    t_lo[axis] = min(t_lo[axis], t0[axis][inside].min())
                    t_hi[axis] = max(t_hi[axis], t1[axis][inside].max())
        tlo = np.clip(t_lo, 0, tshape).astype(np.int64)
        thi = np.clip(t_hi, 0, tshape).astype(np.int64)
        if np.any(thi <= tlo):
            return None
        # domain voxels g whose new box [A(g) + lo_u - half, A(g) + hi_u + half]
        # overlaps the cells [tlo, thi), i.e. the interval [tlo - 0.5, thi - 0.5]
        lo_u, hi_u = new_bounds
        d_lo, d_hi, inside = [], [], np.ones(lo_u.shape[:3], bool)
        for axis in range(3):
            a, b = self.region_range(axis, 0, grid.domain_shape[axis])
            s, o = self.scale[axis], self.offset[axis]
            first = np.floor((tlo[axis] - 0.5 - o - half[axis] - hi_u[..., axis]) / s)
            last = np.ceil((thi[axis] - 0.5 - o + half[axis] - lo_u[..., axis]) / s) + 1
            first = np.maximum(first, along(a, axis))
            last = np.minimum(last, along(b, axis))
            inside &= first < last
            d_lo.append(first)
            d_hi.append(last)
        if not inside.any():  # only the old images reach it: it is cleared, nothing added
            return TargetBlock(Box.from_xyz(tlo.tolist(), thi.tolist()), Box((0, 0, 0), (0, 0, 0)))
        dlo = [int(v[inside].min()) for v in d_lo]
        dhi = [int(v[inside].max()) for v in d_hi]
        return TargetBlock(Box.from_xyz(tlo.tolist(), thi.tolist()), Box.from_xyz(dlo, dhi))


#: Target z planes covered by one step of a stream (:func:`~volwarp_cli.warp.blocks.warp_block`: the
#: domain planes gathered and scattered at a time are this many over the scale along z).
#: Few: the ring of accumulators is the deformation's reach plus a step, and each step's
#: deformation buffers, samples and finished planes are a step's; 4 against 16 (paired,
#: 256^3 warps, 2026-12-05): peak 97 against 169 MiB and 0.96x the wall time with every
#: point of 9^3 moved, 0.93x with one, 0.96x at oversample 2, the frog's label warp 0.94x
#: (the pages a process touches first cost most on the project's VM); 2 took longer
#: (each step's two halo planes of deformation, its calls).
STREAM_PLANES = 4


def ring_planes(reach, chunk: int) -> int:
    """Target planes a block's ring must hold.

    The most that one step of ``chunk`` domain planes, starting anywhere, can
    reach above what is already final (+ rounding).
    """
    dz = len(reach.t_hi)
    if dz == 0:
        return 2
    k = min(chunk, dz)
    windows = np.lib.stride_tricks.sliding_window_view(
        np.concatenate([reach.t_hi, np.full(k - 1, reach.t_hi[-1])]), k)
    return int((windows.max(axis=1) - reach.floor_from).max()) + 2


@dataclass(frozen=True)
class TargetBlock:
    """A ``target`` block and the ``domain`` block whose voxels can reach it.

    Both :class:`~volwarp_cli.box.Box` es (z y x). What a local rebuild
    recomputes (:meth:`Reach.rebuild_block`), and a thread's part of a
    scatter (:func:`.work.thread_parts`).
    """

    target: Box
    domain: Box


@dataclass(frozen=True, eq=False)  # (arrays: compared by identity, as numpy cannot)
class PlaneReach:
    """Per domain z plane g: the target z planes [t_lo[g], t_hi[g]) its voxels can reach."""

    t_lo: np.ndarray
    t_hi: np.ndarray

    def __post_init__(self):
        # the lowest plane any plane from g on can reach: what a stream in g order may
        # finalize below (the per-plane bounds need not grow with g)
        object.__setattr__(self, "floor_from", np.minimum.accumulate(self.t_lo[::-1])[::-1])

    def target_reach(self, g0: int, g1: int) -> tuple[int, int]:
        """``(t0, t1)``: the target planes domain planes [g0, g1) leave open.

        No domain plane from ``g0`` on reaches below t0; planes [g0, g1) reach
        nothing from t1 on.
        """
        return int(self.floor_from[g0]), int(self.t_hi[g0:g1].max())

    def domain_window(self, t0: int, t1: int) -> tuple[int, int]:
        """Domain z range [g0, g1) holding every plane that can reach target planes [t0, t1)."""
        hit = np.flatnonzero((self.t_hi > t0) & (self.t_lo < t1))
        if hit.size == 0:
            return 0, 0
        return int(hit[0]), int(hit[-1]) + 1


def _refined(net: np.ndarray, axis: int) -> np.ndarray:
    """A uniform cubic B-spline's control polygon along ``axis``, its knot spacing halved.

    The same curve over the same spans (Lane and Riesenfeld's subdivision):
    the n - 1 midpoints of the edges and the n - 2 vertices' (1, 6, 1) / 8
    averages, interleaved (2n - 3 points, a test evaluates both curves).
    """
    c = np.moveaxis(net, axis, -1)
    if c.shape[-1] < 4:
        return net
    edge = 0.5 * (c[..., :-1] + c[..., 1:])
    vert = (c[..., :-2] + 6.0 * c[..., 1:-1] + c[..., 2:]) / 8.0
    out = np.empty(c.shape[:-1] + (2 * c.shape[-1] - 3,))
    out[..., 0::2] = edge
    out[..., 1::2] = vert
    return np.moveaxis(out, -1, axis)


def _net_range(nets: np.ndarray, axes, refinements: int) -> tuple[np.ndarray, np.ndarray]:
    """Per leading index, the range of the surfaces of ``nets`` (their ``axes`` the spline's).

    The hull of each net after ``refinements`` halvings of its spacing, a
    batch of nets at a time (:data:`TIGHT_BATCH` refined values at most).
    """
    size = int(np.prod([(n << refinements) for n in nets.shape[1:]])) or 1
    step = max(1, TIGHT_BATCH // size)
    lo, hi = np.empty(len(nets)), np.empty(len(nets))
    for a in range(0, len(nets), step):
        part = nets[a:a + step]
        for _ in range(refinements):
            for axis in axes:
                part = _refined(part, axis)
        flat = part.reshape(len(part), -1)
        lo[a:a + step], hi[a:a + step] = flat.min(axis=1), flat.max(axis=1)
    return lo, hi


def offset_bounds(dq) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)``, each ``[Rz, Ry, Rx, 3]``: bounds of the offsets of a region's voxels.

    They bound the offsets any voxel of a region and its neighbours can have (x y z
    components), from the lattice alone.

    A voxel's offset is a convex combination of its region's 4^3 control
    points, so a voxel and its neighbours (in the next region at most) stay
    within the points [r - 1, r + 4] of each axis (a float32 slack added).
    At the domain's faces the halo is extrapolated (``2 U[0] - U[1]``):
    there the range is widened by itself, as :meth:`Reach.z_reach` does.
    """
    pad = ((1, 1), (1, 1), (1, 1), (0, 0))
    lo = window_reduce(np.pad(dq, pad, constant_values=np.inf), 6, np.minimum)
    hi = window_reduce(np.pad(dq, pad, constant_values=-np.inf), 6, np.maximum)
    edge = np.zeros(lo.shape[:3], bool)
    edge[[0, -1]] = edge[:, [0, -1]] = edge[:, :, [0, -1]] = True
    spread = np.where(edge[..., None], hi - lo, 0.0)
    return lo - spread - OFFSET_SLACK, hi + spread + OFFSET_SLACK
