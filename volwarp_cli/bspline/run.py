"""The ``volwarp warp`` pipeline: an input and a spec to the warped volume and its frames.

The command (:mod:`volwarp_cli.cli.warp`) parses and checks its options, then:

1. :class:`WarpInput` reads the input on a worker thread while the warp modules
   are imported and the spec is loaded, and captures it (with the capture
   settings the spec gives, read before the spec is checked) while the spec is
   checked against its schema: reading and capturing release the GIL. Errors
   keep their order: a spec error first, then the input's. The early capture
   is used only if it matches the checked spec.
2. :class:`IntensityWarp` (a volume or capture file) or :class:`LabelMapWarp`
   (a label map) plans the lattice moves and renders: every frame (handed to a
   callback as a Volume), the final volume whole, or (intensities) streamed
   plane by plane to a writer as the warp finishes them, so that the whole
   target is never held.

Nothing here parses options or writes files: the caller passes the readers
(:class:`WarpInput`) and the writers (callbacks), and stamps and writes what
it gets. Progress and timings go to :data:`volwarp_cli.progress.log`.
"""

from __future__ import annotations

import contextvars
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager
from dataclasses import dataclass

import numpy as np

from ..errors import OutOfMemoryError, SpecError, VolwarpError
from ..progress import log, timed
from ..volume import Volume

#: the fields of a frame's name (``--frames-to``): ``frame`` and its alias ``step`` (0 =
#: unwarped, then one per increment), ``spec_step`` and ``sub`` (the spec step and the
#: increment within it)
FRAME_FIELDS = ("frame", "step", "spec_step", "sub")


@dataclass(frozen=True)
class WarpOptions:
    """What a warp may override of its spec, and the output's form.

    ``pushforward``, ``evaluator``, ``background``: the spec's unless given.
    ``crop``: cut the output back to the input's extent. ``dtype``: the
    output's sample type (default the input's). ``allow_growth``: let the
    padding the moves need grow the output past twice the input (see
    :func:`.warp.prepare`). ``blocks``: the warp runs by output blocks
    (:meth:`IntensityWarp.block_job`), the target never held whole.
    """

    pushforward: str | None = None
    evaluator: str | None = None
    background: float | None = None
    crop: bool = False
    dtype: str | None = None
    allow_growth: bool = False
    blocks: bool = False


def frame_fields(n: int, frame) -> dict[str, int]:
    """The name fields of frame ``n`` (``frame``: its planned frame, None for frame 0)."""
    return {"frame": n, "step": n, "spec_step": frame.step if frame else 0,
            "sub": frame.sub if frame else 0}


def _unchecked_capture_settings(doc):
    """The spec's capture settings read before its schema check; None if they cannot be."""
    from .plan import read_warp_spec

    try:
        spec = read_warp_spec(doc)
    except Exception:  # an invalid spec: the schema check reports it
        return None
    return None if spec.values == "labels" else spec.capture  # labels: their own capture


def capture_input(vol: Volume, settings, name: str, *, defer: bool = False):
    """``vol`` captured with ``settings`` (a spec's ``capture``); errors name ``name``.

    ``defer``: leave the gather to the warp (a one-shot warp gathers the planes as
    it streams them).
    """
    from . import capture as capture_module

    s = settings
    try:
        return capture_module.capture_volume(vol, lattice=s.lattice, placement=s.placement,
                                             oversample=s.oversample, sampling=s.sampling,
                                             pad=None, mean=False, defer=defer)
    except SpecError:
        raise
    except OutOfMemoryError as exc:  # (its type kept: a command may run by blocks instead)
        raise OutOfMemoryError(f"{name}: {exc}") from None
    except VolwarpError as exc:
        raise VolwarpError(f"{name}: {exc}") from None


def _capture_early(reading, settings, name, defer):
    """The capture, started before the spec is checked; None where it cannot be made.

    The capture after the check then reports why, in order.
    """
    if settings is None:
        return None
    try:
        return capture_input(reading.result(), settings, name, defer=defer)
    except Exception:
        return None


