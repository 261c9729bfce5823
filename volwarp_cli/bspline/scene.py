"""The warp state: domain voxmap, control lattice, target accumulators (paper §5 main loop).

A :class:`Scene` holds the captured domain voxmap, the current control-point
offsets and the target accumulators. :meth:`Scene.set_lattice` moves control
points and updates only what they influence:

1. the regions touched by the moved points (``i - 3 <= a <= i`` per axis,
   taken as one bounding box of regions), grown by one domain voxel (the
   face centres of a voxel use its neighbours' entries);
2. subtract those voxels' old contributions from the accumulators;
3. add their new contributions and re-finalize only the touched target block.

Departures: the papers write zeros where the old contributions went (an
approximation); the accumulators here are exact fixed point, so after any
sequence of updates the target equals a full recomputation with the final
lattice bit for bit. Steps 2-3 have an exact alternative, the papers' zeroing
made exact: zero the target block the old and new images can reach and add
back, clipped to it, the new contributions of every domain voxel that can
reach it (the moved block and a thin shell of unchanged voxels around it,
mostly in still regions). One pass instead of two over the moved block; the
scene takes whichever of the two, or a full recomputation, costs least (the
sums are the same). And the deformation mapping array (offsets ``U`` of the
write map from the affine base map) is never held whole: it is evaluated
chunk by chunk along z into a small buffer with a one-voxel margin, for the
old lattice when subtracting and the new one when adding (both in one pass
over the block). The evaluators give every voxel the same value whatever block
it is computed in, so this is exact, and it saves 12 bytes per domain voxel
(200 MiB for a 256^3 domain). :meth:`Scene.render_once`, for a warp without
later updates, also never holds the target accumulators whole.

Only the domain voxels inside the input are the model: on a subdivision grid
(an integer oversample, see :mod:`.lattice`) those around it carry nothing, so
every pass leaves them out (the space they would cover is the background).
"""

from __future__ import annotations

import threading

import numpy as np

from ..errors import VolwarpError
from ..memory import ensure_fits_in_memory, memory_limit
from ..progress import log, timed
from . import basis, pushforward
from .lattice import Grid, affected_regions, window_reduce

#: Blocks are split over threads with at least this many domain voxels per thread.
PARALLEL_MIN_VOXELS = 1 << 18
#: Size of the deformation buffers of one z chunk (the array is never held whole).
CHUNK_BYTES = 32 << 20
#: Cost of a voxel outside the still regions (evaluated, boxed, scattered) relative
#: to one inside (the shortcut), for choosing between the ways of an update. Timed
#: on 128^3 at oversample 2 (9^3 and 13^3 lattices, one or three points moved, an
#: edge point, the papers' size; each way forced): a least-squares fit gives 2.9,
#: and 2.4 picks the fastest way in all but the papers' size, where it takes a full
#: pass of 9.1 ms over a rebuild of 7.9 ms (a tie in its count).
GENERAL_COST = 2.4
#: A split over threads is taken only if no thread gets more than this share of
#: the block's work (the planes whose boxes can straddle a cut are done by both).
SPLIT_MAX_SHARE = 0.8
#: Target z planes covered by one step of :meth:`Scene.render_once`'s stream.
STREAM_PLANES = 16
#: Slack for float32 deformation offsets in bounds derived from the lattice.
OFFSET_SLACK = 0.01


