"""`volwarp warp INPUT|SCENE.vwc --spec WARP.yaml -o OUT`: B-spline volume warping.

Parses and checks the options, then calls the pipeline of
:mod:`volwarp_cli.bspline.run` (read, capture, warp) and writes what it gives.
"""

from __future__ import annotations

import string

import click
import numpy as np
from click.core import ParameterSource

from ..bspline.defaults import GRIDS, VALUES
from ..errors import BadUsage, VolwarpError
from ..io import check_output_path, volume_format, write_volume
from ..progress import timed
from .common import load_input, provenance, stamp
from .options import (
    INPUT_PATH,
    common_options,
    examples,
    finite,
    input_options,
    option,
    output_option,
    write_options,
)
from .resources import scale_options, scale_settings

#: the fields of a --frames-to pattern (:data:`volwarp_cli.bspline.run.FRAME_FIELDS`)
_FIELDS = ("frame", "step", "spec_step", "sub")

PUSHFORWARD_HELP = (
    "How each domain voxel is pushed into the output [default: the spec's, else box]. box: "
    "the papers' antialiasing, each voxel spread over the output voxels its transformed "
    "box overlaps, by overlap volume (smooth edges; with the uniform placement and an "
    "integer oversample an unmoved region is copied exactly). nearest: each voxel lands "
    "whole in the one output voxel "
    "holding its image (the papers' unfiltered map-and-round baseline): jagged edges, and "
    "holes where the warp stretches the model more than the oversample covers.")

JSON_HELP = (
    "After a successful run, print one JSON object on stdout (nothing else goes there; "
    "logs and progress go to stderr). Keys: output (path; null without -o), shape (x y z "
    "voxels of the warped volume), frames (frame files written, with --frames-to), values "
    "and values_why (intensity or labels, and why: given, looks like a label map: N "
    "labels, not a label map), grid (input or grow), background (intensities: the value "
    "where nothing lands), handles (one per "
    "drag handle: step (0-based spec step), index (within the step's drag list), from, "
    "to, reached (world LPS mm; reached: where the solved lattice sends from), miss_mm "
    "(|reached - to|)); with --jacobian-to: jacobian {path, min, max, below_0, below_0_1} "
    "(det dF/dx extremes and the fractions of input voxels below 0 and 0.1); with "
    "--displacement-to: displacement {path, voxels, folded, no_preimage} (output voxel "
    "counts: folded = NaN, no_preimage = without an inverse in the lattice's support); "
    "with --points-in / --mesh-in: points / mesh {path, count, outside}; with labels: "
    "labels (one per input label: label, input_voxels, output_voxels, input_mm3, "
    "output_mm3, predicted_mm3; with --frames-to: the last frame's), vanished and "
    "preserved (label ids); an intensity warp run by blocks: blocks (their count) and "
    "block (x y z voxels of one). A value that is not a finite number is null.")


def _check_pattern(pattern: str) -> None:
    """The --frames-to pattern: known fields only, distinct names for distinct frames."""
    try:
        names = {f for _, f, _, _ in string.Formatter().parse(pattern) if f is not None}
    except ValueError as exc:
        raise click.BadParameter(f"{pattern!r}: {exc}", param_hint="'--frames-to'") from None
    unknown = sorted(n for n in names if n.split(".")[0].split("[")[0] not in _FIELDS)
    if unknown:
        raise click.BadParameter(f"unknown field {{{unknown[0]}}} (use {{frame}} or {{step}}, "
                                 "e.g. 'out_{frame:03d}.nrrd')", param_hint="'--frames-to'")
    try:
        a = pattern.format(frame=1, step=1, spec_step=1, sub=1)
        b = pattern.format(frame=2, step=2, spec_step=1, sub=2)
    except (ValueError, KeyError, IndexError, TypeError, AttributeError) as exc:
        # e.g. {frame[0]} (an int has no items) or {frame.x}
        raise click.BadParameter(f"{pattern!r}: {exc}", param_hint="'--frames-to'") from None
    if a == b:
        raise click.BadParameter("the pattern must number the frames, e.g. "
                                 "'out_{frame:03d}.nrrd'", param_hint="'--frames-to'")
    try:
        volume_format(a)
    except VolwarpError as exc:
        raise click.BadParameter(str(exc), param_hint="'--frames-to'") from None
    from ..io.inputs import refuse_pattern_over_input

    refuse_pattern_over_input(pattern, option="--frames-to")  # any frame's name an input's
    check_output_path(a, option="--frames-to")


