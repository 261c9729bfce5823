"""`volwarp apply IN -o OUT -t T [-t T ...]`: resample through other tools' transforms.

The transforms (:mod:`volwarp_cli.transforms`) act on an output point in the
order listed, as antsApplyTransforms' ``-t``; the resampling is an operation
of the executor (:class:`volwarp_cli.apply.ApplyOperation`: in memory, or by
blocks when it does not fit or --chunked asks); points and meshes of the
input move the other way, by the chain's inverse.
"""

from __future__ import annotations

import click

from ..apply import INTERPOLATIONS
from ..errors import BadUsage
from ..io import check_output_path
from ..labelmap import VALUES
from ..progress import log, timed
from .options import (
    INPUT_PATH,
    Command,
    InputPath,
    common_options,
    examples,
    finite,
    input_options,
    moved_points_options,
    output_option,
    write_options,
)
from .resources import scale_options, scale_settings

#: --reference (input_options' option, taken by this command: the output grid)
REFERENCE_HELP = ("The output grid: REF's size, spacing, origin and direction [default: the "
                  "input's; with an elastix file, the fixed grid it states, as transformix "
                  "takes it]; its samples are not used (for a DICOM SEG or RTSTRUCT input, "
                  "convert it first).")


class TransformArg(InputPath):
    """A ``-t`` value, ``FILE`` or ``[FILE,0|1]`` (a :class:`~volwarp_cli.transforms.TransformSpec`).

    An input option (``volwarp batch`` takes ``-t {transform}`` from a scan's
    table row): its file declared as an input. A folder is refused here,
    before it is declared (exit 1, as a file that is not a transform):
    declared, it would make an output inside it look like one overwriting an
    input.
    """

    name = "transform"

    def convert(self, value, param, ctx):
        """The parsed spec, its file declared."""
        from ..errors import VolwarpError
        from ..io.inputs import declare_input, refuse_stream_input
        from ..transforms import TransformSpec, parse_spec, refuse_folder

        if isinstance(value, TransformSpec):
            return value
        try:
            spec = parse_spec(value)
        except VolwarpError as exc:
            self.fail(str(exc), param, ctx)
        refuse_folder(spec.path)
        refuse_stream_input(spec.path)  # (read for its initial transforms, then again)
        declare_input(spec.path)
        for initial in _initial_transforms(spec.path):
            declare_input(initial)
        return spec


def _initial_transforms(path) -> list:
    """The initial transforms an elastix parameter file names, declared with it as inputs.

    Here, not only when the chain is read: a batch's dry run (its inputs'
    hashes) stops at the first volume read, the input's, which comes first.
    A file that cannot be followed is the chain's reading to refuse.
    """
    from ..errors import VolwarpError
    from ..transforms.elastix import initial_files

    try:
        return initial_files(str(path))
    except (VolwarpError, OSError):
        return []


@click.command(name="apply", cls=Command, epilog=examples(
    "volwarp apply moving.nii.gz -o moved.nii.gz --reference fixed.nii.gz "
    "-t 1Warp.nii.gz -t 0GenericAffine.mat",
    "volwarp apply -t 1Warp.nii.gz -t 0GenericAffine.mat --points-in landmarks.csv "
    "--points-to landmarks_fixed.csv",
))
@click.argument("input", required=False, type=INPUT_PATH)
@output_option("The resampled volume (format by extension): on --reference's grid, the "
               "input's type (unless --dtype).", required=False)
@click.option("-t", "--transform", "transforms", multiple=True, required=True,
              metavar="T|[T,1]", type=TransformArg(),
              help="A transform file, repeated in antsApplyTransforms' order: they act on an "
                   "output point in the order listed (-t A -t B samples the input at B(A(p))). "
                   "ITK .tfm/.txt/.h5, ITK/ANTs .mat, elastix TransformParameters files, "
                   "displacement-field images (.nii.gz, .nrrd, .mha), recognised by content; "
                   "'[T,1]': the inverse of a linear T.")
@click.option("--interpolation", type=click.Choice(INTERPOLATIONS), default=None,
              help="As ITK's: linear, nearest or cubic B-spline [default: nearest for a label "
                   "map, else linear].")
@click.option("--values", type=click.Choice(VALUES), default=None,
              help="Take the samples as intensities or as label ids (nearest: a label map "
                   "never gains a value). Default: labels when INPUT looks like a label map "
                   "(as `volwarp info` hints).")
@click.option("--labels", is_flag=True, help="The same as --values labels.")
@click.option("--allow-outside-field", "outside_field", is_flag=True,
              help="Let the output grid reach past a displacement field's samples, where the "
                   "field is the identity (ITK's and antsApplyTransforms' rule): a template's "
                   "labels into a subject whose scan covers more. Refused by default: a field "
                   "made for another reference, or a chain in the wrong order, looks the same.")
