"""`volwarp distance`: signed distance fields, and updates of a field through an affine move.

volwarp distance INPUT -o SDF.nrrd [--iso V] [--inside above|below] [--label N]
[--values intensity|labels] [--metric euclidean|minnorm|chessboard|taxicab]
[--surface auto|voxel|subvoxel] [--unsigned] [--max-distance D]
volwarp distance --update OLD_SDF.nrrd --transform affine.yaml -o NEW.nrrd [--metric ...]
"""

from __future__ import annotations

import contextlib
import gc

import click

from ..io import check_output_path, write_volume
from ..progress import log, timed
from ..volume import xyz_to_zyx
from .common import load_input, stamp
from .options import (
    INPUT_PATH,
    READ_ONCE_PATH,
    Command,
    band,
    common_options,
    examples,
    finite,
    input_options,
    output_option,
    shape_values_options,
    write_options,
)
from .resources import scale_options, scale_settings

_METRICS = ["euclidean", "minnorm", "chessboard", "taxicab"]


@click.command(name="distance", cls=Command, epilog=examples(
    "volwarp distance head.nrrd -o head_sdf.nrrd --iso 40",
    "volwarp distance seg.nii.gz -o liver_sdf.nrrd --label 3",
))
@click.argument("input", required=False, type=INPUT_PATH)
@output_option("Output distance field: float32 samples (unless --dtype); format by extension.")
@click.option("--iso", type=float, default=None, metavar="V", callback=finite,
              help="Iso level: the shape is the samples on the inside of V (needed unless "
                   "INPUT is a label map).")
@click.option("--inside", type=click.Choice(["above", "below"]), default="above",
              show_default=True, help="Which side of V is inside: above (samples >= V) or below (< V).")
@shape_values_options(
    label="A label map: the distance of label N's voxels (default: of every voxel with a "
          "non-zero label).",
    values="Take the samples as intensities (the shape: --iso V) or as label ids (the labels' "
           "voxels). Default: labels when INPUT looks like a label map (integer ids whose "
           "values are regions, as `volwarp info` hints), else intensity.")
@click.option("--metric", type=click.Choice(_METRICS), default="euclidean", show_default=True,
              help="euclidean (exact); minnorm (the paper's shift-and-min passes; equals the "
                   "spacing-weighted taxicab distance); chessboard/taxicab (voxel steps, per-line passes; "
                   "isotropic spacing only). With --update: the field's own (its "
                   "volwarp_distance key), which another --metric may not contradict.")
@click.option("--surface", type=click.Choice(["auto", "voxel", "subvoxel"]), default="auto",
              show_default=True,
              help="euclidean: distances between voxel centres (binary shapes) or to the "
                   "sub-voxel iso-surface of smooth samples; auto picks by the samples "
                   "(two values, NaN samples aside, are binary). A label map's is always "
                   "the voxel surface.")
@click.option("--unsigned", is_flag=True,
              help="Distance to the shape (0 inside) instead of the signed field.")
@click.option("--max-distance", type=click.FloatRange(min=0, min_open=True), default=None,
              callback=band,
              metavar="D", help="Clamp distances to [-D, D] (world units).")
@click.option("--update", "update", type=INPUT_PATH, default=None,
              metavar="OLD_SDF", help="Update an existing signed field instead (needs --transform).")
@click.option("--transform", type=READ_ONCE_PATH, default=None, metavar="AFFINE.yaml",
              help="With --update: the move (transform spec, see specs/transform.schema.json).")