VALUES_HELP = (
    "How INPUT's samples are warped [default: the spec's values, else labels when INPUT "
    "looks like a label map (integer ids whose values are regions, floats that are all "
    "integers too: `volwarp info` says so), else intensity]. intensity: box-filtered and "
    "blended (scans, densities, distance fields). labels: each output voxel takes the label "
    "of largest box-filter weight (the map's most frequent border label, its background, "
    "competes); ids are never averaged. -v prints each label's volume before and after "
    "(--json: the labels key); with --frames-to, those of the last frame. A capture file "
    "(.vwc) of the uniform placement at an integer oversample holds its input's samples, and "
    "the same rule applies to them. -v and --json say which, and why.")

GRID_HELP = (
    "The output's grid [default: the spec's grid, else input; a pad given (the spec's "
    "capture.pad, `capture --pad`) asks for grow]. input: the input's own grid (shape, "
    "origin, spacing): a scan stays where it was, and what moves past its box is cut off. "
    "grow: padded to hold the whole moved model (the papers' modelling case), the origin "
    "shifted so that unmoved anatomy stays in place; the padding is the spec's capture.pad, "
    "else the largest displacement + 1.")

BACKGROUND_HELP = (
    "Value of the space around the model, given to uncovered output voxels and blended into "
    "partly covered ones [default: the spec's background, else the median of INPUT's border "
    "samples (its six faces, NaN left out): what the scan has outside its anatomy, e.g. "
    "-1024 for a CT, 0 for an MRI; -v prints it]; e.g. a large positive distance for a "
    "signed distance field. Intensities only (a label map's background is its most "
    "frequent border label).")

#: options that shape the warped volume only: refused when no volume is written
_VOLUME_ONLY = (("--values", "values"), ("--labels", "labels"), ("--pushforward", "pushforward"),
                ("--evaluator", "evaluator"), ("--background-value", "background"),
                ("--preserve-labels", "preserve_labels"), ("--dtype", "dtype"),
                ("--compress", "compress"), ("--byte-order", "byte_order"),
                ("--ome-zarr-version", "ome_zarr_version"), ("--pyramid", "pyramid"))
#: what --grid and --crop change without a volume: the displacement field's grid
_GRID_OPTIONS = (("--grid", "grid"), ("--crop", "crop"), ("--allow-growth", "allow_growth"))


@click.command(name="warp", epilog=examples(
    "volwarp warp head.nrrd --spec bend.yaml -o bent.nrrd --points-in p.csv --points-to q.csv",
    "volwarp warp block.vwc --spec pull.yaml -o pulled.nrrd --grid grow "
    "--frames-to 'pulled_{frame:03d}.nrrd'",
))
@click.argument("input", type=INPUT_PATH)
@click.option("--spec", "spec_path", required=True, type=INPUT_PATH,
              help="Warp spec (YAML; schema specs/warp.schema.json).")
@output_option("Warped volume (format by extension). Without it (and --frames-to) no "
               "volume is computed: the exports alone are written (--points-to, "
               "--mesh-to, --transform-to, the fields); at least one output is needed.",
               required=False)
@click.option("--frames-to", default=None, metavar="PATTERN",
              help="Also write every animation frame, e.g. 'out_{frame:03d}.nrrd' "
                   "({frame} and its alias {step}: 0 = unwarped, then one per increment; "
                   "{spec_step}, {sub}: the spec step and the increment within it). A label "
                   "map's frames are each the label warp recomputed exactly from the input "
                   "map for that frame's lattice (not incremental: each frame costs a whole "
                   "label warp).")
@click.option("--pushforward", type=click.Choice(["box", "nearest"]), default=None,
              help=PUSHFORWARD_HELP)
@click.option("--evaluator", type=click.Choice(["separable", "table"]), default=None,
              help="Deformation evaluator [default: the spec's, else separable]: separable "
                   "(three 1-D passes) or table (the papers' tabulated tensor-product "
                   "weights); both give the same output.")
