"""Label maps warped by blocks: slabs of target planes, each the in-memory label passes.

The in-memory label warp (:func:`.labels.warp_labels`) already cuts the target
into z ranges, one per thread, each running the background's and every
label's pass over its own planes (:func:`.labels.label_passes`); the result
does not depend on the cut. By blocks, each task is one such slab of whole
target planes, computed from the lattice and the label map read box by box
(reopened by path in a worker process). It writes the output's part of its
slab and returns its totals: each label's predicted weight and output
voxels, and its voxel of largest weight with the label that voxel ended with.
The report, and ``--preserve-labels``' fix-up of the labels that would
vanish (a few voxels changed in the output before it is committed), come
from those totals, so the output and the report are the in-memory ones, bit
for bit. Target planes outside a cropped output are computed too (the
report counts the whole target, as in memory) but written nowhere.
"""

from __future__ import annotations

import threading

import numpy as np

from ..box import Box
from ..bspline.capture import NoSamples
from ..bspline.scene import Scene
from ..errors import OutOfMemoryError
from ..execute import Blocks, Reduction
from .blocks import SceneRecipe
from .labels import (
    _Q,
    _bounding_boxes,
    _counts,
    _stronger,
    label_passes,
    stream_bytes,
)

_BUILD = threading.Lock()  # one scene per process, even when two threads ask at once