class WarpInput(AbstractContextManager):
    """A warp's input and spec, read, checked and captured with the work overlapped.

    Give ``read_volume`` (a volume input: called on a worker thread at once; a
    mapped, not copied, volume is best, the warp only reads it) or
    ``read_capture`` (a capture file, read when :meth:`source` asks for it).
    ``labels``: the input is a label map (no intensity capture is made early);
    ``stream``: the warp renders only its final lattice (the capture's gather
    is deferred to it). ``name`` (the input's file) prefixes the capture's
    errors. Use it as a context manager; :meth:`load_spec` first, then
    :meth:`source`::

        with WarpInput(path, read_volume=lambda: read_volume(path, mmap=True)) as w:
            doc, spec = w.load_spec(spec_path)
            cap = w.source(doc, spec)
    """

    def __init__(self, name: str, *, read_volume: Callable[[], Volume] | None = None,
                 read_capture: Callable[[], object] | None = None, labels: bool = False,
                 stream: bool = False):
        if (read_volume is None) == (read_capture is None):
            raise ValueError("give read_volume or read_capture (one of them)")
        self.name = name
        self._read_volume = read_volume
        self._read_capture = read_capture
        self._labels = labels
        self._stream = stream
        self._pool = None
        self._reading = None
        self._early = None
        self._settings = None

    def __enter__(self):
        self._pool = ThreadPoolExecutor(1)
        if self._read_volume is not None:  # in this run's context (its files, threads, budget)
            self._reading = self._pool.submit(contextvars.copy_context().run, self._read_volume)
        return self

    def __exit__(self, *exc_info):
        self._reading = self._early = None
        self._pool.shutdown(wait=True)
        return None

    def load_spec(self, spec_path):
        """The spec, loaded and checked against its schema: ``(doc, WarpSpec)``.

        While the schema check runs, the volume (once read) is captured with the
        settings the spec gives (unless it is a label map).
        """
        from ..spec.loader import load_schema, load_spec, validate
        from . import warp as _warp  # noqa: F401 - imported while the volume is read
        from .plan import read_warp_spec

        doc = load_spec(spec_path)
        if self._reading is not None:
            self._settings = None if self._labels else _unchecked_capture_settings(doc)
            self._early = self._pool.submit(contextvars.copy_context().run, _capture_early,
                                            self._reading, self._settings, self.name,
                                            self._stream)
        validate(doc, load_schema("warp"))
        return doc, read_warp_spec(doc)

    def source(self, doc, spec, *, labels: bool = False):
        """What to warp: the :class:`.capture.Capture`, or with ``labels`` the label map Volume.

        The label map is captured by :class:`LabelMapWarp`.

        A capture file's settings are checked against the spec's (a spec error);
        a volume's read error comes here, after every spec error.
        """
        from .warp import check_capture_settings

        if self._read_capture is not None:
            with timed(f"read {self.name}"):
                cap = self._read_capture()
            check_capture_settings(doc, spec, cap, self.name)
            return cap
        if self._reading is None:
            raise RuntimeError("WarpInput.source needs load_spec first, inside the with")
        vol = self._reading.result()  # a read error, after any spec error
        early = self._early.result() if self._settings == spec.capture else None
        self._reading = self._early = None  # the futures hold the volume and the capture
        if labels:
            return vol
        if early is not None:
            return early
        return capture_input(vol, spec.capture, self.name, defer=self._stream)


def handle_report(cap, frames) -> list[dict]:
    """How far each drag handle missed its target, world mm (logged at -v).

    One dict per handle: ``{step, index, from, to, reached, miss_mm}`` (world LPS mm,
    ``step`` 0-based).
    """
    g = cap.geometry
    matrix = g.direction * g.spacing[None, :]
    out = []
    for fr in frames:
        for n, (src, to, reached) in enumerate(fr.handles):
            miss = float(np.linalg.norm(matrix @ (np.asarray(reached) - np.asarray(to))))
            log.info("steps[%d].drag[%d]: reached %s, missed its target by %.3g mm",
                     fr.step - 1, n, np.round(g.index_to_world(reached), 4).tolist(), miss)
            world = [np.asarray(g.index_to_world(np.asarray(p, dtype=np.float64)),
                                dtype=np.float64).reshape(3).tolist()
                     for p in (src, to, reached)]
            out.append({"step": fr.step - 1, "index": n, "from": world[0], "to": world[1],
                        "reached": world[2], "miss_mm": miss})
    return out