@option("--background-value", "background", was="--background", type=float, default=None,
        metavar="B", callback=finite, help=BACKGROUND_HELP)
@click.option("--grid", type=click.Choice(GRIDS), default=None, help=GRID_HELP)
@click.option("--crop", is_flag=True, help="The same as --grid input.")
@click.option("--values", type=click.Choice(VALUES), default=None, help=VALUES_HELP)
@click.option("--labels", is_flag=True, help="The same as --values labels.")
@click.option("--preserve-labels", is_flag=True,
              help="Labels: a label that would vanish keeps its voxel of largest weight.")
@click.option("--displacement-to", default=None, metavar="FIELD",
              help="Write the resampling displacement field y -> F^-1(y) - y (LPS mm) on the "
                   "output grid (see --grid), as ITK, ANTs and Slicer resample with (.nii.gz "
                   "or .nrrd); NaN where the map folds or has no inverse. With --chunked: "
                   "written by slabs, as .nrrd only, uncompressed (the same values).")
@click.option("--forward-field-to", default=None, metavar="FIELD",
              help="Write the forward (modelling) field x -> F(x) - x (LPS mm) on the input "
                   "grid (.nii.gz or .nrrd; with --chunked: by slabs, .nrrd only, uncompressed).")
@click.option("--jacobian-to", default=None, metavar="MAP",
              help="Write det dF/dx on the input grid (float32, any volume format; with "
                   "--chunked: by slabs, a format written by blocks: uncompressed .nrrd, "
                   ".mha, raw or .ome.zarr).")
@click.option("--transform-to", default=None, metavar="F.tfm",
              help="Write the forward map as an ITK BSplineTransform (.tfm), for moving "
                   "points; ITK tools read it as a resampling transform: do not resample "
                   "the input with it (use --displacement-to).")
@click.option("--points-in", default=None, type=INPUT_PATH, metavar="P.csv",
              help="Points to move by the forward map: a CSV with x, y, z columns (LPS mm; "
                   "ANTs' layout works) or a Slicer .mrk.json markups file.")
@click.option("--points-to", default=None, metavar="Q.csv",
              help="Where the moved points go (the same format as --points-in).")
@click.option("--mesh-in", default=None, type=INPUT_PATH, metavar="M.ply",
              help="A mesh (PLY, world coordinates) whose vertices to move by the forward map.")
@click.option("--mesh-to", default=None, metavar="M2.ply",
              help="The moved mesh, normals recomputed (.ply .stl .obj .vtp .vtk).")
@click.option("--allow-growth", is_flag=True,
              help="With --grid grow: let the padding the moves need make the output more "
                   "than 2x the input (and more than 64 voxels larger) along an axis; refused "
                   "otherwise, naming the sizes (a mistyped 320 mm drag made a 181x217x1701 "
                   "volume).")
