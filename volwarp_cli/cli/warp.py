"""`volwarp warp INPUT|SCENE.vwc --spec WARP.yaml -o OUT`: B-spline volume warping.

Parses and checks the options (:mod:`.warp_options`), then hands the files
to :func:`volwarp_cli.warp.request.warp_files` with how to run (whole or
by blocks: the executor decides by the sizes unless --chunked or
--no-chunked says) and prints its summary.
"""

from __future__ import annotations

import click

from ..io import check_output_path
from ..warp.defaults import GRIDS, VALUES
from .common import load_input
from .options import (
    INPUT_PATH,
    READ_ONCE_PATH,
    Command,
    common_options,
    examples,
    finite,
    input_options,
    moved_points_options,
    option,
    output_option,
    write_options,
)
from .resources import scale_options, scale_settings
from .warp_options import (
    BACKGROUND_HELP,
    GRID_HELP,
    JSON_HELP,
    PUSHFORWARD_HELP,
    VALUES_HELP,
    check_exports,
    check_pattern,
    given_values,
    print_json,
    refuse_volume_options,
)


@click.command(name="warp", cls=Command, epilog=examples(
    "volwarp warp head.nrrd --spec bend.yaml -o bent.nrrd --points-in p.csv --points-to q.csv",
    "volwarp warp block.vwc --spec pull.yaml -o pulled.nrrd --grid grow "
    "--frames-to 'pulled_{frame:03d}.nrrd'",
))
@click.argument("input", type=INPUT_PATH)
@click.option("--spec", "spec_path", required=True, type=READ_ONCE_PATH,
              help="Warp spec (YAML; schema specs/warp.schema.json).")
@output_option("Warped volume (format by extension). Without it (and --frames-to) no "
               "volume is computed: the exports alone are written (--points-to, "
               "--mesh-to, --transform-to, the fields); at least one output is needed.",
               required=False)
@click.option("--frames-to", default=None, metavar="PATTERN",
              help="Also write every animation frame, e.g. 'out_{frame:03d}.nrrd' "
                   "({frame} and its alias {step}: 0 = unwarped, then one per increment; "
                   "{spec_step}, {sub}: the spec step and the increment within it, both from "
                   "1; --json's handles count steps from 0). A label "
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
                   "or .nrrd, gzip with --compress); NaN where the map folds or has no "
                   "inverse (ITK's NIfTI reader takes NaN for 0: .nrrd keeps it). With "
                   "--chunked: written by slabs, as uncompressed .nrrd only (the same bytes).")
@click.option("--forward-field-to", default=None, metavar="FIELD",
              help="Write the forward (modelling) field x -> F(x) - x (LPS mm) on the input "
                   "grid (.nii.gz or .nrrd, gzip with --compress; with --chunked: by slabs, "
                   "uncompressed .nrrd only).")
@click.option("--jacobian-to", default=None, metavar="MAP",
              help="Write det dF/dx on the input grid (float32, any volume format; with "
                   "--chunked: by slabs, a format written by blocks: uncompressed .nrrd, "
                   ".mha, raw or .ome.zarr).")
@click.option("--transform-to", default=None, metavar="F.tfm",
              help="Write the forward map as an ITK BSplineTransform (.tfm), for moving "
                   "points; ITK tools read it as a resampling transform: do not resample "
                   "the input with it (use --displacement-to).")
@moved_points_options(
    "Points to move by the forward map: a CSV with x, y, z columns (LPS mm; ANTs' layout "
    "works) or a Slicer .mrk.json markups file.",
    "Where the moved points go (the same format as --points-in).",
    "A mesh (PLY, world coordinates) whose vertices to move by the forward map.",
    "The moved mesh, normals recomputed (.ply .stl .obj .vtp .vtk).")
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
    from .. import execute
    from ..warp.defaults import new_run
    from ..warp.request import WarpFiles, warp_files
    from ..warp.run import WarpOptions
    from .chunked import lazy_input

    new_run()
    options = WarpOptions(pushforward=pushforward, evaluator=evaluator, background=background,
                          crop=crop, dtype=dtype, allow_growth=allow_growth, grid=grid,
                          values=given_values(values, labels), preserve=preserve_labels)
    if output is not None:
        check_output_path(output, option="-o")
    is_capture = input.lower().endswith(".vwc")
    if frames_to:
        check_pattern(frames_to)
    exports = check_exports(displacement_to, forward_field_to, jacobian_to, transform_to,
                             points_in, points_to, mesh_in, mesh_to)
    if exports:  # (the writer options go to every output, the fields' too)
        import dataclasses

        exports = dataclasses.replace(exports, compress=bool(compress), byte_order=byte_order,
                                      ome_zarr_version=ome_zarr["ome_zarr_version"])
        from ..warp.export_outputs import refuse_export_byte_order

        refuse_export_byte_order(exports)  # (before any work, as -o's)
    if output is None and not frames_to and not exports:
        raise click.UsageError("nothing to write: give -o OUT (the warped volume), "
                               "--frames-to, or an export (--points-to, --mesh-to, "
                               "--transform-to, --displacement-to, --forward-field-to, "
                               "--jacobian-to)")
    if is_capture and (raw is not None or volume_index is not None or dicom is not None):
        raise click.UsageError("--raw-*, --volume-index and the DICOM options describe volume "
                               f"inputs, not the capture file {input}")
    settings = scale_settings()
    chunked = settings.chunked
    if chunked and frames_to:  # (each frame updates the last one's accumulators)
        raise click.UsageError("--chunked warps a volume or a capture file to one output: "
                               "not --frames-to (these run in memory)")
    exports_refused = None  # (the fields run by slabs, but not to NIfTI or every format)
    if exports:
        from ..warp.export_outputs import block_export_problem

        exports_refused = block_export_problem(exports)
        if chunked and exports_refused:
            raise click.UsageError(f"--chunked: {exports_refused}")
    if output is None and not frames_to:  # the exports alone: no volume is computed
        refuse_volume_options(bool(displacement_to),
                              bool(exports) and exports.writes_volumes)
    req = WarpFiles(input, spec_path, output, is_capture=is_capture, frames_to=frames_to,
                    exports=exports or None, options=options,
                    write=dict(compress=compress, byte_order=byte_order, **ome_zarr),
                    read_volume=lambda: load_input(input, raw, volume_index, True, dicom),
                    open_lazy=lambda: lazy_input(input, raw, volume_index, dicom))
    how = execute.How(chunked=False if exports_refused else chunked, block=settings.block,
                      open_engine=settings.open_engine)
    summary = warp_files(req, how)
    if as_json:
        print_json(summary)