@write_options(dtype_default="float32, whatever the input's type")
@input_options
@scale_options
@common_options
def command(input, output, iso, inside, label, values, metric, surface, unsigned, max_distance,
            update, transform, dtype, compress, byte_order, raw, volume_index, dicom, ome_zarr):
    """Signed distance field (float32) of the shape in INPUT: negative inside, world units.

    The output's samples are float32, whatever the input's type (--dtype
    converts them); geometry and key/values are kept.

    The shape is the samples on one side of --iso V; a label map's is its
    labels' voxels: every voxel with a non-zero label, or label N's with
    --label N, on the voxel surface (the ids' values never count; --iso is
    not needed). A label map is a volume of integer ids (floats that are all
    integers too) whose values are regions (as `volwarp info` hints);
    --values intensity|labels overrides. -v prints
    the choice; the output's volwarp_distance key records it.

    With --update OLD_SDF --transform AFFINE.yaml, move an existing field by
    the transform, filling the regions the move uncovers by shift-and-increment
    propagation (Dinh & Carvalho 2004, section 0.5.1) instead of recomputing it.
    """
    if update is not None:
        if input is not None:
            raise click.UsageError("give either INPUT or --update OLD_SDF, not both")
        if transform is None:
            raise click.UsageError("--update needs --transform AFFINE.yaml")
        for flag, given in (("--iso", iso is not None), ("--unsigned", unsigned),
                            ("--surface", surface != "auto"), ("--inside", inside != "above"),
                            ("--label", label is not None), ("--values", values is not None)):
            if given:
                raise click.UsageError(f"{flag} does not apply to --update (the field is given)")
        from .view_options import option_given

        metric_given = option_given(click.get_current_context(), "metric")
        if metric not in ("euclidean", "minnorm"):
            raise click.UsageError("--update propagates euclidean or minnorm fields only")
        if scale_settings().chunked:
            raise click.UsageError("--update runs in memory (its fill propagates across the "
                                   "whole field): not --chunked")
        _update(update, transform, output, metric if metric_given else None, max_distance,
                write=dict(dtype=dtype, compress=compress, byte_order=byte_order, **ome_zarr),
                read=dict(raw=raw, volume_index=volume_index, dicom=dicom))
        return
    if transform is not None:
        raise click.UsageError("--transform goes with --update OLD_SDF")
    if input is None:
        raise click.UsageError("missing INPUT (or --update OLD_SDF)")
    from .. import execute
    from ..distance.field import check_method, field_note
    from ..distance.labels import check_options, choose_shape
    from ..distance.minnorm import signed_pass_count
    from ..distance.operation import field_operation
    from ..distance.scan import field_surface, scan_box_voxels
    from ..geometry import Geometry
    from ..labelmap import without_label_keys
    from .chunked import lazy_input

    check_method(metric, surface)
    check_options(values=values, label=label, iso=iso, surface=surface)
    check_output_path(output, option="-o")
    header, source = lazy_input(input, raw, volume_index, dicom)
    box_voxels = scan_box_voxels()
    with timed("label rule"):
        rule = choose_shape(source, values=values, label=label, iso=iso, inside=inside,
                            surface=surface, name=str(input), box_voxels=box_voxels,
                            meta=header.meta)
    log.info("%s", rule.describe())
    surface = field_surface(source, rule, metric=metric, surface=surface,
                            max_distance=max_distance, box_voxels=box_voxels)
    out = stamp(header.replace(meta=without_label_keys(header.meta)), "distance", input)
    out.meta["volwarp_distance"] = field_note(metric, surface, rule, unsigned, max_distance)
    op = field_operation(source, Geometry.of(out), rule, metric=metric, surface=surface,
                         max_distance=max_distance, unsigned=unsigned,
                         target=_target(out, output, dtype, compress, byte_order, ome_zarr),
                         name=input)
    settings = scale_settings()
    with _collector_paused():
        execute.run(op, execute.How(chunked=settings.chunked, block=settings.block,
                                    open_engine=settings.open_engine))
    if metric == "minnorm":
        log.info("min-norm: %d shift-and-min passes", signed_pass_count(source.shape))


def _target(out, output, dtype, compress, byte_order, ome_zarr):
    """The output as the executor writes it (whole, or block by block)."""
    import numpy as np

    from .. import execute

    dtype = np.dtype(dtype or "float32")
    return execute.Target(output, out.replace(dtype=dtype), dtype, compress=compress,
                          byte_order=byte_order, version=ome_zarr["ome_zarr_version"],
                          pyramid=ome_zarr["pyramid"])


@contextlib.contextmanager
def _collector_paused():
    """Pause Python's cyclic garbage collector (restored on exit).

    The first distance kernel call imports numba and loads its type and
    implementation registries (about 100,000 long-lived objects); the
    collector's full passes over them while they load cost about 0.1 s of
    the whole command and free nothing. The computation itself creates no
    reference cycles (numpy arrays and numba kernels).
    """
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _update_metric(meta, given: str | None, old_path) -> str:
    """The metric an update fills with: the field's own (its ``volwarp_distance`` key).

    Without ``--metric`` the euclidean default filled a min-norm field's uncovered
    voxels with Euclidean distances (13 mm off), its key still saying minnorm; a
    ``--metric`` other than the field's is refused, and a field without the key
    takes ``given`` (default euclidean).
    """
    import re

    from ..errors import BadUsage

    found = re.search(r"\bmetric=(\w+)", str((meta or {}).get("volwarp_distance", "")))
    recorded = found.group(1) if found else None
    if recorded is None:
        return given or "euclidean"
    if given is not None and given != recorded:
        raise BadUsage(f"{old_path} is a {recorded} field (its volwarp_distance key): --update "
                       f"--metric {given} would fill it with another metric; leave --metric out")
    if recorded not in ("euclidean", "minnorm"):
        raise BadUsage(f"{old_path} is a {recorded} field: --update propagates euclidean or "
                       "minnorm fields only")
    return recorded


