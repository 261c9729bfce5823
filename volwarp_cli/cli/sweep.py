"""`volwarp sweep SPEC.yaml -o 'OUT_{field}.nrrd'`: image-swept volumes (Winter & Chen 2002).

The fields come from :func:`volwarp_cli.sweep.evaluate`, or by blocks from
:func:`volwarp_cli.sweep.run.sweep_by_blocks`; this module parses, reads the
spec, calls and writes.
"""

from __future__ import annotations

import click

from ..errors import VolwarpError
from .mesh import image_path
from .options import (
    INPUT_PATH,
    VIEW_HELP,
    common_options,
    core_parser,
    examples,
    output_option,
    parse_size,
    parse_view,
    render_size_option,
    write_options,
)
from .resources import scale_options, scale_settings
from .view_options import camera_options


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


#: most samples along one axis of a sweep's grid: beyond it a spacing, margin or size is
#: many orders of magnitude off (and the sizes overflow)
MAX_AXIS = 1 << 31


def _check_grid(shape_xyz, origin, spacing, doc, from_options: bool, lo, hi,
                margin=None) -> None:
    """Refuse a grid whose numbers are absurd (a spacing of 1e-300, a margin of 1e300).

    ``shape_xyz``, ``origin``, ``spacing``: the fitted grid's numbers, before they
    make a :class:`~volwarp_cli.geometry.Geometry`. A spec error at ``grid`` (a
    usage error when --shape/--spacing made it).
    """
    import numpy as np

    shape = np.asarray(shape_xyz, dtype=np.float64)
    spacing = np.asarray(spacing, np.float64)
    values = np.concatenate([np.asarray(origin, np.float64).ravel(), spacing.ravel()])
    bounds = np.concatenate([np.ravel(lo), np.ravel(hi)]).astype(np.float64)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        across = (np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
                  + 2 * float(margin or 0.0)) / spacing
        ok = (np.all(np.isfinite(values)) and np.all((shape >= 1) & (shape <= MAX_AXIS))
              and np.all(np.abs(values) <= 1e15) and np.all(across <= MAX_AXIS))
    if ok:
        return
    what = (f"the output grid ({'x'.join(str(int(v)) if 0 <= v < 1e18 else '?' for v in shape)}"
            f" samples, spacing {' '.join(f'{v:g}' for v in np.ravel(spacing))}) is "
            f"absurd: at most {MAX_AXIS} samples per axis and coordinates within 1e15")
    if from_options:
        raise click.UsageError(f"--shape/--spacing: {what}")
    given = doc.data.get("grid") or {}

    def extreme(name):
        v = np.abs(np.asarray(given[name], dtype=np.float64))
        return bool(np.any(v > 1e15) or (name == "spacing" and np.any(v < 1e-9)))
    names = [n for n in ("spacing", "margin", "origin", "shape") if n in given]
    bad = [n for n in names if extreme(n)]
    if bad:
        raise doc.error(("grid", bad[0]), what)
    if not np.all(np.abs(bounds) <= 1e15):  # the sweep itself: its trajectory or scale
        for name in ("scale", "trajectory", "scene"):
            if name in doc.data:
                raise doc.error((name,), f"the sweep reaches {np.abs(bounds).max():.3g} world "
                                "units from the origin (at most 1e15)")
    raise doc.error(("grid", names[0]) if names else ("grid",), what)


def refuse_unmakeable_grid(what: str, memory_bytes: int, outputs, write_kw: dict) -> None:
    """Refuse, before any work, a grid that fits neither the memory nor, by blocks, the disk.

    ``what``: the work and its sizes, for the message; ``memory_bytes``: the
    least the work holds in memory; ``outputs``: ``[(path, nbytes)]``, every
    output of the grid. Each way of running checks its own need exactly,
    later; this only ends at once, with the sizes, what neither way can run (a
    10^15-voxel grid was otherwise allocated, or tiled into blocks, until
    killed). ``sweep`` and ``morph`` call it once their grid is known.
    """
    from ..errors import OutOfMemoryError
    from ..memory import ensure_fits_in_memory

    chunked = scale_settings().chunked
    in_memory = None
    if not chunked:
        try:
            ensure_fits_in_memory(memory_bytes, what)
            return
        except OutOfMemoryError as exc:
            if chunked is False:
                raise
            in_memory = exc
    by_blocks = _blocks_refusal(outputs, write_kw)
    if by_blocks is None:
        return
    raise OutOfMemoryError(f"{in_memory}, and by blocks {by_blocks}" if in_memory
                           else f"{what}: by blocks {by_blocks}")