#: ``on_frame(fields, volume)``: a frame's name fields (:func:`frame_fields`) and its Volume
OnFrame = Callable[[dict, Volume], None]


class IntensityWarp:
    """The warp of a captured volume (:class:`.capture.Capture`) by a checked spec.

    Construction plans every lattice state and builds the scene (its padded
    target refused before it is made when it cannot fit); then render once,
    with :meth:`render` (the whole output), :meth:`stream` (the output plane by
    plane) or :meth:`render_frames` (every frame, incrementally).
    """

    def __init__(self, cap, doc, spec, options: WarpOptions = WarpOptions(), *,
                 name: str = "input"):
        from .warp import prepare

        self.cap = cap
        self.options = options
        try:
            self.scene, self.frames = prepare(
                cap, doc, spec, method=options.pushforward, evaluator=options.evaluator,
                background=options.background, allow_growth=options.allow_growth,
                whole_target=not options.blocks)
        except OutOfMemoryError as exc:  # the target this input and spec ask for
            raise OutOfMemoryError(f"{name}: {exc}") from None

    @property
    def final_lattice(self) -> np.ndarray:
        """The control-point offsets after the last step."""
        return self.frames[-1].dq if self.frames else self.cap.dq

    def handles(self) -> list[dict]:
        """:func:`handle_report` of this warp's drags."""
        return handle_report(self.cap, self.frames)

    def output(self, target: np.ndarray) -> Volume:
        """A target array as the output Volume (cropped and cast as the options say)."""
        from .warp import output_volume

        return output_volume(self.cap, self.scene, target, crop=self.options.crop,
                             dtype=self.options.dtype)

    def render(self) -> Volume:
        """The final lattice's output, rendered in one pass."""
        from .warp import run

        return self.output(run(self.scene, self.frames))

    def render_frames(self, on_frame: OnFrame) -> Volume:
        """Every frame (0: unwarped, then each increment), incrementally; returns the last.

        Each is handed to ``on_frame`` before the next is made; the last is the output.
        """
        from .warp import run

        def each(n, fr, target):
            on_frame(frame_fields(n, fr), self.output(target))

        return self.output(run(self.scene, self.frames, each))

    def block_job(self, source, sampler=None):
        """The final lattice's output as independent blocks: ``(template, WarpBlocks)``.

        ``template`` is the output Volume with a zero-strided placeholder of its
        shape and dtype; :meth:`.blocks.WarpBlocks.output_block` computes any
        block of it (a picklable job: the tasks may run in other processes).
        ``source``: the input's samples, sliceable (the capture's own, or a
        :class:`.blocks.LazySource` for other processes to reopen); or
        ``sampler``, a held domain's (:meth:`tile_sampler`), for this process.
        """
        from .blocks import WarpBlocks
        from .warp import output_planes, output_window_box

        if self.frames:
            self.scene.set_lattice(self.frames[-1].dq)
        template, _ = output_planes(self.cap, self.scene, crop=self.options.crop,
                                    dtype=self.options.dtype)
        window = output_window_box(self.cap, self.scene, self.options.crop)
        return template, WarpBlocks(self.scene, source, self.cap.placement, self.cap.sampling,
                                    window, template.dtype, sampler=sampler)

    def render_blocks(self, source, engine, open_output, budget: int, *, block=None,
                      sampler=None) -> dict:
        """The final lattice's output by blocks on ``engine``, the target never held whole.

        ``source``/``sampler``: as :meth:`block_job` takes them.
        ``open_output(template, block)``: a context manager giving the block output
        (:class:`~volwarp_cli.io.blockwrite.BlockOutput`) for the output's
        template and block shape (z, y, x), committed when it exits without an
        error. ``budget``: the bytes the tasks may hold together; ``block``:
        the output's block, default the largest the budget holds for the
        engine's tasks at once. Returns the run's summary: the output's shape
        (x y z), the drags' report, the count and shape (x y z) of the blocks.
        """
        from .blocks import warp_by_blocks

        template, job = self.block_job(source, sampler=sampler)
        per_task = budget // max(1, engine.workers)
        block = block or job.choose_blocks(budget, engine.workers)
        with open_output(template, block) as out:
            stats = warp_by_blocks(job, out, engine, memory=per_task)
        return {"shape": list(template.shape_xyz), "handles": self.handles(),
                "blocks": len(stats), "block": list(block[::-1])}

    def tile_sampler(self):
        """The capture's samples box by box, for :func:`.blocks.warp_by_tiles` in this process.

        A captured domain (a capture file's) as it is; a deferred capture's
        gather from the input it already holds in the domain's type.
        """
        from .pullback import BoxSampler, DomainSampler

        if self.cap.domain is not None:
            return DomainSampler(self.cap.domain)
        src = self.cap.sampler
        if isinstance(src, BoxSampler):
            return src
        return BoxSampler(src.samples, self.cap.grid, self.cap.placement, self.cap.sampling,
                          src.dtype)

    def stream(self, open_writer: Callable[[Volume], AbstractContextManager]) -> Volume:
        """The final lattice's output, plane by plane, to a writer; returns its template.

        ``open_writer(template)`` gets the output Volume with a zero-strided
        placeholder of its shape and dtype (for the file's header) and returns a
        context manager giving ``write_planes(z0, samples)``; the planes arrive in
        order of z as the warp finishes them (from the warp's threads) and the
        writer commits when the context exits without an error.
        """
        from .warp import output_planes, run

        template, convert = output_planes(self.cap, self.scene, crop=self.options.crop,
                                          dtype=self.options.dtype)
        with open_writer(template) as write_planes:
            def sink(z0, z1, planes):
                part = convert(z0, planes)
                if part is not None:
                    write_planes(*part)

            run(self.scene, self.frames, sink=sink)
        return template


