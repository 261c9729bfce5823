"""`volwarp sweep SPEC.yaml -o 'OUT_{field}.nrrd'`: image-swept volumes (Winter & Chen 2002).

Parse, read the spec, fit the grid, then one operation
(:class:`volwarp_cli.sweep.run.SweepOperation`) run by the executor
(:func:`volwarp_cli.execute.run`: in memory or by blocks, the same bytes),
and the render of its fields.
"""

from __future__ import annotations

import click

from ..errors import BadUsage, VolwarpError
from .mesh import image_path
from .options import (
    READ_ONCE_PATH,
    VIEW_HELP,
    Command,
    common_options,
    core_parser,
    examples,
    file_name_checked,
    output_option,
    parse_size,
    parse_view,
    render_size_option,
    write_options,
)
from .resources import scale_options, scale_settings
from .view_options import camera_options, refuse_picture_options_without


def _render_size(value):
    """``WxH`` as for every render, within what the ray caster can make."""
    from ..render.raycast import MAX_PIXELS

    w, h = parse_size(value)
    if w * h > MAX_PIXELS:
        raise VolwarpError(f"{w}x{h} is more than the ray caster's {MAX_PIXELS} pixels")
    return w, h


def output_paths(pattern: str, names: list[str], multi: bool) -> dict[str, str]:
    """:func:`volwarp_cli.sweep.run.field_paths`, its refusals usage errors of ``-o``."""
    from ..sweep.run import field_paths

    try:
        return field_paths(pattern, names, multi)
    except BadUsage as exc:
        raise click.BadParameter(str(exc), param_hint="'-o'") from None


@click.command(name="sweep", cls=Command, epilog=examples(
    "volwarp sweep sweep-bottle.yaml -o 'bottle_{field}.nrrd' --render bottle.png --view -70,25",
    "volwarp sweep sweep-at-bezier.yaml -o at.nrrd --multi --spacing 0.5 --method direct",
))
@click.argument("spec", type=READ_ONCE_PATH)
@output_option("Output file pattern: '{field}' becomes each field's name "
               "(e.g. 'at_{field}.nrrd'); format by extension.")
@click.option("--multi", is_flag=True,
              help="Write all fields into one multi-component NRRD (-o without {field}).")
@click.option("--render", "render_path", type=click.Path(dir_okay=False), default=None,
              callback=file_name_checked(core_parser(image_path)),
              help="Also ray-cast the spatial object (opacity, red/green/blue, geometry) "
                   "to this PNG.")
@click.option("--view", default="iso", show_default=True, callback=core_parser(parse_view),
              help=VIEW_HELP)
@render_size_option(parse=_render_size, was=None)
@click.option("--shape", nargs=3, type=click.IntRange(min=1), default=None, metavar="X Y Z",
              help="Output grid size; spacing is fitted (overrides the spec's grid).")
@click.option("--spacing", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Output voxel size (isotropic); shape is fitted (overrides the spec's grid).")
@click.option("--method", type=click.Choice(["voxelize", "direct"]), default=None,
              help="voxelize: adaptive subdivision (§4.2); direct: inverse mapping at every "
                   "voxel (§5.2-5.3). Default: the spec's method, else voxelize.")
@click.option("--tau", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Largest distance between neighbouring templates, world units "
                   "(default: the spec's, else half a voxel).")
@camera_options
@write_options(dtype_default="float32; an integer type scales 0..1 to its maximum")
@scale_options
@common_options
def command(spec, output, multi, render_path, view, render_size, shape, spacing, method, tau,
            dtype, compress, byte_order, camera_from, camera_to, orientation_labels, ome_zarr):
    """Sweep 2-D image templates along the trajectory of SPEC into one volume per field.

    Fields are float32 (--dtype uint8 scales 0..1 to 0..255, other integer
    types to their maximum). The grid comes from the spec's `grid` or is fitted
    around the sweep with a margin. A multi-component file (--multi) reads back
    one field at a time with `--volume-index N` in the other commands.
    """
    from .. import execute
    from ..io import check_output_path
    from ..progress import timed
    from ..spec.loader import load_spec
    from ..sweep.model import output_grid, parse_sweep_spec
    from ..sweep.run import SweepOperation, VolumeRender, render
    from .common import provenance

    if shape is not None and spacing is not None:
        raise click.UsageError("give --shape or --spacing, not both")
    if render_path is None and (camera_from is not None or camera_to is not None
                                or orientation_labels is not None):
        raise click.UsageError("--camera-from, --camera-to and --orientation-labels need "
                               "--render OUT.png")
    refuse_picture_options_without(render_path, "--render OUT.png")
    if multi:  # the output's form is checked before the spec and its templates are read
        output_paths(output, [], multi)
    with timed("read spec and templates"):
        doc = load_spec(spec, "sweep")
        sspec = parse_sweep_spec(doc)
    names = sspec.field_names()
    paths = output_paths(output, names, multi)
    for p in paths.values():
        check_output_path(p, option="-o")
    if render_path is not None:
        if "opacity" not in names:
            raise click.UsageError(f"--render needs an 'opacity' field; {spec} has "
                                   f"{', '.join(names)}")
        given = [c for c in ("red", "green", "blue") if c in names]
        if given and len(given) < 3:  # (a colour needs all three: it rendered white, unsaid)
            missing = [c for c in ("red", "green", "blue") if c not in names]
            from ..progress import log

            log.warning("warning: --render colours by red, green and blue together; %s has "
                        "%s but no %s: rendered in white (give %s: 0 for none)", spec,
                        ", ".join(given), " or ".join(missing), missing[0])
        check_output_path(render_path, option="--render")
    if camera_to is not None:  # (again, now that the spec's templates are known inputs)
        check_output_path(camera_to, option="--camera-to")
    try:
        grid = output_grid(sspec, shape=shape, spacing=spacing)
    except BadUsage as exc:  # (--shape/--spacing made an absurd grid)
        raise click.UsageError(str(exc)) from None
    write = {"compress": compress, "byte_order": byte_order,
             "version": ome_zarr["ome_zarr_version"], "pyramid": ome_zarr["pyramid"]}
    op = SweepOperation(sspec, grid, paths, dtype or "float32",
                        provenance("sweep", [spec], spec), write, method=method, tau=tau)
    settings = scale_settings()
    how = execute.How(chunked=settings.chunked, block=settings.block,
                      open_engine=settings.open_engine)
    picture = None
    if render_path is not None:
        # (the ray caster's numba now: one that does not fit the budget is refused before
        # the fields are computed, not after, and what it holds is off the blocks' share)
        from ..render import _raycast_kernels  # noqa: F401
        from .view_options import orientation_labels_for

        look = VolumeRender(view, render_size, camera=camera_from,
                            orientation_labels=orientation_labels_for(orientation_labels),
                            what=str(render_path))

        def picture(ran):
            by_slabs = ran.results is None and not settings.block  # (else: the block's depth)
            return render(ran, op, look, execute.block_budget() // 2 if by_slabs else None)
    ran = execute.run(op, how, after=picture)
    if render_path is not None:
        _write_render((render_path, camera_to, spec), *ran.after)


def _write_render(render_to, img, camera) -> None:
    """The render's PNG (and ``--camera-to``'s camera), once the fields are written."""
    import numpy as np

    from ..io.images import write_image
    from ..render.camera import write_camera

    path, camera_to, spec = render_to
    write_image(path, np.ascontiguousarray(img))
    if camera_to is not None:
        write_camera(camera, camera_to, source=str(spec))