def _blocks_refusal(outputs, write_kw: dict) -> str | None:
    """Why ``outputs`` (``[(path, nbytes)]``) cannot be written by blocks, or None.

    Their formats, and their sizes against the free space of their folders
    (outputs sharing a folder add up).
    """
    import shutil
    from pathlib import Path

    from ..errors import VolwarpError
    from ..io.blockwrite import check_block_format
    from ..memory import human_bytes

    need: dict[Path, list[int]] = {}
    for path, nbytes in outputs:
        try:
            check_block_format(path, bool(write_kw.get("compress")),
                               int(write_kw.get("pyramid", 0) or 0))
        except VolwarpError as exc:
            return str(exc)
        need.setdefault(Path(path).resolve().parent, []).append(int(nbytes))
    for folder, sizes in need.items():
        try:
            free = shutil.disk_usage(folder).free
        except OSError as exc:
            return f"{folder}: {exc.strerror}"
        if sum(sizes) > free:
            each = "" if len(sizes) == 1 else f" ({len(sizes)} files)"
            return (f"the outputs need {human_bytes(sum(sizes))}{each} where {folder} has "
                    f"{human_bytes(free)} free")
    return None


@click.command(name="sweep", epilog=examples(
    "volwarp sweep sweep-bottle.yaml -o 'bottle_{field}.nrrd' --render bottle.png --view -70,25",
    "volwarp sweep sweep-at-bezier.yaml -o at.nrrd --multi --spacing 0.5 --method direct",
))
@click.argument("spec", type=INPUT_PATH)
@output_option("Output file pattern: '{field}' becomes each field's name "
               "(e.g. 'at_{field}.nrrd'); format by extension.")
@click.option("--multi", is_flag=True,
              help="Write all fields into one multi-component NRRD (-o without {field}).")