def _refuse_label_map(vol, old_path) -> None:
    """Refuse a label map given to ``--update`` as its field (a usage error).

    ``--update`` moves a signed distance field by trilinear resampling: a
    label map given there (a segmentation instead of its field) had its ids
    blended as distances and the result written with exit 0. A field
    ``volwarp distance`` wrote says so (its ``volwarp_distance`` key) and is
    not scanned; any other volume is judged by the label rule and its file's
    word (:func:`~volwarp_cli.labelmap.segmentation_of`), as ``distance``
    judges its input.
    """
    from ..distance.labels import scan_values
    from ..errors import BadUsage
    from ..labelmap import segmentation_of

    if "volwarp_distance" in (vol.meta or {}):
        return
    scan = scan_values(vol.data)
    said = segmentation_of(vol.meta) if scan.values is not None else None
    if scan.looks_like or said:
        why = said or f"looks like a label map: {len(scan.values)} labels"
        raise BadUsage(f"{old_path} is a label map ({why}), not a signed distance field: "
                       f"--update would blend its ids as distances; compute its field first "
                       f"(volwarp distance {old_path} -o SDF), then --update SDF")


#: the memory an update takes a voxel, and beside them (the modules it loads), measured:
#: processes of 357.5 MiB for 256^3 and 93.1 MiB for 128^3, 32 MiB held before the update
UPDATE_BYTES_PER_VOXEL = 19
UPDATE_FIXED_BYTES = 24 << 20


def _update(old_path, transform_path, output, metric, max_distance, *, write, read):
    """The field of ``old_path`` moved (``read``: its read options; ``write``: the output's)."""
    import numpy as np

    from ..distance.field import finish_field
    from ..distance.operation import check_axes
    from ..distance.update import field_and_centre, update_distance
    from ..errors import VolwarpError
    from ..geometry import Geometry
    from ..io.lazy import open_volume_header
    from ..memory import ensure_fits_in_memory
    from ..morph.align import affine_from_params
    from ..morph.spec import check_affine_params
    from ..spec.loader import load_spec
    from .common import check_input_options

    doc = load_spec(transform_path, "transform")
    check_affine_params(doc, (), doc.data)  # (before any sample is read)
    check_output_path(output, option="-o")
    check_input_options(old_path, read["raw"], read["dicom"])
    header = open_volume_header(old_path, raw=read["raw"], volume_index=read["volume_index"],
                                dicom=read["dicom"], samples=False)[0]  # (its shape: none read)
    check_axes(Geometry.of(header), str(old_path))  # (the fill measures along the axes)
    # (in memory: the field read, moved, its unknown voxels and the fill's passes; a hunt
    # measured 357 MiB for 256^3 under --memory-limit 160M, nothing charged)
    ensure_fits_in_memory(UPDATE_BYTES_PER_VOXEL * int(np.prod(header.shape))
                          + UPDATE_FIXED_BYTES, f"the update of {old_path}'s field")
    vol = load_input(old_path, read["raw"], read["volume_index"], dicom=read["dicom"])
    _refuse_label_map(vol, old_path)
    metric = _update_metric(vol.meta, metric, old_path)
    params = {k: v for k, v in doc.data.items() if k != "version"}
    field, center = field_and_centre(vol, params, where=str(old_path))
    try:
        matrix = affine_from_params(params, default_center=center)
    except VolwarpError as exc:
        raise doc.error(("matrix",) if "matrix" in params else (), str(exc)) from None
    with timed("distance update"):
        new, stats = update_distance(field, vol.index_to_world_matrix, matrix,
                                     xyz_to_zyx(vol.spacing), metric=metric)
    log.info("update: %d uncovered voxels filled in %d passes", stats["uncovered"],
             stats["passes"])
    finish_field(new, max_distance=max_distance)
    with timed(f"write {output}"):
        write_volume(stamp(vol.with_data(new), "distance --update", old_path, transform_path),
                     output, **write)
