"""`volwarp morph`: implicit morph frames between two shapes (Dinh & Carvalho 2004).

    volwarp morph --spec MORPH.yaml -o 'frame_{i:03d}.nrrd'
        [--mesh-to 'frame_{i:03d}.ply'] [--render-to 'frame_{i:03d}.png']
    volwarp morph SOURCE TARGET --frames N --iso V -o PATTERN [--inside ...] [--metric ...]

Patterns are Python format strings with ``{i}`` (frame number) and ``{t}``
(its time), e.g. ``frame_{i:03d}.nrrd`` or ``m_{t:.2f}.nrrd``. The frames
come from :func:`volwarp_cli.morph.frames.morph_frames`, or by blocks from
:func:`volwarp_cli.morph.run.morph_by_blocks`; this module parses, reads,
calls and writes.
"""

from __future__ import annotations

import contextlib
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
    finite,
    output_option,
    parse_view,
    render_size_option,
    write_options,
)
from .resources import scale_options, scale_settings
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
@click.option("--iso", type=float, default=None, callback=finite,
              help="Short form: iso level of both shapes.")
@click.option("--inside", type=click.Choice(["above", "below"]), default="above",
              show_default=True, help="Short form: which side of the iso level is inside.")
@click.option("--metric", type=click.Choice(_METRICS), default=None,
              help="Short form: distance metric (default euclidean).")
@click.option("--grid", "grid_choice", type=click.Choice(["source", "target", "union"]),
              default=None, help="Short form: the frame grid when the inputs' grids differ.")
@click.option("--max-distance", type=click.FloatRange(min=0, min_open=True), default=None,
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
            metric, grid_choice, max_distance, as_density, render_size, view, dtype, compress,
            byte_order, camera_from, camera_to, orientation_labels, ome_zarr):
    """Morph SOURCE into TARGET: frame t is the zero level set of (1-t) d_source + t d_target.

    Give a --spec, or SOURCE TARGET with --frames (or --times) and --iso.
    Frames are float32 signed distance fields (negative inside), or a 0..1
    occupancy with --density / output: density (--dtype converts them; a
    spec's attributes keep their own types). Source and target on different
    grids need an alignment or a grid (spec 'grid', --grid).

    With --chunked (or when the morph does not fit the memory budget) the
    fields are computed and kept on disk and every frame is written block by
    block, identical to the in-memory frames: for shapes on any grids, moved
    by an alignment or not, as long as the aligned inputs cover the frame
    grid (no landmark warp), binary shapes or a --max-distance band,
    uncompressed NRRD/MetaImage/raw or OME-Zarr frames.
    """
    from ..morph.spec import MorphJob, ShapeRef

    if spec_path is not None:
        if shapes:
            raise click.UsageError("give either --spec or SOURCE TARGET, not both")
        for flag, given in (("--frames", frames is not None), ("--times", times is not None),
                            ("--iso", iso is not None), ("--metric", metric is not None),
                            ("--grid", grid_choice is not None), ("--density", as_density),
                            ("--max-distance", max_distance is not None),
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
                       grid=grid_choice, max_distance=max_distance)
    if sheet_path is not None and render_to is None:
        raise click.UsageError("--sheet needs --render-to")
    if render_to is None and (camera_from is not None or camera_to is not None
                              or orientation_labels is not None):
        raise click.UsageError("--camera-from, --camera-to and --orientation-labels need "
                               "--render-to")
    _run(job, output, mesh_to, render_to, sheet_path, render_size, view, spec_path,
         dict(dtype=dtype, compress=compress, byte_order=byte_order, **ome_zarr),
         (camera_from, camera_to, orientation_labels))