@click.option("--json", "as_json", is_flag=True, help=JSON_HELP)
@write_options
@input_options
@scale_options
@common_options
def command(input, spec_path, output, frames_to, pushforward, evaluator, background, grid,
            crop, values, labels, preserve_labels, displacement_to, forward_field_to,
            jacobian_to, transform_to, points_in, points_to, mesh_in, mesh_to, allow_growth,
            as_json, dtype, compress, byte_order, raw, volume_index, dicom, ome_zarr):
    """Warp INPUT (a volume, or a capture file .vwc) as the spec says.

    A plain volume is captured on the fly with the spec's `capture` settings
    (lattice, placement, oversample, pad, sampling: see `volwarp capture
    --help`). By default the output is on the input's grid (--grid grow for
    a grid that holds the whole moved model), where nothing lands it takes
    the input's border value, and a label map (as `volwarp info` hints) is
    warped as labels: -v prints these choices. The output keeps the input's
    dtype, spacing, direction and key/values.
    """
    from ..bspline.defaults import new_run
    from ..bspline.run import WarpOptions

    new_run()
    values = _given_values(values, labels)
    if crop and grid == "grow":
        raise click.UsageError("--crop puts the output on the input's grid: it does not go "
                               "with --grid grow")
    if allow_growth and (crop or grid == "input"):
        raise click.UsageError("--allow-growth lets a grown grid grow: give --grid grow")
    if output is not None:
        check_output_path(output, option="-o")
    is_capture = input.lower().endswith(".vwc")
    if values == "labels" and dtype is not None:
        raise click.UsageError("labels keep the label map's own integer type (no --dtype)")
    if values == "labels" and background is not None:
        raise click.UsageError("--background-value does not apply to a label map (its "
                               "background is its most frequent border label)")
    if preserve_labels and values == "intensity":
        raise click.UsageError("--preserve-labels keeps labels: it does not go with "
                               "--values intensity")
    if frames_to:
        _check_pattern(frames_to)
    exports = _check_exports(displacement_to, forward_field_to, jacobian_to, transform_to,
                             points_in, points_to, mesh_in, mesh_to)
    if output is None and not frames_to and not exports:
        raise click.UsageError("nothing to write: give -o OUT (the warped volume), "
                               "--frames-to, or an export (--points-to, --mesh-to, "
                               "--transform-to, --displacement-to, --forward-field-to, "
                               "--jacobian-to)")
    if is_capture and (raw is not None or volume_index is not None or dicom is not None):
        raise click.UsageError("--raw-*, --volume-index and the DICOM options describe volume "
                               f"inputs, not the capture file {input}")
    options = WarpOptions(pushforward=pushforward, evaluator=evaluator, background=background,
                          crop=crop, dtype=dtype, allow_growth=allow_growth, grid=grid)
    blocks_refused = _blocks_refused(frames_to)
    chunked = scale_settings().chunked
    if chunked and blocks_refused:
        raise click.UsageError(f"--chunked warps a volume or a capture file to one output: "
                               f"not {blocks_refused} (these run in memory)")
    exports_refused = None
    if exports:
        from ..bspline.export_outputs import block_export_problem

        exports_refused = block_export_problem(exports)
        if chunked and exports_refused:
            raise click.UsageError(f"--chunked: {exports_refused}")
    if output is None and not frames_to:  # the exports alone: no volume is computed
        _refuse_volume_options(bool(displacement_to))
        summary = _exports_only(input, spec_path, options, exports, is_capture, raw,
                                volume_index, dicom)
        if as_json:
            _print_json(summary)
        return
    write_kw = dict(compress=compress, byte_order=byte_order, **ome_zarr)
    if frames_to:
        summary = _warp_frames(input, spec_path, output, options, frames_to, values,
                               preserve_labels, exports, is_capture, raw, volume_index, dicom,
                               write_kw)
    else:
        summary = _warp_once(input, spec_path, output, options, raw, volume_index, write_kw,
                             values=values, preserve=preserve_labels, dicom=dicom,
                             exports=exports, is_capture=is_capture,
                             blocks_refused=exports_refused)
    if as_json:
        _print_json(summary)


def _given_values(values, labels) -> str | None:
    """``--values``, with ``--labels`` as ``--values labels``; None: not given."""
    if labels:
        if values == "intensity":
            raise click.UsageError("--labels is --values labels: it does not go with "
                                   "--values intensity")
        return "labels"
    return values


def _refuse_volume_options(displacement: bool) -> None:
    """Without a volume output: the options that shape only the volume are usage errors.

    (No option is parsed and ignored.) ``displacement``: a displacement
    field is written, on the output grid that --grid and --crop choose.
    """
    ctx = click.get_current_context()
    given = []
    for name, key in _VOLUME_ONLY + (() if displacement else _GRID_OPTIONS):
        value = ctx.params.get(key)
        if key in ("byte_order", "ome_zarr_version", "pyramid"):
            if ctx.get_parameter_source(key) in (ParameterSource.COMMANDLINE,
                                                 ParameterSource.ENVIRONMENT):
                given.append(name)
        elif value not in (None, False):
            given.append(name)
    if given:
        raise click.UsageError(f"{', '.join(given)} shape{'s' if len(given) == 1 else ''} "
                               "the warped volume, and none is written: give -o OUT, or "
                               "leave them out")


def _blocks_refused(frames_to) -> str | None:
    """Why this warp cannot run by blocks (a phrase), or None.

    (The deformation's exports run by blocks too, but for a NIfTI field or a
    Jacobian in a format not written by blocks:
    :func:`~volwarp_cli.bspline.export_outputs.block_export_problem`.)
    """
    return "--frames-to" if frames_to else None


