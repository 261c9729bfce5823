"""``volwarp warp`` without click: the files a warp reads and writes, and what it did.

The command (:mod:`volwarp_cli.cli.warp`) checks its options and hands a
:class:`WarpFiles` to :func:`warp_files`, which reads the spec and the input,
chooses how the samples are warped, plans the lattice moves and writes the
outputs; the summary it returns is what ``--json`` prints. How the work runs
is the command line's :class:`~volwarp_cli.execute.How`: the final lattice's
warp is one operation of the executor (whole, or by blocks when the sizes
say so), every frame (``--frames-to``) in memory, and the exports alone plan
the lattice and read no sample.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from ..errors import BadUsage, VolwarpError
from ..progress import log, timed
from ..provenance import provenance, stamp
from .run import WarpOptions


@dataclass(frozen=True)
class WarpFiles:
    """A warp's files and choices, checked by the command line.

    ``input``: a volume or a capture file (``is_capture``), opened with
    ``read_volume()`` (whole, mapped where it can be: the frames) or
    ``open_lazy()`` (``(header, source)``: its Header and its samples
    read box by box, reopened by path in other processes). ``spec``: the
    spec file. ``output``: the warped volume (None: ``frames_to`` or the
    exports alone); ``frames_to``: the frames' name pattern
    (:data:`.run.FRAME_FIELDS`); ``exports``: an
    :class:`~.export_outputs.ExportRequests` or None; ``options``: the
    command line's (:class:`.run.WarpOptions`: ``--values``,
    ``--preserve-labels`` among them); ``write``: the volume writer's
    options (``compress``, ``byte_order``, ``ome_zarr_version``, ``pyramid``).
    """

    input: str
    spec: str
    output: str | None
    read_volume: Callable
    open_lazy: Callable
    is_capture: bool = False
    frames_to: str | None = None
    exports: object = None
    options: WarpOptions = WarpOptions()
    write: dict = field(default_factory=lambda: {"compress": False, "byte_order": "little"})

    def stamped(self, vol, inputs=None):
        """``vol`` with this warp's provenance (inputs: the input, unless given)."""
        return stamp(vol, "warp", self.input if inputs is None else inputs, self.spec)


def values_meta(vol, choice):
    """``vol`` (a Volume or Header) whose key/values say what its samples are, as the warp took them.

    (:func:`~volwarp_cli.labelmap.meta_as_taken`: ``--values intensity`` of a label
    map drops its label keys; ``--values labels`` of samples the rule takes for
    intensities records the choice.)
    """
    from ..labelmap import meta_as_taken

    return vol.replace(meta=meta_as_taken(vol.meta, choice.is_labels, choice.against_rule))


def warp_files(req: WarpFiles, how) -> dict:
    """Run the warp ``req`` asks for, ``how`` (:class:`~volwarp_cli.execute.How`) says.

    Returns the ``--json`` summary (see the command's help).
    """
    if req.output is None and not req.frames_to:
        return _exports_only(req, how)
    if req.frames_to:
        return _warp_frames(req)
    return _warp_once(req, how)


def _load_spec(path):
    """The spec: ``(doc, WarpSpec)``, checked against its schema."""
    from ..bspline.plan import read_warp_spec
    from ..spec.loader import load_schema, load_spec, validate

    doc = load_spec(path)
    validate(doc, load_schema("warp"))
    return doc, read_warp_spec(doc)


