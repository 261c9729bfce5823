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
(200 MiB for a 256^3 domain). A warp without later updates (the one-shot
warp, :func:`~volwarp_cli.warp.blocks.warp_block`) never holds the target accumulators whole.

Only the domain voxels inside the input are the model: on a subdivision grid
(an integer oversample, see :mod:`.lattice`) those around it carry nothing, so
every pass leaves them out (the space they would cover is the background).
"""

from __future__ import annotations

import threading

import numpy as np

from ..box import Box
from ..errors import VolwarpError
from ..memory import block_bytes, ensure_fits_in_memory
from ..progress import log, timed
from . import basis, pushforward, work
from .lattice import Lattice, affected_regions
from .reach import PlaneReach, Reach, offset_bounds

#: Largest size of the deformation buffers of one z chunk (the array is never held whole);
#: smaller when the memory budget's share of one thread is (:func:`.memory.block_bytes`).
CHUNK_BYTES = 32 << 20


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


def _to_evaluate(still, grid: Lattice, block: Box, ext: Box):
    """The voxel ranges ``((x0, x1), (y0, y1))`` of ``block`` whose offsets the scatter reads.

    Those of its voxels outside the still regions (in some pass) and their
    neighbours, within the evaluated extent ``ext`` (both boxes of the domain,
    z y x); everything without ``still``; None when every voxel takes the
    still shortcut, which reads no offsets.
    """
    (_, ey0, ex0), (_, ey1, ex1) = ext.lo, ext.hi
    full = ((ex0, ex1), (ey0, ey1))
    if still is None:
        return full
    gx, gy, gz = grid.granularity
    dz = grid.domain_shape[2]
    cz = slice(max(block.lo[0] - 1, 0) // gz, min(block.hi[0], dz - 1) // gz + 1)
    moving = ~still[:, cz].all(axis=(0, 1))  # [Ry, Rx]: not still in some pass and plane
    if not moving.any():
        return None
    out = []
    for (e0, e1), g, profile in ((full[0], gx, moving.any(axis=0)),
                                 (full[1], gy, moving.any(axis=1))):
        idx = np.flatnonzero(profile)
        # general voxels lie within one voxel of a moving region; the scatter reads
        # their neighbours too
        a = max(int(idx[0]) * g - 2, e0)
        b = min((int(idx[-1]) + 1) * g + 2, e1)
        out.append((a, max(a, b)))
    return tuple(out)


class Scene:
    """A captured domain and its write map into a padded target grid.

    Parameters
    ----------
    domain : (Dz, Dy, Dx) float32 or float64, or a :class:`~.pullback.Sampler`
        The captured (pulled back) density; a sampler's planes are gathered
        box by box as :func:`~volwarp_cli.warp.blocks.warp_block` streams them (never whole),
        and in full the first time anything else needs them.
    grid : lattice.Lattice
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
        How :meth:`set_lattice` updates computed accumulators: None (default)
        takes the cheapest by a work estimate; tests and benchmarks force one.
    """

    def __init__(self, domain, grid: Lattice, dq, pad, *, method: str = "box",
                 evaluator: str = "separable", background: float = 0.0, domain_range=None,
                 update: str | None = None):
        if update not in (None, *work.UPDATES):
            raise VolwarpError(f"unknown update {update!r} (use subtract, rebuild or full)")
        self.update = update
        if method not in pushforward.METHODS:
            raise VolwarpError(f"unknown pushforward {method!r} (use box or nearest)")
        if evaluator not in basis.EVALUATORS:
            raise VolwarpError(f"unknown evaluator {evaluator!r} (use separable or table)")
        if tuple(domain.shape[::-1]) != grid.domain_shape:
            raise VolwarpError("domain voxmap does not match the lattice")
        deferred = not isinstance(domain, np.ndarray)  # a sampler (:mod:`.pullback`)
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
        self.reach = Reach(grid, self.offset, self.scale, self.target_shape)
        self._domain_box = Box.from_xyz((0, 0, 0), grid.domain_shape)
        self._data_box = Box.from_xyz(tuple(grid.data_lo), tuple(grid.data_hi))
        #: the whole target, a Box (z, y, x)
        self.target_box = Box.from_xyz((0, 0, 0), self.target_shape)
        self.acc = self.out = None
        #: the target block the last computation or update recomputed (a Box), or None
        self.last_touched = None
        #: bytes of one chunk's deformation buffers: the cap, or the budget's share of a thread
        self.chunk_bytes = min(CHUNK_BYTES, block_bytes())
        self.scratch = Scratch()
        self._lattice_facts = {}
        self._facts_lock = threading.Lock()  # (threads sharing a scene share the cache)
        self._tight_lock = threading.Lock()

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

    def deformation_bytes(self, block: Box, n: int = 1) -> int:
        """At most the bytes of :meth:`contribute`'s deformation buffers for domain ``block``.

        ``block``: a Box (z, y, x) of the domain; ``n``: the lattices (two for an
        update). Its chunk's planes and their neighbours, each plane's voxels
        with a ring of halo, float32 components; twice over with the room
        :class:`Scratch` grows by, for a buffer outgrown while the new one is made.
        """
        _, ny, nx = block.shape
        plane = (ny + 4) * (nx + 4) * 12 * n
        chunk = min(block.shape[0] * plane, max(4 * plane, self.chunk_bytes))
        return (chunk + 4 * plane) * 9 // 4

    def contribute(self, dqs, block: Box, sign, acc=None, held=None, parallel=True,
                   scratch=None, bounds=False, window=None, values=None, acc_xy=(0, 0)):
        """Add (``sign`` +1) or remove (-1) the contributions of the domain voxels ``block``.

        ``block``: a :class:`~volwarp_cli.box.Box` (z, y, x) of the domain.

        ``dqs``: one lattice, or two (old, new) whose contributions are
        removed and added in one pass (``sign`` -1).
        The deformation offsets are evaluated on the fly, chunk by chunk along
        z, into a small buffer covering the voxels and their neighbours (the
        evaluators give a voxel the same value whatever block it is computed
        in, so removing a contribution recomputes exactly what was added).
        ``acc`` (default the scene's) holds the target z planes ``held`` (a
        :class:`.pushforward.HeldPlanes`, default: ``len(acc)`` from plane 0);
        ``window`` ``((x0, x1), (y0, y1))`` also leaves out target voxels
        outside those columns and rows. ``values``: ``(array, z0)``, the
        samples of domain planes from ``z0`` on (those of ``block`` at
        least), instead of the domain's; ``(array, z0, (x0, y0))``: of the
        columns from x0 and rows from y0 of those planes only (an out-of-core
        block's). ``acc_xy``: the target column and row of ``acc[:, 0, 0]``.
        ``parallel`` lets large blocks use the threads in effect. ``scratch`` (a
        :class:`Scratch`, default the scene's) holds the deformation buffers.
        Returns the touched target block (a Box) with ``bounds``, else None.
        """
        acc = self.acc if acc is None else acc
        scratch = self.scratch if scratch is None else scratch
        grid = self.grid
        dshape = grid.domain_shape
        # only the domain voxels inside the input are the model (a subdivision grid's
        # others, around it, carry nothing: the space there is the background)
        block = block.intersect(self._data_box)
        if block.empty:
            return None
        ext = block.grow(1, within=self._domain_box)  # and their neighbours
        _, ny, nx = ext.shape
        cz = int(max(4, self.chunk_bytes // ((nx + 2) * (ny + 2) * 12 * len(dqs))))
        evaluate = basis.EVALUATORS[self.evaluator]
        still = self._still(dqs)
        if values is None:
            samples, planes = self.domain, None
        else:
            samples, planes = values[0], (values[1], grid.domain_shape[2])
        values_xy = (None if values is None or len(values) < 3
                     else (*values[2], grid.domain_shape[0], grid.domain_shape[1]))
        if window is not None:
            window = pushforward.target_clip(window, acc_xy, acc.shape[1:3], 0, 0)
        held = pushforward.HeldPlanes() if held is None else held
        parts_reach = self._plane_reach(dqs) if parallel and not held.ring else None
        boxes = []
        for z0 in range(block.lo[0], block.hi[0], cz):
            chunk = pushforward.with_planes(block, z0, min(z0 + cz, block.hi[0]))
            z1 = chunk.hi[0]
            e0, e1 = max(z0 - 1, 0), min(z1 + 1, dshape[2])
            # planar buffers [3, z, y, x] (the scatter reads each component's rows as
            # vectors), seen by the evaluator and fill_halo as [z, y, x, 3]
            planar = scratch.arrays((3, e1 - e0 + 2, ny + 2, nx + 2), len(dqs))
            ubs = [np.moveaxis(buf, 0, -1) for buf in planar]
            origin = (ext.lo[2], ext.lo[1], e0)
            # voxels in still regions take the scatter's shortcut, which reads no
            # offsets: only the rest (and their neighbours) are evaluated
            sub = _to_evaluate(still, grid, chunk, ext)
            if sub is not None:
                for dq, ub in zip(dqs, ubs, strict=True):
                    evaluate(dq, grid, ub[1:-1, 1:-1, 1:-1], x=sub[0], y=sub[1], z=(e0, e1),
                             origin=origin, parallel=parallel)
                faces = pushforward.domain_faces(e0, e1, ext, dshape)
                for ub in ubs:
                    pushforward.fill_halo(ub, faces)
            parts = (work.thread_parts(self.reach, parts_reach, chunk, held.lo, held.hi, still)
                     if parts_reach is not None else None)
            bb = pushforward.scatter(planar[0], samples, self.offset, self.scale, chunk,
                                     sign, self.vmax, self.method, acc, parts=parts,
                                     origin=origin, held=held,
                                     u_new=planar[1] if len(planar) > 1 else None,
                                     bounds=bounds, still=still, window=window,
                                     granularity=grid.granularity, planes=planes,
                                     values_xy=values_xy, acc_xy=acc_xy)
            if bb is not None:
                boxes.append(bb)
        if not boxes:
            return None
        touched = boxes[0]
        for bb in boxes[1:]:
            touched = touched.union_hull(bb)
        return touched

    def compute(self) -> np.ndarray:
        """Full computation with the current lattice; returns the target ``[z, y, x]``."""
        tshape = self.target_shape[::-1]
        out_dtype = np.float64 if self.dtype == np.float64 else np.float32
        nbytes = int(np.prod(tshape)) * (16 + np.dtype(out_dtype).itemsize) + 2 * self.chunk_bytes
        ensure_fits_in_memory(nbytes, "the warp's target accumulators")
        if self.acc is None:
            self.acc = np.zeros(tshape + (2,), dtype=np.int64)
            self.out = np.empty(tshape, dtype=out_dtype)
        else:
            self.acc.fill(0)
        with timed(f"deformation + {self.method} pushforward"):
            self.contribute([self.dq], self._domain_box, 1)
        with timed("finalize"):
            pushforward.finalize(self.acc, self.vmax, self.target_box, self.out,
                                 background=self.background)
        self.last_touched = self.target_box
        return self.out

    def result(self) -> np.ndarray:
        """The target for the current lattice (computed in full on first use)."""
        if self.out is None:
            return self.compute()
        return self.out

    def set_lattice(self, dq) -> None:
        """Move control points to offsets ``dq``, updating the target locally once computed."""
        dq = np.asarray(dq, dtype=np.float64)
        if dq.shape != self.dq.shape:
            raise VolwarpError("lattice shape changed")
        if self.acc is None:  # nothing computed with accumulators kept: no local update
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
        # the regions' voxels and their neighbours
        voxels = Box.from_xyz((rlo * g - 1).tolist(), (rhi * g + 1).tolist()).intersect(
            self._domain_box)
        block = self.reach.rebuild_block(self._offset_bounds(self.dq), self._offset_bounds(dq),
                                         voxels)
        if block is None:  # neither image reaches the target: nothing changes there
            self.dq = dq.copy()
            self.last_touched = None
            return
        cost = {"subtract": self._work([self.dq, dq], voxels),
                "rebuild": self._work([dq], block.domain),
                "full": self._work([dq], self._domain_box)}
        how = work.choose_update(cost, self.update)
        log.debug("update of regions %s..%s by %s (work: %s)", rlo.tolist(), rhi.tolist(),
                  how, {k: round(v) for k, v in cost.items()})
        if how == "full":
            self.dq = dq.copy()
            self.compute()
            return
        if how == "rebuild":
            target = block.target  # zeroed, then rebuilt
            self.acc[target.slices] = 0
            t0z, t1z = target.lo[0], target.hi[0]
            self.contribute([dq], block.domain, 1, acc=self.acc[t0z:t1z],
                            held=pushforward.HeldPlanes(t0z, t1z), window=target)
        else:
            target = self.contribute([self.dq, dq], voxels, -1, bounds=True)
            if target is None:
                self.dq = dq.copy()
                self.last_touched = None
                return
        self.dq = dq.copy()
        pushforward.finalize(self.acc, self.vmax, target, self.out, background=self.background)
        self.last_touched = target

    def _facts(self, dq) -> dict:
        """A dict of values derived from lattice ``dq`` alone (still regions, offset bounds).

        Kept for the last few lattices: an update needs both the old lattice's and
        the new one's, and the old one was the previous update's new.
        """
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
        """:func:`pushforward.still_regions` of ``dqs``, from cached per-lattice masks.

        None for the nearest method, which has no still shortcut.
        """
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
        """``(lo, hi)``, each ``[Rz, Ry, Rx, 3]``: bounds of the offsets of a region's voxels.

        They bound the offsets any voxel of a region and its neighbours can have (x y z
        components), from the lattice alone.

        :func:`.reach.offset_bounds`, cached per lattice.
        """
        facts = self._facts(dq)
        if "bounds" not in facts:
            facts["bounds"] = offset_bounds(dq)
        return facts["bounds"]

    def _plane_reach(self, dqs):
        """:meth:`.reach.Reach.planes` of the lattices ``dqs`` together (cached per lattice).

        Per domain z plane, the target planes its voxels can reach under any of them.
        """
        reaches = []
        for dq in dqs:
            facts = self._facts(dq)
            if "planes" not in facts:
                facts["planes"] = self.reach.planes(self._offset_bounds(dq))
            reaches.append(facts["planes"])
        if len(reaches) == 1:
            return reaches[0]
        return PlaneReach(np.minimum.reduce([r.t_lo for r in reaches]),
                          np.maximum.reduce([r.t_hi for r in reaches]))

    def tight_plane_reach(self, dq):
        """:meth:`.reach.Reach.tight_planes` of lattice ``dq`` (cached per lattice).

        The warp's blocks and threads' parts, the label warp's shares and
        rings: a part's domain window is its target planes' reach, which the
        control points' hull widened by the whole drag again.
        """
        facts = self._facts(dq)
        with self._tight_lock:  # (the shares' threads ask at once: one computes it)
            if "tight planes" not in facts:
                facts["tight planes"] = self.reach.tight_planes(dq, self._plane_reach([dq]))
        return facts["tight planes"]

    def remember_tight_plane_reach(self, dq, planes) -> None:
        """Take ``planes`` as :meth:`tight_plane_reach` of ``dq`` (computed by another process).

        A block task's scene is rebuilt from a recipe
        (:class:`~volwarp_cli.warp.blocks.SceneRecipe`) that carries it, so the
        tasks do not each compute it again.
        """
        facts = self._facts(dq)
        with self._tight_lock:
            facts["tight planes"] = planes

    def _work(self, dqs, block: Box) -> float:
        """:func:`.work.scatter_work` of the domain voxels ``block``, one pass per lattice of ``dqs``."""
        return work.scatter_work(self.reach, self._still(dqs), len(dqs), block)

    def map_points(self, param) -> np.ndarray:
        """Target indices (x, y, z) of spline parameters (N, 3) under the current map."""
        from .handles import map_params
        return map_params(self.dq, self.grid, param) + self.pad
