"""The ``volwarp warp`` pipeline: an input and a spec to the warped volume and its frames.

The command (:mod:`volwarp_cli.cli.warp`) parses and checks its options, then:

- the final lattice alone (no frames): :class:`IntensityWarp` plans the
  lattice moves of a deferred capture (the input or capture file read box
  by box) and gives the output as an operation of the executor
  (:meth:`IntensityWarp.operation`, :mod:`volwarp_cli.execute`: whole or by
  blocks, the same bytes); a label map's is
  :class:`.label_blocks.OneShotLabelWarp` (whole or by slabs of target planes);
- every frame (``--frames-to``): :class:`WarpInput` reads the input on a
  worker thread while the warp modules are imported and the spec is
  loaded, and captures it (with the capture settings the spec gives, read
  before the spec is checked) while the spec is checked against its schema:
  reading and capturing release the GIL. Errors keep their order: a spec
  error first, then the input's. The early capture is used only if it
  matches the checked spec. :class:`IntensityWarp` computes the frames
  incrementally, :class:`LabelMapWarp` each frame's exact label warp, each
  handed to a callback as a Volume.

Nothing here parses options or writes files: the caller passes the readers
(:class:`WarpInput`) and the writers (callbacks), and stamps and writes what
it gets. Progress and timings go to :data:`volwarp_cli.progress.log`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass

import numpy as np

from ..errors import BadUsage, OutOfMemoryError, SpecError, VolwarpError
from ..parallel import beside
from ..progress import log, timed
from ..volume import Header, Volume

#: the fields of a frame's name (``--frames-to``): ``frame`` and its alias ``step`` (0 =
#: unwarped, then one per increment), ``spec_step`` and ``sub`` (the spec step and the
#: increment within it)
FRAME_FIELDS = ("frame", "step", "spec_step", "sub")


@dataclass(frozen=True)
class WarpOptions:
    """What a warp may override of its spec, and the output's form.

    ``pushforward``, ``evaluator``: the spec's unless given; ``background``:
    the spec's, else the input's border value (:func:`.defaults.background_choice`).
    ``grid``: ``"input"`` (the output on the input's grid) or ``"grow"``
    (grown to hold the moved model); None: the spec's, else input unless a
    pad is given (:func:`.prepare.grid_of`). ``crop``: the same as ``grid="input"``.
    ``dtype``: the output's sample type (default the input's).
    ``allow_growth``: let the padding the moves need grow the output past
    twice the input (the grown grid; see :func:`.prepare.prepare`).
    ``values``: how the samples are warped, ``"intensity"`` or ``"labels"``
    (None: the spec's, else the label rule); ``preserve``: a label that
    would vanish keeps its voxel of largest weight (labels only).
    """

    pushforward: str | None = None
    evaluator: str | None = None
    background: float | None = None
    crop: bool = False
    dtype: str | None = None
    allow_growth: bool = False
    grid: str | None = None
    values: str | None = None
    preserve: bool = False

    def __post_init__(self):
        if self.crop and self.grid == "grow":
            raise BadUsage("--crop puts the output on the input's grid: it does not go "
                           "with --grid grow")
        if self.allow_growth and self.output_grid == "input":
            raise BadUsage("--allow-growth lets a grown grid grow: give --grid grow")
        if self.preserve and self.values == "intensity":
            raise BadUsage("--preserve-labels keeps labels: it does not go with "
                           "--values intensity")
        if self.values == "labels" and self.dtype is not None:
            raise BadUsage("labels keep the label map's own integer type (no --dtype)")

    @property
    def output_grid(self) -> str | None:
        """The grid asked for: ``"input"`` (``grid``, or ``crop``), ``"grow"``, or None."""
        return "input" if self.crop else self.grid


def frame_fields(n: int, frame) -> dict[str, int]:
    """The name fields of frame ``n`` (``frame``: its planned frame, None for frame 0)."""
    return {"frame": n, "step": n, "spec_step": frame.step if frame else 0,
            "sub": frame.sub if frame else 0}


def _unchecked_spec(doc):
    """The spec's settings read before its schema check; None if they cannot be."""
    from ..bspline.plan import read_warp_spec

    try:
        return read_warp_spec(doc)
    except Exception:  # an invalid spec: the schema check reports it
        return None


def capture_input(vol: Volume, settings, name: str):
    """``vol`` captured with ``settings`` (a spec's ``capture``); errors name ``name``."""
    from ..bspline import capture as capture_module

    s = settings
    try:
        return capture_module.capture_volume(vol, lattice=s.lattice, placement=s.placement,
                                             oversample=s.oversample, sampling=s.sampling,
                                             pad=None, mean=False)
    except SpecError:
        raise
    except OutOfMemoryError as exc:  # (its type kept: exit 1 names the memory)
        raise OutOfMemoryError(f"{name}: {exc}") from None
    except VolwarpError as exc:
        raise VolwarpError(f"{name}: {exc}") from None


def check_oversample(doc, spec, shape_xyz) -> None:
    """A spec error at ``capture.oversample`` where the domain is coarser than the input.

    (:func:`~volwarp_cli.bspline.lattice.too_coarse`: the warp carried next to nothing.)
    """
    from ..bspline.lattice import too_coarse

    why = too_coarse(shape_xyz, spec.capture.lattice, spec.capture.oversample)
    if why is not None:
        raise doc.error(("capture", "oversample"), why)


def _capture_early(reading, given, settings, name):
    """``(values choice, capture)``, started before the spec is checked.

    The choice (:func:`.defaults.choose_values` with the values ``given``) and,
    for intensities, the capture with ``settings``: each None where it cannot
    be made (the work after the check then reports why, in order).
    """
    from .defaults import choose_values

    try:
        vol = reading.result()
        choice = choose_values(vol.data, given, name=name, meta=vol.meta)
    except Exception:
        return None, None
    if choice.is_labels or settings is None:  # (labels: their own capture)
        return choice, None
    try:
        return choice, capture_input(vol, settings, name)
    except Exception:
        return choice, None


def capture_spec(spec, cap):
    """``spec`` with the capture settings of ``cap`` (a capture file), for a label warp of it.

    The label warp makes its own capture from the spec's settings; a capture
    file's are its own (the spec's given ones were checked to agree), its
    pad the spec's if given, else the file's.
    """
    from dataclasses import replace

    from ..bspline.plan import CaptureSettings

    pad = spec.capture.pad if "pad" in spec.capture_given else cap.pad
    return replace(spec, capture=CaptureSettings(
        lattice=tuple(cap.grid.lattice), placement=cap.placement, oversample=cap.oversample,
        pad=pad, sampling=cap.sampling))


class WarpInput(AbstractContextManager):
    """A warp's input and spec, read, checked and captured with the work overlapped.

    Give ``read_volume`` (a volume input: called on a worker thread at once; a
    mapped, not copied, volume is best, the warp only reads it) or
    ``read_capture`` (a capture file, read when :meth:`source` asks for it).
    ``values``: the command line's ``--values`` (``"intensity"``,
    ``"labels"``; ``labels=True`` is ``"labels"``), else the spec's, else the
    label rule decides (:func:`.defaults.choose_values`, on the worker
    thread, before any intensity capture is made).
    ``name`` (the input's file) prefixes the capture's errors. Use it as a
    context manager; :meth:`load_spec` first, then :meth:`source`, after
    which :attr:`choice` says how the samples are warped and :attr:`spec`
    is the spec to warp with::

        with WarpInput(path, read_volume=lambda: read_volume(path, mmap=True)) as w:
            doc, spec = w.load_spec(spec_path)
            cap = w.source(doc, spec)
    """

    def __init__(self, name: str, *, read_volume: Callable[[], Volume] | None = None,
                 read_capture: Callable[[], object] | None = None, labels: bool = False,
                 values: str | None = None):
        if (read_volume is None) == (read_capture is None):
            raise ValueError("give read_volume or read_capture (one of them)")
        self.name = name
        self._read_volume = read_volume
        self._read_capture = read_capture
        self._values = "labels" if labels else values
        self._started = []  # the :func:`~volwarp_cli.parallel.beside` work, waited for on exit
        self._reading = None
        self._early = None
        self._early_given = None
        self._settings = None
        #: how the samples are warped (:class:`.defaults.ValuesChoice`), after :meth:`source`
        self.choice = None
        #: the spec to warp with, after :meth:`source` (a capture file's labels: its settings)
        self.spec = None

    def __enter__(self):
        self._started = []
        if self._read_volume is not None:  # in this run's context (its files, threads, budget)
            self._reading = beside(self._read_volume)
            self._started.append(self._reading)
        return self

    def __exit__(self, *exc_info):
        self._reading = self._early = None
        for started in self._started:  # (ended before the with does, as they were started)
            started.wait()
        self._started = []
        return None

    def load_spec(self, spec_path):
        """The spec, loaded and checked against its schema: ``(doc, WarpSpec)``.

        While the schema check runs, the volume (once read) is captured with the
        settings the spec gives (unless it is a label map).
        """
        from ..bspline.plan import read_warp_spec
        from ..spec.loader import load_schema, load_spec, validate
        from . import prepare as _prepare  # noqa: F401 - imported while the volume is read

        doc = load_spec(spec_path)
        if self._reading is not None:
            early = _unchecked_spec(doc)
            self._settings = early.capture if early is not None else None
            self._early_given = self._values or (early.values if early is not None else None)
            self._early = beside(_capture_early, self._reading, self._early_given,
                                 self._settings, self.name)
            self._started.append(self._early)
        validate(doc, load_schema("warp"))
        return doc, read_warp_spec(doc)

    def source(self, doc, spec):
        """What to warp: the :class:`~volwarp_cli.bspline.capture.Capture`, or for labels the label map Volume.

        Labels (:attr:`choice`): the label map is captured by
        :class:`LabelMapWarp`; a capture file's is the volume it holds
        (:class:`~volwarp_cli.bspline.capture.CapturedInput`, on the subdivision grid only), to
        be warped with :attr:`spec` (the file's capture settings).

        A capture file's settings are checked against the spec's (a spec error);
        a volume's read error comes here, after every spec error.
        """
        from .defaults import choose_values
        from .prepare import check_capture_settings

        given = self._values or spec.values
        self.spec = spec
        if self._read_capture is not None:
            with timed(f"read {self.name}"):
                cap = self._read_capture()
            check_capture_settings(doc, spec, cap, self.name)
            return self._capture_source(cap, spec, given)
        if self._reading is None:
            raise RuntimeError("WarpInput.source needs load_spec first, inside the with")
        vol = self._reading.result()  # a read error, after any spec error
        check_oversample(doc, spec, vol.shape_xyz)
        choice, early = self._early.result() if given == self._early_given else (None, None)
        if self._settings != spec.capture:
            early = None
        self._reading = self._early = None  # the futures hold the volume and the capture
        if choice is None:
            choice = choose_values(vol.data, given, name=self.name, meta=vol.meta)
        self._chose(choice)
        if choice.is_labels:
            return vol
        if early is not None:
            return early
        return capture_input(vol, spec.capture, self.name)

    def _chose(self, choice) -> None:
        from .defaults import warn_once

        self.choice = choice
        warn_once(choice.warning)
        log.info("%s: %s", self.name, choice.describe())

    def _capture_source(self, cap, spec, given):
        """:meth:`source` of a capture file: the capture, or the label map it holds."""
        choice, view = capture_values(cap, given, self.name)
        self._chose(choice)
        if not choice.is_labels:
            return cap
        self.spec = capture_spec(spec, cap)
        with timed(f"labels: the map {self.name} holds"):
            return cap.geometry.with_data(view[:, :, :])


def capture_values(cap, given: str | None, name: str):
    """How a capture file's samples are warped: ``(ValuesChoice, CapturedInput or None)``.

    On the subdivision grid the capture holds its input's samples
    (:class:`~volwarp_cli.bspline.capture.CapturedInput`): the label rule reads them, as it reads
    a volume. On the spanning grid they are blends of the input's: warped as
    intensities, and labels asked for (``given``) are a usage error.
    """
    from ..bspline.capture import captured_input
    from .defaults import ValuesChoice, choose_values, spanning_cause

    view = captured_input(cap)
    if view is not None:
        return choose_values(view, given, name=name, meta=cap.geometry.meta), view
    how = spanning_cause(cap.placement, cap.oversample)
    if given == "labels":
        raise BadUsage(f"{name}: a capture with {how} holds blended samples, not labels: "
                       "capture the label map with the uniform placement and an integer "
                       "oversample")
    return ValuesChoice("intensity", "given" if given else
                        f"a capture with {how}: its samples blended"), None


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


class LatticeMoves:
    """What every warp of a capture ``cap`` through planned ``frames`` gives its exports.

    The final lattice (the moved points, meshes and fields are its map) and
    the drag handles' report.
    """

    @property
    def final_lattice(self) -> np.ndarray:
        """The control-point offsets after the last step."""
        return self.frames[-1].dq if self.frames else self.cap.dq

    def handles(self) -> list[dict]:
        """:func:`handle_report` of this warp's drags."""
        return handle_report(self.cap, self.frames)

    def frame_names(self, pattern: str) -> list[str]:
        """Every frame's file (``--frames-to`` ``pattern``), each its own; checked before any is made.

        A pattern can number the frames of one spec step and not the others
        (``{sub}`` restarts at each step): two frames of one name would
        replace each other (a :class:`BadUsage`). Every frame's name is then
        checked as an output of its own (:func:`~volwarp_cli.io.check_output_path`):
        not an input, not a file ``-o`` or an export names (a detached
        header's data file included), its folder there.
        """
        from ..io import check_output_path
        from ..io.inputs import one_file_twice

        names = [pattern.format(**frame_fields(n, fr))
                 for n, fr in enumerate([None, *self.frames])]
        twice = one_file_twice(enumerate(names))
        if twice is not None:
            fix = ("number them all with {frame} (e.g. {frame:03d}), not {sub} alone"
                   if "{frame" not in pattern else "give {frame} a format that tells them "
                   "apart (e.g. {frame:03d}), and each frame its own folder")
            raise BadUsage(f"--frames-to: {pattern!r} names frames {twice[0]} and {twice[1]} "
                           f"both {twice[2]}; {fix}")
        for name in names:
            check_output_path(name, option="--frames-to")
        return names


class IntensityWarp(LatticeMoves):
    """The warp of a captured volume (:class:`~volwarp_cli.bspline.capture.Capture`) by a checked spec.

    Construction plans every lattice state and builds the scene; then the
    final lattice's output is an :meth:`operation` of the executor (by blocks
    or whole), :meth:`compute` computes it whole here, and
    :meth:`compute_frames` every frame, incrementally.
    """

    def __init__(self, cap, doc, spec, options: WarpOptions = WarpOptions(), *,
                 name: str = "input"):
        from .defaults import resampling_warning, warn_once
        from .prepare import background_of, grid_of, prepare

        self.cap = cap
        self.options = options
        self.name = name  # (the input's file: in messages)
        #: the output's grid ("input" or "grow") and why
        self.grid, self.grid_why = grid_of(spec, cap, options.output_grid)
        #: the value where nothing lands, and why
        self.background, self.background_why = background_of(spec, cap, options.background)
        _check_background_fits(self.background, self.background_why,
                               options.dtype or getattr(cap.geometry, "dtype", None))
        try:
            self.scene, self.frames = prepare(
                cap, doc, spec, method=options.pushforward, evaluator=options.evaluator,
                background=self.background, allow_growth=options.allow_growth, grid=self.grid)
        except OutOfMemoryError as exc:  # the target this input and spec ask for
            raise OutOfMemoryError(f"{name}: {exc}") from None
        log.info("output grid: %s (%s)", self.grid, self.grid_why)
        log.info("background: %.9g (%s)", self.background, self.background_why)
        warn_once(resampling_warning(cap.placement, cap.oversample, cap.grid.subdivision))
        self._say_if_nothing_lands()

    def _say_if_nothing_lands(self) -> None:
        """Warn when the final lattice carries the whole model off the output's grid.

        Every voxel is then the background, exit 0: moves in millimetres meant
        as voxels, a displacement ten times too large. Known from the lattice
        alone (:func:`.blocks.domain_box`, the control points' hull: a bound,
        so a model said to reach nothing reaches nothing). A label map's
        vanished labels are said by its own report.
        """
        from .blocks import domain_box
        from .prepare import output_window_box

        window = output_window_box(self.cap, self.scene, self.options.crop)
        if not domain_box(self.scene, window, self.final_lattice).empty:
            return
        grow = " (or --grid grow for a grid that holds it)" if self.grid == "input" else ""
        log.warning("warning: every voxel of the warp of %s is the background (%g): its moves "
                    "carry the whole model off the output's grid; check the spec's moves and "
                    "its units (world: LPS mm; voxel: input voxel indices)%s", self.name,
                    self.background, grow)

    def summary(self) -> dict:
        """The ``--json`` keys of the choices made: grid, background."""
        return {"grid": self.grid, "background": self.background}



    def output(self, target: np.ndarray) -> Volume:
        """A target array as the output Volume (cropped and cast as the options say)."""
        from .prepare import output_volume

        return output_volume(self.cap, self.scene, target, crop=self.options.crop,
                             dtype=self.options.dtype)

    def output_header(self) -> Header:
        """The output's :class:`~volwarp_cli.volume.Header`: its shape, dtype and geometry."""
        from .prepare import output_planes

        header, _ = output_planes(self.cap, self.scene, crop=self.options.crop,
                                  dtype=self.options.dtype)
        return header

    def operation(self, target=None, source=None):
        """The final lattice's output as an operation (:class:`.blocks.WarpOperation`).

        ``target``: the output (:class:`~volwarp_cli.execute.Target`; default
        one at no path, for :meth:`compute`). ``source``: the input's samples,
        sliceable, read box by box by the blocks (a
        :class:`~volwarp_cli.io.lazy.LazySource`, reopened by path in other processes);
        None: the capture's own samples (:meth:`sampler`).
        """
        from ..execute import Target
        from .blocks import WarpOperation
        from .prepare import output_window_box

        if self.frames:
            self.scene.set_lattice(self.frames[-1].dq)
        if target is None:
            header = self.output_header()
            target = Target(None, header, header.dtype)
        window = output_window_box(self.cap, self.scene, self.options.crop)
        return WarpOperation(self.scene, source, self.cap.placement, self.cap.sampling, window,
                             target, sampler=self.sampler() if source is None else None,
                             name=self.name)

    def compute(self) -> Volume:
        """The final lattice's output, computed whole on this process's threads."""
        from .. import parallel

        op = self.operation()
        data = op.compute(op.grid.box, threads=parallel.threads())[op.KEY]
        return op.targets[op.KEY].header.with_data(data)

    def compute_frames(self, on_frame: OnFrame) -> Volume:
        """Every frame (0: unwarped, then each increment), incrementally; returns the last.

        Each is handed to ``on_frame`` before the next is made; the last is the output.
        """
        from .prepare import run

        def each(n, fr, target):
            on_frame(frame_fields(n, fr), self.output(target))

        return self.output(run(self.scene, self.frames, each))

    def sampler(self):
        """The capture's samples box by box (:func:`.blocks.warp_block`'s ``sampler``).

        A captured domain as it is; a deferred capture's gather, from the
        input it holds or reads; a capture file's stored domain, read from
        the file.
        """
        from ..bspline.pullback import DomainSampler

        if self.cap.domain is not None:
            return DomainSampler(self.cap.domain)
        return self.cap.sampler


def prepare_label_warp(vol: Volume | Header, doc, spec, options: WarpOptions, name: str):
    """:func:`.labels.prepare_labels` (of a map or its Header) with the options' overrides.

    Returns ``(cap, scene, frames, grid)``, ``grid`` the output's and why.
    """
    from .labels import prepare_labels
    from .prepare import grid_of

    grid = grid_of(spec, None, options.output_grid)
    try:
        cap, scene, frames = prepare_labels(vol, doc, spec, method=options.pushforward,
                                            evaluator=options.evaluator, source=name,
                                            allow_growth=options.allow_growth, grid=grid[0])
    except OutOfMemoryError as exc:  # the target this input and spec ask for
        raise OutOfMemoryError(f"{name}: {exc}") from None
    log.info("output grid: %s (%s)", *grid)
    return cap, scene, frames, grid


def background_label(samples, given: float | None = None) -> int:
    """A label map's background label, said at -v.

    ``given`` (checked by :func:`.request.check_values_fit`), else the most
    frequent on its border (:func:`~volwarp_cli.border.border_label`).
    """
    if given is not None:
        log.info("labels: background label %d (given)", int(given))
        return int(given)
    from ..border import border_label

    label = border_label(samples)
    log.info("labels: background label %d (the most frequent on the map's border)", label)
    return label



class Deformation(LatticeMoves):
    """A warp's lattice moves and nothing else: what its exports need, no volume computed.

    ``cap``: a capture without samples (:func:`~volwarp_cli.bspline.capture.geometry_capture`,
    :func:`.capture_file.read_capture_lattice`) or any other. The same
    lattice, frames and output grid as the warp of the same input, spec
    and options would have, so moved points, meshes and fields are the same.
    """

    def __init__(self, cap, doc, spec, options: WarpOptions = WarpOptions()):
        from .prepare import grid_of, prepare

        self.cap = cap
        self.options = options
        self.grid, self.grid_why = grid_of(spec, cap, options.output_grid)
        self.scene, self.frames = prepare(
            cap, doc, spec, method=options.pushforward, evaluator=options.evaluator,
            background=0.0, allow_growth=options.allow_growth, grid=self.grid)




class LabelMapWarp(LatticeMoves):
    """The warp of a label map (segmentation) by a checked spec.

    Every output voxel is an input label (see :mod:`.labels`).

    Each frame's lattice gives the whole label warp from the input map, exact (not
    incremental): :meth:`compute` for the final lattice, :meth:`compute_frames`
    for every frame. Both return ``(Volume, report)``, the report per label
    (:func:`.labels.warp_labels`).
    """

    def __init__(self, vol: Volume, doc, spec, options: WarpOptions = WarpOptions(), *,
                 name: str = "input"):
        if options.dtype is not None:
            raise VolwarpError("a label map keeps its own integer type (no dtype)")
        self.vol = vol
        self.options = options
        self.preserve = options.preserve
        self.cap, self.scene, self.frames, (self.grid, self.grid_why) = prepare_label_warp(
            vol, doc, spec, options, name)
        #: the label where nothing lands: the given one, else the most frequent on the
        #: map's border
        self.background = background_label(vol.data, options.background)


    def summary(self) -> dict:
        """The ``--json`` keys of the choices made: the grid."""
        return {"grid": self.grid}


    def warp(self, lattice: np.ndarray) -> tuple[Volume, dict]:
        """The label warp for control-point offsets ``lattice``."""
        from .labels import warp_labels
        from .prepare import output_volume

        self.scene.set_lattice(lattice)
        res = warp_labels(self.vol.data, self.scene, (), preserve=self.preserve,
                          spacing=self.vol.spacing, background=self.background)
        return output_volume(self.cap, self.scene, res.target, crop=self.options.crop), \
            res.report

    def lattices(self) -> Iterator[tuple[dict, np.ndarray]]:
        """Every frame's name fields and lattice: frame 0 (unmoved), then each increment."""
        yield frame_fields(0, None), self.cap.dq
        for n, fr in enumerate(self.frames, start=1):
            yield frame_fields(n, fr), fr.dq

    def compute(self) -> tuple[Volume, dict]:
        """The final lattice's label map and report."""
        return self.warp(self.frames[-1].dq if self.frames else self.cap.dq)

    def compute_frames(self, on_frame: OnFrame) -> tuple[Volume, dict]:
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


def _check_background_fits(background: float, why: str, dtype) -> None:
    """Refuse a background a float output cannot hold (it became inf, without a word).

    Integer outputs clip it and say so (:func:`~volwarp_cli.samples.cast_samples`); a
    float32 output took 1e39 as inf where nothing landed.
    """
    if dtype is None or np.dtype(dtype).kind != "f":
        return
    top = float(np.finfo(np.dtype(dtype)).max)
    if np.isfinite(background) and abs(background) > top:
        where = "--background-value" if why == "given" else "the spec's background"
        raise BadUsage(f"{where} {background:g} is beyond what {np.dtype(dtype).name} holds "
                       f"(at most {top:.4g}): give --dtype float64, or a smaller background")