def _exports_only(req: WarpFiles, how) -> dict:
    """The exports of a warp whose volume is not asked for: the lattice planned, no volume.

    Only the input's geometry is read (a volume's header, a capture file's
    header); the moved points, meshes, transform and fields are those of the
    warp with the same spec and options.
    """
    from .export import check_exportable
    from .prepare import capture_as_spec, check_capture_settings
    from .run import Deformation

    doc, spec = _load_spec(req.spec)
    if req.is_capture:
        from .capture_file import read_capture_lattice

        with timed(f"read {req.input} (header)"):
            cap = read_capture_lattice(req.input)
        check_capture_settings(doc, spec, cap, req.input)
    else:
        from ..bspline.capture import geometry_capture

        header, _ = req.open_lazy()
        cap = capture_as_spec(geometry_capture, spec.capture, req.input, header)
    check_exportable(cap.placement, cap.dq, req.input)
    warp = Deformation(cap, doc, spec, req.options)
    stats = _write_exports(req, warp, how, by_slabs=_exports_by_slabs(req, warp, how))
    # (no volume: no grid of its own; the exports are on the input's)
    return {"output": None, "handles": warp.handles(), "grid": None, **stats}


def plan_final(header, source, doc, spec, options: WarpOptions = WarpOptions(), *,
               name: str = "input", cap=None, choice=None, exportable: bool = False):
    """The final lattice's warp of an input, planned: ``(choice, warp)``; no output computed.

    ``header``: the input's :class:`~volwarp_cli.volume.Header`;
    ``source``: its samples, sliceable (an array, or a lazy source read box
    by box); ``cap``: a capture file's deferred capture instead (its
    ``header``/``source`` None unless its labels are warped, and ``spec``
    then the one with its capture settings: :func:`open_capture_values`).
    How the samples are warped: ``options.values`` (None: the spec's, else
    the label rule, one pass over the samples), unless ``choice`` was made
    (a capture file's). Returns the values choice
    (:class:`.defaults.ValuesChoice`, already said at ``-v``) and the warp:
    a :class:`.label_blocks.OneShotLabelWarp` for labels, else an
    :class:`.run.IntensityWarp` whose :meth:`~.run.IntensityWarp.operation`
    computes the output. ``exportable``: refuse, before any work, a warp
    whose exports cannot be exact.
    """
    from ..bspline.capture import capture_source
    from .defaults import choose_values, warn_once
    from .prepare import capture_as_spec
    from .run import IntensityWarp, check_oversample

    if cap is None:
        check_oversample(doc, spec, header.shape_xyz)
    if choice is None:
        with timed("labels? (the rule, one pass)"):
            choice = choose_values(source, options.values or spec.values, name=name,
                                   meta=header.meta)
    warn_once(choice.warning)
    log.info("%s: %s", name, choice.describe())
    check_values_fit(choice, doc, spec, options, name, getattr(header, "dtype", None))
    if choice.is_labels:
        from .label_blocks import OneShotLabelWarp  # (a label map's only: not every warp's)

        return choice, OneShotLabelWarp(header, source, doc, spec, options, name=name)
    if cap is None:
        with timed("input range (one pass)"):
            cap = capture_as_spec(capture_source, spec.capture, name, header, source)
    if exportable:  # refused before any work where they cannot be exact
        from .export import check_exportable

        check_exportable(cap.placement, cap.dq, name)
    return choice, IntensityWarp(cap, doc, spec, options, name=name)


def open_capture_values(path, doc, spec, values: str | None = None):
    """A capture file opened lazily for :func:`plan_final`: ``(choice, cap, header, source, spec)``.

    Its settings checked against the spec's; how its samples are warped
    chosen (``values``: the command line's, else the spec's, else the label
    rule over the input samples it holds). For labels, the map it holds
    (its Header, samples read box by box; ``cap`` None) and the spec with its
    capture settings; else ``header``, ``source`` None.
    """
    from .capture_file import open_capture_lazy
    from .prepare import check_capture_settings
    from .run import capture_spec, capture_values

    with timed(f"check {path} (one pass)"):
        cap = open_capture_lazy(path)
    check_capture_settings(doc, spec, cap, path)
    with timed(f"labels? (the rule, one pass over {path})"):
        choice, view = capture_values(cap, values or spec.values, path)
    if not choice.is_labels:
        return choice, cap, None, None, spec
    header = cap.geometry.replace(shape=view.shape, dtype=cap.input_dtype)
    return choice, None, header, view, capture_spec(spec, cap)