@click.option("--render", "render_path", type=click.Path(dir_okay=False), default=None,
              callback=core_parser(image_path),
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
@write_options
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
    import numpy as np

    from ..io import check_output_path, write_volume
    from ..progress import timed
    from ..spec.loader import load_spec
    from ..sweep import evaluate
    from ..sweep.model import fit_grid_values, parse_sweep_spec, sweep_geometry
    from ..sweep.run import VolumeRender, render_fields, sweep_volume
    from .common import provenance

    if shape is not None and spacing is not None:
        raise click.UsageError("give --shape or --spacing, not both")
    if render_path is None and (camera_from is not None or camera_to is not None
                                or orientation_labels is not None):
        raise click.UsageError("--camera-from, --camera-to and --orientation-labels need "
                               "--render OUT.png")
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
        check_output_path(render_path, option="--render")
    if camera_to is not None:  # (again, now that the spec's templates are known inputs)
        check_output_path(camera_to, option="--camera-to")
    grid_spec = dict(sspec.grid)
    if shape is not None:
        grid_spec = {"shape": list(shape), "margin": grid_spec.get("margin")}
    elif spacing is not None:
        grid_spec = {"spacing": spacing, "margin": grid_spec.get("margin")}
    grid_spec = {k: v for k, v in grid_spec.items() if v is not None}
    lo, hi = sspec.bounds()
    with np.errstate(over="ignore", invalid="ignore"):
        grid_values = fit_grid_values(grid_spec, lo, hi)  # shape (x, y, z), origin, spacing
    _check_grid(*grid_values, doc, shape is not None or spacing is not None, lo, hi,
                grid_spec.get("margin"))
    grid = sweep_geometry(*grid_values)
    nx, ny, nz = grid.shape_xyz
    out_dtype = dtype or "float32"
    each = grid.size * np.dtype(out_dtype).itemsize
    refuse_unmakeable_grid(f"sweep output {nx}x{ny}x{nz} x {len(names)} fields",
                           grid.size * 4 * len(names),
                           [(p, each * (len(names) if multi else 1)) for p in paths.values()],
                           {"compress": compress, "pyramid": ome_zarr.get("pyramid", 0)})
    stamp_meta = provenance("sweep", [spec], spec)
    chunked = scale_settings().chunked
    render = None
    if render_path is not None:
        from .view_options import orientation_labels_for

        render = VolumeRender(view, render_size, camera=camera_from,
                              orientation_labels=orientation_labels_for(orientation_labels),
                              what=str(render_path))
    render_to = (render_path, camera_to, spec)  # where the picture and its camera go
    by_blocks = dict(paths=paths, names=names, method=method, tau=tau, dtype=out_dtype,
                     meta=stamp_meta, compress=compress, byte_order=byte_order, render=render,
                     render_to=render_to, **ome_zarr)
    if chunked:
        _sweep_by_blocks(sspec, grid, **by_blocks)
        return
    from ..errors import OutOfMemoryError

    try:
        with timed(f"sweep {nx}x{ny}x{nz} ({method or sspec.method})"):
            fields = evaluate(sspec, grid, method=method, tau=tau)
    except OutOfMemoryError as exc:
        from .chunked import blocks_can_write, wants_blocks

        nz, ny, nx = grid.shape
        size = (nz, ny, nx * (len(names) if multi else 1))  # (--multi: one file of them all)
        if chunked is False or not all(
                blocks_can_write(p, size, out_dtype, {"compress": compress})
                for p in paths.values()):
            raise
        if not wants_blocks(str(exc)):
            raise
        _sweep_by_blocks(sspec, grid, **by_blocks)
        return

    with timed("write"):
        if multi:
            from ..io.nrrd import write_nrrd
            comps = [sweep_volume(fields[n], grid, out_dtype, stamp_meta).data for n in names]
            write_nrrd(sweep_volume(fields[names[0]], grid, out_dtype, stamp_meta),
                       paths[None], compress=compress, byte_order=byte_order,
                       components=comps, component_names=names)
        else:
            for n in names:
                write_volume(sweep_volume(fields[n], grid, out_dtype, stamp_meta, n), paths[n],
                             compress=compress, byte_order=byte_order, **ome_zarr)
    if render is not None:
        with timed(f"render {render_path}"):
            img, camera = render_fields(fields, grid, render)
        _write_render(render_to, img, camera)


def _write_render(render_to, img, camera) -> None:
    """The render's PNG (and ``--camera-to``'s camera), once the fields are written."""
    import numpy as np

    from ..io.images import write_image
    from ..render.camera import write_camera

    path, camera_to, spec = render_to
    write_image(path, np.ascontiguousarray(img))
    if camera_to is not None:
        write_camera(camera, camera_to, source=str(spec))


def _sweep_by_blocks(sspec, grid, *, paths, names, method, tau, dtype, meta, compress,
                     byte_order, ome_zarr_version="0.5", pyramid=0, render=None,
                     render_to=None):
    """The sweep by output blocks (:func:`volwarp_cli.sweep.run.sweep_by_blocks`).

    Its outputs are block outputs (one multi-component NRRD for ``paths``
    keyed by None, --multi); the render's PNG is written once they are
    committed.
    """
    from ..sweep.run import sweep_by_blocks
    from .chunked import block_budget, block_output

    def open_output(path, template, dtype, block, components):
        if components is not None:  # (a multi-component NRRD)
            return block_output(path, template, dtype, block=block, compress=compress,
                                byte_order=byte_order, components=components)
        return block_output(path, template, dtype, block=block, compress=compress,
                            byte_order=byte_order, version=ome_zarr_version, pyramid=pyramid)

    settings = scale_settings()
    picture = sweep_by_blocks(sspec, grid, paths=paths, names=names, dtype=dtype, meta=meta,
                              open_output=open_output, open_engine=settings.open_engine,
                              budget=block_budget, block=settings.block, method=method,
                              tau=tau, render=render)
    if render is not None:
        _write_render(render_to, *picture)
