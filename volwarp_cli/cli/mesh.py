"""`volwarp mesh`: isosurface a volume to a mesh file, measure it, render it to PNG.

Parse, then one operation (:class:`volwarp_cli.surface.run.MeshOperation`) run by
the executor (:func:`volwarp_cli.execute.run`: in memory or by blocks, the same
bytes), then print and render.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from ..labelmap import VALUES
from .options import (
    INPUT_PATH,
    VIEW_HELP,
    Command,
    common_options,
    core_parser,
    examples,
    file_name_checked,
    finite,
    input_options,
    option,
    parse_color,
    parse_view,
    render_size_option,
)
from .resources import scale_options, scale_settings
from .view_options import camera_options, orientation_labels_for, refuse_picture_options_without


def image_path(value):
    """An image output's extension, checked when the option is parsed.

    A usage error, before any work; shared by every command that renders.
    """
    from ..io.images import check_image_extension

    return check_image_extension(value)


def mesh_path(value):
    """A mesh output's extension, checked when the option is parsed (a usage error)."""
    from ..surface.mesh_io import mesh_format

    mesh_format(value)
    return value


def _smooth_iterations(value: int) -> int:
    """--smooth: 0 or at least 2 (VTK's windowed sinc finds no filter for 1: the mesh collapsed)."""
    if value == 1:
        raise click.BadParameter("1 iteration: VTK's windowed-sinc filter needs 0 (off) or at "
                                 "least 2 (at 1 it shrank a ball to 0.5% of its volume)")
    return value


def turntable_paths(render: str, n: int) -> list[Path]:
    """``out.png`` -> ``out-000.png`` ... ``out-{n-1}.png``."""
    p = Path(render)
    return [p.with_name(f"{p.stem}-{k:03d}{p.suffix}") for k in range(n)]


def render_files(render: str | Path, turntable: int | None) -> list[Path]:
    """The images ``--render`` writes: its own name, or with ``--turntable N`` only the frames.

    One function for the command and for batch, which records and checks these files.
    """
    return [Path(render)] if turntable is None else turntable_paths(render, turntable)


def _format_stats(d: dict) -> str:
    def vec(v):
        return "-" if v is None else " ".join(f"{x:.6g}" for x in v)
    return "\n".join([
        f"vertices:   {d['vertices']}",
        f"triangles:  {d['triangles']}",
        f"area:       {d['area']:.6g}",
        f"volume:     {d['volume']:.6g}",
        f"bbox min:   {vec(d['bbox_min'])}",
        f"bbox max:   {vec(d['bbox_max'])}",
        f"components: {d['components']}",
        f"closed:     {'yes' if d['closed'] else 'no'}",
    ])


@click.command(name="mesh", cls=Command, epilog=examples(
    "volwarp mesh head.nrrd --iso 40 -o head.ply --render head.png --view front --stats",
    "volwarp mesh seg.nii.gz --labels -o 'seg_{label}.ply' --smooth 20 --json",
))
@click.argument("input", type=INPUT_PATH)
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              callback=file_name_checked(core_parser(mesh_path)),
              help="Mesh file: .ply .stl .obj .vtp .vtk (binary where the format has it). "
                   "May be left out when --render or --stats is given.")
@click.option("--iso", type=float, default=None, callback=finite,
              help="Isosurface level (default: the middle of the value range; a label map's "
                   "surface is its non-zero labels', see --values).")
@click.option("--inside", type=click.Choice(["above", "below"]), default="above",
              show_default=True,
              help="Which side of the level is the shape (sets the outward direction): "
                   "'above' for bright objects, 'below' e.g. for distance fields negative "
                   "inside.")
@click.option("--cap", is_flag=True,
              help="Pad the volume with one layer of outside samples so shapes touching its "
                   "border are closed there.")
@click.option("--smooth", type=click.IntRange(min=0), default=0, show_default=True,
              metavar="N", callback=lambda ctx, param, value: _smooth_iterations(value),
              help="Windowed-sinc smoothing iterations, 0 (off) or at least 2 "
                   "(volume-preserving).")
@click.option("--decimate", type=click.FloatRange(0.0, 1.0, max_open=True), default=0.0,
              show_default=True, metavar="FRACTION",
              help="Fraction of the triangles to remove by quadric decimation (0.9 keeps 10%).")
@click.option("--largest-component", is_flag=True,
              help="Keep only the connected piece with the most triangles.")
@click.option("--allow-empty", is_flag=True,
              help="An empty surface is a warning (exit 0, empty mesh written) instead of an "
                   "error (exit 1).")
@click.option("--render", type=click.Path(dir_okay=False), default=None, metavar="OUT.png",
              callback=file_name_checked(core_parser(image_path)),
              help="Also render the surface, shaded, to this image.")
@click.option("--view", default="iso", show_default=True, callback=core_parser(parse_view),
              help=VIEW_HELP)
@render_size_option()
@click.option("--color", default=None, callback=core_parser(parse_color),
              help="Surface colour: a name, #rrggbb or r,g,b (default: bone).")
