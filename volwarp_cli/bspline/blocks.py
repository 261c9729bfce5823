"""The warp by output blocks: each block of the target from the domain voxels that reach it.

For a warp too large for memory (or ``--chunked``), the target is cut into
blocks and each is computed on its own, by a task that holds only what that
block needs:

1. the domain voxels whose images can reach the block,
   :func:`volwarp_cli.regions.warp_input` (the lattice's convex hull, region
   by region, never the block's corners mapped back, which under-bounds a
   non-linear map);
2. their samples, gathered from the input region they read
   (:class:`.pullback.BoxSampler`: the capture runs inside the task, the
   domain is never held);
3. their pushforward clipped to the block, into accumulators of the block's
   own size, then finalized.

The sums are exact integers with a fixed-point scale from the whole input's
range (a global min/max pass, made before any block): each target voxel gets
the same sums, whichever block computes it and whichever other voxels that
block scatters, so the blocks put together equal the in-memory warp bit for
bit. A voxel near a block's side is scattered by each block it reaches, which
is the price of independent blocks (see :func:`block_work`).

Local updates (animations, ``--frames-to``) stay in memory: each frame's
update reuses the previous frame's accumulators, which blocks do not keep.
"""

from __future__ import annotations

import math

import numpy as np

from ..box import Box
from ..regions import warp_input
from . import pushforward
from .scene import Scene, Scratch


def render_block(scene: Scene, sampler, box: Box) -> np.ndarray:
    """The target block ``box`` (z, y, x of the padded target) of ``scene``'s current lattice.

    ``sampler`` (a :class:`.pullback.BoxSampler`) gathers the domain voxels'
    samples; the scene's own domain is not used. Equal to the same block of
    :meth:`.scene.Scene.render` bit for bit.

    The block is streamed as the in-memory one-shot render streams the whole
    target (:mod:`.stream`): the domain box's z planes a few at a time, each
    slab gathered just before it is scattered into a ring of the block's
    target planes, and a plane finished as soon as no later slab can reach
    it. So a block may be tall (its accumulators are a ring of planes of its
    own columns and rows, not the whole block), and only its sides cost a
    halo of domain voxels scattered by two blocks.
    """
    from .stream import STREAM_PLANES, _ring_planes

    out_dtype = np.float64 if scene.dtype == np.float64 else np.float32
    out = np.empty(box.shape, dtype=out_dtype)
    (tx0, ty0, tz0), (_, _, tz1) = box.xyz()
    need = domain_box(scene, box)
    reach = scene.reach.planes(scene._offset_bounds(scene.dq))
    chunk = max(1, int(STREAM_PLANES / float(scene.scale[2])))  # domain planes per step
    planes = max(1, min(_ring_planes(reach, chunk), box.shape[0]))
    acc = np.zeros((planes,) + box.shape[1:] + (2,), dtype=np.int64)
    base = tz0  # target planes [base, ...) accumulate; those below are in out

    def flush(upto):
        nonlocal base
        while base < upto:
            s0 = base % planes
            k = min(upto - base, planes - s0)  # contiguous slots of the ring
            pushforward.finalize(acc[s0:s0 + k], scene.vmax, Box((0, 0, 0), (k, *box.shape[1:])),
                                 out[base - tz0:base - tz0 + k], parallel=False,
                                 background=scene.background, clear=True)
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


def domain_box(scene: Scene, box: Box) -> Box:
    """The domain voxels (z, y, x) whose images can reach target block ``box``.

    Those inside the model only (on a subdivision grid the voxels around the
    input carry nothing).
    """
    need = warp_input(box, scene.dq, scene.grid, scene.pad)
    model = Box.from_xyz(scene.grid.data_lo, scene.grid.data_hi)
    return need.intersect(model)


def target_box(scene: Scene) -> Box:
    """The whole padded target as a Box (z, y, x)."""
    return Box.from_shape(scene.target_shape[::-1])


def block_work(scene: Scene, blocks) -> float:
    """Domain voxels the blocks scatter, over the voxels the whole warp scatters once.

    1.0 when no voxel reaches two blocks; the extra is the blocks' halos.
    """
    whole = domain_box(scene, target_box(scene)).size
    if whole == 0:
        return 1.0
    return sum(domain_box(scene, b).size for b in blocks) / whole