class Scratch:
    """Deformation buffers kept between updates (fresh pages are slow to fault in)."""

    def __init__(self):
        self.flat = np.zeros(0, dtype=np.float32)

    def arrays(self, shape, n: int) -> list[np.ndarray]:
        """``n`` float32 arrays of ``shape`` (..., z, y, x), views of one reused buffer.

        Not cleared: the evaluator writes every entry the scatter reads (the
        voxels outside still regions and their neighbours; ``fill_halo`` the
        domain's faces), and the rest, zeros or a previous use's finite
        offsets, is read only into ``fill_halo``'s unread edges and corners.
        Clearing even the faces would fault in every page of a buffer that
        the still shortcut barely touches (3.6% of a 256^3 warp command).
        """
        size = int(np.prod(shape))
        if self.flat.size < n * size:  # with room to grow: updates' blocks vary a little
            self.flat = np.zeros(n * size + n * size // 4, dtype=np.float32)
        return [self.flat[i * size:(i + 1) * size].reshape(shape) for i in range(n)]


def _to_evaluate(still, grid: Grid, lo, hi, elo, ehi):
    """The voxel ranges ``((x0, x1), (y0, y1))`` of block [lo, hi) whose offsets the scatter reads.

    Those of its voxels outside the still regions (in some pass) and their
    neighbours, within the evaluated extent [elo, ehi) (x, y); everything
    without ``still``; None when every voxel takes the still shortcut, which
    reads no offsets.
    """
    full = ((int(elo[0]), int(ehi[0])), (int(elo[1]), int(ehi[1])))
    if still is None:
        return full
    gx, gy, gz = grid.granularity
    dz = grid.domain_shape[2]
    cz = slice(max(lo[2] - 1, 0) // gz, min(hi[2], dz - 1) // gz + 1)
    moving = ~still[:, cz].all(axis=(0, 1))  # [Ry, Rx]: not still in some pass and plane
    if not moving.any():
        return None
    out = []
    for axis, g, profile in ((0, gx, moving.any(axis=0)), (1, gy, moving.any(axis=1))):
        idx = np.flatnonzero(profile)
        # general voxels lie within one voxel of a moving region; the scatter reads
        # their neighbours too
        a = max(int(idx[0]) * g - 2, int(elo[axis]))
        b = min((int(idx[-1]) + 1) * g + 2, int(ehi[axis]))
        out.append((a, max(a, b)))
    return tuple(out)


class Scene:
    """A captured domain and its write map into a padded target grid.

    Parameters
    ----------
    domain : (Dz, Dy, Dx) float32 or float64, or a :class:`~.pullback.Sampler`
        The captured (pulled back) density; a sampler's planes are gathered
        as :meth:`render_once` streams them (never whole), and in full the
        first time anything else needs them.
    grid : lattice.Grid
    dq : (Cz, Cy, Cx, 3) float64
        Control-point offsets from the uniform lattice (input voxels, x y z).
    pad : (x, y, z) ints
        Target padding per side; target index = input index + pad.
    method : {"box", "nearest"}
    evaluator : {"separable", "table"}
    background : float
        Value of the space around the model (uncovered target voxels).
    domain_range : (min, max) bounding the domain's samples (default: the domain's
        own, found in two passes, which gathers a deferred domain whole): sets
        the fixed-point scale of the sums, so scenes meant to agree bit for bit
        must get the same (a capture's: the input's range).

    update : {None, "subtract", "rebuild", "full"}
        How :meth:`set_lattice` updates rendered accumulators: None (default)
        takes the cheapest by a work estimate; tests and benchmarks force one.
    """

    UPDATES = ("subtract", "rebuild", "full")

    def __init__(self, domain, grid: Grid, dq, pad, *, method: str = "box",
                 evaluator: str = "separable", background: float = 0.0, domain_range=None,
                 update: str | None = None):
        if update not in (None, *self.UPDATES):
            raise VolwarpError(f"unknown update {update!r} (use subtract, rebuild or full)")
        self.update = update
        if method not in pushforward.METHODS:
            raise VolwarpError(f"unknown pushforward {method!r} (use box or nearest)")
        if evaluator not in basis.EVALUATORS:
            raise VolwarpError(f"unknown evaluator {evaluator!r} (use separable or table)")
        if tuple(domain.shape[::-1]) != grid.domain_shape:
            raise VolwarpError("domain voxmap does not match the lattice")
        deferred = hasattr(domain, "planes")  # a Sampler
        self.sampler = domain if deferred else None
        self._domain = None if deferred else domain
        self.dtype = np.dtype(domain.dtype)
        self.grid = grid
        self.dq = np.array(dq, dtype=np.float64)
        self.pad = np.array([int(p) for p in np.broadcast_to(pad, (3,))])
        if np.any(self.pad < 0):
            raise VolwarpError(f"pad must not be negative, got {self.pad.tolist()}")
        self.method = method
        self.evaluator = evaluator
        self.background = float(background)
        if not np.isfinite(self.background):
            raise VolwarpError(f"the background must be a finite number, got {background}")
        size = int(np.prod(domain.shape))
        # max |v| without a whole-volume temporary
        if domain_range is None and size:
            domain_range = (float(self.domain.min()), float(self.domain.max()))
        vmax = max(-domain_range[0], domain_range[1]) if size else 0.0
        self.vmax = vmax if vmax > 0 else 1.0
        self.offset = grid.affine_offset(self.pad)
        self.scale = grid.scale
        self.acc = self.out = None
        self.last_touched = None
        self.scratch = Scratch()
        self._lattice_facts = {}
        self._facts_lock = threading.Lock()  # render_once's threads share the cache

    @property
    def domain(self) -> np.ndarray:
        """The domain voxmap (a deferred one gathered in full on first use)."""
        if self._domain is None:
            with timed("capture (pullback)"):
                self._domain, _ = self.sampler.whole()
            self.sampler = None
        return self._domain

    @property
    def target_shape(self) -> tuple[int, int, int]:
        """Target size (x, y, z)."""
        return tuple(int(i + 2 * p) for i, p in zip(self.grid.input_shape, self.pad, strict=False))

    def _contribute(self, dqs, vlo, vhi, sign, acc=None, tzo=0, parallel=True, scratch=None,
                    bounds=False, tz_hi=None, ring=False, window=None, values=None):
        """Add (``sign`` +1) or remove (-1) the contributions of domain voxels [vlo, vhi).

        ``dqs``: one lattice, or two (old, new) whose contributions are
        removed and added in one pass (``sign`` -1).
        The deformation offsets are evaluated on the fly, chunk by chunk along
        z, into a small buffer covering the voxels and their neighbours (the
        evaluators give a voxel the same value whatever block it is computed
        in, so removing a contribution recomputes exactly what was added).
        ``acc`` (default the scene's) holds target z planes from ``tzo`` on
        (up to ``tz_hi``; with ``ring``, plane z in ``acc[z % len(acc)]``);
        ``window`` ``((x0, x1), (y0, y1))`` also leaves out target voxels
        outside those columns and rows. ``values``: ``(array, z0)``, the
        samples of domain planes from ``z0`` on (those of [vlo, vhi) at
        least), instead of the domain's.
        ``parallel`` lets large blocks use the threads in effect. ``scratch`` (a
        :class:`Scratch`, default the scene's) holds the deformation buffers.
        Returns the touched target bounding box with ``bounds``, else None.
        """
        acc = self.acc if acc is None else acc
        scratch = self.scratch if scratch is None else scratch
        grid = self.grid
        dshape = np.array(grid.domain_shape)
        # only the domain voxels inside the input are the model (a subdivision grid's
        # others, around it, carry nothing: the space there is the background)
        vlo = np.maximum(np.asarray(vlo, dtype=np.int64), grid.data_lo)
        vhi = np.minimum(np.asarray(vhi, dtype=np.int64), grid.data_hi)
        if np.any(vhi <= vlo):
            return None
        elo = np.maximum(vlo - 1, 0)  # the voxels and their neighbours
        ehi = np.minimum(vhi + 1, dshape)
        nx = int(ehi[0] - elo[0])
        ny = int(ehi[1] - elo[1])
        cz = int(max(4, CHUNK_BYTES // ((nx + 2) * (ny + 2) * 12 * len(dqs))))
        evaluate = basis.EVALUATORS[self.evaluator]
        still = self._still(dqs)
        if values is None:
            samples, planes = self.domain, None
        else:
            samples, planes = values[0], (values[1], grid.domain_shape[2])
        boxes = []
        for z0 in range(int(vlo[2]), int(vhi[2]), cz):
            z1 = min(z0 + cz, int(vhi[2]))
            e0, e1 = max(z0 - 1, 0), min(z1 + 1, int(dshape[2]))
            # planar buffers [3, z, y, x] (the scatter reads each component's rows as
            # vectors), seen by the evaluator and fill_halo as [z, y, x, 3]
            planar = scratch.arrays((3, e1 - e0 + 2, ny + 2, nx + 2), len(dqs))
            ubs = [np.moveaxis(buf, 0, -1) for buf in planar]
            origin = (int(elo[0]), int(elo[1]), e0)
            lo = (int(vlo[0]), int(vlo[1]), z0)
            # voxels in still regions take the scatter's shortcut, which reads no
            # offsets: only the rest (and their neighbours) are evaluated
            sub = _to_evaluate(still, grid, lo, (int(vhi[0]), int(vhi[1]), z1), elo, ehi)
            if sub is not None:
                for dq, ub in zip(dqs, ubs, strict=True):
                    evaluate(dq, grid, ub[1:-1, 1:-1, 1:-1], x=sub[0], y=sub[1], z=(e0, e1),
                             origin=origin, parallel=parallel)
                faces = [(0, 0)] if e0 == 0 else []
                if e1 == dshape[2]:
                    faces.append((0, 1))
                for axis_xyz, axis in ((0, 2), (1, 1)):
                    if elo[axis_xyz] == 0:
                        faces.append((axis, 0))
                    if ehi[axis_xyz] == dshape[axis_xyz]:
                        faces.append((axis, 1))
                for ub in ubs:
                    pushforward.fill_halo(ub, faces)
            hi = (int(vhi[0]), int(vhi[1]), z1)
            parts = self._parts(np.stack(dqs), lo, hi, tzo, tz_hi, still) if parallel and not ring else None
            bb = pushforward.scatter(planar[0], samples, self.offset, self.scale, lo, hi,
                                     sign, self.vmax, self.method, acc, parts=parts,
                                     origin=origin, tzo=tzo, tz_hi=tz_hi, ring=ring,
                                     u_new=planar[1] if len(planar) > 1 else None,
                                     bounds=bounds, still=still, window=window,
                                     granularity=grid.granularity, planes=planes)
            if bb is not None:
                boxes.append(bb)
        if not boxes:
            return None
        return (np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0))

    def _z_reach(self, dq) -> tuple[float, float]:
        """``(below, above)``: domain voxel g's box lies in target z ``[A(g) - below, A(g) + above]``.

        ``A(g) = offset + scale * g`` is the affine base map. The bound comes
        from the lattice alone: a voxel's offset is a convex combination of
        control-point offsets, and its box (face centres, halo extrapolation)
        stays within that range widened by the range itself.
        """
        dz = dq[..., 2]
        top, bottom = float(dz.max()), float(dz.min())
        spread = top - bottom
        half = 0.5 * float(self.scale[2])
        slack = 0.01  # float32 deformation arrays
        return half - bottom + spread + slack, half + top + spread + slack

    def _parts(self, dq, lo, hi, tzo=0, tz_hi=None, still=None):
        """``[(t0, t1, g0, g1), ...]``: block [lo, hi)'s work split by target planes over threads
        (for :func:`pushforward.scatter`).

        Target planes [t0, t1) cover the planes held, [tzo, tz_hi); domain z
        range [g0, g1) holds every voxel that can reach them. The cuts fall
        where the cumulative work (:meth:`_work`'s measure, ``still``: the
        scatter's still regions, or None) reaches k/n of the whole, mapped to
        the target plane its domain plane's centre goes to. Voxels whose boxes
        straddle a cut are scattered by both parts: with a long reach (a
        lattice moved far in z) that can be most of the block, so the count
        of parts is the one (up to the threads in effect) with the shortest
        longest part, and None (one thread) unless it beats one part by
        ``1 / SPLIT_MAX_SHARE``. None for small blocks.
        """
        from .. import parallel

        lo = np.asarray(lo)
        hi = np.asarray(hi)
        size = int(np.prod(hi - lo))
        n_max = min(parallel.threads(), size // max(PARALLEL_MIN_VOXELS, 1))
        if n_max < 2:
            return None
        z0 = int(lo[2])
        # general voxels cost more: balance by work, not planes
        work = self._plane_work(still, lo, hi) if still is not None else np.ones(hi[2] - z0)
        cum = np.concatenate([[0.0], np.cumsum(work)])  # work of planes [lo, lo + i)
        total = cum[-1]
        if total <= 0:
            return None
        tz_end = self.target_shape[2] if tz_hi is None else tz_hi
        s, o = float(self.scale[2]), float(self.offset[2])
        best, best_time = None, total * SPLIT_MAX_SHARE
        for n in range(n_max, 1, -1):
            cuts = []
            for k in range(1, n):
                mid = z0 + int(np.searchsorted(cum, total * k / n)) - 0.5
                # the target plane whose centre the domain plane's centre maps to
                cuts.append(int(np.floor(o + s * mid + 0.5)))
            cuts = sorted({c for c in cuts if tzo < c < tz_end})
            if not cuts:
                continue
            edges = [int(tzo), *cuts, int(tz_end)]
            parts, longest = [], 0.0
            for t0, t1 in zip(edges[:-1], edges[1:], strict=True):
                g0, g1 = self._domain_z_window(dq, t0, t1)
                g0, g1 = max(g0, z0), min(g1, int(hi[2]))
                parts.append((t0, t1, g0, g1))
                if g1 > g0:
                    longest = max(longest, cum[g1 - z0] - cum[g0 - z0])
            if longest < best_time:
                best, best_time = parts, longest
        return best

    def _target_z_reach(self, dq, g0: int, g1: int) -> tuple[int, int]:
        """Target z planes [t0, t1) that domain z planes [g0, g1) can reach."""
        below, above = self._z_reach(dq)
        s, o = float(self.scale[2]), float(self.offset[2])
        t0 = int(np.floor(o + s * g0 - below - 0.5))
        t1 = int(np.ceil(o + s * (g1 - 1) + above + 0.5)) + 1
        return t0, t1

    def _domain_z_window(self, dq, t0: int, t1: int) -> tuple[int, int]:
        """Domain z range [g0, g1) holding every voxel that can reach target z planes [t0, t1)."""
        below, above = self._z_reach(dq)
        s, o = float(self.scale[2]), float(self.offset[2])
        dz = self.grid.domain_shape[2]
        g0 = int(np.floor((t0 - 0.5 - o - above) / s))
        g1 = int(np.ceil((t1 - 0.5 - o + below) / s)) + 1
        return max(g0, 0), min(g1, dz)

    def render(self) -> np.ndarray:
        """Full computation with the current lattice; returns the target ``[z, y, x]``."""
        tshape = self.target_shape[::-1]
        out_dtype = np.float64 if self.dtype == np.float64 else np.float32
        nbytes = int(np.prod(tshape)) * (16 + np.dtype(out_dtype).itemsize) + 2 * CHUNK_BYTES
        ensure_fits_in_memory(nbytes, "the warp's target accumulators")
        if self.acc is None:
            self.acc = np.zeros(tshape + (2,), dtype=np.int64)
            self.out = np.empty(tshape, dtype=out_dtype)
        else:
            self.acc.fill(0)
        with timed(f"deformation + {self.method} pushforward"):
            self._contribute([self.dq], (0, 0, 0), self.grid.domain_shape, 1)
        with timed("finalize"):
            pushforward.finalize(self.acc, self.vmax, (0, 0, 0), self.target_shape, self.out,
                                 background=self.background)
        self.last_touched = ((0, 0, 0), self.target_shape)
        return self.out

    def render_once(self, sink=None, block_planes: int | None = None) -> np.ndarray | None:
        """The same target as :meth:`render`, without keeping accumulators for later updates.

        The target is cut along z into blocks, one per thread (see
        :mod:`volwarp_cli.parallel`), each streamed on its own: domain z
        chunks in order, scattered into a rolling accumulator of a few target
        planes; a plane is finalized and dropped as soon as no later chunk can
        reach it (see :meth:`_z_reach`). Contributions are integer sums
        clipped to the planes held, so every voxel gets exactly the sums of a
        full :meth:`render`, whatever the blocks, and the whole-target
        accumulators (16 bytes per voxel) are never allocated. Later
        :meth:`set_lattice` calls start from scratch. A deferred domain (a
        sampler) is gathered chunk by chunk just before its chunk is
        scattered, never whole: its gather runs in the block's thread (the
        domain planes near a cut are gathered by both blocks).

        Each block also scatters the domain planes reaching past its ends, so
        blocks are at least a step's reach long; the thread count shrinks to
        keep them so, and to keep the blocks' rings within the memory budget.
        ``block_planes`` forces blocks of that many target planes (tests).

        ``sink(z0, z1, planes)``, if given, receives the finished target planes
        [z0, z1) (``[z1 - z0, y, x]``, a buffer reused after the call) from the
        blocks' threads, each range once, in no particular order; the whole
        target is then never held and None is returned.
        """
        from .. import parallel

        tx, ty, tz = self.target_shape
        out_dtype = np.float64 if self.dtype == np.float64 else np.float32
        s = float(self.scale[2])
        chunk = max(1, int(STREAM_PLANES / s))  # domain planes per step
        r_lo, r_hi = self._target_z_reach(self.dq, 0, chunk)
        planes = r_hi - r_lo + 2  # target planes one step can reach (+ rounding)
        itemsize = np.dtype(out_dtype).itemsize
        ring = planes * tx * ty * 16 + 2 * CHUNK_BYTES  # one block's accumulators and buffers
        # target planes held at a time: the whole target, or each block's finished
        # planes and their converted copy
        held = (lambda n: 4 * planes * n) if sink is not None else (lambda n: tz)
        budget = memory_limit()
        if block_planes is not None:
            edges = list(range(0, tz, max(1, int(block_planes)))) + [tz]
            workers = parallel.threads()
        else:
            workers = max(1, min(parallel.threads(), tz // max(planes, 1)))
            while workers > 1 and tx * ty * held(workers) * itemsize + workers * ring > budget:
                workers -= 1
            edges = parallel.cuts(0, tz, workers)
        workers = min(workers, len(edges) - 1)
        ensure_fits_in_memory(tx * ty * held(workers) * itemsize + workers * ring,
                              "the warped target")
        out = None if sink is not None else np.empty((tz, ty, tx), dtype=out_dtype)
        dshape = self.grid.domain_shape
        sampler = self.sampler

        def stream(t_lo, t_hi):
            # a ring of target planes: plane z in acc[z % planes]; planes [base, ...)
            # are still accumulating, those below are finalized
            acc = np.zeros((planes, ty, tx, 2), dtype=np.int64)
            scratch = Scratch()
            base = t_lo
            gathered = None if sampler is None else np.empty((chunk,) + sampler.shape[1:],
                                                             dtype=sampler.dtype)
            done = None if sink is None else np.empty((planes, ty, tx), dtype=out_dtype)

            def flush(upto):
                nonlocal base
                while base < upto:
                    s0 = base % planes
                    k = min(upto - base, planes - s0)  # contiguous slots
                    dest = out[base:base + k] if sink is None else done[:k]
                    pushforward.finalize(acc[s0:s0 + k], self.vmax, (0, 0, 0), (tx, ty, k),
                                         dest, parallel=False,
                                         background=self.background, clear=True)
                    if sink is not None:
                        sink(base, base + k, dest)
                    base += k

            g_lo, g_hi = self._domain_z_window(self.dq, t_lo, t_hi)
            for g0 in range(g_lo, g_hi, chunk):
                g1 = min(g0 + chunk, g_hi)
                r_lo, r_hi = self._target_z_reach(self.dq, g0, g1)
                flush(min(max(r_lo, base), t_hi))  # no later chunk reaches below r_lo
                if min(r_hi, t_hi) - base > planes:  # pragma: no cover - cannot happen
                    raise AssertionError("rolling accumulator too small")
                values = None
                if sampler is not None:
                    values = (sampler.planes(g0, g1, out=gathered[:g1 - g0]), g0)
                self._contribute([self.dq], (0, 0, g0), (dshape[0], dshape[1], g1), 1, acc=acc,
                                 tzo=base, tz_hi=min(base + planes, t_hi), ring=True,
                                 parallel=False, scratch=scratch, values=values)
            flush(t_hi)

        with timed(f"deformation + {self.method} pushforward + finalize "
                   f"({len(edges) - 1} blocks, {workers} threads)"):
            parallel.run_blocks(lambda i: stream(edges[i], edges[i + 1]), range(len(edges) - 1),
                                workers)
        self.acc = None
        self.out = out
        self.last_touched = ((0, 0, 0), self.target_shape)
        return out

    def result(self) -> np.ndarray:
        """The target for the current lattice (computed in full on first use)."""
        if self.out is None:
            return self.render()
        return self.out

    def set_lattice(self, dq) -> None:
        """Move control points to offsets ``dq``, updating the target locally when rendered."""
        dq = np.asarray(dq, dtype=np.float64)
        if dq.shape != self.dq.shape:
            raise VolwarpError("lattice shape changed")
        if self.acc is None:  # nothing rendered, or rendered once: no local update
            if np.any(dq != self.dq):
                self.out = None
            self.dq = dq.copy()
            return
        moved = np.argwhere(np.any(dq != self.dq, axis=-1))  # (k, j, i)
        if moved.size == 0:
            self.last_touched = None
            return
        rlo, rhi = affected_regions(moved[:, ::-1], self.grid)
        g = np.array(self.grid.granularity)
        dshape = np.array(self.grid.domain_shape)
        vlo = np.maximum(rlo * g - 1, 0)  # the regions' voxels and their neighbours
        vhi = np.minimum(rhi * g + 1, dshape)
        block = self._rebuild_block(dq, vlo, vhi)
        if block is None:  # neither image reaches the target: nothing changes there
            self.dq = dq.copy()
            self.last_touched = None
            return
        work = {"subtract": self._work([self.dq, dq], vlo, vhi),
                "rebuild": self._work([dq], *block[2:]),
                "full": self._work([dq], (0, 0, 0), dshape)}
        how = self.update or min(("full", "rebuild", "subtract"), key=work.get)  # ties: full
        log.debug("update of regions %s..%s by %s (work: %s)", rlo.tolist(), rhi.tolist(),
                  how, {k: round(v) for k, v in work.items()})
        if how == "full":
            self.dq = dq.copy()
            self.render()
            return
        if how == "rebuild":
            (t0x, t0y, t0z), (t1x, t1y, t1z), dlo, dhi = block
            part = self.acc[t0z:t1z]  # the block's planes, a view
            part[:, t0y:t1y, t0x:t1x] = 0
            self._contribute([dq], dlo, dhi, 1, acc=part, tzo=t0z, tz_hi=t1z,
                             window=((t0x, t1x), (t0y, t1y)))
            tlo, thi = block[0], block[1]
        else:
            bb = self._contribute([self.dq, dq], vlo, vhi, -1, bounds=True)
            if bb is None:
                self.dq = dq.copy()
                self.last_touched = None
                return
            tlo, thi = bb
        self.dq = dq.copy()
        pushforward.finalize(self.acc, self.vmax, tlo, thi, self.out,
                             background=self.background)
        self.last_touched = (tuple(int(v) for v in tlo), tuple(int(v) for v in thi))

    def _facts(self, dq) -> dict:
        """A dict of values derived from lattice ``dq`` alone (still regions, offset
        bounds), kept for the last few lattices: an update needs both the old
        lattice's and the new one's, and the old one was the previous update's new."""
        key = np.asarray(dq).tobytes()
        with self._facts_lock:
            facts = self._lattice_facts.pop(key, None)
            if facts is None:
                facts = {}
                while len(self._lattice_facts) >= 3:
                    del self._lattice_facts[next(iter(self._lattice_facts))]
            self._lattice_facts[key] = facts  # the most recent last
        return facts

    def _still(self, dqs) -> np.ndarray | None:
        """:func:`pushforward.still_regions` of ``dqs`` (None for the nearest method, which
        has no still shortcut), from cached per-lattice masks."""
        if self.method != "box":
            return None
        masks = []
        for dq in dqs:
            facts = self._facts(dq)
            if "still" not in facts:
                facts["still"] = pushforward.still_mask(dq)
            masks.append(facts["still"])
        still = np.stack(masks)
        return np.ascontiguousarray(still, dtype=np.uint8) if still.any() else None

    def _offset_bounds(self, dq) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)``, each ``[Rz, Ry, Rx, 3]``: bounds of the offsets any voxel of a region
        and its neighbours can have (x y z components), from the lattice alone.

        A voxel's offset is a convex combination of its region's 4^3 control
        points, so a voxel and its neighbours (in the next region at most) stay
        within the points [r - 1, r + 4] of each axis (a float32 slack added).
        At the domain's faces the halo is extrapolated (``2 U[0] - U[1]``):
        there the range is widened by itself, as :meth:`_z_reach` does.
        """
        facts = self._facts(dq)
        if "bounds" not in facts:
            facts["bounds"] = self._compute_offset_bounds(dq)
        return facts["bounds"]

    def _compute_offset_bounds(self, dq) -> tuple[np.ndarray, np.ndarray]:
        pad = ((1, 1), (1, 1), (1, 1), (0, 0))
        lo = window_reduce(np.pad(dq, pad, constant_values=np.inf), 6, np.minimum)
        hi = window_reduce(np.pad(dq, pad, constant_values=-np.inf), 6, np.maximum)
        edge = np.zeros(lo.shape[:3], bool)
        edge[[0, -1]] = edge[:, [0, -1]] = edge[:, :, [0, -1]] = True
        spread = np.where(edge[..., None], hi - lo, 0.0)
        return lo - spread - OFFSET_SLACK, hi + spread + OFFSET_SLACK

    def _rebuild_block(self, dq, vlo, vhi):
        """``(tlo, thi, dlo, dhi)`` (x y z) for an update of domain voxels [vlo, vhi) to ``dq``.

        Target block [tlo, thi): every target voxel the old or new image of
        those voxels can reach; domain block [dlo, dhi): every voxel whose new
        image can reach that target block. Both from :meth:`_offset_bounds`,
        region by region. None when the images miss the target.
        """
        grid = self.grid
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
                a, b = self._region_range(axis, wlo[axis], whi[axis])
                inside &= along(a < b, axis)
                a_img = self.offset[axis] + self.scale[axis] * along(a, axis)
                b_img = self.offset[axis] + self.scale[axis] * (along(b, axis) - 1)
                t0.append(np.floor(a_img + lo_u[..., axis] - half[axis] - 0.5))
                t1.append(np.ceil(b_img + hi_u[..., axis] + half[axis] + 0.5) + 1)
            return t0, t1, inside

        t_lo, t_hi = np.full(3, np.inf), np.full(3, -np.inf)
        new_bounds = self._offset_bounds(dq)
        for bounds in (self._offset_bounds(self.dq), new_bounds):  # (cached)
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
            a, b = self._region_range(axis, 0, grid.domain_shape[axis])
            s, o = self.scale[axis], self.offset[axis]
            first = np.floor((tlo[axis] - 0.5 - o - half[axis] - hi_u[..., axis]) / s)
            last = np.ceil((thi[axis] - 0.5 - o + half[axis] - lo_u[..., axis]) / s) + 1
            first = np.maximum(first, along(a, axis))
            last = np.minimum(last, along(b, axis))
            inside &= first < last
            d_lo.append(first)
            d_hi.append(last)
        if not inside.any():  # pragma: no cover - the moved voxels' images reach it
            return None
        dlo = np.array([int(v[inside].min()) for v in d_lo])
        dhi = np.array([int(v[inside].max()) for v in d_hi])
        return tlo, thi, dlo, dhi

    def _region_range(self, axis: int, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        """Per region along ``axis`` (0 = x): its voxels within [lo, hi), as [a, b)
        (empty where b <= a)."""
        g = self.grid.granularity[axis]
        r = np.arange(self.grid.regions[axis])
        return np.maximum(r * g, lo), np.minimum((r + 1) * g, hi)

    def _region_voxels(self, vlo, vhi) -> list[np.ndarray]:
        """Per axis (x, y, z): how many voxels of each region lie in [vlo, vhi)."""
        counts = []
        for axis in range(3):  # (the voxels the pushforward scatters: those inside the input)
            a, b = self._region_range(axis, max(int(vlo[axis]), self.grid.data_lo[axis]),
                                      min(int(vhi[axis]), self.grid.data_hi[axis]))
            counts.append(np.clip(b - a, 0, None))
        return counts

    def _plane_work(self, still, vlo, vhi) -> np.ndarray:
        """:meth:`_work`'s measure of each domain z plane of block [vlo, vhi), all passes."""
        cx, cy, _ = self._region_voxels(vlo, vhi)
        cost = np.where(still, 1.0, GENERAL_COST).sum(axis=0)  # [Rz, Ry, Rx]
        per_region_plane = np.einsum("kji,j,i->k", cost, cy, cx)
        planes = np.arange(int(vlo[2]), int(vhi[2]))
        inside = (planes >= self.grid.data_lo[2]) & (planes < self.grid.data_hi[2])
        return np.where(inside, per_region_plane[planes // self.grid.granularity[2]], 0.0)

    def _work(self, dqs, vlo, vhi) -> float:
        """Scatter work over domain voxels [vlo, vhi) (x, y, z), one pass per lattice of ``dqs``.

        In still-voxel units: a voxel in a region still in a pass costs 1, any
        other ``GENERAL_COST``.
        """
        counts = self._region_voxels(vlo, vhi)
        n = np.einsum("k,j,i->kji", counts[2], counts[1], counts[0])  # [Rz, Ry, Rx]
        total = float(n.sum()) * len(dqs)
        still = self._still(dqs)
        if still is None:
            return total * GENERAL_COST
        k = float((still * n).sum())
        return k + (total - k) * GENERAL_COST

    def map_points(self, param) -> np.ndarray:
        """Target indices (x, y, z) of spline parameters (N, 3) under the current map."""
        from .handles import map_params
        return map_params(self.dq, self.grid, param) + self.pad
