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
from ..labelmap import VALUES
from ..progress import log, timed
from .common import load_input, stamp
from .options import (
    INPUT_PATH,
    common_options,
    examples,
    finite,
    input_options,
    output_option,
    write_options,
)
from .resources import scale_options, scale_settings

_METRICS = ["euclidean", "minnorm", "chessboard", "taxicab"]


@click.command(name="distance", epilog=examples(
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
@click.option("--label", "label", type=int, default=None, metavar="N",
              help="A label map: the distance of label N's voxels (default: of every voxel "
                   "with a non-zero label).")
@click.option("--values", "values", type=click.Choice(VALUES), default=None,
              help="Take the samples as intensities (the shape: --iso V) or as label ids "
                   "(the labels' voxels). Default: labels when INPUT looks like a label map "
                   "(integer ids whose values are regions, as `volwarp info` hints), else "
                   "intensity.")
@click.option("--metric", type=click.Choice(_METRICS), default="euclidean", show_default=True,
              help="euclidean (exact); minnorm (the paper's shift-and-min passes; equals the "
                   "spacing-weighted taxicab distance); chessboard/taxicab (chamfer scans, "
                   "isotropic spacing only).")
@click.option("--surface", type=click.Choice(["auto", "voxel", "subvoxel"]), default="auto",
              show_default=True,
              help="euclidean: distances between voxel centres (binary shapes) or to the "
                   "sub-voxel iso-surface of smooth samples; auto picks by the samples. "
                   "A label map's is always the voxel surface.")
@click.option("--unsigned", is_flag=True,
              help="Distance to the shape (0 inside) instead of the signed field.")
@click.option("--max-distance", type=click.FloatRange(min=0, min_open=True), default=None,
              metavar="D", help="Clamp distances to [-D, D] (world units).")
@click.option("--update", "update", type=INPUT_PATH, default=None,
              metavar="OLD_SDF", help="Update an existing signed field instead (needs --transform).")
@click.option("--transform", type=INPUT_PATH, default=None, metavar="AFFINE.yaml",
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
        if metric not in ("euclidean", "minnorm"):
            raise click.UsageError("--update propagates euclidean or minnorm fields only")
        _update(update, transform, output, metric, max_distance, dtype, compress, byte_order,
                raw, volume_index, dicom, ome_zarr)
        return
    if transform is not None:
        raise click.UsageError("--transform goes with --update OLD_SDF")
    if input is None:
        raise click.UsageError("missing INPUT (or --update OLD_SDF)")
    from ..distance.field import check_method, finish_field
    from ..distance.labels import check_options, choose_shape, rule_signed_distance
    from ..errors import OutOfMemoryError
    from ..volume import xyz_to_zyx

    check_method(metric, surface)
    check_options(values=values, label=label, iso=iso, surface=surface)
    check_output_path(output, option="-o")
    given = dict(values=values, label=label, iso=iso, inside=inside, surface=surface,
                 name=str(input))
    blocks = dict(given=given, metric=metric, surface=surface, unsigned=unsigned,
                  max_distance=max_distance, dtype=dtype, compress=compress,
                  byte_order=byte_order, **ome_zarr)
    chunked = scale_settings().chunked
    if chunked:
        _by_blocks(input, output, raw, volume_index, dicom, **blocks)
        return
    rule = None
    try:
        vol = load_input(input, raw, volume_index, dicom=dicom)
        rule = _chosen(choose_shape(vol.data, **given))
        with timed(f"distance ({metric})"), _collector_paused():
            field, info = rule_signed_distance(vol.data, xyz_to_zyx(vol.spacing), rule,
                                               metric=metric, surface=surface)
    except OutOfMemoryError as exc:
        from .chunked import blocks_can_write, wants_blocks

        if chunked is False:
            raise
        from ..io.lazy import open_volume_lazy

        geometry, array = open_volume_lazy(input, raw=raw, volume_index=volume_index,
                                           dicom=dicom)
        if not blocks_can_write(output, geometry.shape, dtype or "float32", blocks):
            raise
        del geometry, array
        if not wants_blocks(str(exc)):
            raise
        _by_blocks(input, output, raw, volume_index, dicom, rule=rule, **blocks)
        return
    if info["passes"]:
        log.info("min-norm: %d shift-and-min passes", info["passes"])
    finish_field(field, unsigned=unsigned, max_distance=max_distance)
    out = stamp(vol.with_data(field), "distance", input)
    out.meta["volwarp_distance"] = _note(metric, info["surface"], rule, unsigned, max_distance)
    with timed(f"write {output}"):
        write_volume(out, output, dtype=dtype, compress=compress, byte_order=byte_order,
                     **ome_zarr)


def _chosen(rule):
    """Log the shape ``rule`` chose (-v) and return it."""
    log.info("%s", rule.describe())
    return rule


def _note(metric, surface, rule, unsigned, max_distance) -> str:
    """The output's ``volwarp_distance`` key: how the field was defined.

    The same however it was computed, in memory or by blocks (the samples are
    the same); the shape's part says labels or intensity, and why
    (:meth:`~volwarp_cli.distance.labels.ShapeRule.note`).
    """
    return (f"metric={metric} surface={surface} {rule.note()}"
            + (" unsigned" if unsigned else "")
            + (f" max_distance={max_distance:g} (exact inside the band, clamped outside)"
               if max_distance is not None else ""))


def _finish_block(field, *, unsigned, dtype, what):
    """--unsigned and --dtype on one block of the field (a block task's last step)."""
    from ..distance.field import finish_field
    from ..samples import cast_samples

    if unsigned:
        finish_field(field, unsigned=True)
    return cast_samples(field, dtype, what=what) if dtype is not None else field


def _by_blocks(input, output, raw, volume_index, dicom=None, *, given, metric, surface,
               unsigned, max_distance, dtype, compress, byte_order, ome_zarr_version="0.5",
               pyramid=0, rule=None):
    """The distance field by blocks on Dask (:mod:`volwarp_cli.distance.chunked`).

    The shape's rule read box by box (``given``: :func:`choose_shape`'s
    options; ``rule``: already chosen). The exact field runs as three passes
    whose fields go to a scratch folder next to the output between passes
    (memory: the blocks in flight); a banded one (--max-distance) as
    overlapping blocks.
    """
    import functools

    import numpy as np

    from ..distance.chunked import field_by_blocks
    from ..distance.labels import choose_shape
    from ..volume import xyz_to_zyx
    from .chunked import block_budget, block_output, lazy_input

    settings = scale_settings()
    template, source = lazy_input(input, raw, volume_index, dicom)
    shape = template.data.shape
    if rule is None:
        with timed("label rule by blocks"):
            rule = _chosen(choose_shape(source, box_voxels=max(1, block_budget() // 16),
                                        **given))
    out_dtype = np.dtype(dtype or "float32")
    finish = functools.partial(_finish_block, unsigned=unsigned,
                               dtype=None if dtype is None else out_dtype, what=str(output))
    kw = dict(compress=compress, byte_order=byte_order, version=ome_zarr_version,
              pyramid=pyramid)

    def open_output(grid, info):
        out = stamp(template.with_data(np.broadcast_to(np.zeros((), out_dtype), shape)),
                    "distance", input)
        out.meta["volwarp_distance"] = _note(metric, info["surface"], rule, unsigned,
                                             max_distance)
        log.info("distance by blocks: %s", info["chunked"])
        return block_output(output, out, out_dtype, block=grid, **kw)

    with settings.open_engine() as engine, _collector_paused(), \
            timed("distance by blocks"):
        info = field_by_blocks(source, xyz_to_zyx(template.spacing), engine, open_output,
                               iso=rule.iso, inside=rule.inside, metric=metric,
                               surface=surface, max_distance=max_distance, finish=finish,
                               out_dtype=out_dtype,
                               block_bytes=block_budget() // max(1, engine.workers),
                               block=settings.block, scratch_near=output, rule=rule)
    if info.get("passes"):
        log.info("min-norm: %d shift-and-min passes", info["passes"])


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


def _update(old_path, transform_path, output, metric, max_distance, dtype, compress, byte_order,
            raw, volume_index, dicom, ome_zarr):
    import numpy as np

    from ..distance.field import finish_field
    from ..distance.update import update_distance
    from ..errors import VolwarpError
    from ..morph.align import affine_from_params, shape_centroid
    from ..spec.loader import load_spec
    from ..volume import xyz_to_zyx

    doc = load_spec(transform_path, "transform")
    check_output_path(output, option="-o")
    vol = load_input(old_path, raw, volume_index, dicom=dicom)
    field = np.asarray(vol.data, dtype=np.float32)
    if not np.all(np.isfinite(field)):
        raise VolwarpError(f"{old_path}: the field has NaN or infinite samples")
    params = dict(doc.data)
    params.pop("version", None)
    center = None
    if "center" not in params and "matrix" not in params:
        inside = field < 0
        if not inside.any():
            raise VolwarpError(f"{old_path}: the field has no negative (inside) samples, so the "
                               "shape has no centroid; give 'center' in the transform")
        center = shape_centroid(inside, vol.index_to_world_matrix)
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
                     output, dtype=dtype, compress=compress, byte_order=byte_order,
                     **ome_zarr)
