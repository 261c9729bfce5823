"""`volwarp morph`: implicit morph frames between two shapes (Dinh & Carvalho 2004).

    volwarp morph --spec MORPH.yaml -o 'frame_{i:03d}.nrrd'
        [--mesh-to 'frame_{i:03d}.ply'] [--render-to 'frame_{i:03d}.png']
    volwarp morph SOURCE TARGET --frames N --iso V -o PATTERN [--inside ...] [--metric ...]
    volwarp morph SEG_A SEG_B --frames N -o PATTERN [--label N] [--values intensity|labels]

Patterns are Python format strings with ``{i}`` (frame number) and ``{t}``
(its time), e.g. ``frame_{i:03d}.nrrd`` or ``m_{t:.2f}.nrrd``. The frames
come from :func:`volwarp_cli.morph.run.run_morph` (in memory or by blocks, as
:func:`volwarp_cli.morph.run.plan_morph` decides); this module parses and
calls.
"""

from __future__ import annotations

from pathlib import Path

import click

from ..errors import VolwarpError
from ..progress import log
from .mesh import image_path, mesh_path
from .options import (
    INPUT_PATH,
    READ_ONCE_PATH,
    VIEW_HELP,
    Command,
    band,
    common_options,
    core_parser,
    examples,
    file_name_checked,
    finite,
    output_option,
    parse_view,
    render_size_option,
    shape_values_options,
    write_options,
)
from .resources import scale_options, scale_settings
from .view_options import camera_options, refuse_picture_options_without

_METRICS = ["euclidean", "minnorm", "chessboard", "taxicab"]


def _pattern_check(kind: str):
    """A click callback checking a frame pattern's extension on its first frame's name.

    ``kind``: volume, mesh or image. Checked when the option is parsed: an unknown
    extension is a usage error found before any input or spec is read.
    """
    def check(name: str) -> None:
        if kind == "volume":
            from ..io import volume_format

            volume_format(name)
        elif kind == "mesh":
            mesh_path(name)
        else:
            image_path(name)

    def callback(ctx, param, value):
        if value is None:
            return None
        from ..morph.outputs import expand

        try:
            check(expand(value, [0.0], param.opts[-1])[0])
        except VolwarpError as exc:
            raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
        return value
    return callback


@click.command(name="morph", cls=Command, epilog=examples(
    "volwarp morph ball.nrrd torus.nrrd --frames 9 --iso 0.5 -o 'frame_{i:02d}.nrrd'",
    "volwarp morph --spec morph.yaml -o 'f_{i:03d}.nrrd' --render-to 'f_{i:03d}.png' "
    "--sheet sheet.png",
))
@click.argument("shapes", nargs=-1, type=INPUT_PATH, metavar="[SOURCE TARGET]")
@click.option("--spec", "spec_path", type=READ_ONCE_PATH, default=None,
              help="Morph spec (YAML, see specs/morph.schema.json).")
@output_option("Frame file pattern, e.g. 'frame_{i:03d}.nrrd' ({i} frame number, {t} time); "
               "format by extension. An earlier run's frames beyond this run's count are "
               "not removed (a frames folder of its own per run keeps them apart).",
               callback=_pattern_check("volume"))
@click.option("--mesh-to", default=None, callback=file_name_checked(_pattern_check("mesh")),
              help="Also write each frame's surface: pattern with a mesh extension "
                   "(.ply .stl .obj .vtp .vtk).")
@click.option("--render-to", default=None, callback=file_name_checked(_pattern_check("image")),
              help="Also render each frame's surface to an image (.png ...): pattern.")
@click.option("--sheet", "sheet_path", default=None, type=click.Path(dir_okay=False),
              callback=file_name_checked(core_parser(image_path)),
              help="With --render-to: also one contact sheet of all frames' renders, each "
                   "titled with its time t.")
@click.option("--frames", type=click.IntRange(min=2), default=None,
              help="Short form: number of frames (t = 0 .. 1).")
@click.option("--times", default=None, metavar="T1,T2,...",
              help="Short form: explicit times in [0, 1] instead of --frames.")