class _Outputs:
    """Every output path of a morph, expanded from the patterns and checked before any work."""

    def __init__(self, job, output, mesh_to, render_to, sheet_path):
        from ..io import check_output_path

        self.frames = _expand(output, job.times, "-o")
        self.meshes = _expand(mesh_to, job.times, "--mesh-to") if mesh_to else None
        self.renders = _expand(render_to, job.times, "--render-to") if render_to else None
        self.sheet = sheet_path
        self.attributes = {a.name: [_attribute_name(p, a.name) for p in self.frames]
                           for a in job.attributes}
        for p in self.frames:
            check_output_path(p, option="-o")
        for paths in self.attributes.values():
            for p in paths:
                check_output_path(p, option="attributes")
        if self.meshes:
            from ..surface.mesh_io import check_mesh_output

            for p in self.meshes:
                check_mesh_output(p, option="--mesh-to")
        if self.renders:
            for p in self.renders:
                check_output_path(p, option="--render-to")
            if sheet_path:
                check_output_path(sheet_path, option="--sheet")

    def write_surface(self, frame, comments, renders: list) -> None:
        """Frame's mesh and render, as asked (the render kept for the sheet)."""
        i = frame.index
        if self.meshes:
            from ..surface.mesh_io import write_mesh

            write_mesh(frame.mesh, self.meshes[i], comments=comments)
        if self.renders:
            from ..io.images import write_image

            write_image(self.renders[i], frame.image)
            if self.sheet:
                renders.append(frame.image)

    def finish(self, job, frame, render, camera_to, renders: list) -> None:
        """The camera file and the contact sheet, after the last frame."""
        if camera_to is not None and render is not None:
            from ..render.camera import write_camera

            write_camera(frame.camera, camera_to, source=str(job.source.path))
        if self.sheet:
            from ..io.images import write_image
            from ..render.sheet import contact_sheet

            titles = [f"t = {t:.3g}" for t in job.times]
            write_image(self.sheet, contact_sheet(renders, titles=titles))


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
    from ..errors import OutOfMemoryError

    outputs = _Outputs(job, output, mesh_to, render_to, sheet_path)
    if cameras[1] is not None:  # (again, now that the spec's inputs are known)
        from ..io import check_output_path

        check_output_path(cameras[1], option="--camera-to")
    loaded = _refuse_unmakeable_frames(job, outputs, spec_path, write_kw)
    chunked = scale_settings().chunked
    if chunked:
        loaded.clear()  # (the block path opens its inputs itself)
        _run_by_blocks(job, outputs, size, view, spec_path, write_kw, cameras)
        return
    try:
        _run_in_memory(job, outputs, size, view, spec_path, write_kw, cameras, loaded)
    except OutOfMemoryError as exc:
        if chunked is False:
            raise
        _run_by_blocks(job, outputs, size, view, spec_path, write_kw, cameras, fallback=exc)


@contextlib.contextmanager
def _one_volume_inputs():
    """A morph input that holds several volumes is the input's fault (exit 1).

    Morph has no ``--volume-index`` nor ``--series`` to choose one with: the
    reader's usage error becomes a file error saying how to extract one.
    """
    from ..errors import ChoiceNeeded, FormatError

    try:
        yield
    except ChoiceNeeded as exc:
        raise FormatError(f"{exc} (morph takes one volume per input: extract it first, e.g. "
                          "volwarp convert IN --volume-index N -o one.nrrd)") from None


def _input_header(path, loaded: dict):
    """The Volume of ``path`` without its samples where the format allows, else read whole.

    A volume read whole goes into ``loaded`` (by path), for the in-memory morph.
    """
    from ..io import read_volume
    from ..io.lazy import open_volume_template

    try:
        return open_volume_template(path, require_lazy=True)[0]
    except VolwarpError:  # (compressed, or not a volume: read_volume says what is wrong)
        loaded[str(path)] = read_volume(path)
        return loaded[str(path)]


def _refuse_unmakeable_frames(job, outputs, spec_path, write_kw) -> dict:
    """Refuse, before any sample is read, frames that fit neither the memory nor the disk.

    The frame grid from the spec and the inputs' headers (exact, or its least
    size where an alignment turns about a centroid:
    :func:`~volwarp_cli.morph.grid.least_frame_shape`), checked as ``sweep``
    checks its grid (:func:`volwarp_cli.execute.refuse_unmakeable`). Returns the inputs
    it had to read whole (compressed files), by path.
    """
    import math

    import numpy as np

    from ..execute import refuse_unmakeable
    from ..geometry import Geometry
    from ..morph.grid import GridError, least_frame_shape

    loaded = {}
    with _one_volume_inputs():
        source = _input_header(job.source.path, loaded)
        target = _input_header(job.target.path, loaded)
    try:
        shape = least_frame_shape(job, Geometry.of(source), Geometry.of(target))
    except GridError as exc:
        raise _grid_error(job, spec_path, exc) from None
    n = math.prod(shape)
    frame_type = np.dtype(write_kw.get("dtype") or (
        source.dtype if job.output == "density" and job.density_range == "source"
        else np.float32))
    sizes = [(p, n * frame_type.itemsize) for p in outputs.frames]
    for a in job.attributes:  # (an attribute's own type: one byte at least)
        sizes += [(p, n * np.dtype(a.dtype or np.uint8).itemsize)
                  for p in outputs.attributes[a.name]]
    refuse_unmakeable(f"a morph on a {'x'.join(map(str, shape))} grid", 8 * n, sizes,
                      chunked=scale_settings().chunked, compress=bool(write_kw.get("compress")),
                      pyramid=int(write_kw.get("pyramid", 0) or 0))
    return loaded


