"""`volwarp sweep SPEC.yaml -o 'OUT_{field}.nrrd'`: image-swept volumes (Winter & Chen 2002)."""

from __future__ import annotations

import click

from ..errors import VolwarpError
from .options import (
    INPUT_PATH,
    VIEW_HELP,
    common_options,
    core_parser,
    output_option,
    parse_size,
    parse_view,
    write_options,
)


def _render_size(value):
    """``WxH`` as for every render, within what the ray caster can make."""
    from ..render.raycast import MAX_PIXELS

    w, h = parse_size(value)
    if w * h > MAX_PIXELS:
        raise VolwarpError(f"{w}x{h} is more than the ray caster's {MAX_PIXELS} pixels")
    return w, h


def output_paths(pattern: str, names: list[str], multi: bool) -> dict[str, str]:
    """Output file per field from ``pattern`` (``{field}`` is replaced by the field name).

    With ``multi`` one multi-component NRRD holds every field (key ``None``).
    """
    if multi:
        if "{field}" in pattern:
            raise click.BadParameter("with --multi all fields go into one file: drop {field}",
                                     param_hint="'-o'")
        low = pattern.lower()
        if not (low.endswith(".nrrd") or low.endswith(".nhdr")):
            raise click.BadParameter("--multi writes a multi-component NRRD: use .nrrd or .nhdr",
                                     param_hint="'-o'")
        return {None: pattern}
    if "{field}" not in pattern:
        if len(names) > 1:
            raise click.BadParameter(
                f"the spec has {len(names)} fields ({', '.join(names)}): put {{field}} in the "
                "output name (e.g. 'out_{field}.nrrd') or use --multi", param_hint="'-o'")
        return {names[0]: pattern}
    return {n: pattern.replace("{field}", n) for n in names}


def scale_to_dtype(data, dtype):
    """Float fields in [0, 1] scaled to an integer type's full range (floats unchanged)."""
    import numpy as np

    if dtype is None or np.dtype(dtype).kind == "f":
        return data
    return data.astype(np.float64) * np.iinfo(np.dtype(dtype)).max


@click.command(name="sweep")
@click.argument("spec", type=INPUT_PATH)
@output_option("Output file pattern: '{field}' becomes each field's name "
               "(e.g. 'at_{field}.nrrd'); format by extension.")
@click.option("--multi", is_flag=True,
              help="Write all fields into one multi-component NRRD (-o without {field}).")
@click.option("--render", "render_path", type=click.Path(dir_okay=False), default=None,
              help="Also ray-cast the spatial object (opacity, red/green/blue, geometry) "
                   "to this PNG.")
@click.option("--view", default="iso", show_default=True, callback=core_parser(parse_view),
              help=VIEW_HELP)
@click.option("--render-size", default="512x512", show_default=True, metavar="WxH",
              callback=core_parser(_render_size),
              help="Render size in pixels (as `volwarp mesh --size`).")
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
@write_options
@common_options
def command(spec, output, multi, render_path, view, render_size, shape, spacing, method, tau,
            dtype, compress, byte_order):
    """Sweep 2-D image templates along the trajectory of SPEC into one volume per field.

    Fields are float32 (--dtype uint8 scales 0..1 to 0..255, other integer
    types to their maximum). The grid comes from the spec's `grid` or is fitted
    around the sweep with a margin. A multi-component file (--multi) reads back
    one field at a time with `--volume-index N` in the other commands.
    """
    import numpy as np

    from ..io import check_output_path, write_volume
    from ..io.common import cast_samples
    from ..progress import timed
    from ..spec.loader import load_spec
    from ..sweep import evaluate
    from ..sweep.model import fit_grid, parse_sweep_spec
    from ..volume import Volume
    from .common import provenance

    if shape is not None and spacing is not None:
        raise click.UsageError("give --shape or --spacing, not both")
    with timed("read spec and templates"):
        doc = load_spec(spec, "sweep")
        sspec = parse_sweep_spec(doc)
    names = sspec.field_names()
    paths = output_paths(output, names, multi)
    for p in paths.values():
        check_output_path(p)
    if render_path is not None:
        if "opacity" not in names:
            raise click.UsageError(f"--render needs an 'opacity' field; {spec} has "
                                   f"{', '.join(names)}")
        check_output_path(render_path)
    grid_spec = dict(sspec.grid)
    if shape is not None:
        grid_spec = {"shape": list(shape), "margin": grid_spec.get("margin")}
    elif spacing is not None:
        grid_spec = {"spacing": spacing, "margin": grid_spec.get("margin")}
    grid_spec = {k: v for k, v in grid_spec.items() if v is not None}
    lo, hi = sspec.bounds()
    grid = fit_grid(grid_spec, lo, hi)
    with timed(f"sweep {grid.shape[0]}x{grid.shape[1]}x{grid.shape[2]} ({method or sspec.method})"):
        fields = evaluate(sspec, grid, method=method, tau=tau)
    out_dtype = dtype or "float32"
    stamp_meta = provenance("sweep", [spec], spec)

    def as_volume(data, name=None):
        data = cast_samples(scale_to_dtype(data, out_dtype), out_dtype, what=str(name))
        meta = dict(stamp_meta, volwarp_sweep_field=name) if name else dict(stamp_meta)
        return Volume(data, spacing=grid.spacing, origin=grid.origin, meta=meta)

    with timed("write"):
        if multi:
            from ..io.nrrd import write_nrrd
            comps = [as_volume(fields[n]).data for n in names]
            write_nrrd(as_volume(fields[names[0]]),
                       paths[None], compress=compress, byte_order=byte_order,
                       components=comps, component_names=names)
        else:
            for n in names:
                write_volume(as_volume(fields[n], n), paths[n], compress=compress,
                             byte_order=byte_order)
    if render_path is not None:
        from ..io.images import write_image
        from ..render.raycast import render_volume
        colour = None
        if all(c in fields for c in ("red", "green", "blue")):
            colour = [fields["red"], fields["green"], fields["blue"]]
        with timed(f"render {render_path}"):
            img = render_volume(fields["opacity"], colour=colour, geometry=fields.get("geometry"),
                                spacing=grid.spacing, view=view, size=render_size)
            write_image(render_path, np.ascontiguousarray(img))