@click.option("--iso", type=float, default=None, callback=finite,
              help="Short form: iso level of both shapes (needed unless they are label maps).")
@click.option("--inside", type=click.Choice(["above", "below"]), default="above",
              show_default=True, help="Short form: which side of the iso level is inside.")
@shape_values_options(
    label="Short form: label maps: morph label N's voxels (default: every voxel with a "
          "non-zero label).",
    values="Short form: take both inputs' samples as intensities (the shape: --iso V) or as "
           "label ids (the labels' voxels), as `volwarp distance` does. Default: labels for an "
           "input that looks like a label map, else intensity.")
@click.option("--metric", type=click.Choice(_METRICS), default=None,
              help="Short form: distance metric (default euclidean).")
@click.option("--grid", "grid_choice", type=click.Choice(["source", "target", "union"]),
              default=None, help="Short form: the frame grid when the inputs' grids differ.")
@click.option("--max-distance", type=click.FloatRange(min=0, min_open=True), default=None,
              callback=band,
              metavar="D", help="Short form: clamp both fields to [-D, D] (world units); lets "
                                "smooth samples (scans) morph by blocks (--chunked).")
@click.option("--density", "as_density", is_flag=True,
              help="Short form: write a 0..1 occupancy (0.5 on the surface) instead of the SDF.")
@render_size_option(help_text="Render size in pixels, for --render-to.")
@click.option("--view", default="iso", show_default=True,
              callback=core_parser(parse_view), help=VIEW_HELP)
@write_options(dtype_default="float32; a density whose range is the source's: its type")
@camera_options
@scale_options
@common_options
def command(shapes, spec_path, output, mesh_to, render_to, sheet_path, frames, times, iso, inside,
            label, values, metric, grid_choice, max_distance, as_density, render_size, view,
            dtype, compress, byte_order, camera_from, camera_to, orientation_labels, ome_zarr):
    """Morph SOURCE into TARGET: frame t is the zero level set of (1-t) d_source + t d_target.

    Give a --spec, or SOURCE TARGET with --frames (or --times) and --iso
    (unless they are label maps).
    Frames are float32 signed distance fields (negative inside), or a 0..1
    occupancy with --density / output: density (--dtype converts them; a
    spec's attributes keep their own types). Source and target on different
    grids need an alignment or a grid (spec 'grid', --grid).

    Each shape is what `volwarp distance` takes: a label map's is its labels'
    voxels (every non-zero label, or label N with --label N), on the voxel
    surface, whatever its ids' values (no --iso needed; an --iso is accepted
    when it selects exactly those voxels); --values intensity|labels
    overrides. -v prints each shape's choice. A spec attribute that is a
    label map is refused (its ids would be blended) unless it says values:
    intensity.

    With --chunked (or when the morph does not fit the memory budget) the
    fields are computed and kept on disk and every frame is written block by
    block, identical to the in-memory frames: for shapes on any grids, moved
    by an alignment or not, as long as the aligned inputs cover the frame
    grid (no landmark warp), binary shapes, label maps or a --max-distance band,
    uncompressed NRRD/MetaImage/raw or OME-Zarr frames.
    """
    from ..morph.spec import MorphJob, ShapeRef, check_shape_options

    if spec_path is not None:
        if shapes:
            raise click.UsageError("give either --spec or SOURCE TARGET, not both")
        for flag, given in (("--frames", frames is not None), ("--times", times is not None),
                            ("--iso", iso is not None), ("--metric", metric is not None),
                            ("--grid", grid_choice is not None), ("--density", as_density),
                            ("--max-distance", max_distance is not None),
                            ("--inside", inside != "above"), ("--label", label is not None),
                            ("--values", values is not None)):
            if given:
                raise click.UsageError(f"{flag} belongs to the short form; with --spec, set it "
                                       "in the spec")
        from ..morph.spec import job_from_spec
        from ..spec.loader import load_spec

        job = job_from_spec(load_spec(spec_path, "morph"))
    else:
        if len(shapes) != 2:
            raise click.UsageError("give SOURCE and TARGET (or --spec MORPH.yaml)")
        if (frames is None) == (times is None):
            raise click.UsageError("give --frames N or --times T1,T2,... (one of them)")
        if times is not None:
            try:
                tlist = [float(v) for v in times.split(",") if v.strip()]
            except ValueError:
                raise click.BadParameter(f"{times!r} is not a comma-separated list of numbers",
                                         param_hint="--times") from None
            bad = [t for t in tlist if not 0.0 <= t <= 1.0]
            if bad or not tlist:
                raise click.BadParameter(f"times must lie in [0, 1], got {times}",
                                         param_hint="--times")
        else:
            tlist = [i / (frames - 1) for i in range(frames)]
        job = MorphJob(source=ShapeRef(Path(shapes[0]), iso, inside, values, label),
                       target=ShapeRef(Path(shapes[1]), iso, inside, values, label), times=tlist,
                       metric=metric or "euclidean", output="density" if as_density else "sdf",
                       grid=grid_choice, max_distance=max_distance)
        check_shape_options(job.source, job.surface)
    if sheet_path is not None and render_to is None:
        raise click.UsageError("--sheet needs --render-to")
    if render_to is None and (camera_from is not None or camera_to is not None
                              or orientation_labels is not None):
        raise click.UsageError("--camera-from, --camera-to and --orientation-labels need "
                               "--render-to")
    refuse_picture_options_without(render_to, "--render-to PATTERN")
    _run(job, output, mesh_to, render_to, sheet_path, render_size, view, spec_path,
         dict(dtype=dtype, compress=compress, byte_order=byte_order, **ome_zarr),
         (camera_from, camera_to, orientation_labels))