@click.option("--reference-series", default=None, metavar="UID|N",
              help="A DICOM --reference holding several volumes: which one, by "
                   "SeriesInstanceUID or by its number in `volwarp info`'s list (--series "
                   "chooses INPUT's).")
@click.option("--background-value", "background", type=float, default=None, metavar="B",
              callback=finite,
              help="Output value where the point falls outside the input [default: the median "
                   "of the input's border samples, a label map's most frequent border label].")
@moved_points_options(
    "Points of the input (moving) space to move into the output space, by the chain's "
    "inverse: a CSV with x, y, z columns (LPS mm; ANTs' layout; other columns kept) or a "
    "Slicer .mrk.json.",
    "Where the moved points go (the format of --points-in).",
    "A mesh (PLY, LPS mm) of the input space whose vertices move as the points.",
    "The moved mesh, faces kept, normals recomputed (.ply .stl .obj .vtp .vtk).")
@write_options
@input_options(reference_help=REFERENCE_HELP, reference_metavar="REF")
@scale_options
@common_options
def command(input, output, transforms, reference, interpolation, values, labels, outside_field,
            reference_series, background, points_in, points_to, mesh_in, mesh_to, dtype,
            compress, byte_order, raw, volume_index, dicom, ome_zarr):
    """Resample INPUT through a chain of transforms onto the --reference grid.

    Each transform maps an output (fixed) point to an input (moving) point,
    in LPS millimetres, as ITK, ANTs and transformix have them: the output
    voxel at p takes the input's value at T(p). Points and meshes of the
    input go the other way (by the inverse of T): they move with the image
    content into the output space. A label map (as `volwarp info` hints) is
    resampled by nearest neighbour: it gains no value. -v prints the choices.
    """
    from ..parallel import beside
    from ..transforms import read_chain

    if (points_in is None) != (points_to is None):
        raise click.UsageError("--points-in and --points-to go together")
    if (mesh_in is None) != (mesh_to is None):
        raise click.UsageError("--mesh-in and --mesh-to go together")
    if (input is None) != (output is None):
        raise click.UsageError("INPUT and -o OUT go together (the volume to resample and "
                               "where it goes)")
    if input is None and points_in is None and mesh_in is None:
        raise click.UsageError("nothing to do: give INPUT -o OUT, --points-in/--points-to or "
                               "--mesh-in/--mesh-to")
    given = _values(values, labels, interpolation)
    if input is None:
        for flag, value in (("--reference", reference), ("--reference-series", reference_series),
                            ("--interpolation", interpolation),
                            ("--values", given), ("--background-value", background),
                            ("--dtype", dtype), ("--allow-outside-field", outside_field or None)):
            if value is not None:
                raise click.UsageError(f"{flag} applies to the resampled volume (INPUT -o OUT)")
        _refuse_volume_options()
    if output is not None:
        check_output_path(output, option="-o")
    points = _points(points_in, points_to)
    mesh = _mesh(mesh_in, mesh_to)
    opened = failed = sampling = None
    if input is not None:
        try:
            opened = _open_input(input, reference, (raw, volume_index, dicom), reference_series)
        except Exception as exc:  # (said after the transforms' errors, as always)
            failed = exc
    if opened is not None:  # the label rule reads the input while a field inflates
        sampling = beside(_sampling, opened[1], str(input),
                          dict(interpolation=interpolation, values=given,
                               background=background, meta=opened[0].meta))
    try:
        with timed("read the transforms"):
            chain = read_chain(transforms)
    except Exception:  # (the transforms' error is said once the input's scan has ended)
        if sampling is not None:
            sampling.wait()
        raise
    if failed is not None:
        raise failed
    log.info("chain: %s", " -> ".join(s.name for s in chain.steps))
    for note in chain.notes:
        log.info("%s", note)
    if opened is not None:
        _resample(input, output, chain, (*opened, sampling.result), dtype,
                  dict(compress=compress, byte_order=byte_order, **ome_zarr),
                  [t.path for t in transforms], outside_field)
    if points is not None or mesh is not None:
        from ..apply import move_mesh, move_points

        if points is not None:
            move_points(chain, *points)
        if mesh is not None:
            move_mesh(chain, *mesh)


#: options of the volume's reading, writing and blocks: with points or a mesh only, none
#: has anything to act on (they were parsed and ignored)
_VOLUME_OPTIONS = ("compress", "byte_order", "ome_zarr_version", "pyramid", "raw_shape",
                   "raw_dtype", "raw_endian", "raw_spacing", "raw_origin", "raw_header_bytes",
                   "volume_index", "series", "irregular", "duplicates", "keep_shear", "keep_phi",
                   "segment", "structure", "chunked", "block", "scheduler", "workers",
                   "threads_per_worker")