# -- the out-of-core warp: blocks as tasks ------------------------------------------------
class LazySource:
    """An input opened on demand: picklable, so a worker process opens it itself.

    ``path`` and the reader's options; the opened array (a memory map, a zarr
    array) is dropped from a pickled copy and opened again where it is used,
    with the permission the run that made it had to read a detached header's
    data file outside its folder (``--allow-outside-data``: a worker process
    or thread has its own run scope, :mod:`volwarp_cli.runscope`).
    """

    def __init__(self, path, *, raw=None, volume_index=None, array=None, dicom=None):
        from ..runscope import run_files

        self.path = str(path)
        self.raw = raw
        self.volume_index = volume_index
        self.dicom = dicom
        self.allow_outside_data = run_files().allow_outside_data
        self._array = array

    @property
    def array(self):
        """The input's samples, sliceable ``[z, y, x]`` (opened on first use)."""
        if self._array is None:
            from ..io.lazy import open_volume_lazy
            from ..runscope import run_scope

            with run_scope() as files:  # (this thread's own: the permission it was given)
                files.allow_outside_data = self.allow_outside_data
                _, self._array = open_volume_lazy(self.path, raw=self.raw,
                                                  volume_index=self.volume_index,
                                                  dicom=self.dicom)
        return self._array

    @property
    def shape(self):
        """The input's shape (z, y, x)."""
        return tuple(self.array.shape)

    @property
    def dtype(self) -> np.dtype:
        """The input's sample type."""
        return np.dtype(self.array.dtype)

    def __getitem__(self, key):
        return self.array[key]

    def __getstate__(self):
        # an array that carries all it reads (a DICOM stack's frames) goes along: reopening
        # by path would scan the folder's headers again in every process
        keep = self._array if getattr(self._array, "portable", False) else None
        return {"path": self.path, "raw": self.raw, "volume_index": self.volume_index,
                "dicom": self.dicom, "allow_outside_data": self.allow_outside_data,
                "_array": keep}


class SceneRecipe:
    """What rebuilds a :class:`~.scene.Scene` where block tasks run: all of it but its samples.

    Picklable (the lattice is its only array): a task in another process
    builds its own scene from it, with the domain it has there.
    """

    def __init__(self, scene: Scene):
        self.grid = scene.grid
        self.dq = scene.dq
        self.pad = tuple(int(p) for p in scene.pad)
        self.method = scene.method
        self.evaluator = scene.evaluator
        self.background = scene.background
        self.vmax = scene.vmax

    def build(self, domain) -> Scene:
        """The scene over ``domain`` (a sampler, or a stand-in with only a shape)."""
        return Scene(domain, self.grid, self.dq, self.pad, method=self.method,
                     evaluator=self.evaluator, background=self.background,
                     domain_range=(-self.vmax, self.vmax))