def _prepare_labels(vol: Volume, doc, spec, options: WarpOptions, name: str):
    """:func:`.labels.prepare_labels` with the options' overrides: ``(cap, scene, frames)``."""
    from .labels import prepare_labels

    return prepare_labels(vol, doc, spec, method=options.pushforward,
                          evaluator=options.evaluator, background=options.background,
                          source=name, allow_growth=options.allow_growth)


class LabelMapBlocks:
    """The warp of a label map read by boxes, by slabs of target planes (never held whole).

    ``template``: the map's Volume with a placeholder of its shape and dtype;
    ``source``: its samples, sliceable ``[z, y, x]`` (a lazy source, reopened
    by path in worker processes). The output and the per-label report equal
    :class:`LabelMapWarp`'s (:mod:`.label_blocks`). Construction plans the
    lattice and the output (:attr:`template`, refused before any work when
    the spec cannot apply); :meth:`render` runs it.
    """

    def __init__(self, template: Volume, source, doc, spec,
                 options: WarpOptions = WarpOptions(), *, preserve: bool = False,
                 name: str = "input"):
        from .warp import output_planes, output_window_box

        self.source = source
        self.input = template
        self.preserve = preserve
        self.cap, self.scene, self.frames = _prepare_labels(template, doc, spec, options, name)
        if self.frames:
            self.scene.set_lattice(self.frames[-1].dq)
        #: the output's Volume, a placeholder of its shape and dtype
        self.template, _ = output_planes(self.cap, self.scene, crop=options.crop)
        self.window = output_window_box(self.cap, self.scene, options.crop)

    def render(self, engine, open_output, budget: int, *, slab: int | None = None) -> dict:
        """Warp by slabs on ``engine``; returns the output's shape, the drags' and the labels' report.

        ``open_output(template, block)``: as :meth:`IntensityWarp.render_blocks`
        takes it (a slab's block: ``(slab, y, x)`` of the output); ``budget``:
        the bytes the tasks may hold together; ``slab``: target planes per
        task (default: as many as the budget holds).
        """
        import functools

        from .label_blocks import LabelBlocks, bounding_boxes_by_blocks, warp_labels_by_blocks

        per_task = budget // max(1, engine.workers)
        run = functools.partial(engine.map, label="label boxes", memory=per_task)
        nz, ny, nx = self.input.data.shape
        # slabs of the map read for its labels' boxes: each one's samples and counts
        depth = max(1, min(nz, per_task // max(1, ny * nx * (self.input.dtype.itemsize + 16))))
        with timed("labels: bounding boxes (one pass)"):
            labels, nvox, boxes = bounding_boxes_by_blocks(self.source, run, depth)
        job = LabelBlocks(self.scene, self.source, labels, boxes, self.window,
                          self.input.dtype, preserve=self.preserve)
        slab = slab or job.choose_depth(budget, engine.workers)
        shape = self.template.data.shape
        with open_output(self.template, (slab, shape[1], shape[2])) as out, \
                timed(f"labels: {len(labels)} label passes + background, by slabs"):
            report = warp_labels_by_blocks(job, out, engine, nvox=nvox,
                                           spacing=self.input.spacing, memory=per_task)
        return {"shape": list(self.template.shape_xyz),
                "handles": handle_report(self.cap, self.frames), "report": report}


class LabelMapWarp:
    """The warp of a label map (segmentation) by a checked spec.

    Every output voxel is an input label (see :mod:`.labels`).

    Each rendered lattice is the whole label warp from the input map, exact (not
    incremental): :meth:`render` for the final lattice, :meth:`render_frames`
    for every frame. Both return ``(Volume, report)``, the report per label
    (:func:`.labels.warp_labels`).
    """

    def __init__(self, vol: Volume, doc, spec, options: WarpOptions = WarpOptions(), *,
                 preserve: bool = False, name: str = "input"):
        if options.dtype is not None:
            raise VolwarpError("a label map keeps its own integer type (no dtype)")
        self.vol = vol
        self.options = options
        self.preserve = preserve
        self.cap, self.scene, self.frames = _prepare_labels(vol, doc, spec, options, name)

    def handles(self) -> list[dict]:
        """:func:`handle_report` of this warp's drags."""
        return handle_report(self.cap, self.frames)

    def warp(self, lattice: np.ndarray) -> tuple[Volume, dict]:
        """The label warp for control-point offsets ``lattice``."""
        from .labels import warp_labels
        from .warp import output_volume

        self.scene.set_lattice(lattice)
        res = warp_labels(self.vol.data, self.scene, (), preserve=self.preserve,
                          spacing=self.vol.spacing)
        return output_volume(self.cap, self.scene, res.target, crop=self.options.crop), \
            res.report

    def lattices(self) -> Iterator[tuple[dict, np.ndarray]]:
        """Every frame's name fields and lattice: frame 0 (unmoved), then each increment."""
        yield frame_fields(0, None), self.cap.dq
        for n, fr in enumerate(self.frames, start=1):
            yield frame_fields(n, fr), fr.dq

    def render(self) -> tuple[Volume, dict]:
        """The final lattice's label map and report."""
        return self.warp(self.frames[-1].dq if self.frames else self.cap.dq)

    def render_frames(self, on_frame: OnFrame) -> tuple[Volume, dict]:
        """Every frame's label map, each handed to ``on_frame``.

        Returns the last one (the output) and its report.
        """
        last = None
        count = len(self.frames)
        for fields, lattice in self.lattices():
            with timed(f"labels: frame {fields['frame']} of {count}"):
                last = self.warp(lattice)
            on_frame(fields, last[0])
        return last