def _exports_only(input, spec_path, options, exports, is_capture, raw, volume_index,
                  dicom) -> dict:
    """The exports of a warp whose volume is not asked for: the lattice planned, no volume.

    Only the input's geometry is read (a volume's header, a capture file's
    header); the moved points, meshes, transform and fields are those of the
    warp with the same spec and options.
    """
    from ..bspline.export import check_exportable
    from ..bspline.plan import read_warp_spec
    from ..bspline.run import Deformation
    from ..bspline.warp import check_capture_settings
    from ..spec.loader import load_schema, load_spec, validate

    doc = load_spec(spec_path)
    validate(doc, load_schema("warp"))
    spec = read_warp_spec(doc)
    if is_capture:
        from ..bspline.capture_file import read_capture_lattice

        with timed(f"read {input} (header)"):
            cap = read_capture_lattice(input)
        check_capture_settings(doc, spec, cap, input)
    else:
        from ..bspline.capture import geometry_capture
        from .chunked import lazy_input

        template, _ = lazy_input(input, raw, volume_index, dicom)
        c = spec.capture
        try:
            cap = geometry_capture(template, lattice=c.lattice, placement=c.placement,
                                   oversample=c.oversample, sampling=c.sampling)
        except VolwarpError as exc:
            raise VolwarpError(f"{input}: {exc}") from None
    check_exportable(cap.placement, cap.dq, input)
    warp = Deformation(cap, doc, spec, options)
    stats = _write_exports(exports, warp, input, spec_path,
                           by_slabs=bool(scale_settings().chunked))
    # (no volume: no grid of its own; the exports are on the input's)
    return {"output": None, "handles": warp.handles(), "grid": None, **stats}


def _values_choice_json(choice) -> dict:
    """The --json keys of the values choice."""
    return {"values": choice.values, "values_why": choice.why}


def _check_labels_fit(choice, doc, spec, options, preserve: bool, name, values) -> None:
    """What a warp as labels, or as intensities, cannot have: usage or spec errors.

    Found once the values are chosen (the rule reads the samples), before
    any work. Where the rule chose, the message names the way out; where the
    spec's ``values: labels`` chose (``values``, the command line's, None),
    a clash is the spec's error at that key.
    """
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
            raise clash(f"{way} with their most frequent border label as their background: "
                        "--background-value does not apply")
        if spec.background is not None:
            raise doc.error(("background",), out(f"does not apply: {way} with their most "
                                                 "frequent border label as their background"))
        c = spec.capture
        if c.placement != "uniform" and "placement" in spec.capture_given:
            raise doc.error(("capture", "placement"), out(
                f"{way} with the uniform placement (each domain voxel one input voxel's "
                "label)"))
        if c.oversample != int(c.oversample):
            raise doc.error(("capture", "oversample"), out(
                f"{way} with an integer oversample (each domain voxel one input voxel's "
                "label)"))
    elif preserve:
        raise BadUsage(f"--preserve-labels keeps labels, but {name} is warped as intensities "
                       f"({choice.why}): give --values labels")


