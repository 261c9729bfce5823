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

JSON_HELP = (
    "After a successful run, print one JSON object on stdout (nothing else goes there; "
    "logs and progress go to stderr). Keys: output (path), shape (x y z voxels of the "
    "written output), frames (frame files written, with --frames-to), handles (one per "
    "drag handle: step (0-based spec step), index (within the step's drag list), from, "
    "to, reached (world LPS mm; reached: where the solved lattice sends from), miss_mm "
    "(|reached - to|)); with --jacobian-to: jacobian {path, min, max, below_0, below_0_1} "
    "(det dF/dx extremes and the fractions of input voxels below 0 and 0.1); with "
    "--displacement-to: displacement {path, voxels, folded, no_preimage} (output voxel "
    "counts: folded = NaN, no_preimage = without an inverse in the lattice's support); "
    "with --points-in / --mesh-in: points / mesh {path, count, outside}; with labels: "
    "labels (one per input label: label, input_voxels, output_voxels, input_mm3, "
    "output_mm3, predicted_mm3; output_*: the warped map before --crop; with --frames-to: "
    "the last frame's), vanished and preserved (label ids). A value that is "
    "not a finite number is null.")


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
        spec = read_warp_spec(doc)
    except Exception:  # an invalid spec: the schema check reports it
        return None
    return None if spec.values == "labels" else spec.capture  # labels: their own capture


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
                   "{spec_step}, {sub}: the spec step and the increment within it). With "
                   "--labels every frame is the label warp recomputed exactly from the input "
                   "map for that frame's lattice (not incremental: each frame costs a whole "
                   "label warp).")
@click.option("--pushforward", type=click.Choice(["box", "nearest"]), default=None,
              help="Pushforward filter [default: the spec's, else box].")
@click.option("--evaluator", type=click.Choice(["separable", "table"]), default=None,
              help="Deformation evaluator [default: the spec's, else separable].")
@click.option("--background", type=float, default=None, metavar="B", callback=finite,
              help="Value of the space around the model, given to uncovered output voxels "
                   "and blended into partly covered ones [default: the spec's, else 0]; "
                   "e.g. a large positive distance for a signed distance field.")
@click.option("--crop", is_flag=True, help="Cut the output back to the input's extent.")
@click.option("--labels", is_flag=True,
              help="INPUT is a label map (segmentation): each output voxel takes the label of "
                   "largest box-filter weight (the background 0 competes); ids are never "
                   "averaged. -v prints each label's volume before and after (--json: the "
                   "labels key); with --frames-to, those of the last frame.")
@click.option("--preserve-labels", is_flag=True,
              help="With --labels: a label that would vanish keeps its voxel of largest weight.")
@click.option("--displacement-to", default=None, metavar="FIELD",
              help="Write the resampling displacement field y -> F^-1(y) - y (LPS mm) on the "
                   "output grid, as ITK, ANTs and Slicer resample with (.nii.gz or .nrrd); "
                   "NaN where the map folds or has no inverse.")
@click.option("--forward-field-to", default=None, metavar="FIELD",
              help="Write the forward (modelling) field x -> F(x) - x (LPS mm) on the input "
                   "grid (.nii.gz or .nrrd).")
@click.option("--jacobian-to", default=None, metavar="MAP",
              help="Write det dF/dx on the input grid (float32, any volume format).")
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
              help="Let the padding the moves need make the output more than 2x the input "
                   "(and more than 64 voxels larger) along an axis; refused otherwise, naming "
                   "the sizes (a mistyped 320 mm drag made a 181x217x1701 volume).")