class LabelBlocks:
    """A label warp's job for block tasks: picklable, its scene rebuilt where it runs.

    ``source``: the label map, sliceable ``[z, y, x]`` (a
    :class:`~volwarp_cli.io.lazy.LazySource`); ``labels``, ``boxes``: its labels but
    ``background`` and their input bounding boxes
    (:func:`bounding_boxes_by_blocks`); ``window``: the output's box of the
    target; ``background``: the label where nothing lands (the map's most
    frequent border label, :func:`~volwarp_cli.border.border_label`).
    """

    def __init__(self, scene: Scene, source, labels, boxes, window: Box, dtype, *,
                 preserve: bool = False, background: int = 0):
        self.recipe = SceneRecipe(scene)  # (the scene's background 0: unused by labels)
        self.background = int(background)
        self.source = source
        self.labels = [int(v) for v in labels]
        self.boxes = list(boxes)
        self.window = window
        self.dtype = np.dtype(dtype)
        self.preserve = bool(preserve)
        self._scene = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_scene"] = None
        return state

    def scene(self) -> Scene:
        """The warp's scene (built once per process)."""
        with _BUILD:
            if self._scene is None:
                grid = self.recipe.grid
                self._scene = self.recipe.build(NoSamples(tuple(grid.domain_shape[::-1])))
        return self._scene

    @property
    def target_shape(self) -> tuple[int, int, int]:
        """The whole target's shape (z, y, x)."""
        tx, ty, tz = self.scene().target_shape
        return tz, ty, tx

    def slab(self, t_lo: int, t_hi: int):
        """Target planes ``[t_lo, t_hi)``: ``(labels, predicted, peak, counts, peak_labels)``.

        ``labels``: the slab's output labels; ``predicted``, ``peak``:
        :func:`.labels.label_passes`'; ``counts``: output voxels per label;
        ``peak_labels``: the label each peak voxel ended with.
        """
        scene = self.scene()
        _, ty, tx = self.target_shape
        best_w = np.full((t_hi - t_lo, ty, tx), _Q, dtype=np.int64)
        best_l = np.full((t_hi - t_lo, ty, tx), self.background, dtype=self.dtype)
        predicted, peak = label_passes(scene, scene.dq, self.source, self.labels, self.boxes,
                                       t_lo, t_hi, best_w, best_l, preserve=self.preserve,
                                       z_base=t_lo, background=self.background)
        del best_w
        peak_labels = {L: int(best_l[at[0] - t_lo, at[1], at[2]])
                       for L, (_, at) in peak.items() if at is not None}
        return (best_l, predicted, peak, _counts(best_l, self.labels, self.background),
                peak_labels)

    def slab_bytes(self, depth: int) -> int:
        """Memory a task of ``depth`` target planes holds at its peak (an upper bound).

        The slab's weights and labels, and a label pass's buffers
        (:func:`.labels.stream_bytes`).
        """
        scene = self.scene()
        _, ty, tx = self.target_shape
        return (depth * ty * tx * (8 + self.dtype.itemsize)
                + stream_bytes(scene, scene.dq, self.source.dtype))

    def choose_depth(self, budget: int, tasks_at_once: int) -> int:
        """Slab depth for ``tasks_at_once`` tasks within ``budget`` bytes (two slabs a task)."""
        tz = self.target_shape[0]
        want = max(1, -(-tz // (2 * max(1, tasks_at_once))))
        depth = want
        while depth > 1 and self.slab_bytes(depth) * tasks_at_once > budget:
            depth = max(1, depth // 2)
        if self.slab_bytes(depth) * tasks_at_once > budget:
            from ..memory import human_bytes

            raise OutOfMemoryError(
                f"a label warp's slab of one target plane needs "
                f"{human_bytes(self.slab_bytes(1))} a task, {tasks_at_once} at once: more "
                f"than the {human_bytes(budget)} the memory budget leaves (raise "
                "--memory-limit, or run fewer tasks: --workers)")
        return depth


def bounding_boxes_by_blocks(source, run, depth: int, background: int = 0):
    """:func:`.labels._bounding_boxes` of a sliceable map read in slabs of ``depth`` planes.

    ``run(task, items)``: who runs the slabs (an engine's ``map``). Returns
    ``(labels, voxel counts, boxes)`` of the labels but ``background``: the
    same as the whole map's.
    """
    import functools

    nz = source.shape[0]
    task = functools.partial(_slab_boxes, source=source, background=int(background))
    found: dict[int, list] = {}
    for z0, labels, nvox, boxes in run(task, [(z, min(z + depth, nz))
                                             for z in range(0, nz, depth)]):
        for L, n, box in zip(labels, nvox, boxes, strict=True):
            box = box.shift((z0, 0, 0))
            if L in found:
                found[L][0] += n
                found[L][1] = found[L][1].union_hull(box)
            else:
                found[L] = [n, box]
    labels = sorted(found)
    return labels, [found[L][0] for L in labels], [found[L][1] for L in labels]


def _slab_boxes(zs, source, background=0):
    z0, z1 = zs
    labels, nvox, boxes, _ = _bounding_boxes(np.asarray(source[z0:z1]), background)
    return z0, labels, nvox, boxes


def label_slab_task(job: LabelBlocks, writer, t_lo: int, t_hi: int, out_boxes) -> tuple:
    """One slab's task: write its part of the output, return its totals."""
    best_l, predicted, peak, counts, peak_labels = job.slab(t_lo, t_hi)
    for box in out_boxes:
        part = box.shift(job.window.lo)  # (target indices)
        writer.write(box, best_l[part.lo[0] - t_lo:part.hi[0] - t_lo, part.lo[1]:part.hi[1],
                                 part.lo[2]:part.hi[2]])
    return predicted, peak, counts, peak_labels


def slab_plan(job: LabelBlocks, out, depth: int) -> list[tuple[int, int, list[Box]]]:
    """The slabs ``(t_lo, t_hi, output boxes)`` covering the whole target.

    The output's blocks (whole output planes) each give the slab of their
    target planes; the target planes the output does not keep (a crop) go
    in slabs of ``depth`` that write nothing.
    """
    tz = job.target_shape[0]
    w0 = job.window.lo[0]
    slabs = {}
    for box in out.blocks():
        key = (box.lo[0] + w0, box.hi[0] + w0)
        slabs.setdefault(key, []).append(box)
    for lo, hi in ((0, w0), (job.window.hi[0], tz)):
        for z in range(lo, hi, depth):
            slabs[(z, min(z + depth, hi))] = []
    return [(a, b, slabs[(a, b)]) for a, b in sorted(slabs)]


def warp_labels_by_blocks(job: LabelBlocks, out, engine, *, nvox, spacing,
                          memory: int | None = None):
    """The label warp into ``out`` (a :class:`~volwarp_cli.io.blockwrite.BlockOutput`).

    One task per slab on ``engine``; then the labels that would vanish are
    kept (``job.preserve``) by changing their voxels in ``out``, and the
    report is made as :func:`.labels.warp_labels` makes it. Returns the
    report. ``out``'s blocks must be whole output planes.
    """
    import dask

    from .labels import label_report

    depth = max(b.shape[0] for b in out.blocks()) if out.blocks() else 1
    plan = slab_plan(job, out, depth)
    job_node = dask.delayed(job, pure=False)
    out_node = dask.delayed(out.writer(), pure=False)
    tasks = [engine.block_delayed(label_slab_task, f"labels-{a}", job_node, out_node, a, b,
                                  boxes, memory=memory, keep=True)
             for a, b, boxes in plan]
    stats = engine.run(tasks, label="label slabs")
    out.mark_written([box for _, _, boxes in plan for box in boxes])
    predicted = {L: 0 for L in job.labels}
    peak = {L: (0, None) for L in job.labels}
    counts = {L: 0 for L in job.labels}
    initial = {}  # peak voxel -> the label it ended with
    for s in stats:
        got, top, n, ended = s.value
        for L, total in got.items():
            predicted[L] += total
        for L, c in n.items():
            counts[L] += c
        for L, (w, at) in top.items():
            if at is not None and _stronger(w, at, *peak[L]):
                peak[L] = (w, at)
                initial[at] = ended[L]
    changed: dict[tuple, int] = {}

    def label_at(at):
        return changed.get(at, initial.get(at, job.background))

    def set_label(at, L):
        changed[at] = L

    report = label_report(job.labels, nvox, predicted, peak, counts, float(np.prod(spacing)),
                          preserve=job.preserve, label_at=label_at, set_label=set_label)
    report["background"] = job.background
    _patch(out, job.window, changed)
    return report


def _patch(out, window: Box, changed: dict) -> None:
    """Set the voxels ``changed`` (target index -> label) that the output keeps."""
    blocks = out.blocks()
    for at, label in changed.items():
        local = [a - lo for a, lo in zip(at, window.lo, strict=True)]
        if not all(0 <= v < n for v, n in zip(local, window.shape, strict=True)):
            continue  # (outside a cropped output: counted, not written, as in memory)
        box = next(b for b in blocks if all(lo <= v < hi for v, lo, hi in
                                            zip(local, b.lo, b.hi, strict=True)))
        data = out.read(box).copy()
        data[tuple(v - lo for v, lo in zip(local, box.lo, strict=True))] = label
        out.write(box, data)


class LabelWarpOperation(Reduction):
    """A label map's warp on the executor: whole, or by slabs of target planes.

    ``warp``: the planned :class:`.run.LabelMapBlocks`; ``path``,
    ``template``: the output file and its Volume (key/values stamped, its
    samples a placeholder); ``write``: :func:`~volwarp_cli.io.write_volume`'s
    options. In memory the map is read whole and warped here
    (:meth:`.run.LabelMapBlocks.compute_whole`, :meth:`memory` its peak); by
    blocks, each task is a slab of whole target planes read box by box
    (:meth:`.run.LabelMapBlocks.compute_by_slabs`). The output (:attr:`Ran.output`
    of the run) is the per-label report; the file is the same either way.
    """

    blocks_share = 1.0  # (a slab returns its totals only: nothing to hold beside the tasks)

    def __init__(self, warp, path, template, write: dict):
        from ..geometry import Geometry

        self.warp, self.path, self.template, self.write = warp, path, template, dict(write)
        self.grid = Geometry.of(template)
        self.what = f"the warp of {warp.name}'s labels"

    def outputs(self) -> list:
        """The output file and its size (checked against the disk by blocks)."""
        return [(self.path, self.template.data.size * self.template.dtype.itemsize)]

    def _job(self) -> LabelBlocks:
        """The slabs' job without the labels (for its sizes; the labels come by blocks)."""
        w = self.warp
        return LabelBlocks(w.scene, w.source, [], [], w.window, w.input.dtype,
                           preserve=w.preserve, background=w.background)

    def memory(self, box: Box) -> int:
        """The whole in memory (:meth:`.run.LabelMapBlocks.memory_whole`), else a slab's."""
        if box == self.grid.box:
            return self.warp.memory_whole()
        return self._job().slab_bytes(box.shape[0])

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """Slabs of whole output planes, as deep as ``per_task`` holds (two slabs a task)."""
        _, ny, nx = self.grid.shape
        return (self._job().choose_depth(per_task * workers, workers), ny, nx)

    def reduce(self, blocks: Blocks) -> dict:
        """Warp and write; returns the per-label report."""
        from ..io import write_volume
        from ..io.blockwrite import open_volume_blocks
        from ..progress import timed

        if blocks.whole:
            out, report = self.warp.compute_whole()
            with timed(f"write {self.path}"):  # (pyramid levels take the mode: never averaged ids)
                write_volume(self.template.with_data(out.data, origin=out.origin), self.path,
                             **self.write, labels=True)
            return report
        w = self.write

        def open_output(template, block):
            return open_volume_blocks(self.path, self.template, block=block,
                                      compress=w.get("compress", False),
                                      byte_order=w.get("byte_order", "little"),
                                      version=w.get("ome_zarr_version", "0.5"),
                                      pyramid=w.get("pyramid", 0), labels=True)

        return self.warp.compute_by_slabs(blocks.engine, open_output, blocks.memory * blocks.engine.workers,
                                slab=blocks.shape[0])
