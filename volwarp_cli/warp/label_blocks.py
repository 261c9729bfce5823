"""A label map's one-shot warp (the final lattice): whole, or by slabs of target planes.

:class:`OneShotLabelWarp` is the computation, :class:`LabelWarpOperation` its
operation for the executor (:mod:`volwarp_cli.execute`), which decides by the
sizes, before the map is read, whether it runs whole or by slabs.

The in-memory label warp (:func:`.labels.warp_labels`) already cuts the target
into z ranges, one per thread, each streaming every label's weights in one
pass over its own planes (:class:`.labels.LabelStream`); the result does not
depend on the cut. By slabs, each task is one such slab of whole target
planes, computed from the lattice and the label map read a few planes at a
time (reopened by path in a worker process). It writes the output's part of its
slab and returns its totals: each label's predicted weight and output
voxels, and its voxel of largest weight with the label that voxel ended with.
The report, and ``--preserve-labels``' fix-up of the labels that would
vanish (a few voxels changed in the output before it is committed), come
from those totals, so the output and the report are the in-memory ones, bit
for bit. Target planes outside a cropped output are computed too (the
report counts the whole target, as in memory) but written nowhere.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from ..box import Box
from ..bspline.capture import NoSamples
from ..bspline.scene import Scene
from ..errors import OutOfMemoryError
from ..execute import Blocks, Reduction
from ..progress import timed
from ..volume import Header, Volume
from .blocks import SceneRecipe
from .labels import (
    TILE,
    LabelCodes,
    LabelStream,
    LabelTotals,
    _bounding_boxes,
    _stronger,
    label_window,
    needed_tiles,
    stream_bytes,
)
from .run import LatticeMoves, WarpOptions, background_label, prepare_label_warp

_BUILD = threading.Lock()  # one scene per process, even when two threads ask at once

#: what a slab task needs where it runs: the only state pickled (the planned capture,
#: frames and Headers stay with the caller)
_SLAB_STATE = ("recipe", "source", "window", "dtype", "preserve", "background",
               "target_shape")


class OneShotLabelWarp(LatticeMoves):
    """A label map's warp for the final lattice: whole, or by slabs of target planes.

    ``header``: the map's :class:`~volwarp_cli.volume.Header` (its shape,
    dtype and geometry); ``source``: its samples, sliceable ``[z, y, x]`` (a
    :class:`~volwarp_cli.io.lazy.LazySource`, reopened by path in worker
    processes). Construction plans the lattice and the output
    (:attr:`header`, refused before any work when the spec cannot apply)
    and reads the map's border (its background label,
    :func:`~volwarp_cli.border.border_label`); :meth:`compute_whole` reads the
    map whole and warps it here (:func:`.labels.warp_labels`, within
    :meth:`memory_whole`), :meth:`compute_by_slabs` by slabs on an engine,
    the map read box by box: the same output and per-label report.

    By slabs, the instance is the tasks' job: pickled with what a slab needs
    only (:data:`_SLAB_STATE`), its scene rebuilt from its recipe once per
    process (:meth:`slab_scene`).
    """

    def __init__(self, header: Header, source, doc, spec,
                 options: WarpOptions = WarpOptions(), *, name: str = "input"):
        from .prepare import output_planes, output_window_box

        self.source = source
        #: the map's Header
        self.input = header
        self.dtype = np.dtype(header.dtype)
        self.preserve = options.preserve
        self.options = options
        self.name = name  # (the input's file: in messages)
        self.cap, self.scene, self.frames, (self.grid, self.grid_why) = prepare_label_warp(
            header, doc, spec, options, name)
        #: the label where nothing lands: the given one, else the most frequent on the
        #: map's border
        self.background = background_label(source, options.background)
        if self.frames:
            self.scene.set_lattice(self.frames[-1].dq)
        #: the output's Header: its shape, dtype and geometry
        self.header, _ = output_planes(self.cap, self.scene, crop=options.crop)
        #: the output's box of the target
        self.window = output_window_box(self.cap, self.scene, options.crop)
        #: the whole target's shape (z, y, x)
        self.target_shape = tuple(self.scene.target_shape[::-1])
        self.recipe = SceneRecipe(self.scene)  # (the scene's background 0: unused by labels)
        self._slab_scene = None

    def __getstate__(self):
        state = {key: self.__dict__[key] for key in _SLAB_STATE}
        state["_slab_scene"] = None
        return state

    def memory_whole(self) -> int:
        """The bytes :meth:`compute_whole` holds at its peak (an upper bound).

        The map read whole, the target's labels, each thread's stream
        (:func:`.labels.stream_bytes`) and the output's copy.
        """
        from .. import parallel

        tx, ty, tz = self.scene.target_shape
        item = self.input.dtype.itemsize
        workers = max(1, min(parallel.threads(), tz // 4))
        return (math.prod(self.input.shape) * item + tx * ty * tz * item
                + workers * stream_bytes(self.scene, self.scene.dq, self.input.dtype)
                + math.prod(self.header.shape) * item)

    def compute_whole(self) -> tuple[Volume, dict]:
        """The output and the per-label report, the map read whole and warped here."""
        from .labels import warp_labels
        from .prepare import output_volume

        with timed("labels: read the map"):
            data = np.asarray(self.source[:, :, :])
        res = warp_labels(data, self.scene, (), preserve=self.preserve,
                          spacing=self.input.spacing, background=self.background)
        return output_volume(self.cap, self.scene, res.target, crop=self.options.crop), \
            res.report

    def compute_by_slabs(self, engine, open_output, budget: int, *,
                         slab: int | None = None) -> dict:
        """Warp by slabs on ``engine``; returns the per-label report.

        ``open_output(header, block)``: a context manager giving the block
        output (:class:`~volwarp_cli.io.blockwrite.BlockOutput`) for the
        output's Header and block shape (a slab's: ``(slab, y, x)`` of the
        output), committed on a clean exit; ``budget``: the bytes the tasks
        may hold together; ``slab``: target planes per task (default: as many
        as the budget holds).
        """
        import functools

        per_task = budget // max(1, engine.workers)
        run = functools.partial(engine.map, label="label boxes", memory=per_task)
        nz, ny, nx = self.input.shape
        # slabs of the map read for its labels' boxes: each one's samples and counts
        depth = max(1, min(nz, per_task // max(1, ny * nx * (self.input.dtype.itemsize + 16))))
        with timed("labels: bounding boxes (one pass)"):
            labels, nvox, boxes, tiles = bounding_boxes_by_blocks(
                self.source, run, depth, self.background, TILE)
        codes = LabelCodes(labels, self.background, self.dtype)
        hull = None
        for box in boxes:
            hull = box if hull is None else hull.union_hull(box)
        window = label_window(self.scene, self.scene.dq, hull)
        need = needed_tiles(self.scene, self.scene.dq, tiles, TILE)
        slab = slab or self.choose_depth(budget, engine.workers)
        shape = self.header.shape
        with open_output(self.header, (slab, shape[1], shape[2])) as out, \
                timed(f"labels: {len(labels)} labels + background, one pass, by slabs"):
            return self._warp_slabs(out, engine, codes, nvox, (window, need), memory=per_task)

    def slab_scene(self) -> Scene:
        """The scene the slabs are computed with: rebuilt from the recipe, once per process."""
        with _BUILD:
            if self._slab_scene is None:
                grid = self.recipe.grid
                self._slab_scene = self.recipe.build(NoSamples(tuple(grid.domain_shape[::-1])))
        return self._slab_scene

    def slab(self, t_lo: int, t_hi: int, codes: LabelCodes, where):
        """Target planes ``[t_lo, t_hi)``: ``(labels, totals, peak_labels)``.

        ``codes``: the map's :class:`.labels.LabelCodes`; ``where``: its
        :func:`.labels.label_window` and :func:`.labels.needed_tiles`.
        Returned: the slab's output labels, its :class:`.labels.LabelTotals`
        and, per label with a peak voxel, the label that voxel ended with.
        """
        scene = self.slab_scene()
        _, ty, tx = self.target_shape
        best_l = np.empty((t_hi - t_lo, ty, tx), dtype=self.dtype)
        window, need = where
        totals = LabelStream(scene, scene.dq, self.source, t_lo, t_hi, best_l, codes,
                             window=window, need=need).run()
        peak_labels = {L: int(best_l[at[0] - t_lo, at[1], at[2]])
                       for L, (_, at) in totals.peak.items() if at is not None}
        return best_l, totals, peak_labels

    def slab_bytes(self, depth: int) -> int:
        """Memory a task of ``depth`` target planes holds at its peak (an upper bound).

        The slab's labels and its stream's buffers (:func:`.labels.stream_bytes`).
        """
        scene = self.slab_scene()
        _, ty, tx = self.target_shape
        return (depth * ty * tx * self.dtype.itemsize
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

    def slab_plan(self, out, depth: int) -> list[tuple[int, int, list[Box]]]:
        """The slabs ``(t_lo, t_hi, output boxes)`` covering the whole target.

        The output's blocks (whole output planes) each give the slab of their
        target planes; the target planes the output does not keep (a crop) go
        in slabs of ``depth`` that write nothing.
        """
        tz = self.target_shape[0]
        w0 = self.window.lo[0]
        slabs = {}
        for box in out.blocks():
            key = (box.lo[0] + w0, box.hi[0] + w0)
            slabs.setdefault(key, []).append(box)
        for lo, hi in ((0, w0), (self.window.hi[0], tz)):
            for z in range(lo, hi, depth):
                slabs[(z, min(z + depth, hi))] = []
        return [(a, b, slabs[(a, b)]) for a, b in sorted(slabs)]

    def _warp_slabs(self, out, engine, codes, nvox, where, *, memory: int | None) -> dict:
        """The label warp into ``out`` (a :class:`~volwarp_cli.io.blockwrite.BlockOutput`).

        One task per slab on ``engine``; then the labels that would vanish are
        kept (``preserve``) by changing their voxels in ``out``, and the
        report is made as :func:`.labels.warp_labels` makes it. Returns the
        report. ``out``'s blocks must be whole output planes.
        """
        import dask

        from .labels import label_report

        depth = max(b.shape[0] for b in out.blocks()) if out.blocks() else 1
        plan = self.slab_plan(out, depth)
        job_node = dask.delayed(self, pure=False)
        out_node = dask.delayed(out.writer(), pure=False)
        found_node = dask.delayed((codes, where), pure=False, traverse=False)
        tasks = [engine.block_delayed(label_slab_task, f"labels-{a}", job_node, out_node,
                                      found_node, a, b, out_boxes, memory=memory, keep=True)
                 for a, b, out_boxes in plan]
        stats = engine.run(tasks, label="label slabs")
        out.mark_written([box for _, _, out_boxes in plan for box in out_boxes])
        totals = LabelTotals()
        initial = {}  # peak voxel -> the label it ended with
        for s in stats:
            got, ended = s.value
            for L, (w, at) in got.peak.items():
                if at is not None and _stronger(w, at, *totals.peak.get(L, (0, None))):
                    initial[at] = ended[L]
            totals.add(got)
        changed: dict[tuple, int] = {}

        def label_at(at):
            return changed.get(at, initial.get(at, self.background))

        def set_label(at, L):
            changed[at] = L

        labels = codes.labels
        report = label_report(labels, nvox, {L: totals.predicted.get(L, 0) for L in labels},
                              {L: totals.peak.get(L, (0, None)) for L in labels},
                              {L: totals.counts.get(L, 0) for L in labels},
                              float(np.prod(self.input.spacing)), preserve=self.preserve,
                              label_at=label_at, set_label=set_label)
        report["background"] = self.background
        _patch(out, self.window, changed)
        return report


def bounding_boxes_by_blocks(source, run, depth: int, background: int = 0, tile: int = 0):
    """:func:`.labels._bounding_boxes` of a sliceable map read in slabs of ``depth`` planes.

    ``run(task, items)``: who runs the slabs (an engine's ``map``). Returns
    ``(labels, voxel counts, boxes)`` of the labels but ``background``: the
    same as the whole map's; with ``tile`` (input voxels), also the tiles
    holding their voxels (:func:`.labels.label_tiles`), read in the same pass.
    """
    import functools

    nz, ny, nx = source.shape
    if tile:  # (slabs of whole tiles)
        depth = tile * max(1, depth // tile)
    task = functools.partial(_slab_boxes, source=source, background=int(background),
                             tile=int(tile))
    found: dict[int, list] = {}
    tiles = np.zeros([-(-n // tile) for n in (nz, ny, nx)], np.uint8) if tile else None
    for z0, labels, nvox, boxes, part in run(task, [(z, min(z + depth, nz))
                                                   for z in range(0, nz, depth)]):
        for L, n, box in zip(labels, nvox, boxes, strict=True):
            box = box.shift((z0, 0, 0))
            if L in found:
                found[L][0] += n
                found[L][1] = found[L][1].union_hull(box)
            else:
                found[L] = [n, box]
        if tile:
            tiles[z0 // tile:z0 // tile + len(part)] |= part
    labels = sorted(found)
    out = labels, [found[L][0] for L in labels], [found[L][1] for L in labels]
    return (*out, tiles) if tile else out


def _slab_boxes(zs, source, background=0, tile=0):
    from .labels import label_tiles

    z0, z1 = zs
    data = np.asarray(source[z0:z1])
    labels, nvox, boxes, _ = _bounding_boxes(data, background)
    return z0, labels, nvox, boxes, label_tiles(data != background, tile) if tile else None


def label_slab_task(job: OneShotLabelWarp, writer, found, t_lo: int, t_hi: int,
                    out_boxes) -> tuple:
    """One slab's task: write its part of the output, return its totals.

    ``found``: ``(codes, where)``, the map's :class:`.labels.LabelCodes`, and
    its :func:`.labels.label_window` and :func:`.labels.needed_tiles`. Returned:
    the slab's :class:`.labels.LabelTotals` and the labels its peak voxels
    ended with.
    """
    best_l, totals, peak_labels = job.slab(t_lo, t_hi, *found)
    for box in out_boxes:
        part = box.shift(job.window.lo)  # (target indices)
        writer.write(box, best_l[part.lo[0] - t_lo:part.hi[0] - t_lo, part.lo[1]:part.hi[1],
                                 part.lo[2]:part.hi[2]])
    return totals, peak_labels


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

    ``warp``: the planned :class:`OneShotLabelWarp`; ``path``, ``header``:
    the output file and its :class:`~volwarp_cli.volume.Header` (key/values
    stamped); ``write``: :func:`~volwarp_cli.io.write_volume`'s options.
    In memory the map is read whole and warped here
    (:meth:`OneShotLabelWarp.compute_whole`, :meth:`memory` its peak); by
    blocks, each task is a slab of whole target planes read box by box
    (:meth:`OneShotLabelWarp.compute_by_slabs`). The output (:attr:`Ran.output`
    of the run) is the per-label report; the file is the same either way.
    """

    blocks_share = 1.0  # (a slab returns its totals only: nothing to hold beside the tasks)

    def __init__(self, warp: OneShotLabelWarp, path, header, write: dict):
        from ..geometry import Geometry

        self.warp, self.path, self.header, self.write = warp, path, header, dict(write)
        self.grid = Geometry.of(header)
        self.what = f"the warp of {warp.name}'s labels"

    def outputs(self) -> list:
        """The output file and its size (checked against the disk by blocks)."""
        return [(self.path, math.prod(self.header.shape) * self.header.dtype.itemsize)]

    def memory(self, box: Box) -> int:
        """The whole in memory (:meth:`OneShotLabelWarp.memory_whole`), else a slab's."""
        if box == self.grid.box:
            return self.warp.memory_whole()
        return self.warp.slab_bytes(box.shape[0])

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """Slabs of whole output planes, as deep as ``per_task`` holds (two slabs a task)."""
        _, ny, nx = self.grid.shape
        return (self.warp.choose_depth(per_task * workers, workers), ny, nx)

    def reduce(self, blocks: Blocks) -> dict:
        """Warp and write; returns the per-label report."""
        from ..io import write_volume
        from ..io.blockwrite import open_volume_blocks

        if blocks.whole:
            out, report = self.warp.compute_whole()
            with timed(f"write {self.path}"):  # (pyramid levels take the mode: never averaged ids)
                write_volume(self.header.with_data(out.data, origin=out.origin), self.path,
                             **self.write, labels=True)
            return report
        w = self.write

        def open_output(header, block):
            return open_volume_blocks(self.path, self.header, block=block,
                                      compress=w.get("compress", False),
                                      byte_order=w.get("byte_order", "little"),
                                      version=w.get("ome_zarr_version", "0.5"),
                                      pyramid=w.get("pyramid", 0), labels=True)

        return self.warp.compute_by_slabs(blocks.engine, open_output,
                                          blocks.memory * blocks.engine.workers,
                                          slab=blocks.shape[0])
