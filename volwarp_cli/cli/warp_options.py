"""The options of `volwarp warp`: their help, and the checks made before any work.

Each check turns a bad combination into a usage error (exit 2) naming the
option, before a sample is read; :func:`check_exports` also reads the points
and mesh inputs, so a file that does not parse fails before any output.
"""

from __future__ import annotations

import click
from click.core import ParameterSource

from ..errors import VolwarpError
from ..io import check_output_path, volume_format

#: the fields of a --frames-to pattern (:data:`volwarp_cli.warp.run.FRAME_FIELDS`)
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
    "labels (one per input label but the background: label, input_voxels, output_voxels, "
    "input_mm3, output_mm3, predicted_mm3; with --frames-to: the last frame's), vanished "
    "and preserved (label ids), background (its label); an intensity warp run by blocks: blocks (their count) and "
    "block (x y z voxels of one). A value that is not a finite number is null.")


def check_pattern(pattern: str) -> None:
    """The --frames-to pattern: known fields only, distinct names for distinct frames."""
    import string

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
    from ..io.inputs import note_pattern, refuse_pattern_over_input

    refuse_pattern_over_input(pattern, option="--frames-to")  # any frame's name an input's
    note_pattern(pattern, "--frames-to")
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
    "signed distance field. A label map's background is a label: its most frequent border "
    "label unless B (an id its type holds) is given; uncovered voxels take it.")

#: options that shape the warped volume only: refused when no volume is written
_VOLUME_ONLY = (("--values", "values"), ("--labels", "labels"), ("--pushforward", "pushforward"),
                ("--evaluator", "evaluator"), ("--background-value", "background"),
                ("--preserve-labels", "preserve_labels"), ("--dtype", "dtype"),
                ("--compress", "compress"), ("--byte-order", "byte_order"),
                ("--ome-zarr-version", "ome_zarr_version"), ("--pyramid", "pyramid"))
#: what --grid and --crop change without a volume: the displacement field's grid
_GRID_OPTIONS = (("--grid", "grid"), ("--crop", "crop"), ("--allow-growth", "allow_growth"))


def given_values(values, labels) -> str | None:
    """``--values``, with ``--labels`` as ``--values labels``; None: not given."""
    if labels:
        if values == "intensity":
            raise click.UsageError("--labels is --values labels: it does not go with "
                                   "--values intensity")
        return "labels"
    return values


def refuse_volume_options(displacement: bool, fields: bool = False) -> None:
    """Without a volume output: the options that shape only the volume are usage errors.

    (No option is parsed and ignored.) ``displacement``: a displacement
    field is written, on the output grid that --grid and --crop choose;
    ``fields``: a field or the Jacobian is written, which the writer options
    (--compress, --byte-order, --ome-zarr-version) reach too.
    """
    ctx = click.get_current_context()
    given = []
    writer = ("compress", "byte_order", "ome_zarr_version") if fields else ()
    for name, key in _VOLUME_ONLY + (() if displacement else _GRID_OPTIONS):
        if key in writer:
            continue
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


def print_json(summary: dict) -> None:
    """The --json summary: one JSON document on stdout."""
    import json

    click.echo(json.dumps(_jsonable(summary), allow_nan=False))


def check_exports(displacement_to, forward_field_to, jacobian_to, transform_to, points_in,
                   points_to, mesh_in, mesh_to):
    """The export options, checked before any work, as an ``ExportRequests``.

    Bad options are usage errors, and their inputs are read here (a points or mesh
    file that does not parse fails before any output); see
    :class:`~volwarp_cli.warp.export_outputs.ExportRequests`.
    """
    if all(v is None for v in (displacement_to, forward_field_to, jacobian_to, transform_to,
                               points_in, points_to, mesh_in, mesh_to)):
        return None  # (nothing asked: the export modules are not imported)
    from ..warp.export import check_points_pair, field_format, read_points
    from ..warp.export_outputs import ExportRequests

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
        check_points_pair(points_in, points_to)
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