def _refuse_volume_options() -> None:
    """A usage error for a volume's option given with points or a mesh only."""
    from .resources import scale_settings
    from .view_options import option_given

    ctx = click.get_current_context()
    scale = scale_settings()
    for name in _VOLUME_OPTIONS:
        if option_given(ctx, name) or getattr(scale, name, None) is not None:
            flag = "--no-chunked" if name == "chunked" and scale.chunked is False else \
                "--" + name.replace("_", "-")
            raise click.UsageError(f"{flag} applies to a volume (INPUT -o OUT); with "
                                   "--points-in or --mesh-in only there is none")


def _values(values, labels, interpolation):
    if labels and values == "intensity":
        raise click.UsageError("--labels and --values intensity contradict each other")
    given = "labels" if labels else values
    if given == "labels" and interpolation not in (None, "nearest"):
        raise click.UsageError(f"--interpolation {interpolation} would blend label ids: a label "
                               "map is resampled by nearest neighbour")
    return given


def _points(points_in, points_to):
    if points_in is None:
        return None
    from ..warp.export import check_points_pair, read_points

    check_points_pair(points_in, points_to)
    return read_points(points_in), points_to


def _mesh(mesh_in, mesh_to):
    if mesh_in is None:
        return None
    from ..errors import VolwarpError
    from ..surface.mesh_io import check_mesh_output, read_mesh

    try:
        check_mesh_output(mesh_to, option="--mesh-to")
    except VolwarpError as exc:
        raise click.BadParameter(str(exc), param_hint="'--mesh-to'") from None
    return read_mesh(mesh_in), mesh_in, mesh_to


def _open_input(input, reference, read, reference_series=None):
    """INPUT opened (header, samples) and the reference's header.

    Before the transforms, in this thread: an input read whole and a field
    read whole each check the memory left, which two threads at once would
    both count as theirs.
    """
    from .chunked import lazy_input

    header, source = lazy_input(input, *read)
    if reference_series is not None and reference is None:
        raise click.UsageError("--reference-series chooses a DICOM --reference's volume: give "
                               "--reference")
    grid = _reference_grid(reference, reference_series) if reference is not None else None
    return header, source, grid


def _reference_grid(reference, series=None):
    """The reference's header, of its first three dimensions: the output grid.

    A 4-D (fMRI, DWI) or vector (a field) reference gives its first volume's
    header, the same grid, as antsApplyTransforms takes it: --volume-index
    chooses the input's volume, and the reference's samples are not used.
    """
    from ..errors import ChoiceNeeded
    from ..io import volume_format
    from ..io.common import dicom_read_options
    from ..io.lazy import open_volume_header

    dicom = volume_format(reference, reading=True) == "dicom"
    if series is not None and not dicom:
        raise click.UsageError(f"--reference-series chooses a DICOM --reference's volume; "
                               f"{reference} is not DICOM")
    try:
        return open_volume_header(reference, samples=False,
                                  dicom=dicom_read_options(series) if dicom else None)[0]
    except ChoiceNeeded as exc:
        if dicom:  # (a DICOM folder of several series: the user says which)
            raise type(exc)(str(exc).replace("--series", "--reference-series")) from None
        if volume_format(reference, reading=True) not in ("nifti", "nrrd", "metaimage",
                                                          "omezarr"):
            raise
        return open_volume_header(reference, samples=False, volume_index=0)[0]


def _sampling(source, name, options):
    """How INPUT is sampled (:func:`volwarp_cli.apply.choose_sampling`): reads, says nothing.

    Run beside the reading of the transforms (a field's inflating releases
    the GIL); its reads of the samples are a box at a time, checked by no
    budget either way.
    """
    from ..apply import choose_sampling

    return choose_sampling(source, name=name, **options)


def _resample(input, output, chain, ready, dtype, write, transform_paths, outside_field=False):
    """INPUT through ``chain`` onto the grid (:func:`volwarp_cli.apply.plan_resample`), run.

    ``ready``: the opened input (:func:`_open_input`) and the call giving its
    :func:`_sampling` (its thread's ``Beside.result``).
    """
    from .. import execute
    from ..apply import plan_resample
    from ..provenance import stamp

    header, source, ref, sampling = ready
    try:  # (the label scan's result is asked for after the coverage check, as before)
        op = plan_resample(header, source, chain, ref, name=str(input), dtype=dtype,
                           sampling=sampling, outside_field=outside_field)
    except BadUsage as exc:
        raise click.UsageError(str(exc)) from None
    target = op.targets[op.KEY]
    out = stamp(target.header, "apply", [input, *transform_paths])
    op.targets[op.KEY] = execute.Target(output, out, target.dtype, compress=write["compress"],
                                      byte_order=write["byte_order"],
                                      version=write["ome_zarr_version"],
                                      pyramid=write["pyramid"], labels=target.labels)
    op.expect_label_ids()
    op.expect_inside()
    settings = scale_settings()
    ran = execute.run(op, execute.How(chunked=settings.chunked, block=settings.block,
                                      open_engine=settings.open_engine))
    if ran.by_blocks:
        log.info("by %d blocks of %s", ran.blocks, "x".join(map(str, ran.block)))