def _grid_error(job, spec_path, exc):
    """The frame grid's error as the command reports it (a usage or spec error)."""
    if spec_path is None:
        return click.UsageError(f"{exc} (short form: --grid union|source|target)")
    if job.doc is not None:
        return job.doc.error(exc.key, str(exc))
    from ..errors import SpecError

    return SpecError(str(exc), file=str(spec_path), key=".".join(exc.key))


def _render_settings(job, render_paths, view, size, camera_from, labels_flag, volumes):
    if not render_paths:
        return None
    from ..morph.frames import RenderSettings
    from .view_options import orientation_labels_for

    return RenderSettings(view, size, camera=camera_from,
                          orientation_labels=orientation_labels_for(labels_flag, *volumes))


def _run(job, output, mesh_to, render_to, sheet_path, size, view, spec_path, write_kw,
         cameras=(None, None, None)):
    """Outputs checked, the run decided before any sample is read, the frames written."""
    from .. import execute
    from ..geometry import Geometry
    from ..morph.grid import GridError
    from ..morph.outputs import MorphOutputs
    from ..morph.run import BlocksRefused, FrameWrite, plan_morph, run_morph
    from .common import provenance

    outputs = MorphOutputs(job, output, mesh_to, render_to, sheet_path)
    camera_from, camera_to, labels_flag = cameras
    if camera_to is not None:  # (again, now that the spec's inputs are known)
        from ..io import check_output_path

        check_output_path(camera_to, option="--camera-to")
    settings = scale_settings()
    try:
        plan = plan_morph(job, outputs, FrameWrite.of(write_kw), settings.chunked)
        render = _render_settings(job, outputs.renders, view, size, camera_from, labels_flag,
                                  plan.headers)
        grid = run_morph(job, outputs, plan, write_kw=write_kw, render=render,
                         camera_to=camera_to,
                         meta=provenance("morph", [job.source.path, job.target.path],
                                         spec_path),
                         how=execute.How(block=settings.block, open_engine=settings.open_engine,
                                         scheduler=settings.scheduler))
    except GridError as exc:
        raise _grid_error(job, spec_path, exc) from None
    except BlocksRefused as exc:
        if exc.usage:
            raise click.UsageError(str(exc)) from None
        raise VolwarpError(str(exc)) from None
    log.info("wrote %d frames on a %s grid%s", len(job.times),
             "x".join(map(str, Geometry.of(grid).shape_xyz)),
             ", by blocks" if plan.by_blocks else "")