def _warp_once(input, spec_path, output, options, raw, volume_index, write_kw, *,
               values: str | None = None, preserve: bool = False, dicom=None, exports=None,
               is_capture: bool = False, blocks_refused: str | None = None) -> dict:
    """The final lattice's warp (no frames): one operation, run whole or by blocks.

    The input is opened lazily (a capture file's domain left in the file),
    the values chosen (``values``: the command line's; None: the spec's,
    else the label rule in one pass over the samples), the lattice planned;
    then :func:`volwarp_cli.execute.run` decides, from the output's and the
    blocks' sizes, whether the output is computed whole here or by blocks on
    the engine (the same code, the same bytes). ``blocks_refused``: why the
    run may not go by blocks (exports written whole), or None.
    """
    from .. import execute
    from ..bspline.capture import capture_source
    from ..bspline.defaults import choose_values, warn_once
    from ..bspline.plan import read_warp_spec
    from ..bspline.run import IntensityWarp, capture_spec, capture_values
    from ..progress import log
    from ..spec.loader import load_schema, load_spec, validate
    from .chunked import lazy_input

    doc = load_spec(spec_path)
    validate(doc, load_schema("warp"))
    spec = read_warp_spec(doc)
    given = values or spec.values
    if is_capture:
        from ..bspline.capture_file import open_capture_lazy
        from ..bspline.warp import check_capture_settings

        with timed(f"check {input} (one pass)"):
            cap = open_capture_lazy(input)
        check_capture_settings(doc, spec, cap, input)
        template = source = None
        with timed(f"labels? (the rule, one pass over {input})"):
            choice, view = capture_values(cap, given, input)
        if choice.is_labels:  # the label map the capture holds, read box by box
            template = cap.geometry.with_data(np.broadcast_to(
                np.zeros((), cap.input_dtype), view.shape))
            source, spec = view, capture_spec(spec, cap)
    else:
        template, source = lazy_input(input, raw, volume_index, dicom)
        with timed("labels? (the rule, one pass)"):
            choice = choose_values(source, given, name=input)
    warn_once(choice.warning)
    log.info("%s: %s", input, choice.describe())
    _check_labels_fit(choice, doc, spec, options, preserve, input, values)
    settings = scale_settings()
    how = execute.How(chunked=False if blocks_refused else settings.chunked,
                      block=settings.block, open_engine=settings.open_engine)
    if choice.is_labels:
        summary = _warp_labels(template, source, input, spec_path, output, options, write_kw,
                               doc, spec, how, preserve=preserve, exports=exports)
        return {**summary, **_values_choice_json(choice)}
    if not is_capture:
        c = spec.capture
        with timed("input range (one pass)"):
            try:
                cap = capture_source(template, source, lattice=c.lattice,
                                     placement=c.placement, oversample=c.oversample,
                                     sampling=c.sampling)
            except VolwarpError as exc:
                raise VolwarpError(f"{input}: {exc}") from None
    if exports:  # refused before any work where they cannot be exact
        from ..bspline.export import check_exportable

        check_exportable(cap.placement, cap.dq, input)
    warp = IntensityWarp(cap, doc, spec, options, name=input)
    target = execute.Target(output, stamp(warp.output_template(), "warp", input, spec_path),
                            warp.output_template().dtype, compress=write_kw["compress"],
                            byte_order=write_kw["byte_order"],
                            version=write_kw.get("ome_zarr_version", "0.5"),
                            pyramid=write_kw.get("pyramid", 0))
    ran = execute.run(warp.operation(target, source=source), how)
    summary = {"output": str(output), "shape": list(target.template.shape_xyz),
               "handles": warp.handles(), **_values_choice_json(choice), **warp.summary()}
    if ran.by_blocks:
        summary.update(blocks=ran.blocks, block=list(ran.block[::-1]))
    if exports:
        summary.update(_write_exports(exports, warp, input, spec_path, by_slabs=ran.by_blocks))
    return summary


def _write_exports(exports, warp, input, spec_path, *, by_slabs: bool) -> dict:
    """The deformation's exports, stamped with their provenance; their --json figures.

    Written after -o: a run that fails or is stopped before its output leaves
    the old exports as they were (each export file is atomic on its own).
    ``by_slabs``: the fields computed and written by slabs of z planes within
    the block budget (a warp by blocks).
    """
    from ..bspline.export_outputs import FieldBlocks, write_exports

    blocks = None
    if by_slabs:
        from .chunked import block_budget

        settings = scale_settings()
        blocks = FieldBlocks(memory=block_budget(),
                             depth=settings.block[0] if settings.block else None)
    mesh_src = [exports.mesh[1]] if exports.mesh is not None else []
    return write_exports(exports, warp, meta=provenance("warp", input, spec_path),
                         mesh_meta=provenance("warp", [input, *mesh_src], spec_path),
                         blocks=blocks)


