"""`volwarp morph`: implicit morph frames between two shapes (Dinh & Carvalho 2004).

    volwarp morph --spec MORPH.yaml -o 'frame_{i:03d}.nrrd'
        [--mesh-to 'frame_{i:03d}.ply'] [--render-to 'frame_{i:03d}.png']
    volwarp morph SOURCE TARGET --frames N --iso V -o PATTERN [--inside ...] [--metric ...]

Patterns are Python format strings with ``{i}`` (frame number) and ``{t}``
(its time), e.g. ``frame_{i:03d}.nrrd`` or ``m_{t:.2f}.nrrd``. The frames
come from :func:`volwarp_cli.morph.frames.morph_frames`; this module parses,
reads, calls and writes.
"""

from __future__ import annotations

from pathlib import Path

import click

from ..errors import VolwarpError
from ..progress import log, timed
from .mesh import image_path, mesh_path
from .options import (
    INPUT_PATH,
    VIEW_HELP,
    common_options,
    core_parser,
    examples,
    output_option,
    parse_view,
    render_size_option,
    write_options,
)
from .view_options import camera_options

_METRICS = ["euclidean", "minnorm", "chessboard", "taxicab"]


def _expand(pattern: str, times: list[float], option: str) -> list[str]:
    try:
        names = [pattern.format(i=i, t=t) for i, t in enumerate(times)]
    except (KeyError, IndexError, ValueError, AttributeError) as exc:
        raise click.BadParameter(f"bad pattern {pattern!r} ({exc}); use {{i}} and {{t}}, "
                                 "e.g. frame_{i:03d}.nrrd", param_hint=option) from None
    if len(set(names)) != len(names):
        raise click.BadParameter(f"{pattern!r} gives the same file name to several frames; "
                                 "put {i} (or {t}) in it", param_hint=option)
    return names


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
        option = " / ".join(f"'{o}'" for o in param.opts)
        first = _expand(value, [0.0], option)[0]
        try:
            check(first)
        except VolwarpError as exc:
            raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
        return value
    return callback


def _attribute_name(frame_path: str, name: str) -> str:
    p = Path(frame_path)
    suffix = "".join(p.suffixes[-2:]) if p.name.endswith(".nii.gz") else p.suffix
    stem = p.name[: len(p.name) - len(suffix)] if suffix else p.name
    return str(p.with_name(f"{stem}_{name}{suffix}"))


@click.command(name="morph", epilog=examples(
    "volwarp morph ball.nrrd torus.nrrd --frames 9 --iso 0.5 -o 'frame_{i:02d}.nrrd'",
    "volwarp morph --spec morph.yaml -o 'f_{i:03d}.nrrd' --render-to 'f_{i:03d}.png' "
    "--sheet sheet.png",
))
@click.argument("shapes", nargs=-1, type=INPUT_PATH, metavar="[SOURCE TARGET]")
@click.option("--spec", "spec_path", type=INPUT_PATH, default=None,
              help="Morph spec (YAML, see specs/morph.schema.json).")
@output_option("Frame file pattern, e.g. 'frame_{i:03d}.nrrd' ({i} frame number, {t} time); "
               "format by extension.", callback=_pattern_check("volume"))
@click.option("--mesh-to", default=None, callback=_pattern_check("mesh"),
              help="Also write each frame's surface: pattern with a mesh extension "
                   "(.ply .stl .obj .vtp .vtk).")
@click.option("--render-to", default=None, callback=_pattern_check("image"),
              help="Also render each frame's surface to an image (.png ...): pattern.")
@click.option("--sheet", "sheet_path", default=None, type=click.Path(dir_okay=False),
              callback=core_parser(image_path),
              help="With --render-to: also one contact sheet of all frames' renders, each "
                   "titled with its time t.")
@click.option("--frames", type=click.IntRange(min=2), default=None,
              help="Short form: number of frames (t = 0 .. 1).")
@click.option("--times", default=None, metavar="T1,T2,...",
              help="Short form: explicit times in [0, 1] instead of --frames.")
@click.option("--iso", type=float, default=None, help="Short form: iso level of both shapes.")
@click.option("--inside", type=click.Choice(["above", "below"]), default="above",
              show_default=True, help="Short form: which side of the iso level is inside.")
@click.option("--metric", type=click.Choice(_METRICS), default=None,
              help="Short form: distance metric (default euclidean).")
@click.option("--grid", "grid_choice", type=click.Choice(["source", "target", "union"]),
              default=None, help="Short form: the frame grid when the inputs' grids differ.")
@click.option("--density", "as_density", is_flag=True,
              help="Short form: write a 0..1 occupancy (0.5 on the surface) instead of the SDF.")
@render_size_option(help_text="Render size in pixels, for --render-to.")
@click.option("--view", default="iso", show_default=True,
              callback=core_parser(parse_view), help=VIEW_HELP)