def _warp_once(req: WarpFiles, how) -> dict:
    """The final lattice's warp (no frames): one operation, run whole or by blocks.

    The input is opened lazily (a capture file's domain left in the file),
    the warp planned (:func:`plan_final`); then :func:`volwarp_cli.execute.run`
    decides, from the output's and the blocks' sizes, whether the output is
    computed whole here or by blocks on the engine (the same code, the same
    bytes).
    """
    from .. import execute

    doc, spec = _load_spec(req.spec)
    cap = choice = None
    if req.is_capture:
        choice, cap, header, source, spec = open_capture_values(req.input, doc, spec,
                                                                req.options.values)
    else:
        header, source = req.open_lazy()
    choice, warp = plan_final(header, source, doc, spec, req.options, name=req.input,
                              cap=cap, choice=choice, exportable=bool(req.exports))
    if choice.is_labels:
        return {**_warp_labels(req, warp, how, choice), **values_json(choice)}
    header = warp.output_header()
    w = req.write
    # (--values intensity: the pyramid's levels take the mean, as asked, not the writer's
    # rule on the warped samples, which took a nearest-pushed map's mode)
    target = execute.Target(req.output, req.stamped(values_meta(header, choice)),
                            header.dtype, compress=w["compress"], byte_order=w["byte_order"],
                            version=w.get("ome_zarr_version", "0.5"),
                            pyramid=w.get("pyramid", 0),
                            labels=False if _intensity_asked(choice) else "auto")
    op = warp.operation(target, source=source)
    # (the output the in-memory warp keeps while the exports are made: none when written
    # as computed)
    held = 0 if execute.written_as_computed(op) else target.nbytes(header.shape)
    slabs = _exports_by_slabs(req, warp, how, held=held)
    ran = execute.run(op, how)
    summary = {"output": str(req.output), "shape": list(header.shape_xyz),
               "handles": warp.handles(), **values_json(choice), **warp.summary()}
    if ran.by_blocks:
        summary.update(blocks=ran.blocks, block=list(ran.block[::-1]))
    if req.exports:
        summary.update(_write_exports(req, warp, how, by_slabs=ran.by_blocks or slabs))
    return summary


def _exports_by_slabs(req: WarpFiles, warp, how, *, held: int = 0) -> bool:
    """Whether the field exports go by slabs although the warp may not: decided before any work.

    By slabs where the warp runs by blocks anyway (``--chunked``), or where
    the whole fields (with ``held``, the output the in-memory warp keeps
    while they are made) do not fit the budget; refused, before any work,
    where they fit neither whole nor by slabs (a NIfTI or compressed field).
    """
    if not req.exports:
        return False  # (the export modules are not imported)
    from ..execute import fits
    from ..memory import ensure_fits_in_memory, human_bytes
    from .export_outputs import block_export_problem, whole_fields_bytes

    need = whole_fields_bytes(req.exports, warp)
    if not need or how.chunked:
        if need and how.chunked:  # (--chunked used: the fields go by slabs for it)
            from ..cli.resources import scale_settings

            scale_settings().used.add("--chunked")
        return bool(need and how.chunked)
    if fits(held + need):
        return False
    problem = block_export_problem(req.exports)
    if problem is not None:
        try:
            ensure_fits_in_memory(held + need, "writing the deformation's fields whole")
        except VolwarpError as exc:
            raise type(exc)(f"{exc}, and by slabs: {problem}") from None
    log.warning("the deformation's field exports need %s: written by slabs",
                human_bytes(held + need))
    return True