def _warp_labels(template, source, input, spec_path, output, options, write_kw, doc, spec,
                 how, *, preserve=False, exports=None) -> dict:
    """A label map's warp (:class:`~volwarp_cli.bspline.run.LabelMapBlocks`): whole or by slabs.

    ``source``: the map's samples, sliceable (read whole when the warp fits the
    memory budget, else box by box by slabs of target planes); ``how``: as
    :func:`volwarp_cli.execute.run` takes it, and decided the same way, by
    the sizes, before the map is read. The same output and per-label report
    either way.
    """
    from .. import execute
    from ..bspline.labels import format_report
    from ..bspline.run import LabelMapBlocks
    from ..memory import human_bytes
    from ..progress import log

    warp = LabelMapBlocks(template, source, doc, spec, options, preserve=preserve, name=input)
    stamped = stamp(warp.template, "warp", input, spec_path)
    need = warp.memory_whole()
    if how.chunked is not True and execute.fits(need):
        out, report = warp.render_whole()
        with timed(f"write {output}"):  # (pyramid levels take the mode: never averaged ids)
            write_volume(stamped.with_data(out.data, origin=out.origin), output, **write_kw,
                         labels=True)
        by_slabs = False
    else:
        what = f"the warp of {input}'s labels"
        nbytes = warp.template.data.size * warp.template.dtype.itemsize
        execute.refuse_unmakeable(what, need, [(output, nbytes)], chunked=how.chunked,
                                  compress=write_kw["compress"],
                                  pyramid=write_kw.get("pyramid", 0))
        if how.chunked is None:
            log.warning("%s needs %s: running by blocks (--no-chunked to refuse instead)",
                        what, human_bytes(need))
        settings = scale_settings()
        with how.open_engine() as engine:
            report = warp.render(engine, _label_output(output, stamped, write_kw),
                                 execute.block_budget(),
                                 slab=settings.block[0] if settings.block else None)
        by_slabs = True
    log.info("per-label volumes (mm^3):\n%s", format_report(report))
    summary = {"output": str(output), "shape": list(warp.template.shape_xyz),
               "handles": warp.handles(), "grid": warp.grid, **_labels_json(report)}
    if exports:
        summary.update(_write_exports(exports, warp, input, spec_path, by_slabs=by_slabs))
    return summary


def _label_output(output, stamped, write_kw):
    """``open_output(template, block)`` for a label warp's slabs: the output file, stamped."""
    from .chunked import block_output

    def open_output(template, block):
        return block_output(output, stamped, block=block, compress=write_kw["compress"],
                            byte_order=write_kw["byte_order"],
                            version=write_kw.get("ome_zarr_version", "0.5"),
                            pyramid=write_kw.get("pyramid", 0), labels=True)

    return open_output


def _warp_frames(input, spec_path, output, options, frames_to, values, preserve_labels,
                 exports, is_capture, raw, volume_index, dicom, write_kw) -> dict:
    """Every frame of the warp (--frames-to), in memory; ``output`` (if given) the last.

    Intensities: frame 0 in full, then each frame a local update of the last
    (the accumulators kept). Labels: each frame the label warp of the input
    map for that frame's lattice.
    """
    from ..bspline.run import IntensityWarp, LabelMapWarp, WarpInput
    if is_capture:
        from ..bspline.capture_file import read_capture

        source = WarpInput(input, values=values, read_capture=lambda: read_capture(input))
    else:  # mapped, not copied, where it can be: the warp only reads it
        source = WarpInput(input, values=values,
                           read_volume=lambda: load_input(input, raw, volume_index, True, dicom))
    with source:
        doc, spec = source.load_spec(spec_path)
        what = source.source(doc, spec)
        choice, spec = source.choice, source.spec
        _check_labels_fit(choice, doc, spec, options, preserve_labels, input, values)
    labels = choice.is_labels

    def write(vol, path):
        with timed(f"write {path}"):
            # (a label map's pyramid levels take the mode, as by blocks: never averaged ids)
            write_volume(stamp(vol, "warp", input, spec_path), path, **write_kw,
                         **({"labels": True} if labels else {}))

    written = [0]  # frame files

    def write_frame(fields, vol):
        write(vol, frames_to.format(**fields))
        written[0] += 1

    if labels:
        from ..bspline.labels import format_report
        from ..progress import log

        warp = LabelMapWarp(what, doc, spec, options, preserve=preserve_labels, name=input)
        del what
        out, report = warp.render_frames(write_frame)
        log.info("per-label volumes (mm^3):\n%s", format_report(report))
        stats = _labels_json(report)
    else:
        if exports:  # refused before any work where they cannot be exact
            from ..bspline.export import check_exportable

            check_exportable(what.placement, what.dq, input)
        warp = IntensityWarp(what, doc, spec, options, name=input)
        del what
        out, stats = warp.render_frames(write_frame), {}
    if output is not None:
        write(out, output)
    if exports:
        stats.update(_write_exports(exports, warp, input, spec_path, by_slabs=False))
    return {"output": None if output is None else str(output), "shape": list(out.shape_xyz),
            "frames": written[0], "handles": warp.handles(), **_values_choice_json(choice),
            **warp.summary(), **stats}


