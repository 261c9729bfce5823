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
    """
    out_dtype = np.float64 if scene.dtype == np.float64 else np.float32
    out = np.empty(box.shape, dtype=out_dtype)
    acc = np.zeros(box.shape + (2,), dtype=np.int64)
    (tx0, ty0, tz0), (tx1, ty1, tz1) = box.xyz()
    need = domain_box(scene, box)
    if not need.empty:
        values = sampler.box(need)
        (dx0, dy0, dz0), (dx1, dy1, dz1) = need.xyz()
        scene.contribute([scene.dq], (dx0, dy0, dz0), (dx1, dy1, dz1), 1, acc=acc, tzo=tz0,
                         tz_hi=tz1, window=((tx0, tx1), (ty0, ty1)), acc_xy=(tx0, ty0),
                         parallel=False, scratch=Scratch(), values=(values, dz0, (dx0, dy0)))
    shape_xyz = box.shape[::-1]
    pushforward.finalize(acc, scene.vmax, (0, 0, 0), shape_xyz, out, parallel=False,
                         background=scene.background)
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
    array) is dropped from a pickled copy and opened again where it is used.
    """

    def __init__(self, path, *, raw=None, volume_index=None, array=None):
        self.path = str(path)
        self.raw = raw
        self.volume_index = volume_index
        self._array = array

    @property
    def array(self):
        """The input's samples, sliceable ``[z, y, x]`` (opened on first use)."""
        if self._array is None:
            from ..io.lazy import open_volume_lazy

            _, self._array = open_volume_lazy(self.path, raw=self.raw,
                                              volume_index=self.volume_index)
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
        return {"path": self.path, "raw": self.raw, "volume_index": self.volume_index,
                "_array": None}


class WarpBlocks:
    """Everything a block task needs, and nothing that cannot be pickled.

    No locks and no arrays but the lattice's: the scene is rebuilt, once per
    process, where the tasks run.
    """

    def __init__(self, scene: Scene, source, placement: str, sampling: str, window: Box,
                 dtype):
        self.grid = scene.grid
        self.dq = scene.dq
        self.pad = tuple(int(p) for p in scene.pad)
        self.method = scene.method
        self.evaluator = scene.evaluator
        self.background = scene.background
        self.vmax = scene.vmax
        self.domain_dtype = scene.dtype
        self.source = source
        self.placement = placement
        self.sampling = sampling
        self.window = window  # the output's box of the target
        self.dtype = np.dtype(dtype)
        self._built = None

    def _scene(self):
        if self._built is None:
            from .pullback import BoxSampler

            sampler = BoxSampler(self.source, self.grid, self.placement, self.sampling,
                                 self.domain_dtype)
            scene = Scene(sampler, self.grid, self.dq, self.pad, method=self.method,
                          evaluator=self.evaluator, background=self.background,
                          domain_range=(-self.vmax, self.vmax))
            self._built = (scene, sampler)
        return self._built

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_built"] = None
        return state

    def output_block(self, out_box: Box) -> np.ndarray:
        """Output block ``out_box`` (z, y, x of the output), cast to the output's type."""
        from ..samples import cast_samples

        scene, sampler = self._scene()
        target = render_block(scene, sampler, out_box.shift(self.window.lo))
        return cast_samples(target, self.dtype, what="warped volume")

    def block_bytes(self, box: Box) -> int:
        """Memory a task of output block ``box`` holds at its peak (bytes, an upper bound)."""
        scene, sampler = self._scene()
        need = domain_box(scene, box.shift(self.window.lo))
        inputs = sampler.input_box(need).size if not need.empty else 0
        item = np.dtype(self.domain_dtype).itemsize
        return (box.size * (16 + item + self.dtype.itemsize)  # accumulators, target, cast
                + need.size * item  # the domain box's samples
                + inputs * (item + np.dtype(sampler.source.dtype).itemsize)  # its input box
                + 2 * scene.chunk_bytes)  # the deformation buffers

    def choose_blocks(self, budget: int, tasks_at_once: int) -> tuple[int, int, int]:
        """The largest cubic block (z, y, x) whose tasks, ``tasks_at_once`` of them, fit ``budget``.

        Larger blocks scatter fewer halo voxels twice; the output's size clips them.
        """
        shape = self.window.shape
        centre = [n // 2 for n in shape]
        for edge in (512, 384, 256, 192, 128, 96, 64, 48, 32, 24, 16):
            block = tuple(min(edge, n) for n in shape)
            lo = [max(0, min(c - b // 2, n - b)) for c, b, n in zip(centre, block, shape,
                                                                     strict=True)]
            box = Box(lo, [a + b for a, b in zip(lo, block, strict=True)])
            if self.block_bytes(box) * tasks_at_once <= budget:
                return block
        return tuple(min(16, n) for n in shape)


def write_block(job: WarpBlocks, out, box: Box) -> None:
    """Compute output block ``box`` and write it to ``out`` (a block output)."""
    out.write(box, job.output_block(box))


def warp_by_blocks(job: WarpBlocks, out, engine, *, memory: int | None = None):
    """Every block of ``out`` (a :class:`~volwarp_cli.io.blockwrite.BlockOutput`) on ``engine``.

    One task per block of the output's block grid; returns the tasks' stats.
    """
    import dask

    job_node = dask.delayed(job, pure=False)
    out_node = dask.delayed(out.writer(), pure=False)
    boxes = Box.from_shape(job.window.shape).blocks(out.chunks)
    tasks = [engine.block_delayed(write_block, f"warp-{'-'.join(map(str, b.lo))}", job_node,
                                  out_node, b, memory=memory)
             for b in boxes]
    stats = engine.run(tasks, label="warp blocks")
    out.mark_written(boxes)  # (every task succeeded: a failure raised)
    return stats