def _warp_labels(req: WarpFiles, warp, how, choice) -> dict:
    """A label map's warp (:class:`.label_blocks.LabelWarpOperation`): whole or by slabs.

    The map is read whole when the warp fits the memory budget, else box by
    box by slabs of target planes; :func:`volwarp_cli.execute.run` decides,
    by the sizes, before the map is read. The same output and per-label
    report either way.
    """
    from .. import execute
    from .label_blocks import LabelWarpOperation
    from .labels import format_report

    slabs = _exports_by_slabs(req, warp, how)
    ran = execute.run(LabelWarpOperation(warp, req.output,
                                         req.stamped(values_meta(warp.header, choice)),
                                         req.write), how)
    report, by_slabs = ran.output, ran.by_blocks or slabs
    log.info("per-label volumes (mm^3):\n%s", format_report(report))
    summary = {"output": str(req.output), "shape": list(warp.header.shape_xyz),
               "handles": warp.handles(), "grid": warp.grid, **labels_json(report)}
    if req.exports:
        summary.update(_write_exports(req, warp, how, by_slabs=by_slabs))
    return summary


def _warp_frames(req: WarpFiles) -> dict:
    """Every frame of the warp (``frames_to``), in memory; ``output`` (if given) the last.

    Intensities: frame 0 in full, then each frame a local update of the last
    (the accumulators kept). Labels: each frame the label warp of the input
    map for that frame's lattice.
    """
    from ..io import write_volume
    from .run import IntensityWarp, LabelMapWarp, WarpInput

    if req.is_capture:
        from .capture_file import read_capture

        source = WarpInput(req.input, values=req.options.values,
                           read_capture=lambda: read_capture(req.input))
    else:  # mapped, not copied, where it can be: the warp only reads it
        source = WarpInput(req.input, values=req.options.values, read_volume=req.read_volume)
    with source:
        doc, spec = source.load_spec(req.spec)
        what = source.source(doc, spec)
        choice, spec = source.choice, source.spec
        check_values_fit(choice, doc, spec, req.options, req.input,
                         getattr(what, "dtype", None))
    labels = choice.is_labels

    def write(vol, path):
        with timed(f"write {path}"):
            # (a label map's pyramid levels take the mode, as by blocks: never averaged ids)
            write_volume(req.stamped(values_meta(vol, choice)), path,
                         **req.write,
                         **({"labels": True} if labels else
                            {"labels": False} if _intensity_asked(choice) else {}))

    written = [0]  # frame files

    def write_frame(fields, vol):
        write(vol, req.frames_to.format(**fields))
        written[0] += 1

    def checked(warp):  # (every frame's file its own, before any is made)
        warp.frame_names(req.frames_to)
        return warp

    if labels:
        from .labels import format_report

        warp = checked(LabelMapWarp(what, doc, spec, req.options, name=req.input))
        del what
        out, report = warp.compute_frames(write_frame)
        log.info("per-label volumes (mm^3):\n%s", format_report(report))
        stats = labels_json(report)
    else:
        if req.exports:  # refused before any work where they cannot be exact
            from .export import check_exportable

            check_exportable(what.placement, what.dq, req.input)
        warp = checked(IntensityWarp(what, doc, spec, req.options, name=req.input))
        del what
        out, stats = warp.compute_frames(write_frame), {}
    if req.output is not None:
        write(out, req.output)
    if req.exports:
        stats.update(_write_exports(req, warp, None, by_slabs=False))
    return {"output": None if req.output is None else str(req.output),
            "shape": list(out.shape_xyz), "frames": written[0], "handles": warp.handles(),
            **values_json(choice), **warp.summary(), **stats}


def _write_exports(req: WarpFiles, warp, how, *, by_slabs: bool) -> dict:
    """The deformation's exports, stamped with their provenance; their --json figures.

    Written after the volume: a run that fails or is stopped before its
    output leaves the old exports as they were (each export file is atomic
    on its own). ``by_slabs``: the fields computed and written by slabs of z
    planes within the block budget (a warp by blocks; ``how.block``'s depth
    when given).
    """
    from .export_outputs import FieldBlocks, write_exports

    blocks = None
    if by_slabs:
        from ..execute import block_budget

        blocks = FieldBlocks(memory=block_budget(),
                             depth=how.block[0] if how is not None and how.block else None)
        if how is not None and how.block:  # (used: said so, not warned of as unused)
            from ..cli.resources import scale_settings

            scale_settings().used |= {"--block", "--chunked"}
    exports = req.exports
    mesh_src = [exports.mesh[1]] if exports.mesh is not None else []
    return write_exports(exports, warp, meta=provenance("warp", req.input, req.spec),
                         mesh_meta=provenance("warp", [req.input, *mesh_src], req.spec),
                         blocks=blocks)