def _jsonable(v):
    """``v`` as strict JSON values.

    numpy scalars and arrays become Python ones, a float that is not finite None.
    """
    import math

    import numpy as np

    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return v if math.isfinite(v) else None
    return v


def _print_json(summary: dict) -> None:
    """The --json summary: one JSON document on stdout."""
    import json

    click.echo(json.dumps(_jsonable(summary), allow_nan=False))


def _labels_json(report: dict) -> dict:
    """The per-label report (:func:`..bspline.labels.warp_labels`) as --json keys."""
    keys = ("input_voxels", "output_voxels", "input_mm3", "output_mm3", "predicted_mm3")
    return {"labels": [{"label": int(L), **{k: r[k] for k in keys}}
                       for L, r in report["labels"].items()],
            "vanished": [int(L) for L in report["vanished"]],
            "preserved": [int(L) for L in report["preserved"]]}


def _check_exports(displacement_to, forward_field_to, jacobian_to, transform_to, points_in,
                   points_to, mesh_in, mesh_to):
    """The export options, checked before any work, as an ``ExportRequests``.

    Bad options are usage errors, and their inputs are read here (a points or mesh
    file that does not parse fails before any output); see
    :class:`~volwarp_cli.bspline.export_outputs.ExportRequests`.
    """
    from ..bspline.export import field_format, points_format, read_points
    from ..bspline.export_outputs import ExportRequests

    for name, path in (("--displacement-to", displacement_to),
                       ("--forward-field-to", forward_field_to)):
        if path is not None:
            try:
                field_format(path)
            except VolwarpError as exc:
                raise click.BadParameter(str(exc), param_hint=f"'{name}'") from None
            check_output_path(path, option=name)
    if jacobian_to is not None:
        try:
            volume_format(jacobian_to)
        except VolwarpError as exc:
            raise click.BadParameter(str(exc), param_hint="'--jacobian-to'") from None
        check_output_path(jacobian_to, option="--jacobian-to")
    if transform_to is not None:
        if not transform_to.lower().endswith(".tfm"):
            raise click.BadParameter(f"{transform_to}: the ITK transform is written as .tfm",
                                     param_hint="'--transform-to'")
        check_output_path(transform_to, option="--transform-to")
    if (points_in is None) != (points_to is None):
        raise click.UsageError("--points-in and --points-to go together")
    if (mesh_in is None) != (mesh_to is None):
        raise click.UsageError("--mesh-in and --mesh-to go together")
    if points_in is not None:
        try:
            kinds = points_format(points_in), points_format(points_to)
        except VolwarpError as exc:
            raise click.UsageError(str(exc)) from None
        if kinds[0] != kinds[1]:
            raise click.UsageError(f"--points-to {points_to}: write the points in the format "
                                   f"they were read in ({'.csv' if kinds[0] == 'csv' else '.mrk.json'})")
        check_output_path(points_to, option="--points-to")
    if mesh_in is not None:
        from ..surface.mesh_io import check_mesh_output

        if not mesh_in.lower().endswith(".ply"):
            raise click.BadParameter(f"{mesh_in}: volwarp reads meshes from PLY files only",
                                     param_hint="'--mesh-in'")
        try:
            check_mesh_output(mesh_to, option="--mesh-to")
        except VolwarpError as exc:
            raise click.BadParameter(str(exc), param_hint="'--mesh-to'") from None
    points = mesh = None
    if points_in is not None:
        points = (read_points(points_in), points_to)
    if mesh_in is not None:
        from ..surface.mesh_io import read_mesh

        mesh = (read_mesh(mesh_in), mesh_in, mesh_to)
    return ExportRequests(displacement=displacement_to, forward=forward_field_to,
                          jacobian=jacobian_to, transform=transform_to, points=points,
                          mesh=mesh)
