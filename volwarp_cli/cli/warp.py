"""`volwarp warp INPUT|SCENE.vwc --spec WARP.yaml -o OUT`: B-spline volume warping."""

from __future__ import annotations

import string
from concurrent.futures import ThreadPoolExecutor

import click

from ..errors import OutOfMemoryError, VolwarpError
from ..io import check_output_path, volume_format, write_volume
from ..progress import timed
from .common import load_input, stamp
from .options import (
    INPUT_PATH,
    common_options,
    finite,
    input_options,
    output_option,
    write_options,
)

_FIELDS = ("frame", "step", "spec_step", "sub")


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
    check_output_path(a)


def _unchecked_capture_settings(doc):
    """The spec's capture settings read before its schema check; None if they cannot be."""
    from ..bspline.plan import read_warp_spec

    try:
        return read_warp_spec(doc).capture
    except Exception:  # an invalid spec: the schema check reports it
        return None


def _capture(vol, settings, input, defer):
    """``vol`` captured with ``settings``; errors name the input. ``defer``: leave the
    gather to the warp (a one-shot warp gathers the planes as it streams them)."""
    from ..bspline.capture import capture_volume
    from ..errors import SpecError, VolwarpError

    s = settings
    try:
        return capture_volume(vol, lattice=s.lattice, placement=s.placement,
                              oversample=s.oversample, sampling=s.sampling, pad=None,
                              mean=False, defer=defer)
    except SpecError:
        raise
    except VolwarpError as exc:
        raise VolwarpError(f"{input}: {exc}") from None


def _capture_early(reading, settings, input, defer):
    """The capture, started before the spec is checked; None where it cannot be made
    (the capture after the check then reports why, in order)."""
    if settings is None:
        return None
    try:
        return _capture(reading.result(), settings, input, defer)
    except Exception:
        return None


@click.command(name="warp")
@click.argument("input", type=INPUT_PATH)
@click.option("--spec", "spec_path", required=True, type=INPUT_PATH,
              help="Warp spec (YAML; schema specs/warp.schema.json).")
@output_option("Warped volume (format by extension).")
@click.option("--frames-to", default=None, metavar="PATTERN",
              help="Also write every animation frame, e.g. 'out_{frame:03d}.nrrd' "
                   "({frame} and its alias {step}: 0 = unwarped, then one per increment; "
                   "{spec_step}, {sub}: the spec step and the increment within it).")
@click.option("--pushforward", type=click.Choice(["box", "nearest"]), default=None,
              help="Pushforward filter [default: the spec's, else box].")
@click.option("--evaluator", type=click.Choice(["separable", "table"]), default=None,
              help="Deformation evaluator [default: the spec's, else separable].")
@click.option("--background", type=float, default=None, metavar="B", callback=finite,
              help="Value of the space around the model, given to uncovered output voxels "
                   "and blended into partly covered ones [default: the spec's, else 0]; "
                   "e.g. a large positive distance for a signed distance field.")
@click.option("--crop", is_flag=True, help="Cut the output back to the input's extent.")
@write_options
@input_options
@common_options
def command(input, spec_path, output, frames_to, pushforward, evaluator, background, crop, dtype,
            compress, byte_order, raw, volume_index, dicom):
    """Warp INPUT (a volume, or a capture file .vwc) as the spec says.

    A plain volume is captured on the fly with the spec's `capture` settings.
    The output keeps the input's dtype, spacing, direction and key/values;
    it is padded (origin shifted, anatomy in place) unless --crop.
    """
    check_output_path(output)
    if frames_to:
        _check_pattern(frames_to)
    is_capture = input.lower().endswith(".vwc")
    one_shot = not frames_to  # only the final lattice is rendered, streamed
    if is_capture and (raw is not None or volume_index is not None or dicom is not None):
        raise click.UsageError("--raw-*, --volume-index and the DICOM options describe volume inputs, "
                               f"not the capture file {input}")
    with ThreadPoolExecutor(1) as pool:
        # The volume is read while the warp modules are imported and the spec is
        # loaded, and captured (with the settings the spec gives, read before it is
        # checked) while the spec is checked against its schema, which imports
        # jsonschema: reading and capturing release the GIL. A spec error still
        # comes first; the early capture is used only if it matches the checked spec.
        # (mapped, not copied, where it can be: the warp only reads it)
        reading = None if is_capture else pool.submit(load_input, input, raw, volume_index,
                                                      True, dicom)
        from ..bspline.capture_file import read_capture
        from ..bspline.plan import read_warp_spec
        from ..bspline.warp import (
            check_capture_settings,
            output_planes,
            output_volume,
            prepare,
            run,
        )
        from ..spec.loader import load_schema, load_spec, validate

        doc = load_spec(spec_path)
        if reading is not None:
            settings = _unchecked_capture_settings(doc)
            early = pool.submit(_capture_early, reading, settings, input, one_shot)
        validate(doc, load_schema("warp"))
        spec = read_warp_spec(doc)
        if is_capture:
            with timed(f"read {input}"):
                cap = read_capture(input)
            check_capture_settings(doc, spec, cap, input)
        else:
            vol = reading.result()  # a read error, after any spec error
            cap = early.result() if settings == spec.capture else None
            del reading, early  # the futures hold the volume and the capture too
    if not is_capture:
        if cap is None:
            cap = _capture(vol, spec.capture, input, one_shot)
        del vol
    try:
        scene, frames = prepare(cap, doc, spec, method=pushforward, evaluator=evaluator,
                                background=background)
    except OutOfMemoryError as exc:  # the target this input and spec ask for
        raise OutOfMemoryError(f"{input}: {exc}") from None

    def write(target, path):
        out = stamp(output_volume(cap, scene, target, crop=crop, dtype=dtype), "warp", input,
                    spec_path)
        with timed(f"write {path}"):
            write_volume(out, path, compress=compress, byte_order=byte_order)

    on_frame = None
    if frames_to:
        def on_frame(n, fr, target):
            name = frames_to.format(frame=n, step=n, spec_step=fr.step if fr else 0,
                                    sub=fr.sub if fr else 0)
            write(target, name)

    if one_shot and output.lower().endswith(".nrrd") and not compress:
        # raw NRRD: the warp's planes go to the file as they are finished (the
        # whole target is never held, and the writing runs in the warp's threads)
        from ..io.nrrd import nrrd_plane_writer

        template, convert = output_planes(cap, scene, crop=crop, dtype=dtype)
        template = stamp(template, "warp", input, spec_path)
        with nrrd_plane_writer(template, output, byte_order=byte_order) as write_planes:
            def sink(z0, z1, planes):
                part = convert(z0, planes)
                if part is not None:
                    write_planes(*part)

            run(scene, frames, sink=sink)
        return
    target = run(scene, frames, on_frame)
    write(target, output)