def _not_a_label(value: float, dtype) -> str | None:
    """Why ``value`` cannot be a label id of a map of ``dtype`` (the background's), or None."""
    from ..samples import holds_value

    if not float(value).is_integer():
        return "is not a label id (an integer): a label map's background is a label"
    if dtype is not None and not holds_value(dtype, value):
        return f"does not fit the map's {dtype} ids (labels keep the map's own type)"
    return None


def check_values_fit(choice, doc, spec, options: WarpOptions, name, dtype=None) -> None:
    """What a warp as labels, or as intensities, cannot have: usage or spec errors.

    Found once the values are chosen (the rule reads the samples), before
    any work. Where the rule chose, the message names the way out; where the
    spec's ``values: labels`` chose (``options.values``, the command line's,
    None), a clash is the spec's error at that key.
    """
    values = options.values
    if choice.is_labels:
        if choice.ruled:
            way = f"{name} looks like a label map ({choice.labels} labels) and is warped as labels"
        else:
            way = "labels are warped"

        def out(what):
            return (f"{what}; --values intensity warps its samples as intensities"
                    if choice.ruled else what)

        def clash(what):
            if values is None and not choice.ruled:  # the spec's values: labels
                return doc.error(("values",), what)
            return BadUsage(out(what))

        if options.dtype is not None:
            raise clash(f"{way} in the map's own integer type: --dtype does not apply")
        if options.background is not None:
            why = _not_a_label(options.background, dtype)
            if why is not None:
                raise BadUsage(out(f"{way}: --background-value {options.background:g} {why}"))
        if spec.background is not None:
            # (a spec is shared by a scan and its segmentation: its background is the scan's,
            # -1024 for a CT, which would have become a new label around the anatomy; the
            # command line's --background-value names a label for this run)
            raise doc.error(("background",), out(
                f"does not apply: {way} with their most frequent border label as their "
                "background (--background-value N names another for a run)"))
        c = spec.capture
        if c.placement != "uniform" and "placement" in spec.capture_given:
            raise doc.error(("capture", "placement"), out(
                f"{way} with the uniform placement (each domain voxel one input voxel's "
                "label)"))
        if c.oversample != int(c.oversample):
            raise doc.error(("capture", "oversample"), out(
                f"{way} with an integer oversample (each domain voxel one input voxel's "
                "label)"))
    elif options.preserve:
        raise BadUsage(f"--preserve-labels keeps labels, but {name} is warped as intensities "
                       f"({choice.why}): give --values labels")


def values_json(choice) -> dict:
    """The ``--json`` keys of the values choice."""
    return {"values": choice.values, "values_why": choice.why}


def labels_json(report: dict) -> dict:
    """The per-label report (:func:`.labels.warp_labels`) as ``--json`` keys."""
    keys = ("input_voxels", "output_voxels", "input_mm3", "output_mm3", "predicted_mm3")
    return {"labels": [{"label": int(L), **{k: r[k] for k in keys}}
                       for L, r in report["labels"].items()],
            "vanished": [int(L) for L in report["vanished"]],
            "preserved": [int(L) for L in report["preserved"]],
            "background": int(report["background"])}


def _intensity_asked(choice) -> bool:
    """Whether intensities were asked for (the option, the spec, a capture's record), not ruled.

    Then an OME-Zarr output's pyramid takes the mean, whatever the writer's rule would
    say of the warped samples (a nearest-pushed map's mode).
    """
    return choice.values == "intensity" and (choice.why == "given"
                                            or choice.why.startswith("recorded"))