@option("--background-color", "background_color", was="--background", default=None,
        callback=core_parser(parse_color),
        help="Background colour of the render: a name, #rrggbb or r,g,b (default: white).")
@click.option("--turntable", type=click.IntRange(min=1, max=360), default=None, metavar="N",
              help="Render N views around the vertical axis, starting at --view, written as "
                   "OUT-000.png ... next to --render's name.")
@click.option("--label", "label", type=int, default=None, metavar="N",
              help="A label map: the surface of label N (its indicator's isosurface at 0.5, "
                   "closed at the border as with --cap); no --iso.")
@click.option("--labels", "labels", is_flag=True,
              help="A label map: one mesh per non-zero label, to -o's pattern with {label}, "
                   "e.g. -o 'seg_{label}.ply' (--stats / --json: one entry per label); "
                   "no --iso or --render.")
@click.option("--values", "values", type=click.Choice(VALUES), default=None,
              help="Take the samples as intensities (the isosurface at --iso) or as label ids "
                   "(the surface of every voxel with a non-zero label). Default: labels when "
                   "INPUT looks like a label map (integer ids whose values are regions, as "
                   "`volwarp info` hints), else intensity.")
@click.option("--stats", "show_stats", is_flag=True,
              help="Print counts, area, enclosed volume, bounding box, components, closed.")
@click.option("--json", "as_json", is_flag=True,
              help="Print the statistics as one JSON object (implies --stats).")
@camera_options
@input_options
@scale_options
@common_options
def command(input, output, iso, inside, cap, smooth, decimate, largest_component, allow_empty,
            render, view, render_size, color, background_color, turntable, label, labels,
            values, show_stats, as_json, raw, volume_index, dicom, camera_from, camera_to,
            orientation_labels):
    """Isosurface INPUT at level --iso and write it to OUTPUT (world coordinates).

    A label map of several labels (as `volwarp info` hints; --values
    overrides) gives the surface of every voxel with a non-zero label, never
    a level of its ids taken as intensities: --label N for one label's,
    --labels for a mesh each. A two-valued mask is meshed at its --iso.

    Triangles are wound counter-clockwise seen from outside and normals point
    outwards. The surface is closed wherever the shape does not touch the
    volume's border; use --cap to close it there too. An empty surface (a level
    outside the data range, or never crossed) is an error, exit 1, and nothing
    is written, unless --allow-empty.
    """
    from .. import execute
    from ..io.atomic import check_output_path
    from ..io.inputs import note_pattern, refuse_pattern_over_input
    from ..surface.mesh_io import check_mesh_output
    from ..surface.ops import Cleanup
    from ..surface.run import ALL_LABELS, NONZERO_LABELS, Level, MeshFile, MeshOperation
    from .chunked import lazy_input
    from .common import provenance

    if output is None and render is None and not (show_stats or as_json):
        raise click.UsageError("nothing to do: give -o/--output, --render or --stats")
    if turntable is not None and render is None:
        raise click.UsageError("--turntable needs --render OUT.png (the frames' name)")
    if labels and label is not None:
        raise click.UsageError("--label N and --labels exclude each other")
    if values == "intensity" and (labels or label is not None):
        raise click.UsageError("--label N and --labels take a label map's ids as labels: they "
                               "do not go with --values intensity")
    if (labels or label is not None) and iso is not None:
        raise click.UsageError("--iso does not apply to --label/--labels (the level is 0.5 of "
                               "each label's indicator)")
    if (labels or label is not None) and inside != "above":
        raise click.UsageError("--inside does not apply to --label/--labels (inside is "
                               "where the label is)")
    if labels and render is not None:
        raise click.UsageError("--render does not apply to --labels (render one --label N)")
    if (labels or label is not None) and cap:
        raise click.UsageError("--cap does not apply to --label/--labels: a label's surface "
                               "is always closed at the border")
    if render is None and (camera_from is not None or camera_to is not None
                           or orientation_labels is not None):
        raise click.UsageError("--camera-from, --camera-to and --orientation-labels need "
                               "--render OUT.png")
    refuse_picture_options_without(render, "--render OUT.png")
    # Fail on bad outputs before any work (their extensions are checked by the options).
    if output is not None:
        check_mesh_output(_label_pattern(output) if labels else output, option="-o")
        if labels:  # every name the pattern can give, against the inputs
            refuse_pattern_over_input(output, option="-o")
            note_pattern(output, "-o")
    if render is not None:
        for path in render_files(render, turntable):
            check_output_path(path, option="--render")

    header, source = lazy_input(input, raw, volume_index, dicom)
    which = ALL_LABELS if labels else label
    choice = None
    if which is None:  # DESIGN.md: a label map's surface is its labels', not its ids' level
        from ..progress import log, timed
        from ..surface.labels import mesh_values

        with timed("label rule"):
            choice = mesh_values(source, values=values, iso=iso, inside=inside, name=input,
                                 meta=header.meta, allow_empty=allow_empty)
        log.info("%s: values: %s (%s)", input, choice.values, choice.why)
        if choice.labels:
            which = NONZERO_LABELS
            if cap:  # (said, not ignored: --label/--labels with --cap are refused)
                log.warning("warning: --cap does not apply: %s is taken for a label map, "
                            "whose surface is always closed at the border", input)
        else:
            _say_inside_out(header.meta, input)
    op = MeshOperation(header, source, Level(iso, inside, cap),
                       cleanup=Cleanup(largest_component=largest_component, smooth=smooth,
                                       decimate=decimate),
                       labels=which, allow_empty=allow_empty,
                       name=input, stats=show_stats or as_json,
                       to=None if output is None else MeshFile(output,
                                                                provenance("mesh", input)))
    settings = scale_settings()
    surfaces = execute.run(op, execute.How(chunked=settings.chunked, block=settings.block,
                                           open_engine=settings.open_engine)).output
    if labels:
        if show_stats or as_json:
            _print_stats({s.label: s.stats for s in surfaces}, as_json, label_lines=True)
        return
    (surface,) = surfaces
    if show_stats or as_json:
        chosen = {} if choice is None else {"values": choice.values, "values_why": choice.why}
        _print_stats(dict(surface.stats, iso=surface.iso, **chosen), as_json)
    if render is not None:
        camera = camera_from
        if camera is None and surface.mesh.is_empty:  # (--allow-empty: frame the volume)
            camera = _volume_camera(header, view, render_size)
        _render(surface.mesh, render, turntable, orientation_labels_for(orientation_labels,
                                                                        header),
                dict(view=view, size=render_size, color=color, background=background_color,
                     camera=camera), (camera_to, input))


