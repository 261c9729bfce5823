"""`volwarp mesh`: isosurface a volume to a mesh file, measure it, render it to PNG.

The surface comes from :mod:`volwarp_cli.surface.pipeline`; this module parses,
reads, calls and writes.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from .common import load_input
from .options import (
    INPUT_PATH,
    VIEW_HELP,
    common_options,
    core_parser,
    examples,
    finite,
    input_options,
    option,
    parse_color,
    parse_view,
    render_size_option,
)
from .resources import scale_options, scale_settings
from .view_options import camera_options, orientation_labels_for


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


def turntable_paths(render: str, n: int) -> list[Path]:
    """``out.png`` -> ``out-000.png`` ... ``out-{n-1}.png``."""
    p = Path(render)
    return [p.with_name(f"{p.stem}-{k:03d}{p.suffix}") for k in range(n)]


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


@click.command(name="mesh", epilog=examples(
    "volwarp mesh head.nrrd --iso 40 -o head.ply --render head.png --view front --stats",
    "volwarp mesh seg.nii.gz --labels -o 'seg_{label}.ply' --smooth 20 --json",
))
@click.argument("input", type=INPUT_PATH)
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              callback=core_parser(mesh_path),
              help="Mesh file: .ply .stl .obj .vtp .vtk (binary where the format has it). "
                   "May be left out when --render or --stats is given.")
@click.option("--iso", type=float, default=None, callback=finite,
              help="Isosurface level (default: the middle of the value range).")
@click.option("--inside", type=click.Choice(["above", "below"]), default="above",
              show_default=True,
              help="Which side of the level is the shape (sets the outward direction): "
                   "'above' for bright objects, 'below' e.g. for distance fields negative "
                   "inside.")
@click.option("--cap", is_flag=True,
              help="Pad the volume with one layer of outside samples so shapes touching its "
                   "border are closed there.")
@click.option("--smooth", type=click.IntRange(min=0), default=0, show_default=True,
              metavar="N", help="Windowed-sinc smoothing iterations (volume-preserving; 0: off).")
@click.option("--decimate", type=click.FloatRange(0.0, 1.0, max_open=True), default=0.0,
              show_default=True, metavar="FRACTION",
              help="Fraction of the triangles to remove by quadric decimation (0.9 keeps 10%).")
@click.option("--largest-component", is_flag=True,
              help="Keep only the connected piece with the most triangles.")
@click.option("--allow-empty", is_flag=True,
              help="An empty surface is a warning (exit 0, empty mesh written) instead of an "
                   "error (exit 1).")
@click.option("--render", type=click.Path(dir_okay=False), default=None, metavar="OUT.png",
              callback=core_parser(image_path),
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
            show_stats, as_json, raw, volume_index, dicom, camera_from, camera_to,
            orientation_labels):
    """Isosurface INPUT at level --iso and write it to OUTPUT (world coordinates).

    Triangles are wound counter-clockwise seen from outside and normals point
    outwards. The surface is closed wherever the shape does not touch the
    volume's border; use --cap to close it there too. An empty surface (a level
    outside the data range, or never crossed) is an error, exit 1, and nothing
    is written, unless --allow-empty.
    """
    from ..io.atomic import check_output_path
    from ..io.inputs import refuse_pattern_over_input
    from ..progress import log, timed
    from ..surface.mesh_io import check_mesh_output
    from ..surface.pipeline import Cleanup, label_indicator, surface_mesh

    if output is None and render is None and not (show_stats or as_json):
        raise click.UsageError("nothing to do: give -o/--output, --render or --stats")
    if turntable is not None and render is None:
        raise click.UsageError("--turntable needs --render OUT.png (the frames' name)")
    if labels and label is not None:
        raise click.UsageError("--label N and --labels exclude each other")
    if (labels or label is not None) and iso is not None:
        raise click.UsageError("--iso does not apply to --label/--labels (the level is 0.5 of "
                               "each label's indicator)")
    if (labels or label is not None) and inside != "above":
        raise click.UsageError("--inside does not apply to --label/--labels (inside is "
                               "where the label is)")
    if labels and render is not None:
        raise click.UsageError("--render does not apply to --labels (render one --label N)")
    if render is None and (camera_from is not None or camera_to is not None
                           or orientation_labels is not None):
        raise click.UsageError("--camera-from, --camera-to and --orientation-labels need "
                               "--render OUT.png")
    # Fail on bad outputs before any work (their extensions are checked by the options).
    if output is not None:
        check_mesh_output(_label_pattern(output) if labels else output, option="-o")
        if labels:  # every name the pattern can give, against the inputs
            refuse_pattern_over_input(output, option="-o")
    if render is not None:
        for path in [render] if turntable is None else turntable_paths(render, turntable):
            check_output_path(path, option="--render")

    cleanup = Cleanup(largest_component=largest_component, smooth=smooth, decimate=decimate)
    chunked = scale_settings().chunked

    def write_labels(meshes):
        _mesh_labels(meshes, input, output, show_stats or as_json, as_json)

    blocks = dict(label=label, labels=write_labels if labels else None, dicom=dicom)
    by_blocks = bool(chunked)
    if chunked:
        vol, mesh, iso = _mesh_by_blocks(input, raw, volume_index, iso, inside, cap,
                                         allow_empty, cleanup, **blocks)
    else:
        from ..errors import OutOfMemoryError

        try:
            vol = load_input(input, raw, volume_index, dicom=dicom)
            mesh = None
        except OutOfMemoryError as exc:
            from .chunked import wants_blocks

            if chunked is False:
                raise
            if not wants_blocks(str(exc)):
                raise
            by_blocks = True
            vol, mesh, iso = _mesh_by_blocks(input, raw, volume_index, iso, inside, cap,
                                             allow_empty, cleanup, **blocks)
    if labels:  # (by blocks, the meshes were written as they came)
        if not by_blocks:
            from ..surface.pipeline import label_meshes

            write_labels(label_meshes(vol, allow_empty=allow_empty, cleanup=cleanup,
                                      name=input))
        return
    if mesh is None:
        if label is not None:
            vol, iso, inside, cap = label_indicator(vol, label, name=input), 0.5, "above", True
        mesh, iso = surface_mesh(vol, iso, inside=inside, cap=cap, allow_empty=allow_empty,
                                 cleanup=cleanup, name=input)
    log.info("mesh: %d vertices, %d triangles", mesh.n_vertices, mesh.n_faces)

    if output is not None:
        from ..surface.mesh_io import write_mesh
        from .common import provenance
        with timed(f"write {output}"):
            write_mesh(mesh, output, comments=dict(provenance("mesh", input),
                                                   volwarp_iso=f"{iso:.9g}"))

    if show_stats or as_json:
        from ..surface.stats import mesh_stats
        with timed("statistics"):
            stats = mesh_stats(mesh)
        stats["iso"] = iso
        if as_json:
            click.echo(json.dumps(stats, sort_keys=True))
        else:
            click.echo(_format_stats(stats))

    if render is not None:
        from ..io.images import write_image
        from ..render import surface as rs
        from ..render.camera import write_camera
        letters = orientation_labels_for(orientation_labels, vol)
        if turntable is None:
            with timed(f"render {render}"):
                image, camera = rs.render_mesh(mesh, view=view, size=render_size, color=color,
                                               background=background_color, camera=camera_from,
                                               orientation_labels=letters, return_camera=True)
                write_image(render, image)
        else:
            paths = turntable_paths(render, turntable)
            with timed(f"render {turntable} turntable views"):
                images, cameras = rs.render_turntable(
                    mesh, turntable, view=view, size=render_size, color=color,
                    background=background_color, camera=camera_from,
                    orientation_labels=letters, return_cameras=True)
                for path, image in zip(paths, images, strict=True):
                    write_image(path, image)
            camera = cameras[0]
        if camera_to is not None:
            write_camera(camera, camera_to, source=str(input))


def _mesh_by_blocks(input, raw, volume_index, iso, inside, cap, allow_empty, cleanup, *,
                    label=None, labels=None, dicom=None):
    """The isosurface by blocks (:mod:`volwarp_cli.surface.chunked`): ``(template, mesh, iso)``.

    ``label``: the surface of that label of a label map (its indicator at
    0.5, capped), as ``--label``; ``labels``: a callable that gets the
    ``(label, mesh)`` of every non-zero label (``--labels``; the mesh is then
    None). Blocks run on the Dask scheduler when one is named (VTK holds the
    GIL: processes or a cluster run them in parallel), else on this process's
    threads.
    """
    import contextlib

    from .. import parallel
    from ..errors import VolwarpError
    from ..geometry import Geometry
    from ..progress import log, timed
    from ..surface.chunked import (
        label_meshes_blocks,
        label_values,
        slab_block,
        surface_mesh_blocks,
    )
    from ..surface.pipeline import check_label_map
    from .chunked import block_budget, lazy_input

    settings = scale_settings()
    settings.used.add("--block")  # (on this process's threads unless a scheduler is named)
    template, source = lazy_input(input, raw, volume_index, dicom)
    tasks = parallel.threads() if settings.scheduler is None else max(1, settings.workers or 1)
    block = settings.block or slab_block(template.data.shape, block_budget(), tasks)
    with contextlib.ExitStack() as stack:
        how = {"threads": parallel.threads()}
        if settings.scheduler is not None:
            engine = stack.enter_context(settings.open_engine())
            per_task = block_budget() // max(1, engine.workers)

            def run(task, blocks):
                return engine.map(task, blocks, label="mesh", memory=per_task)

            how = {"run": run}
        geometry = Geometry.of(template)
        if label is not None or labels is not None:
            what = "--label" if label is not None else "--labels"
            check_label_map(template, input, what)
            with timed("labels (one pass)"):
                values = label_values(source, block, **how)
            if label is not None and label not in values:
                raise VolwarpError(f"{input}: label {label} does not occur in the volume")
            if labels is not None:
                found = [v for v in values if v != 0]
                if not found:
                    raise VolwarpError(f"{input}: no label other than 0 in the volume")
                log.info("%d labels: %s", len(found), " ".join(map(str, found[:20])))
                labels(label_meshes_blocks(source, geometry, found, block_shape=block,
                                           allow_empty=allow_empty, cleanup=cleanup,
                                           name=input, **how))
                return template, None, None
            from ..surface.chunked import LabelIndicator

            source, iso, inside, cap = LabelIndicator(source, label), 0.5, "above", True
        mesh, iso = surface_mesh_blocks(source, geometry, iso, block_shape=block, inside=inside,
                                        cap=cap, allow_empty=allow_empty, cleanup=cleanup,
                                        name=input, **how)
    return template, mesh, iso


def _mesh_labels(meshes, input, output, show_stats, as_json):
    """``mesh --labels``: write ``meshes`` (``(label, mesh)``) to ``output.format(label=L)``."""
    from ..progress import timed

    all_stats = {}
    for label, mesh in meshes:
        if output is not None:
            from ..surface.mesh_io import write_mesh
            from .common import provenance
            path = output.format(label=label)
            with timed(f"write {path}"):
                write_mesh(mesh, path, comments=dict(provenance("mesh", input),
                                                     volwarp_label=str(label)))
        if show_stats:
            from ..surface.stats import mesh_stats
            all_stats[label] = mesh_stats(mesh)
    if as_json:
        click.echo(json.dumps({str(k): v for k, v in all_stats.items()}, sort_keys=True))
    elif show_stats:
        for label, st in all_stats.items():
            click.echo(f"label:      {label}")
            click.echo(_format_stats(st))


def _label_pattern(output):
    """``--labels``' output: a pattern with ``{label}`` (checked before any work)."""
    try:
        a, b = output.format(label=1), output.format(label=2)
    except (ValueError, KeyError, IndexError, AttributeError) as exc:
        raise click.BadParameter(f"{output!r}: {exc} (use e.g. 'seg_{{label}}.ply')",
                                 param_hint="'-o'") from None
    if a == b:
        raise click.BadParameter("with --labels the name must hold {label}, e.g. "
                                 "'seg_{label}.ply'", param_hint="'-o'")
    return a