@click.option("--json", "as_json", is_flag=True, help=JSON_HELP)
@write_options
@input_options
@common_options
def command(input, spec_path, output, frames_to, pushforward, evaluator, background, crop,
            labels, preserve_labels, displacement_to, forward_field_to, jacobian_to, transform_to, points_in, points_to,
            mesh_in, mesh_to, allow_growth, as_json, dtype, compress, byte_order, raw, volume_index, dicom):
    """Warp INPUT (a volume, or a capture file .vwc) as the spec says.

    A plain volume is captured on the fly with the spec's `capture` settings.
    The output keeps the input's dtype, spacing, direction and key/values;
    it is padded (origin shifted, anatomy in place) unless --crop.
    """
    check_output_path(output)
    if labels and input.lower().endswith(".vwc"):
        raise click.UsageError("--labels warps a label-map volume (not a capture file)")
    if labels and dtype is not None:
        raise click.UsageError("--labels keeps the label map's own integer type (no --dtype)")
    if frames_to:
        _check_pattern(frames_to)
    exports = _check_exports(displacement_to, forward_field_to, jacobian_to, transform_to,
                             points_in, points_to, mesh_in, mesh_to)
    if labels and exports:
        raise click.UsageError("--labels with the deformation's exports: export them from a "
                               "warp without --labels (the deformation is the same)")
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
            # (a label map is captured by its own path, below: no float capture)
            settings = None if labels else _unchecked_capture_settings(doc)
            early = pool.submit(_capture_early, reading, settings, input, one_shot)
        validate(doc, load_schema("warp"))
        spec = read_warp_spec(doc)
        if spec.values == "labels" and not labels:  # the spec says what --labels says
            for clash, given in (("a capture file", is_capture),
                                 ("--dtype", dtype is not None),
                                 ("the deformation's exports", bool(exports))):
                if given:
                    raise doc.error(("values",), f"labels are warped from a volume, "
                                    f"without {clash}")
            labels = True
        if preserve_labels and not labels:
            raise click.UsageError("--preserve-labels needs --labels (or the spec's "
                                   "values: labels)")
        if labels:  # what a label map cannot have: usage or spec errors, before any work
            if background not in (None, 0, 0.0):
                raise click.UsageError("--background does not apply to a label map (its "
                                       "background is the label 0)")
            c = spec.capture
            if c.placement != "uniform" and "placement" in spec.capture_given:
                raise doc.error(("capture", "placement"), "a label map is warped with the "
                                "uniform placement (each domain voxel one input voxel's label)")
            if c.oversample != int(c.oversample):
                raise doc.error(("capture", "oversample"), "a label map needs an integer "
                                "oversample (each domain voxel one input voxel's label)")
        if is_capture:
            with timed(f"read {input}"):
                cap = read_capture(input)
            check_capture_settings(doc, spec, cap, input)
        else:
            vol = reading.result()  # a read error, after any spec error
            cap = early.result() if settings == spec.capture else None
            del reading, early  # the futures hold the volume and the capture too
    if labels:
        from ..bspline.labels import format_report, prepare_labels, warp_labels
        from ..progress import log

        cap, scene, frames = prepare_labels(vol, doc, spec, method=pushforward,
                                            evaluator=evaluator, background=background,
                                            source=input, allow_growth=allow_growth)
        handles = _report_handles(cap, frames)

        def label_volume(lattice):
            # exact: the whole label warp for this lattice, from the input map
            scene.set_lattice(lattice)
            res = warp_labels(vol.data, scene, (), preserve=preserve_labels,
                              spacing=vol.spacing)
            out = stamp(output_volume(cap, scene, res.target, crop=crop), "warp", input,
                        spec_path)
            return out, res.report

        written = 0
        if frames_to:
            # frame 0 (the unmoved lattice), then every increment's lattice; the last
            # frame is the output too
            lattices = [cap.dq] + [fr.dq for fr in frames]
            for n, lattice in enumerate(lattices):
                fr = frames[n - 1] if n else None
                with timed(f"labels: frame {n} of {len(lattices) - 1}"):
                    out, report = label_volume(lattice)
                name = frames_to.format(frame=n, step=n, spec_step=fr.step if fr else 0,
                                        sub=fr.sub if fr else 0)
                with timed(f"write {name}"):
                    write_volume(out, name, compress=compress, byte_order=byte_order)
                written += 1
        else:
            out, report = label_volume(frames[-1].dq if frames else cap.dq)
        with timed(f"write {output}"):
            write_volume(out, output, compress=compress, byte_order=byte_order)
        log.info("per-label volumes (mm^3):\n%s", format_report(report))
        if as_json:
            summary = {"output": str(output), "shape": list(out.shape_xyz)}
            if frames_to:
                summary["frames"] = written
            _print_json({**summary, "handles": handles, **_labels_json(report)})
        return
    if not is_capture:
        if cap is None:
            cap = _capture(vol, spec.capture, input, one_shot)
        del vol
    try:
        scene, frames = prepare(cap, doc, spec, method=pushforward, evaluator=evaluator,
                                background=background, allow_growth=allow_growth)
    except OutOfMemoryError as exc:  # the target this input and spec ask for
        raise OutOfMemoryError(f"{input}: {exc}") from None
    handles = _report_handles(cap, frames)
    if exports:  # refused before any work where they cannot be exact
        from ..bspline.export import check_exportable

        check_exportable(cap.placement, cap.dq, input)

    def write(target, path):
        out = stamp(output_volume(cap, scene, target, crop=crop, dtype=dtype), "warp", input,
                    spec_path)
        with timed(f"write {path}"):
            write_volume(out, path, compress=compress, byte_order=byte_order)
        return list(out.shape_xyz)

    on_frame = None
    written = [0]  # frame files
    if frames_to:
        def on_frame(n, fr, target):
            name = frames_to.format(frame=n, step=n, spec_step=fr.step if fr else 0,
                                    sub=fr.sub if fr else 0)
            write(target, name)
            written[0] += 1

    if one_shot and output.lower().endswith(".nrrd") and not compress:
        # raw NRRD: the warp's planes go to the file as they are finished (the
        # whole target is never held, and the writing runs in the warp's threads)
        from ..io.nrrd import nrrd_plane_writer

        template, convert = output_planes(cap, scene, crop=crop, dtype=dtype)
        template = stamp(template, "warp", input, spec_path)
        shape = list(template.shape_xyz)
        with nrrd_plane_writer(template, output, byte_order=byte_order) as write_planes:
            def sink(z0, z1, planes):
                part = convert(z0, planes)
                if part is not None:
                    write_planes(*part)

            run(scene, frames, sink=sink)
    else:
        target = run(scene, frames, on_frame)
        shape = write(target, output)
    stats = {}
    if exports:
        # after -o: a run that fails or is stopped before its output leaves the old
        # exports as they were (each export file is atomic on its own)
        stats = _write_exports(exports, cap, scene, frames, crop, input, spec_path)
    if as_json:
        summary = {"output": str(output), "shape": shape}
        if frames_to:
            summary["frames"] = written[0]
        _print_json({**summary, "handles": handles, **stats})