def _say_inside_out(meta, name) -> None:
    """Warn when volwarp's own signed field (negative inside) is meshed with --inside above unasked.

    The default takes the samples above the level for the shape: of a
    distance field (``volwarp_distance``) or a morph's SDF frame, its outside,
    so the surface came out wound inwards (a negative enclosed volume, its
    renders lit from inside), exit 0. An --inside given is done as asked.
    """
    from click.core import ParameterSource

    if click.get_current_context().get_parameter_source("inside") is not ParameterSource.DEFAULT:
        return
    meta = meta or {}
    if "volwarp_distance" in meta:
        what = "a distance field"
    elif "output=sdf" in str(meta.get("volwarp_morph", "")):
        what = "a morph frame's signed distance field"
    else:
        return
    from ..progress import log

    log.warning("warning: %s is %s, negative inside: --inside above (the default) meshes its "
                "outside, wound inwards; give --inside below", name, what)


def _volume_camera(header, view, size):
    """The camera an empty surface's render takes: the volume's box, as its surface would.

    (It was a camera at the world's origin, whose ``--camera-to`` file framed
    nothing of the volume: a before/after pipeline's later renders were empty.)
    """
    import itertools

    import numpy as np

    from ..render.surface import fit_camera

    nx, ny, nz = header.shape_xyz
    corners = np.array(list(itertools.product((-0.5, nx - 0.5), (-0.5, ny - 0.5),
                                              (-0.5, nz - 0.5))))
    return fit_camera(header.index_to_world(corners), view, size)


def _print_stats(stats: dict, as_json: bool, label_lines: bool = False) -> None:
    """Statistics on stdout: one JSON object, or lines (``label_lines``: per label)."""
    if as_json:
        click.echo(json.dumps({str(k): v for k, v in stats.items()} if label_lines else stats,
                              sort_keys=True))
    elif label_lines:
        for label, st in stats.items():
            click.echo(f"label:      {label}")
            click.echo(_format_stats(st))
    else:
        click.echo(_format_stats(stats))


def _render(mesh, render, turntable, letters, look: dict, camera_to) -> None:
    """``--render``: the shaded mesh (or ``--turntable`` frames) and ``--camera-to``'s camera."""
    from ..io.images import write_image
    from ..progress import timed
    from ..render import surface as rs
    from ..render.camera import write_camera

    look = dict(look, orientation_labels=letters)
    if turntable is None:
        with timed(f"render {render}"):
            image, camera = rs.render_mesh(mesh, return_camera=True, **look)
            write_image(render, image)
    else:
        with timed(f"render {turntable} turntable views"):
            images, cameras = rs.render_turntable(mesh, turntable, return_cameras=True, **look)
            for path, image in zip(turntable_paths(render, turntable), images, strict=True):
                write_image(path, image)
        camera = cameras[0]
    path, source = camera_to
    if path is not None:
        write_camera(camera, path, source=str(source))


def _label_pattern(output):
    """``--labels``' output: a pattern with ``{label}`` (checked before any work)."""
    try:
        a, b = output.format(label=1), output.format(label=2)
    except (ValueError, KeyError, IndexError, AttributeError, TypeError) as exc:
        raise click.BadParameter(f"{output!r}: {exc} (use e.g. 'seg_{{label}}.ply')",
                                 param_hint="'-o'") from None
    if a == b:
        raise click.BadParameter("with --labels the name must hold {label}, e.g. "
                                 "'seg_{label}.ply'", param_hint="'-o'")
    return a
