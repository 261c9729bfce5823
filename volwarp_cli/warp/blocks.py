"""The one-shot warp, written once against a block of the output (:class:`WarpOperation`).

Any block of the target is computed on its own, by a task that holds only
what that block needs; the in-memory warp is the one-block case (the whole
output, cut into slabs over the calling threads), a warp too large for
memory (or ``--chunked``) runs many blocks on an engine
(:mod:`volwarp_cli.execute`). A block needs:

1. the domain voxels whose images can reach the block,
   :func:`volwarp_cli.regions.warp_input` (the lattice's convex hull, region
   by region, never the block's corners mapped back, which under-bounds a
   non-linear map), their planes narrowed to those the deformation itself
   can move into the block's (:func:`domain_box`);
2. their samples, gathered from the input region they read
   (:class:`~volwarp_cli.bspline.pullback.BoxSampler`: the capture runs inside the task, the
   domain is never held);
3. their pushforward clipped to the block, into accumulators of the block's
   own size, then finalized.

The sums are exact integers with a fixed-point scale from the whole input's
range (a global min/max pass, made before any block): each target voxel gets
the same sums, whichever block computes it and whichever other voxels that
block scatters, so the blocks put together equal the in-memory warp bit for
bit. A voxel near a block's side is scattered by each block it reaches, which
is the price of independent blocks (see :func:`block_work`): measured on a
256^3 warp with every control point of a 9^3 lattice moved, the whole output
on one thread is one block (no halo), on two threads two slabs along z
scatter 1.02 times the domain voxels (:func:`least_time_cut`).

Local updates (animations, ``--frames-to``) stay in memory: each frame's
update reuses the previous frame's accumulators, which blocks do not keep.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from .. import parallel
from ..box import Box
from ..bspline import pushforward
from ..bspline.reach import STREAM_PLANES, ring_planes
from ..bspline.scene import Scene, Scratch
from ..execute import Operation
from ..regions import warp_input

#: Output voxels below which a block is computed on one thread: cutting it for threads
#: (planning the cut, starting them) costs more than they save (measured: a 32^3 warp is
#: 4% faster on 2 threads, a 16^3 one slower)
PARALLEL_VOXELS = 1 << 14


def warp_block(scene: Scene, sampler, box: Box, into: np.ndarray | None = None,
               what: str = "warped volume", *, place=None, dtype=None) -> np.ndarray | None:
    """The target block ``box`` (z, y, x of the padded target) of ``scene``'s current lattice.

    ``sampler`` (a :class:`~volwarp_cli.bspline.pullback.BoxSampler`) gathers the domain voxels'
    samples; the scene's own domain is not used. Equal to the same block of
    :meth:`~volwarp_cli.bspline.scene.Scene.compute` bit for bit.

    ``into``: where the block goes (an array of its shape, a part's view of
    the whole output: no block of its own is made, then copied), its planes
    cast to its type as they are finished (:func:`~volwarp_cli.samples.cast_samples`,
    ``what`` naming it in a refusal); by default a new float array.
    ``place(z, planes)``: instead, where finished planes go as they are made
    (``planes`` of ``dtype``, the block's planes from ``z`` on, relative to
    ``box``; valid during the call only): no array of the block is held, and
    None is returned.

    The block is streamed: the domain box's z planes a few at a time, each
    slab gathered just before it is scattered into a ring of the block's
    target planes, and a plane finished as soon as no later slab can reach
    it. So a block may be tall (its accumulators are a ring of planes of its
    own columns and rows, not the whole block), and only its sides cost a
    halo of domain voxels scattered by two blocks.
    """
    from ..samples import cast_samples

    out_dtype = np.float64 if scene.dtype == np.float64 else np.float32
    if place is None:
        out = np.empty(box.shape, dtype=out_dtype) if into is None else into
        dtype = out.dtype
    else:
        out, dtype = None, np.dtype(dtype or out_dtype)
    (tx0, ty0, tz0), (_, _, tz1) = box.xyz()
    need = domain_box(scene, box)
    reach, chunk, planes = _stream(scene, box)
    acc = np.zeros((planes,) + box.shape[1:] + (2,), dtype=np.int64)
    # finished planes go straight into a whole array of the float type; else through a
    # ring's worth of float planes, cast and placed or copied
    direct = out is not None and dtype == out_dtype and out.flags.c_contiguous
    finished = None if direct else np.empty((planes,) + box.shape[1:], dtype=out_dtype)
    base = tz0  # target planes [base, ...) accumulate; those below are finished

    def flush(upto):
        nonlocal base
        while base < upto:
            s0 = base % planes
            k = min(upto - base, planes - s0)  # contiguous slots of the ring
            dest = out[base - tz0:base - tz0 + k] if direct else finished[:k]
            pushforward.finalize(acc[s0:s0 + k], scene.vmax, Box((0, 0, 0), (k, *box.shape[1:])),
                                 dest, parallel=False, background=scene.background, clear=True)
            if not direct:
                samples = cast_samples(dest, dtype, what=what)
                if place is not None:
                    place(base - tz0, samples)
                else:
                    out[base - tz0:base - tz0 + k] = samples
            base += k

    if not need.empty:
        (dx0, dy0, dz0), (dx1, dy1, dz1) = need.xyz()
        # the lowest target plane the domain planes from g on can reach
        floor = np.minimum.accumulate(reach.t_lo[dz0:dz1][::-1])[::-1]
        scratch = Scratch()
        for g0 in range(dz0, dz1, chunk):
            g1 = min(g0 + chunk, dz1)
            flush(min(max(int(floor[g0 - dz0]), base), tz1))
            voxels = Box((g0, dy0, dx0), (g1, dy1, dx1))
            scene.contribute([scene.dq], voxels, 1, acc=acc,
                             held=pushforward.HeldPlanes(base, min(base + planes, tz1), ring=True),
                             window=box, acc_xy=(tx0, ty0),
                             parallel=False, scratch=scratch,
                             values=(sampler.box(voxels), g0, (dx0, dy0)))
    flush(tz1)
    return out


def _stream(scene: Scene, box: Box):
    """``(reach, chunk, planes)`` of block ``box``'s stream (:func:`warp_block`).

    Each domain plane's target reach, the domain planes gathered and
    scattered a step, and the ring's target planes.
    """
    reach = scene.tight_plane_reach(scene.dq)
    chunk = max(1, int(STREAM_PLANES / float(scene.scale[2])))  # domain planes per step
    return reach, chunk, max(1, min(ring_planes(reach, chunk), box.shape[0]))


def domain_box(scene: Scene, box: Box, dq=None) -> Box:
    """The domain voxels (z, y, x) whose images can reach target block ``box``.

    Those inside the model only (on a subdivision grid the voxels around the
    input carry nothing). Their planes are those the deformation itself can
    move into the block's (:meth:`~volwarp_cli.bspline.scene.Scene.tight_plane_reach`):
    the control points' hull reaches far wider where they spread, so parts
    cut along z scattered many planes twice (a 256^3 warp with every point of
    a 9^3 lattice moved, two parts: 1.14 times the voxels cut along y, 1.16
    along z; now 1.02 along z). ``dq``: for that lattice (default the scene's).
    """
    dq = scene.dq if dq is None else dq
    need = warp_input(box, dq, scene.grid, scene.pad, scene._offset_bounds(dq))
    model = Box.from_xyz(scene.grid.data_lo, scene.grid.data_hi)
    g0, g1 = scene.tight_plane_reach(dq).domain_window(box.lo[0], box.hi[0])
    planes = Box((g0, need.lo[1], need.lo[2]), (max(g0, g1), need.hi[1], need.hi[2]))
    return need.intersect(model).intersect(planes)


def _makespan(work, threads: int) -> float:
    """The time ``threads`` threads take over parts of ``work``, dealt largest first."""
    loads = [0.0] * max(1, threads)
    for w in sorted(work, reverse=True):
        loads[loads.index(min(loads))] += w
    return max(loads)


def least_time_cut(scene: Scene, box: Box, threads: int, origin=(0, 0, 0)) -> list[Box]:
    """Output box ``box`` cut for ``threads`` threads (:meth:`WarpOperation.slabs`' cut).

    Of the cuts into ``threads`` or ``2 * threads`` parts of whole rows (z
    times y), the one whose longest thread (each part's scatter work, dealt
    largest first) is least. ``origin``: the output's corner in the target.
    """
    best = None
    for parts in (threads, 2 * threads):
        for nz in range(1, parts + 1):
            if parts % nz or nz > box.shape[0] or parts // nz > box.shape[1]:
                continue
            zc = parallel.cuts(box.lo[0], box.hi[0], nz)
            yc = parallel.cuts(box.lo[1], box.hi[1], parts // nz)
            cut = [Box((z0, y0, box.lo[2]), (z1, y1, box.hi[2]))
                   for z0, z1 in zip(zc[:-1], zc[1:], strict=True)
                   for y0, y1 in zip(yc[:-1], yc[1:], strict=True)]
            cost = _makespan([scene._work([scene.dq], domain_box(scene, b.shift(origin)))
                              for b in cut], threads)
            if best is None or cost < best[0]:
                best = (cost, cut)
    return best[1] if best is not None else [box]


def block_work(scene: Scene, blocks) -> float:
    """Domain voxels the blocks scatter, over the voxels the whole warp scatters once.

    1.0 when no voxel reaches two blocks; the extra is the blocks' halos.
    """
    whole = domain_box(scene, scene.target_box).size
    if whole == 0:
        return 1.0
    return sum(domain_box(scene, b).size for b in blocks) / whole


class SceneRecipe:
    """What rebuilds a :class:`~volwarp_cli.bspline.scene.Scene` where block tasks run: all of it but its samples.

    Picklable (the lattice and its planes' reach are its arrays): a task in
    another process builds its own scene from it, with the domain it has there.
    """

    def __init__(self, scene: Scene):
        self.grid = scene.grid
        self.dq = scene.dq
        # (its planes' reach, computed here once: each task's scene would compute it again)
        self.tight_planes = scene.tight_plane_reach(scene.dq)
        self.pad = tuple(int(p) for p in scene.pad)
        self.method = scene.method
        self.evaluator = scene.evaluator
        self.background = scene.background
        self.vmax = scene.vmax

    def build(self, domain) -> Scene:
        """The scene over ``domain`` (a sampler, or a stand-in with only a shape)."""
        scene = Scene(domain, self.grid, self.dq, self.pad, method=self.method,
                      evaluator=self.evaluator, background=self.background,
                      domain_range=(-self.vmax, self.vmax))
        scene.remember_tight_plane_reach(self.dq, self.tight_planes)
        return scene


class WarpOperation(Operation):
    """The one-shot warp of intensities as an operation of :mod:`volwarp_cli.execute`.

    Any block of the output is :func:`warp_block` of the final lattice over
    that block's box of the target, cast to the output's type: in memory the
    whole output is one block (cut into parts over the calling threads,
    :meth:`slabs`), by blocks each task computes its own; the same
    code, so the same bytes. Picklable (for tasks in other processes): the
    scene is rebuilt from its recipe where the tasks run, and the input is
    read box by box there.

    ``source``: the input's samples, sliceable (a :class:`~volwarp_cli.io.lazy.LazySource`), or
    None with ``sampler``, a capture file's stored domain
    (:class:`~.capture_file.StoredDomain`, reopened by path in another
    process). ``window``: the output's box of the target; ``target``: the
    output (:class:`~volwarp_cli.execute.Target`, dropped when pickled: the
    tasks write through the executor's writers); ``name``: the input's, in
    messages.
    """

    KEY = "warped"
    streams = True  # (compute_into: the planes are written as they are finished)

    def __init__(self, scene: Scene, source, placement: str, sampling: str, window: Box,
                 target, *, sampler=None, name: str = "input"):
        from ..geometry import Geometry

        self.recipe = SceneRecipe(scene)
        self.domain_dtype = scene.dtype
        self.source = source
        self.placement = placement
        self.sampling = sampling
        self.window = window  # the output's box of the target
        self.dtype = np.dtype(target.dtype)
        self.grid = Geometry.of(target.header)
        self.targets = {self.KEY: target}
        nx, ny, nz = self.grid.shape_xyz
        self.what = (f"the warp of {name} to {nx}x{ny}x{nz} voxels (deformation + "
                     f"{scene.method} pushforward)")
        self._sampler = sampler
        self._built = None
        self._lock = threading.Lock()
        self._cuts = {}

    def _scene(self):
        with self._lock:  # (one scene for the threads of an in-memory run)
            if self._built is None:
                from ..bspline.pullback import BoxSampler

                sampler = self._sampler if self._sampler is not None else BoxSampler(
                    self.source, self.recipe.grid, self.placement, self.sampling,
                    self.domain_dtype)
                self._built = (self.recipe.build(sampler), sampler)
        return self._built

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_built"] = state["_lock"] = None
        state["targets"] = {}
        state["_cuts"] = {}
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def output_block(self, out_box: Box, into: np.ndarray | None = None) -> np.ndarray:
        """Output block ``out_box`` (z, y, x of the output), cast to the output's type.

        ``into``: the array (of the block's shape and the output's type) it goes to.
        """
        scene, sampler = self._scene()
        if into is None:
            into = np.empty(out_box.shape, dtype=self.dtype)
        return warp_block(scene, sampler, out_box.shift(self.window.lo), into)

    def slabs(self, box: Box, threads: int) -> list[Box]:
        """``box`` cut for ``threads`` threads: parts of whole rows, cut along z and y.

        One thread takes the box whole (no halo at all), and so does a box of
        fewer than :data:`PARALLEL_VOXELS` (the cut's planning and the threads'
        start cost more than they save). Otherwise each part
        streams its planes through a ring of its own rows, and a domain voxel
        whose image reaches two parts is scattered by both (the halo, which
        grows with the parts' surface): of the cuts into ``threads`` or twice
        as many parts (z times y), the one whose estimated time is least,
        each part's scatter work (:func:`~volwarp_cli.bspline.work.scatter_work` of the domain
        voxels that reach it) dealt to the threads largest first
        (:func:`least_time_cut`). On a 256^3 warp with every point of a 9^3
        lattice moved, the parts scatter 1.02 times the domain voxels at 2
        threads, 1.34 at 16 and 2.0 at 64 (``benchmarks/bench_threads.py``).
        """
        if threads <= 1 or box.size < PARALLEL_VOXELS:
            return [box]
        key = (box, threads)
        if key not in self._cuts:  # (asked by memory() and compute() alike)
            self._cuts[key] = least_time_cut(self._scene()[0], box, threads, self.window.lo)
        return self._cuts[key]

    def compute(self, box: Box, *, threads: int) -> dict:
        """``{KEY: samples}`` of output block ``box``, over ``threads`` threads."""
        from ..progress import progress

        parts = self.slabs(box, threads)
        out = np.empty(box.shape, dtype=self.dtype)
        if len(parts) == 1:
            return {self.KEY: self.output_block(box, out)}
        with progress(len(parts), "warp") as bar:
            def task(part):  # (each part's planes straight into its view of the output)
                with parallel.use_threads(1):
                    self.output_block(part, out[part.shift([-v for v in box.lo]).slices])
                bar.advance()

            parallel.run_blocks(task, parts, threads)
        return {self.KEY: out}

    def compute_into(self, box: Box, *, threads: int, place: dict) -> None:
        """Output block ``box`` over ``threads`` threads, its planes placed as they are finished.

        ``place[KEY](box, samples)``: where a part's finished planes go (an
        output written by offset, :meth:`~volwarp_cli.io.blockwrite.BlockOutput.place`),
        from the thread that finished them. The parts are :meth:`compute`'s
        and their samples the same; no array of the whole is made.
        """
        from ..progress import progress

        put = place[self.KEY]
        scene, sampler = self._scene()

        def task(part):
            (z0, y0, x0), (_, y1, x1) = part.lo, part.hi

            def placed(z, planes):  # (z: the part's first finished plane, relative to it)
                put(Box((z0 + z, y0, x0), (z0 + z + len(planes), y1, x1)), planes)

            with parallel.use_threads(1):
                warp_block(scene, sampler, part.shift(self.window.lo), place=placed,
                           dtype=self.dtype)
            bar.advance()

        parts = self.slabs(box, threads)
        with progress(len(parts), "warp") as bar:
            parallel.run_blocks(task, parts, threads)

    def memory(self, box: Box) -> int:
        """The bytes computing ``box`` holds at its peak, over the threads in effect.

        The output's samples, and each thread's part's stream at its peak
        (:meth:`stream_bytes`; the parts write into the output).
        """
        threads = parallel.threads()
        parts = self.slabs(box, threads)
        return box.size * self.dtype.itemsize + min(threads, len(parts)) * max(
            self.stream_bytes(p) for p in parts)

    def block_bytes(self, box: Box) -> int:
        """Memory one thread computing output block ``box`` holds at its peak (an upper bound).

        The block's samples in the output's type (unless its task places its
        planes into the output as they are finished,
        :func:`~volwarp_cli.execute.places_blocks`) and its stream (:meth:`stream_bytes`).
        """
        from ..execute import places_blocks

        held = 0 if places_blocks(self) else box.size * self.dtype.itemsize
        return held + self.stream_bytes(box)

    def stream_bytes(self, box: Box) -> int:
        """What streaming output block ``box`` holds besides its output (see :func:`warp_block`).

        The ring of target planes (and its finished planes in float, for a
        strided view of the output, another type or an output written as
        computed, with their cast), one step's slab of the domain box's samples
        with the input they read, and its deformation buffers.
        """
        scene, sampler = self._scene()
        target = box.shift(self.window.lo)
        need = domain_box(scene, target)
        _, chunk, planes = _stream(scene, box)
        item = np.dtype(self.domain_dtype).itemsize
        slab = deformation = 0
        if not need.empty:
            z0 = need.lo[0]
            part = Box((z0, need.lo[1], need.lo[2]), (min(z0 + chunk, need.hi[0]), *need.hi[1:]))
            inputs = sampler.input_box(part).size
            slab = part.size * item + inputs * (item + np.dtype(sampler.source.dtype).itemsize)
            deformation = scene.deformation_bytes(part)
        plane = box.shape[1] * box.shape[2]
        floats = np.dtype(np.float64 if self.domain_dtype == np.float64 else np.float32)
        # finished planes in float where the part's view of the output is strided (a cut
        # along y) or of another type, and then rint's and the cast's copies of them
        finished = planes * plane * floats.itemsize
        if self.dtype != floats:
            finished += planes * plane * (floats.itemsize + self.dtype.itemsize)
        return planes * plane * 16 + finished + slab + deformation

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """Output blocks (z, y, x) for ``workers`` tasks of ``per_task`` bytes each.

        Slabs of whole rows (x) and the whole depth, cut along y into equal
        parts: a block streams its planes (depth costs no halo), its rows are
        contiguous in the output file (one write a plane) and its halo is on
        two sides only. The fewest parts that give each task two blocks (for
        balance) and fit; shallower where no slab of one row does.
        """
        shape = self.window.shape
        want = 2 * max(1, workers)
        for depth in (shape[0], (shape[0] + 1) // 2, (shape[0] + 3) // 4, 64, 32, 16, 8):
            for parts in range(min(want, shape[1]), shape[1] + 1):
                block = (min(depth, shape[0]), math.ceil(shape[1] / parts), shape[2])
                box = Box((0, 0, 0), block).shift([(n - b) // 2 for n, b in
                                                   zip(shape, block, strict=True)])
                if self.block_bytes(box) <= per_task:
                    return block
                if block[1] == 1:
                    break
        # none fits the task's share (its fixed deformation buffers alone may not): the
        # whole-depth slabs two a task, not thousands of one-row blocks that fit no better
        return (shape[0], math.ceil(shape[1] / min(want, shape[1])), shape[2])