def _run_in_memory(job, outputs, size, view, spec_path, write_kw, cameras, loaded=None):
    from ..io import read_volume, write_volume
    from ..morph.frames import morph_frames
    from ..morph.grid import GridError
    from ..morph.pipeline import prepare
    from ..morph.run import morph_note
    from .common import provenance

    loaded = {} if loaded is None else loaded

    def read(path):  # (taken out: the caller keeps none of them)
        vol = loaded.pop(str(path), None)
        return read_volume(path) if vol is None else vol
    with timed("read inputs"), _one_volume_inputs():
        source = read(job.source.path)
        target = read(job.target.path)
        attrs = {a.name: (read_volume(a.source), read_volume(a.target)) for a in job.attributes}
    try:
        prep = prepare(job, source, target, attrs)
    except GridError as exc:
        raise _grid_error(job, spec_path, exc) from None
    meta = {"volwarp_morph": morph_note(job),
            **provenance("morph", [job.source.path, job.target.path], spec_path)}
    camera_from, camera_to, labels_flag = cameras
    render = _render_settings(job, outputs.renders, view, size, camera_from, labels_flag,
                              (source, target))
    attr_kw = {k: v for k, v in write_kw.items() if k != "dtype"}  # their own types
    renders = []
    for frame in morph_frames(job, prep, source, attrs, meta=meta,
                              meshes=bool(outputs.meshes), render=render):
        i = frame.index
        write_volume(frame.volume, outputs.frames[i], **write_kw)
        for name, vol in frame.attributes.items():
            write_volume(vol, outputs.attributes[name][i], **attr_kw)
        outputs.write_surface(frame, frame.volume.meta, renders)
    outputs.finish(job, frame, render, camera_to, renders)
    log.info("wrote %d frames on a %s grid", len(job.times),
             "x".join(map(str, prep.grid.shape_xyz)))


def _run_by_blocks(job, outputs, size, view, spec_path, write_kw, cameras, *,
                   fallback=None):
    """The morph by blocks (:func:`volwarp_cli.morph.run.morph_by_blocks`): frames by blocks.

    ``fallback``: the in-memory morph's refusal, when this runs instead of it
    (no --chunked); raised again where blocks cannot help either.
    """
    import contextlib

    from ..geometry import Geometry
    from ..morph.grid import GridError
    from ..morph.run import BlocksRefused, morph_by_blocks
    from .chunked import block_budget, block_output, blocks_can_write, lazy_input, wants_blocks
    from .common import provenance

    try:
        with _one_volume_inputs():
            source = lazy_input(job.source.path)
            target = lazy_input(job.target.path)
            attrs = {a.name: (lazy_input(a.source), lazy_input(a.target))
                     for a in job.attributes}
    except VolwarpError:
        if fallback is not None:
            raise fallback from None
        raise
    settings = scale_settings()
    camera_from, camera_to, labels_flag = cameras
    render = _render_settings(job, outputs.renders, view, size, camera_from, labels_flag,
                              (source[0], target[0]))
    kw = dict(compress=write_kw.get("compress", False),
              byte_order=write_kw.get("byte_order", "little"),
              version=write_kw.get("ome_zarr_version", "0.5"),
              pyramid=write_kw.get("pyramid", 0))

    def open_output(path, template, dtype, block):
        return block_output(path, template, dtype, block=block, **kw)

    def check_output(path, shape, dtype):
        if not blocks_can_write(path, shape, dtype, write_kw):
            from ..io.blockwrite import check_block_format

            check_block_format(path, write_kw.get("compress", False))
            raise VolwarpError(f"{path}: the frames do not fit the free space of its folder")

    frames = morph_by_blocks(
        job, source, target, attrs, frame_paths=outputs.frames,
        attribute_paths=outputs.attributes,
        meta=provenance("morph", [job.source.path, job.target.path], spec_path),
        dtype=write_kw.get("dtype"), meshes=bool(outputs.meshes), render=render,
        open_engine=settings.open_engine, budget=block_budget, block=settings.block,
        scheduler=settings.scheduler, open_output=open_output, check_output=check_output,
        fallback=fallback, confirm=wants_blocks)
    renders = []
    frame = None
    try:
        with contextlib.closing(frames):
            for frame in frames:
                outputs.write_surface(frame, frame.template.meta, renders)
    except GridError as exc:
        raise _grid_error(job, spec_path, exc) from None
    except BlocksRefused as exc:
        raise click.UsageError(str(exc)) from None
    outputs.finish(job, frame, render, camera_to, renders)
    log.info("wrote %d frames on a %s grid, by blocks", len(job.times),
             "x".join(map(str, Geometry.of(frame.template).shape_xyz)))