def _jsonable(v):
    """``v`` as strict JSON values: numpy scalars and arrays to Python ones, a float
    that is not finite to None."""
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
                   points_to, mesh_in, mesh_to) -> dict:
    """The export options, checked before any work (usage errors), and their inputs read
    (a points or mesh file that does not parse fails here, before any output)."""
    from ..bspline.export import field_format, points_format, read_points

    out = {}
    for name, path in (("--displacement-to", displacement_to),
                       ("--forward-field-to", forward_field_to)):
        if path is not None:
            try:
                field_format(path)
            except VolwarpError as exc:
                raise click.BadParameter(str(exc), param_hint=f"'{name}'") from None
            check_output_path(path)
    if jacobian_to is not None:
        try:
            volume_format(jacobian_to)
        except VolwarpError as exc:
            raise click.BadParameter(str(exc), param_hint="'--jacobian-to'") from None
        check_output_path(jacobian_to)
    if transform_to is not None:
        if not transform_to.lower().endswith(".tfm"):
            raise click.BadParameter(f"{transform_to}: the ITK transform is written as .tfm",
                                     param_hint="'--transform-to'")
        check_output_path(transform_to)
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
        check_output_path(points_to)
    if mesh_in is not None:
        from ..surface.mesh_io import check_mesh_output

        if not mesh_in.lower().endswith(".ply"):
            raise click.BadParameter(f"{mesh_in}: volwarp reads meshes from PLY files only",
                                     param_hint="'--mesh-in'")
        try:
            check_mesh_output(mesh_to)
        except VolwarpError as exc:
            raise click.BadParameter(str(exc), param_hint="'--mesh-to'") from None
    out.update({k: v for k, v in (("displacement", displacement_to),
                                   ("forward", forward_field_to), ("jacobian", jacobian_to),
                                   ("transform", transform_to)) if v is not None})
    if points_in is not None:
        out["points"] = (read_points(points_in), points_to)
    if mesh_in is not None:
        from ..surface.mesh_io import read_mesh

        out["mesh"] = (read_mesh(mesh_in), mesh_in, mesh_to)
    return out


def _final_dq(cap, frames):
    return frames[-1].dq if frames else cap.dq