@write_options
@camera_options
@common_options
def command(shapes, spec_path, output, mesh_to, render_to, sheet_path, frames, times, iso, inside,
            metric, grid_choice, as_density, render_size, view, dtype, compress, byte_order,
            camera_from, camera_to, orientation_labels, ome_zarr):
    """Morph SOURCE into TARGET: frame t is the zero level set of (1-t) d_source + t d_target.

    Give a --spec, or SOURCE TARGET with --frames (or --times) and --iso.
    Frames are float32 signed distance fields (negative inside), or a 0..1
    occupancy with --density / output: density (--dtype converts them; a
    spec's attributes keep their own types). Source and target on different
    grids need an alignment or a grid (spec 'grid', --grid).
    """
    from ..morph.spec import MorphJob, ShapeRef

    if spec_path is not None:
        if shapes:
            raise click.UsageError("give either --spec or SOURCE TARGET, not both")
        for flag, given in (("--frames", frames is not None), ("--times", times is not None),
                            ("--iso", iso is not None), ("--metric", metric is not None),
                            ("--grid", grid_choice is not None), ("--density", as_density),
                            ("--inside", inside != "above")):
            if given:
                raise click.UsageError(f"{flag} belongs to the short form; with --spec, set it "
                                       "in the spec")
        from ..morph.spec import job_from_spec
        from ..spec.loader import load_spec

        job = job_from_spec(load_spec(spec_path, "morph"))
    else:
        if len(shapes) != 2:
            raise click.UsageError("give SOURCE and TARGET (or --spec MORPH.yaml)")
        if iso is None:
            raise click.UsageError("--iso V is required in the short form")
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
        job = MorphJob(source=ShapeRef(Path(shapes[0]), iso, inside),
                       target=ShapeRef(Path(shapes[1]), iso, inside), times=tlist,
                       metric=metric or "euclidean", output="density" if as_density else "sdf",
                       grid=grid_choice)
    if sheet_path is not None and render_to is None:
        raise click.UsageError("--sheet needs --render-to")
    if render_to is None and (camera_from is not None or camera_to is not None
                              or orientation_labels is not None):
        raise click.UsageError("--camera-from, --camera-to and --orientation-labels need "
                               "--render-to")
    _run(job, output, mesh_to, render_to, sheet_path, render_size, view, spec_path,
         dict(dtype=dtype, compress=compress, byte_order=byte_order, **ome_zarr),
         (camera_from, camera_to, orientation_labels))


def _run(job, output, mesh_to, render_to, sheet_path, size, view, spec_path, write_kw,
         cameras=(None, None, None)):
    from ..io import check_output_path, read_volume, write_volume
    from ..morph.frames import RenderSettings, morph_frames
    from ..morph.grid import GridError
    from ..morph.pipeline import prepare
    from .common import provenance

    frame_paths = _expand(output, job.times, "-o")
    mesh_paths = _expand(mesh_to, job.times, "--mesh-to") if mesh_to else None
    render_paths = _expand(render_to, job.times, "--render-to") if render_to else None
    for p in frame_paths:
        check_output_path(p)
    for a in job.attributes:
        for p in frame_paths:
            check_output_path(_attribute_name(p, a.name))
    if mesh_paths:
        from ..surface.mesh_io import check_mesh_output

        for p in mesh_paths:
            check_mesh_output(p)
    if render_paths:
        for p in render_paths:
            check_output_path(p)
        if sheet_path:
            check_output_path(sheet_path)
    with timed("read inputs"):
        source = read_volume(job.source.path)
        target = read_volume(job.target.path)
        attrs = {a.name: (read_volume(a.source), read_volume(a.target)) for a in job.attributes}
    try:
        prep = prepare(job, source, target, attrs)
    except GridError as exc:
        if spec_path is None:
            raise click.UsageError(f"{exc} (short form: --grid union|source|target)") from None
        if job.doc is not None:
            raise job.doc.error(exc.key, str(exc)) from None
        from ..errors import SpecError

        raise SpecError(str(exc), file=str(spec_path), key=".".join(exc.key)) from None
    meta = {"volwarp_morph": f"metric={job.metric} output={job.output}",
            **provenance("morph", [job.source.path, job.target.path], spec_path)}
    camera_from, camera_to, labels_flag = cameras
    render = None
    if render_paths:
        from .view_options import orientation_labels_for

        render = RenderSettings(view, size, camera=camera_from,
                                orientation_labels=orientation_labels_for(labels_flag, source,
                                                                          target))
    attr_kw = {k: v for k, v in write_kw.items() if k != "dtype"}  # their own types
    renders = []
    for frame in morph_frames(job, prep, source, attrs, meta=meta, meshes=bool(mesh_paths),
                              render=render):
        i = frame.index
        write_volume(frame.volume, frame_paths[i], **write_kw)
        for name, vol in frame.attributes.items():
            write_volume(vol, _attribute_name(frame_paths[i], name), **attr_kw)
        if mesh_paths:
            from ..surface.mesh_io import write_mesh

            write_mesh(frame.mesh, mesh_paths[i], comments=frame.volume.meta)
        if render_paths:
            from ..io.images import write_image

            write_image(render_paths[i], frame.image)
            if sheet_path:
                renders.append(frame.image)
    if camera_to is not None and render is not None:
        from ..render.camera import write_camera

        write_camera(frame.camera, camera_to, source=str(job.source.path))
    if sheet_path:
        from ..io.images import write_image
        from ..render.sheet import contact_sheet

        titles = [f"t = {t:.3g}" for t in job.times]
        write_image(sheet_path, contact_sheet(renders, titles=titles))
    log.info("wrote %d frames on a %s grid", len(job.times),
             "x".join(map(str, prep.grid.shape_xyz)))