class WarpBlocks:
    """Everything a block task needs, and nothing that cannot be pickled.

    No locks and no arrays but the lattice's: the scene is rebuilt, once per
    process, where the tasks run.
    """

    def __init__(self, scene: Scene, source, placement: str, sampling: str, window: Box,
                 dtype, sampler=None):
        self.recipe = SceneRecipe(scene)
        self.domain_dtype = scene.dtype
        self.source = source
        self.placement = placement
        self.sampling = sampling
        self.window = window  # the output's box of the target
        self.dtype = np.dtype(dtype)
        # given: in this process only, dropped when pickled, unless it is ``portable``
        # (a capture file's stored domain: its path travels, the worker reads the file)
        self._sampler = sampler
        self._built = None

    def _scene(self):
        if self._built is None:
            from .pullback import BoxSampler

            sampler = self._sampler if self._sampler is not None else BoxSampler(
                self.source, self.recipe.grid, self.placement, self.sampling,
                self.domain_dtype)
            scene = self.recipe.build(sampler)
            self._built = (scene, sampler)
        return self._built

    def __getstate__(self):
        portable = getattr(self._sampler, "portable", False)
        if self.source is None and not portable:
            raise TypeError("a warp job of a held domain runs in this process only")
        state = dict(self.__dict__)
        state["_built"] = None
        if not portable:
            state["_sampler"] = None
        return state

    def output_block(self, out_box: Box) -> np.ndarray:
        """Output block ``out_box`` (z, y, x of the output), cast to the output's type."""
        from ..samples import cast_samples

        scene, sampler = self._scene()
        target = render_block(scene, sampler, out_box.shift(self.window.lo))
        return cast_samples(target, self.dtype, what="warped volume")

    def block_bytes(self, box: Box) -> int:
        """Memory a task of output block ``box`` holds at its peak (bytes, an upper bound).

        The ring of target planes, the block's target and its cast, one slab
        of the domain box's samples with the input they read, and the
        deformation buffers (see :func:`render_block`).
        """
        from .stream import STREAM_PLANES, _ring_planes

        scene, sampler = self._scene()
        target = box.shift(self.window.lo)
        need = domain_box(scene, target)
        reach = scene.reach.planes(scene._offset_bounds(scene.dq))
        chunk = max(1, int(STREAM_PLANES / float(scene.scale[2])))
        planes = max(1, min(_ring_planes(reach, chunk), box.shape[0]))
        item = np.dtype(self.domain_dtype).itemsize
        slab = 0
        if not need.empty:
            z0 = need.lo[0]
            part = Box((z0, need.lo[1], need.lo[2]), (min(z0 + chunk, need.hi[0]), *need.hi[1:]))
            inputs = sampler.input_box(part).size
            slab = part.size * item + inputs * (item + np.dtype(sampler.source.dtype).itemsize)
        return (planes * box.shape[1] * box.shape[2] * 16
                + box.size * (item + self.dtype.itemsize) + slab + 2 * scene.chunk_bytes)

    def choose_blocks(self, budget: int, tasks_at_once: int) -> tuple[int, int, int]:
        """Output blocks (z, y, x) for ``tasks_at_once`` tasks within ``budget`` bytes.

        Slabs of whole rows (x) and the whole depth, cut along y into equal
        parts: a block streams its planes (depth costs no halo), its rows are
        contiguous in the output file (one write a plane) and its halo is on
        two sides only. The fewest parts that give each task two blocks (for
        balance) and fit; shallower where no slab of one row does.
        """
        shape = self.window.shape
        want = 2 * max(1, tasks_at_once)
        for depth in (shape[0], (shape[0] + 1) // 2, (shape[0] + 3) // 4, 64, 32, 16, 8):
            for parts in range(min(want, shape[1]), shape[1] + 1):
                block = (min(depth, shape[0]), math.ceil(shape[1] / parts), shape[2])
                box = Box((0, 0, 0), block).shift([(n - b) // 2 for n, b in
                                                   zip(shape, block, strict=True)])
                if self.block_bytes(box) * tasks_at_once <= budget:
                    return block
                if block[1] == 1:
                    break
        return (min(8, shape[0]), 1, shape[2])


def write_block(job: WarpBlocks, out, box: Box) -> None:
    """Compute output block ``box`` and write it to ``out`` (a block output)."""
    out.write(box, job.output_block(box))


def warp_by_tiles(job: WarpBlocks, out, *, threads: int | None = None) -> int:
    """Every block of ``out`` on this process's threads (no Dask): the in-memory warp's way.

    Whole-depth slabs stream their planes through a ring of their own
    rows (:func:`render_block`): less memory, and more of it in
    cache, than one ring of whole target planes per thread. Returns the
    number of blocks.
    """
    from .. import parallel
    from ..progress import progress

    boxes = out.blocks()
    writer = out.writer()
    n = parallel.threads() if threads is None else threads
    with progress(len(boxes), "warp") as bar:
        def task(box):
            with parallel.use_threads(1):
                writer.write(box, job.output_block(box))
            bar.advance()

        parallel.run_blocks(task, boxes, n)
    out.mark_written(boxes)
    return len(boxes)


def warp_by_blocks(job: WarpBlocks, out, engine, *, memory: int | None = None):
    """Every block of ``out`` (a :class:`~volwarp_cli.io.blockwrite.BlockOutput`) on ``engine``.

    One task per block of the output's block grid; returns the tasks' stats.
    """
    import dask

    job_node = dask.delayed(job, pure=False)
    out_node = dask.delayed(out.writer(), pure=False)
    boxes = out.blocks()
    tasks = [engine.block_delayed(write_block, f"warp-{'-'.join(map(str, b.lo))}", job_node,
                                  out_node, b, memory=memory)
             for b in boxes]
    stats = engine.run(tasks, label="warp blocks")
    out.mark_written(boxes)  # (every task succeeded: a failure raised)
    return stats