def _report_handles(cap, frames) -> list:
    """How far each handle missed its target, world mm (-v); returned for --json as
    ``{step, index, from, to, reached, miss_mm}`` (world LPS mm, ``step`` 0-based)."""
    import numpy as np

    from ..progress import log

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


def _write_exports(exports, cap, scene, frames, crop, input, spec_path) -> dict:
    """The deformation's exports (see :mod:`volwarp_cli.bspline.export`), written after
    the warp's output; they describe the final lattice. Returns their figures, as
    --json keys (``jacobian``, ``displacement``, ``points``, ``mesh``)."""
    import numpy as np

    from ..bspline.export import (
        ForwardMap,
        field_stats_ok,
        jacobian_stats,
        report_outside,
        write_field,
        write_points,
        write_tfm,
    )
    from ..bspline.warp import _output_window
    from ..progress import log
    from ..volume import Volume
    from .common import provenance

    meta = provenance("warp", input, spec_path)
    stats = {}
    fmap = ForwardMap(cap.grid, _final_dq(cap, frames), cap.geometry)
    g = cap.geometry
    nx, ny, nz = cap.grid.input_shape
    in_grid = Volume(np.zeros((nz, ny, nx), np.uint8), spacing=g.spacing, origin=g.origin,
                     direction=g.direction, space=g.space)
    if "displacement" in exports:
        path = exports["displacement"]
        window, origin = _output_window(cap, scene, crop)
        shape = tuple(w.stop - w.start for w in window)
        out_grid = Volume(np.zeros(shape, np.uint8), spacing=g.spacing, origin=origin,
                          direction=g.direction, space=g.space)
        shift = np.array([window[2].start, window[1].start, window[0].start]) - np.array(scene.pad)
        with timed(f"invert the map on {shape[2]}x{shape[1]}x{shape[0]} voxels"):
            field, counts = fmap.resampling_field(shape[::-1], shift)
        log.info("%s: %s", path, field_stats_ok(counts))
        if counts["folded"]:
            log.warning("%s: the map folds: %d voxels have no single inverse (NaN)", path,
                        counts["folded"])
        with timed(f"write {path}"):
            write_field(field, out_grid, path, meta, "resampling")
        stats["displacement"] = {"path": str(path), "voxels": counts["voxels"],
                                 "folded": counts["folded"],
                                 "no_preimage": counts["no_inverse"]}
        del field
    if "forward" in exports:
        path = exports["forward"]
        with timed(f"write {path}"):
            write_field(fmap.forward_field(), in_grid, path, meta, "forward")
    if "jacobian" in exports:
        path = exports["jacobian"]
        det = fmap.jacobian()
        st = jacobian_stats(det)
        log.info("%s: det dF/dx min %.4g, max %.4g; %.3g%% of voxels below 0, %.3g%% below 0.1",
                 path, st["min"], st["max"], 100 * st["below_0"], 100 * st["below_0.1"])
        stats["jacobian"] = {"path": str(path), "min": st["min"], "max": st["max"],
                             "below_0": st["below_0"], "below_0_1": st["below_0.1"]}
        jmeta = {**dict(g.meta), **meta, "volwarp_field": "jacobian"}
        with timed(f"write {path}"):
            write_volume(in_grid.with_data(det, meta=jmeta), path)
    if "transform" in exports:
        path = exports["transform"]
        with timed(f"write {path}"):
            write_tfm(fmap, path, meta)
    if "points" in exports:
        pf, path = exports["points"]
        moved, inside = fmap.map_world(pf.points)
        outside = report_outside(pf.path, inside, fmap)
        with timed(f"write {path}"):
            write_points(pf, moved, path)
        stats["points"] = {"path": str(path), "count": len(inside), "outside": outside}
    if "mesh" in exports:
        from ..surface.mesh import Mesh
        from ..surface.mesh_io import write_mesh

        mesh, src, path = exports["mesh"]
        moved, inside = fmap.map_world(mesh.vertices)
        outside = report_outside(src, inside, fmap)
        out = Mesh(moved, mesh.faces).with_normals()
        with timed(f"write {path}"):
            write_mesh(out, path, comments={**provenance("warp", [input, src], spec_path),
                                            "volwarp_field": "forward"})
        stats["mesh"] = {"path": str(path), "count": len(inside), "outside": outside}
    return stats
