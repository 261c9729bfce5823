"""volwarp from Python: the commands' own code, with volumes, specs and meshes as values.

Each function runs the code its command runs (the same reading, planning
and computing, as the one-block case of :mod:`volwarp_cli.execute`) and
returns what the command would write; :func:`write` writes it, atomically,
with the command's writer, so that the file is the command's output byte for
byte::

    from volwarp_cli import api

    ball = "tests/data/ball_30_uint8.nrrd"
    dent = {"version": 1, "units": "voxel", "values": "intensity",
            "steps": [{"move": [{"index": [4, 6, 4], "by": [0, -3, 0]}]}]}
    warped = api.warp(ball, dent)              # a Volume
    api.write(warped, "dented.nrrd")           # = volwarp warp BALL --spec dent.yaml ...
    surface = api.mesh(warped, iso=100)        # a Mesh (world coordinates)
    api.write(surface, "dented.ply")
    scene = api.capture(ball, lattice=6)       # a Capture (.vwc)
    api.write(scene, "ball.vwc")

Inputs: a volume is a :class:`~volwarp_cli.volume.Volume` or a path (read
as the command reads it: the read options of :func:`read` are keyword
arguments of every function that takes a path, e.g. ``raw_shape``,
``volume_index``, ``series``); a spec is a path or a ``dict`` of the same
schema (``specs/*.schema.json``), checked the same way: its errors are
:class:`~volwarp_cli.errors.SpecError` naming the same key paths (a
``dict`` has no line numbers; its relative file names are relative to the
current folder). Errors are the commands' (:mod:`volwarp_cli.errors`):
``SpecError`` and ``BadUsage`` where the command exits 2, another
``VolwarpError`` where it exits 1.

Provenance: the commands record in their outputs' key/values the command,
its inputs' file names and the spec's SHA-256
(:func:`volwarp_cli.provenance.provenance`). Given paths, these functions
record exactly the same; given values, what is known: no
``volwarp_input`` for a Volume (nor for a dict spec of ``sweep``), no
``volwarp_spec_sha256`` for a dict spec (a file's bytes are hashed, and a
dict has none). An earlier step's provenance keys are replaced either way.

Inputs are never overwritten: a path read through this module (and every
file its header names) is an input of the current run
(:mod:`volwarp_cli.runscope`; outside any :func:`~volwarp_cli.runscope.run_scope`,
the process's), and :func:`write` refuses to replace one, as every command
does. Nothing here prints: warnings (and ``-v``'s steps, at INFO) go to
the ``volwarp`` logger (:data:`volwarp_cli.progress.log`), as the command
says them: once a call, and what a command says when its run ends (a cast's
clipping over all its blocks, an output all background: a sweep beside its
grid, a morph's empty frame) when the call returns
(:func:`~volwarp_cli.runscope.call_scope`; not when it raises).
How the work runs: on :func:`volwarp_cli.parallel.threads` threads, within
:func:`volwarp_cli.memory.memory_limit` (work that cannot fit is refused
before it starts, an :class:`~volwarp_cli.errors.OutOfMemoryError`; the
commands would run it by blocks, into their files).
"""

from __future__ import annotations

import contextlib
import functools
import os
from collections.abc import Mapping
from dataclasses import dataclass, field

from .errors import BadUsage
from .surface.mesh import Mesh as _Mesh
from .volume import Header, Volume

__all__ = ["Mesh", "READ_OPTIONS", "capture", "distance", "mesh", "morph", "read", "sweep",
           "warp", "write"]

#: The keyword options of :func:`read` (those of ``volwarp convert``, snake_case); every
#: function that takes a volume path takes them too.
READ_OPTIONS = ("raw_shape", "raw_dtype", "raw_endian", "raw_spacing", "raw_origin",
                "raw_header_bytes", "volume_index", "series", "irregular", "duplicates",
                "keep_shear", "keep_phi", "allow_outside_data", "reference", "segment",
                "structure")


@dataclass
class Mesh(_Mesh):
    """A :class:`volwarp_cli.surface.mesh.Mesh` with the key/values its file records.

    ``meta``: what :func:`write` puts where the format has room for text
    (PLY and OBJ comments, a VTP comment): the provenance and the level,
    as ``volwarp mesh`` writes them.
    """

    meta: dict = field(default_factory=dict)


def _said_as_the_command(fn):
    """``fn`` in a :func:`~volwarp_cli.runscope.call_scope`: its warnings said as its command's.

    Without one, a note a command gathers over its blocks was said at every
    block (a warp cast to uint8: its clipping once a plane group), or never
    (a sweep that reaches none of its grid: zeros without a word).
    """
    @functools.wraps(fn)
    def call(*args, **kwargs):
        from .runscope import call_scope

        with call_scope():
            return fn(*args, **kwargs)

    return call


# -- files -------------------------------------------------------------------------------
@_said_as_the_command
def read(path: str | os.PathLike, **options) -> Volume:
    """The volume file ``path``, read as ``volwarp convert`` reads its input.

    Parameters
    ----------
    path : path
        A volume file (NRRD, NIfTI, MetaImage, TIFF, raw, OME-Zarr) or a DICOM
        file, folder or DICOMDIR.
    raw_shape, raw_dtype : optional
        A headerless ``.raw``/``.bin`` file: its samples along (x, y, z) and
        their type (the two go together); ``raw_endian`` (``"little"``),
        ``raw_spacing`` and ``raw_origin`` ((x, y, z)), ``raw_header_bytes``.
    volume_index : int, optional
        A 4-D NIfTI or MetaImage: which volume; a multi-component NRRD: which
        component.
    series, irregular, duplicates, keep_shear, keep_phi : optional
        DICOM inputs: as the commands' ``--series`` (a SeriesInstanceUID or
        its number), ``--irregular resample``, ``--duplicates first|last``,
        ``--keep-shear``, ``--keep-phi``.
    reference : path, optional
        A DICOM SEG or RTSTRUCT input: the image series (folder, DICOMDIR or
        file) it lies on, as the commands' ``--reference``. An RTSTRUCT needs
        it (its ROIs are rasterised on that grid); a SEG is put on that whole
        grid (default: its own frames' grid). ``series``, ``irregular`` and
        ``duplicates`` then choose how the reference is read.
    segment : int, optional
        A DICOM SEG input: segment ``segment`` (1 or more) alone, as a 0/1
        mask (``--segment``; default: every segment, valued by its number).
    structure : str, optional
        A DICOM RTSTRUCT input: the ROI of that name alone, as a 0/1 mask
        (``--structure``; default: every ROI, valued by its ROI Number).
    allow_outside_data : bool
        Let a detached header read data files outside its folder.

    Returns
    -------
    Volume
        Samples ``[z, y, x]``, geometry (x, y, z) in LPS, the file's key/values.
    """
    from .io import read_volume

    raw, volume_index, dicom, outside = _read_arguments(path, options)
    _declare_inputs(path, dicom)
    with _outside_data(outside):
        return read_volume(path, raw=raw, volume_index=volume_index, dicom=dicom)


@_said_as_the_command
def write(obj, path: str | os.PathLike, *, dtype: str | None = None, compress: bool = False,
          byte_order: str = "little", ome_zarr_version: str = "0.5", pyramid: int = 0,
          labels="auto") -> None:
    """Write ``obj`` to ``path`` atomically, with the writer its command uses.

    Parameters
    ----------
    obj : Volume, dict of Volume, Mesh or Capture
        A Volume (format by extension: :func:`volwarp_cli.io.write_volume`);
        :func:`sweep`'s fields (``path`` a pattern with ``{field}``, or the
        name of a spec's one field); a mesh (``.ply .stl .obj .vtp .vtk``,
        its :attr:`Mesh.meta` as comments); a capture (``.vwc``).
    dtype, compress, byte_order, ome_zarr_version, pyramid : optional
        Volumes: as the commands' ``--dtype``, ``--compress``,
        ``--byte-order``, ``--ome-zarr-version`` and ``--pyramid``.
    labels : True, False or ``"auto"``
        Whether the samples are a label map (True) or intensities; ``"auto"``:
        the label-map rule. A label map's pyramid levels take the most
        frequent label, and a ``dtype`` that cannot hold every id is refused
        (:class:`~volwarp_cli.errors.BadUsage`); intensities are clipped to
        ``dtype``'s range and their levels take the mean (as ``convert
        --values``). ``volwarp warp`` writes a label map's warp with True.

    Notes
    -----
    The output is written to a temporary file in its folder and renamed into
    place; an output that would replace an input of this run (a path read
    here, a file its header names) is refused (:class:`~volwarp_cli.errors.BadUsage`)
    before anything is written.
    """
    from .bspline.capture import Capture

    volume_options = dict(dtype=dtype, compress=compress, byte_order=byte_order,
                          ome_zarr_version=ome_zarr_version, pyramid=pyramid)
    defaults = dict(dtype=None, compress=False, byte_order="little", ome_zarr_version="0.5",
                    pyramid=0)
    if isinstance(obj, Volume):
        from .io import write_volume

        if dtype is not None and dtype != obj.dtype.name:  # (as convert: ids kept)
            from .labelmap import keep_label_ids

            keep_label_ids(obj.data, dtype, str(path), labels, obj.meta)
        write_volume(obj, path, labels=labels, **volume_options)
        return
    if isinstance(obj, Mapping) and obj and all(isinstance(v, Volume) for v in obj.values()):
        from .io.atomic import outputs_together
        from .sweep.run import field_paths

        paths = field_paths(str(path), [str(k) for k in obj])
        with outputs_together():  # (all the fields, or none: a later one's failure wrote some)
            for name, vol in obj.items():
                write(vol, paths[str(name)], labels=labels, **volume_options)
        return
    given = [k for k, v in volume_options.items() if v != defaults[k]]
    if labels != "auto":
        given.append("labels")
    if isinstance(obj, (_Mesh, Capture)) and given:
        raise BadUsage(f"{', '.join(given)} apply to volume outputs, not to a "
                       f"{'mesh' if isinstance(obj, _Mesh) else 'capture'}")
    if isinstance(obj, _Mesh):
        from .surface.mesh_io import write_mesh

        write_mesh(obj, path, comments=getattr(obj, "meta", None))
    elif isinstance(obj, Capture):
        from .warp.capture_file import write_capture

        if not str(path).lower().endswith(".vwc"):
            raise BadUsage(f"{path}: a capture file must end in .vwc")
        write_capture(obj, path)
    else:
        raise TypeError(f"api.write writes a Volume, a dict of Volumes (a sweep's fields), a "
                        f"Mesh or a Capture, not {type(obj).__name__}")


# -- operations --------------------------------------------------------------------------
@_said_as_the_command
def capture(volume, *, lattice=9, placement: str = "uniform", oversample: float = 2.0,
            pad=None, sampling: str = "linear", name: str | None = None,
            values: str | None = None, **read_options):
    """``volwarp capture``: ``volume`` pulled back into a B-spline domain voxmap.

    Parameters
    ----------
    volume : Volume or path
        The volume to capture (a path is read with ``read_options``, as
        :func:`read` reads it).
    lattice : int or (int, int, int)
        Control points per axis (x, y, z), 4 at least (6 with ``tripled``).
    placement : {"uniform", "tripled"}
        Where the capture lattice's points go (``volwarp capture --help``).
    oversample : float
        Domain voxels per input voxel along each axis, in (0, 16].
    pad : int or (int, int, int), optional
        Output padding in voxels per side, for later warps.
    sampling : {"linear", "nearest"}
        How a domain voxel takes its value from the input.
    name : str, optional
        The input in messages (default: its path, else "the volume").
    values : {"intensity", "labels"}, optional
        As ``--values``: a label map (by the rule, or ``"labels"``) is
        refused on the spanning grid (``tripled``, or a non-integer
        ``oversample``), which blends its ids for good; ``"intensity"``
        captures its samples as intensities on any grid.

    Returns
    -------
    Capture
        :class:`volwarp_cli.bspline.capture.Capture`; :func:`write` it to a
        ``.vwc`` file, or keep it.

    References
    ----------
    Hughes, "Volume warping", 1992, sections 3, 5 and 7.
    """
    import math
    import numbers

    from .bspline.capture import capture_volume
    from .bspline.lattice import PLACEMENTS
    from .bspline.pullback import SAMPLINGS
    from .errors import VolwarpError
    from .labelmap import VALUES

    _check_keys(read_options)
    if not (isinstance(oversample, numbers.Real) and math.isfinite(oversample)
            and 0 < oversample <= 16):
        raise BadUsage(f"oversample must be a number in (0, 16], got {oversample!r}")
    _choice(values, VALUES, "values")
    _choice(placement, PLACEMENTS, "placement")
    _choice(sampling, SAMPLINGS, "sampling")
    lattice = _three_ints(lattice, "lattice")  # (the command's checks: its usage errors)
    least = 6 if placement == "tripled" else 4
    if min(lattice) < least:
        raise BadUsage(f"lattice: at least {least} control points per axis"
                       f"{' with the tripled placement' if least == 6 else ''}, got {lattice}")
    if pad is not None and min(_three_ints(pad, "pad")) < 0:
        raise BadUsage(f"pad: voxels per side, 0 or more, got {pad!r}")
    path = _path_of(volume)
    vol = read(volume, **read_options) if path is not None else _volume(volume, read_options)
    name = str(name or path or "the volume")
    _refuse_blended_labels(vol, name, placement, oversample, values)
    if values is not None:  # (recorded: the warp of the capture takes it, not the rule)
        from .labelmap import VALUES_KEY

        vol = vol.replace(meta={**vol.meta, VALUES_KEY: values})
    try:
        return capture_volume(vol, lattice=lattice, placement=placement,
                              oversample=oversample, sampling=sampling, pad=pad)
    except VolwarpError as exc:
        raise VolwarpError(f"{name}: {exc}") from None


@_said_as_the_command
def warp(volume, spec, *, values: str | None = None, pushforward: str | None = None,
         evaluator: str | None = None, background_value: float | None = None,
         grid: str | None = None, crop: bool = False, preserve_labels: bool = False,
         dtype: str | None = None, allow_growth: bool = False, **read_options) -> Volume:
    """``volwarp warp``: ``volume`` warped as ``spec`` says (its final lattice).

    Parameters
    ----------
    volume : Volume or path
        A volume, a volume file, or a capture file (``.vwc``, as
        :func:`capture` and ``volwarp capture`` write them).
    spec : path or dict
        A warp spec (schema ``specs/warp.schema.json``).
    values : {"intensity", "labels"}, optional
        How the samples are warped (default: the spec's, else labels for what
        looks like a label map).
    pushforward, evaluator, background_value, grid, crop, preserve_labels, dtype, allow_growth
        As the command's ``--pushforward``, ``--evaluator``,
        ``--background-value``, ``--grid``, ``--crop``, ``--preserve-labels``,
        ``--dtype`` and ``--allow-growth``.

    Returns
    -------
    Volume
        The warped volume, with ``volwarp warp``'s provenance (see the module
        notes). A label map's warp keeps its labels: write its OME-Zarr
        pyramid with ``labels=True``, as the command does.

    Notes
    -----
    The command's own planning (:func:`volwarp_cli.warp.request.plan_final`),
    and its output computed whole, as :func:`volwarp_cli.execute.run` does in
    memory (a label map's: :meth:`~volwarp_cli.warp.label_blocks.OneShotLabelWarp.compute_whole`).
    The frames (``--frames-to``) and the exports are not made here.

    References
    ----------
    Hughes, "Volume warping", 1992, sections 4 to 7.
    """
    import math

    from .bspline.plan import read_warp_spec
    from .io import SUPPORTED_DTYPES
    from .warp.defaults import GRIDS, VALUES, new_run
    from .warp.request import open_capture_values, plan_final
    from .warp.run import WarpOptions

    _check_keys(read_options)
    _choice(values, VALUES, "values")
    _choice(pushforward, ("box", "nearest"), "pushforward")
    _choice(evaluator, ("separable", "table"), "evaluator")
    _choice(grid, GRIDS, "grid")
    _choice(dtype, SUPPORTED_DTYPES, "dtype")
    if background_value is not None and not math.isfinite(background_value):
        raise BadUsage(f"background_value must be a finite number, got {background_value!r}")
    options = WarpOptions(pushforward=pushforward, evaluator=evaluator,
                          background=background_value, crop=crop, dtype=dtype,
                          allow_growth=allow_growth, grid=grid, values=values,
                          preserve=preserve_labels)
    new_run()
    doc, spec_path = _spec(spec, "warp")
    wspec = read_warp_spec(doc)
    path = _path_of(volume)
    name = str(path) if path is not None else "the volume"
    cap = choice = None
    with _outside_data(read_options.get("allow_outside_data", False)):
        if path is not None and str(path).lower().endswith(".vwc"):
            if _given(read_options):
                raise BadUsage("--raw-*, --volume-index and the DICOM options describe volume "
                               f"inputs, not the capture file {path}")
            from .io.inputs import declare_input

            declare_input(path)
            choice, cap, header, source, wspec = open_capture_values(path, doc, wspec,
                                                                     values)
        else:
            header, source = _header_and_source(volume, path, read_options)
        choice, planned = plan_final(header, source, doc, wspec, options, name=name,
                                     cap=cap, choice=choice)
        if choice.is_labels:
            return _warp_labels(planned, name, path, spec_path, choice)
        from .warp.request import values_meta

        out = values_meta(planned.output_header(), choice)
        op = planned.operation(_target(_stamped(out, "warp", path, spec_path)), source=source)
        (result,) = _compute_whole(op).values()
        return result


@_said_as_the_command
def sweep(spec, *, shape=None, spacing: float | None = None, method: str | None = None,
          tau: float | None = None, dtype: str | None = None) -> dict[str, Volume]:
    """``volwarp sweep``: the image-swept volume of ``spec``, one Volume per field.

    Parameters
    ----------
    spec : path or dict
        A sweep spec (schema ``specs/sweep.schema.json``); its template images
        are relative to its folder (a dict's: to the current folder).
    shape : (int, int, int), optional
        The output grid's samples (x, y, z); the spacing is fitted.
    spacing : float, optional
        The output grid's (isotropic) spacing; the shape is fitted. Neither:
        the spec's ``grid``, else fitted around the sweep.
    method : {"voxelize", "direct"}, optional
        Adaptive subdivision or inverse mapping (default: the spec's).
    tau : float, optional
        The largest distance between neighbouring templates (world units).
    dtype : str, optional
        The fields' type (default float32; an integer type scales 0..1 to its
        maximum).

    Returns
    -------
    dict of str to Volume
        Field name to field; :func:`write` them with a ``{field}`` pattern
        (the command's ``-o``; ``--multi``'s one file is not made here).

    References
    ----------
    Winter and Chen, "Image-swept volumes", 2002, sections 3 to 5.
    """
    from .io import SUPPORTED_DTYPES
    from .sweep.model import output_grid, parse_sweep_spec
    from .sweep.run import SweepOperation

    _choice(method, ("voxelize", "direct"), "method")
    _choice(dtype, SUPPORTED_DTYPES, "dtype")
    if tau is not None and not tau > 0:
        raise BadUsage(f"tau must be a positive number, got {tau!r}")
    doc, spec_path = _spec(spec, "sweep")
    sspec = parse_sweep_spec(doc)
    geometry = output_grid(sspec, shape=shape, spacing=spacing)
    meta = _provenance("sweep", [spec_path], spec_path)
    names = sspec.field_names()
    op = SweepOperation(sspec, geometry, dict.fromkeys(names), dtype or "float32", meta, {},
                        method=method, tau=tau)
    return _compute_whole(op)


@_said_as_the_command
def morph(spec, *, meshes: bool = False) -> list:
    """``volwarp morph``: the frames of a morph spec, computed in memory.

    Parameters
    ----------
    spec : path or dict
        A morph spec (schema ``specs/morph.schema.json``): source and target
        shapes, times, metric, output, alignment, grid, warp, attributes.
    meshes : bool
        Also each frame's zero-level surface (the command's ``--mesh-to``).

    Returns
    -------
    list of :class:`volwarp_cli.morph.frames.Frame`
        In time order: ``volume`` (the frame, its key/values as the command
        writes them), ``attributes`` (name -> Volume), ``mesh`` (an
        :class:`Mesh` with the frame's key/values, with ``meshes``).
        ``write(frame.volume, path)`` is the command's frame file byte for
        byte; every frame is held (the command writes them one by one).

    References
    ----------
    Dinh and Carvalho, "Implicit morphing by signed-distance interpolation", 2004.
    """
    from .io import read_volume
    from .io.inputs import declare_input
    from .morph.frames import frame_space, morph_frames, source_keys
    from .morph.pipeline import prepare
    from .morph.run import morph_note, one_volume_inputs
    from .morph.spec import job_from_spec

    if not isinstance(meshes, bool):
        raise BadUsage(f"meshes must be True or False, got {meshes!r}")
    doc, spec_path = _spec(spec, "morph")
    job = job_from_spec(doc)
    paths = [job.source.path, job.target.path]
    for a in job.attributes:
        paths += [a.source, a.target]
    for path in paths:
        declare_input(path)
    with one_volume_inputs():
        source, target = read_volume(job.source.path), read_volume(job.target.path)
        attributes = {a.name: (read_volume(a.source), read_volume(a.target))
                      for a in job.attributes}
    prepared = prepare(job, source, target, attributes)
    meta = {**source_keys(source), "volwarp_morph": morph_note(job, prepared.rules),
            **_provenance("morph", [job.source.path, job.target.path], spec_path)}
    frames = []
    for frame in morph_frames(job, prepared, source, attributes, meta=meta, meshes=meshes,
                              space=frame_space(source, target)):
        if frame.mesh is not None:
            m = frame.mesh
            frame.mesh = Mesh(m.vertices, m.faces, m.normals, meta=dict(frame.volume.meta))
        frames.append(frame)
    return frames


@_said_as_the_command
def distance(volume, iso: float | None = None, *, inside: str = "above",
             label: int | None = None, values: str | None = None, metric: str = "euclidean",
             surface: str = "auto", unsigned: bool = False,
             max_distance: float | None = None, **read_options) -> Volume:
    """``volwarp distance``: the signed distance field of a shape (float32, negative inside).

    Parameters
    ----------
    volume : Volume or path
        The volume (a path is read as the command reads it).
    iso, inside : the shape, the samples on one side of ``iso``
        (``inside="above"``: samples >= iso).
    label, values : a label map's shape
        Its voxels (every non-zero label's, or label ``label``'s); ``values``
        ``"labels"`` or ``"intensity"`` overrides the label-map rule, as
        ``--values`` does.
    metric : {"euclidean", "minnorm", "chessboard", "taxicab"}
    surface : {"auto", "voxel", "subvoxel"}
        The euclidean field's: between voxel centres or to the sub-voxel surface.
    unsigned, max_distance
        As ``--unsigned`` and ``--max-distance``.

    Returns
    -------
    Volume
        The field on the input's grid, its ``volwarp_distance`` key and
        provenance as the command writes them (float32: :func:`write`'s
        ``dtype`` converts, as ``--dtype`` does).
    """
    import numbers

    import numpy as np

    from .distance.field import check_method, field_note
    from .distance.labels import check_options, choose_shape
    from .distance.operation import field_operation
    from .distance.scan import field_surface, scan_box_voxels
    from .geometry import Geometry
    from .progress import log

    _check_keys(read_options)
    _choice(inside, ("above", "below"), "inside")
    check_method(metric, surface)
    check_options(values=values, label=label, iso=iso, surface=surface)
    _finite(iso, "iso")
    _finite(max_distance, "max_distance", positive=True)
    if label is not None and not isinstance(label, numbers.Integral):
        raise BadUsage(f"label must be a whole number (a label's id), got {label!r}")
    if not isinstance(unsigned, bool):
        raise BadUsage(f"unsigned must be True or False, got {unsigned!r}")
    path = _path_of(volume)
    with _outside_data(read_options.get("allow_outside_data", False)):
        header, source = _header_and_source(volume, path, read_options)
        box_voxels = scan_box_voxels()
        name = str(path) if path is not None else "the volume"
        rule = choose_shape(source, values=values, label=label, iso=iso, inside=inside,
                            surface=surface, name=name, box_voxels=box_voxels,
                            meta=header.meta)
        log.info("%s", rule.describe())
        surface = field_surface(source, rule, metric=metric, surface=surface,
                                max_distance=max_distance, box_voxels=box_voxels)
        from .labelmap import without_label_keys

        out = _stamped(header.replace(meta=without_label_keys(header.meta)), "distance", path,
                       None)
        out.meta["volwarp_distance"] = field_note(metric, surface, rule, unsigned, max_distance)
        out = out.replace(dtype=np.float32)
        op = field_operation(source, Geometry.of(out), rule, metric=metric, surface=surface,
                             max_distance=max_distance, unsigned=unsigned, target=_target(out),
                             name=name)
        (field,) = _compute_whole(op).values()
    return field


@_said_as_the_command
def mesh(volume, iso: float | None = None, *, inside: str = "above", cap: bool = False,
         smooth: int = 0, decimate: float = 0.0, largest_component: bool = False,
         allow_empty: bool = False, label: int | None = None, labels: bool = False,
         values: str | None = None, **read_options) -> Mesh | dict[int, Mesh]:
    """``volwarp mesh``: the isosurface of ``volume`` at ``iso``, in world coordinates.

    Parameters
    ----------
    volume : Volume or path
        The volume (a path is read as the command reads it).
    iso : float, optional
        The level (default: the middle of the value range).
    inside : {"above", "below"}
        Which side of the level is the shape (the outward normals).
    cap : bool
        Close the surface where the shape touches the volume's border.
    smooth, decimate, largest_component
        As the command's ``--smooth``, ``--decimate`` and ``--largest-component``.
    allow_empty : bool
        An empty surface gives an empty mesh (a warning) instead of an error.
    label : int, optional
        A label map: the surface of label ``label`` (no ``iso`` or ``inside``).
    labels : bool
        A label map: a mesh of each label (``--labels``), as ``{label: Mesh}``.
    values : {"intensity", "labels"}, optional
        As ``--values``: None lets the label rule decide, and a label map's
        surface (without ``label``) is that of its non-zero labels' voxels.

    Returns
    -------
    Mesh
        Triangles counter-clockwise seen from outside, outward normals; its
        :attr:`Mesh.meta` the provenance and level ``volwarp mesh`` records.
        With ``labels``: a dict of them, one per label, in increasing order.
    """
    import math
    import numbers

    from . import execute
    from .labelmap import VALUES
    from .surface.ops import Cleanup
    from .surface.run import Level, MeshOperation, surface_keys

    _check_keys(read_options)
    _choice(inside, ("above", "below"), "inside")
    if not (isinstance(smooth, numbers.Integral) and smooth >= 0):
        raise BadUsage(f"smooth must be a whole number of iterations (0: none), got {smooth!r}")
    if not (isinstance(decimate, numbers.Real) and 0 <= decimate < 1):
        raise BadUsage(f"decimate must be a fraction in [0, 1), got {decimate!r}")
    if iso is not None and not (isinstance(iso, numbers.Real) and math.isfinite(iso)):
        raise BadUsage(f"iso must be a finite number, got {iso!r}")
    if labels and label is not None:
        raise BadUsage("--label N and --labels exclude each other")
    if (labels or label is not None) and iso is not None:
        raise BadUsage("--iso does not apply to --label/--labels (the level is 0.5 of "
                       "each label's indicator)")
    if (labels or label is not None) and inside != "above":
        raise BadUsage("--inside does not apply to --label/--labels (inside is where the "
                       "label is)")
    _choice(values, VALUES, "values")
    if values == "intensity" and (labels or label is not None):
        raise BadUsage("--label N and --labels take a label map's ids as labels: they do not "
                       "go with --values intensity")
    path = _path_of(volume)
    name = str(path) if path is not None else "the volume"
    with _outside_data(read_options.get("allow_outside_data", False)):
        header, source = _header_and_source(volume, path, read_options)
        from .surface.run import ALL_LABELS

        which = ALL_LABELS if labels else label
        if which is None:
            from .surface.labels import mesh_values
            from .surface.run import NONZERO_LABELS

            if mesh_values(source, values=values, iso=iso, inside=inside, name=name,
                           meta=header.meta, allow_empty=allow_empty).labels:
                which = NONZERO_LABELS
        op = MeshOperation(header, source, Level(iso, inside, cap),
                           cleanup=Cleanup(largest_component=largest_component, smooth=smooth,
                                           decimate=decimate),
                           labels=which, allow_empty=allow_empty, name=name,
                           keep_labels=bool(labels))
        surfaces = execute.run(op, execute.How(chunked=False)).output

    def made(surface) -> Mesh:
        meta = _provenance("mesh", [path], None)
        meta.update(surface_keys(which, surface.iso, surface.label))  # (as the command's file)
        m = surface.mesh
        return Mesh(m.vertices, m.faces, m.normals, meta=meta)

    if labels:
        return {int(s.label): made(s) for s in sorted(surfaces, key=lambda s: s.label)}
    (surface,) = surfaces
    return made(surface)


# -- the pieces --------------------------------------------------------------------------
def _path_of(volume) -> str | os.PathLike | None:
    """``volume`` when it is a path, else None (a Volume)."""
    if isinstance(volume, (str, os.PathLike)):
        return volume
    if isinstance(volume, Volume):
        return None
    raise TypeError(f"a volume is a Volume or a path, not {type(volume).__name__}")


def _volume(vol: Volume, read_options: dict) -> Volume:
    """A Volume input: read options do not apply."""
    given = _given(read_options)
    if given:
        raise BadUsage(f"{', '.join(sorted(given))}: read options apply to a path input, "
                       "not to a Volume")
    return vol


def _check_keys(read_options: dict) -> None:
    """A TypeError, as Python's own, for a keyword that is not a read option (a typo)."""
    unknown = sorted(set(read_options) - set(READ_OPTIONS))
    if unknown:
        raise TypeError(f"unexpected keyword argument {unknown[0]!r} (the read options: "
                        f"{', '.join(READ_OPTIONS)})")


def _given(read_options: dict) -> dict:
    """The read options given a value (not None, not False)."""
    return {k: v for k, v in read_options.items() if v is not None and v is not False}


def _read_arguments(path, options: dict):
    """``(raw, volume_index, dicom, allow_outside_data)`` of :func:`read`'s keyword options.

    As the commands' ``--raw-*`` and DICOM options combine
    (``volwarp_cli.cli.options.input_options``), refused as they refuse them
    (:func:`volwarp_cli.io.check_read_options`): an option for another
    format than ``path``'s is a usage error.
    """
    from .io import RawLayout, check_read_options
    from .io.common import dicom_read_options

    _check_keys(options)
    o = dict.fromkeys(READ_OPTIONS)
    o.update(options)
    raw = None
    if o["raw_shape"] is not None or o["raw_dtype"] is not None:
        if o["raw_shape"] is None or o["raw_dtype"] is None:
            raise BadUsage("--raw-shape and --raw-dtype go together")
        raw = RawLayout(shape=tuple(int(v) for v in o["raw_shape"]), dtype=o["raw_dtype"],
                        endian=o["raw_endian"] or "little",
                        spacing=tuple(o["raw_spacing"] or (1.0, 1.0, 1.0)),
                        origin=tuple(o["raw_origin"] or (0.0, 0.0, 0.0)),
                        header_bytes=int(o["raw_header_bytes"] or 0))
    elif o["raw_spacing"] or o["raw_origin"] or o["raw_header_bytes"]:
        raise BadUsage("--raw-spacing/--raw-origin/--raw-header-bytes need --raw-shape and "
                       "--raw-dtype")
    dicom = dicom_read_options(o["series"], o["irregular"], o["duplicates"], o["keep_shear"],
                               o["keep_phi"], **_segmentation_arguments(
                                   o["reference"], o["segment"], o["structure"]))
    check_read_options(path, raw, dicom)
    return raw, o["volume_index"], dicom, bool(o["allow_outside_data"])


def _segmentation_arguments(reference, segment, structure) -> dict:
    """The segmentation inputs' options as ``read_dicom``'s keywords, typed as the commands type them.

    (``--reference`` a path, ``--segment`` a whole number >= 1, ``--structure``
    a name: what click checks before the command runs.) What they mean, and
    every error of a value that does not fit the file (an RTSTRUCT without
    ``reference``, ``segment`` of an RTSTRUCT, a name no ROI has, ...), is the
    readers' (:func:`volwarp_cli.io.dicom.read_dicom`), the same for both.
    """
    import numbers

    given = {}
    if reference is not None:
        if not isinstance(reference, (str, os.PathLike)):
            raise BadUsage(f"reference must be a path (the image series), got {reference!r}")
        given["reference"] = os.fspath(reference)
    if segment is not None:
        if isinstance(segment, bool) or not isinstance(segment, numbers.Integral) or segment < 1:
            raise BadUsage(f"segment must be a whole number >= 1 (a segment number), got "
                           f"{segment!r}")
        given["segment"] = int(segment)
    if structure is not None:
        if not isinstance(structure, str):
            raise BadUsage(f"structure must be a ROI's name (a str), got {structure!r}")
        given["structure"] = structure
    return given


def _declare_inputs(path, dicom: dict | None) -> None:
    """``path`` and its ``reference`` series as inputs of this run (never overwritten)."""
    from .io.inputs import declare_input

    declare_input(path)
    if dicom and dicom.get("reference") is not None:
        declare_input(dicom["reference"])


@contextlib.contextmanager
def _outside_data(allowed: bool):
    """The run's readers may open data files outside a detached header's folder, for a while."""
    from .runscope import run_files

    files = run_files()
    before = files.allow_outside_data
    if allowed:
        files.allow_outside_data = True
    try:
        yield
    finally:
        files.allow_outside_data = before


def _header_and_source(volume, path, read_options: dict):
    """``(header, source)``: a path opened lazily (:func:`_open_lazy`), a Volume's as they are."""
    if path is not None:
        return _open_lazy(path, read_options)
    vol = _volume(volume, read_options)
    return vol.header, vol.data


def _open_lazy(path, read_options: dict):
    """``(header, source)`` of a volume path, opened as the commands open it by blocks.

    (``volwarp_cli.cli.chunked.lazy_input``: the header read, the samples
    read box by box.)
    """
    from .io.lazy import LazySource, open_volume_header

    raw, volume_index, dicom, _ = _read_arguments(path, read_options)
    _declare_inputs(path, dicom)
    header, array = open_volume_header(path, raw=raw, volume_index=volume_index, dicom=dicom)
    return header, LazySource(path, raw=raw, volume_index=volume_index, array=array,
                              dicom=dicom)


def _spec(spec, kind: str):
    """``(doc, path or None)``: a spec file or dict, checked against ``kind``'s schema."""
    from .io.inputs import declare_input
    from .spec.loader import load_spec, load_spec_data

    if isinstance(spec, Mapping):
        return load_spec_data(spec, kind), None
    if not isinstance(spec, (str, os.PathLike)):
        raise TypeError(f"a spec is a path or a dict, not {type(spec).__name__}")
    declare_input(spec)
    return load_spec(spec, kind), spec


def _provenance(command: str, inputs: list, spec) -> dict:
    """:func:`volwarp_cli.provenance.provenance` of what is known (see the module notes)."""
    from .provenance import provenance

    known = [p for p in inputs if p is not None]
    meta = provenance(command, known, spec)
    if len(known) < len(inputs) or not known:
        del meta["volwarp_input"]
    return meta


def _stamped(vol: Header, command: str, path, spec_path) -> Header:
    """``vol`` with its provenance (:func:`volwarp_cli.provenance.stamp`'s, of what is known)."""
    from .provenance import computed_meta

    meta = computed_meta(vol.meta)
    meta.update(_provenance(command, [path], spec_path))
    return vol.replace(meta=meta)


def _target(header: Header):
    """An output at no path (:class:`volwarp_cli.execute.Target`): computed, not written."""
    from .execute import Target

    return Target(None, header, header.dtype)


def _compute_whole(op) -> dict:
    """``op``'s outputs as Volumes, computed as :func:`volwarp_cli.execute.run` does in memory.

    The whole grid as one block on this process's threads (refused before any
    work where it cannot fit the memory budget); key -> the Volume its
    target's file would hold.
    """
    from .execute import compute_whole
    from .memory import ensure_fits_once_loaded

    ensure_fits_once_loaded(op.memory(op.grid.box), op.what, op.load)
    results = compute_whole(op)
    return {key: target.header.with_data(op.output(results, key))
            for key, target in op.targets.items()}


def _warp_labels(planned, name: str, path, spec_path, choice) -> Volume:
    """A label map's warp, whole (as ``volwarp warp`` makes it in memory)."""
    from .memory import ensure_fits_once_loaded
    from .progress import log
    from .warp.labels import format_report
    from .warp.request import values_meta

    ensure_fits_once_loaded(planned.memory_whole(), f"the warp of {name}'s labels", None)
    out, report = planned.compute_whole()
    log.info("per-label volumes (mm^3):\n%s", format_report(report))
    stamped = _stamped(values_meta(planned.header, choice), "warp", path, spec_path)
    return stamped.with_data(out.data, origin=out.origin)


def _refuse_blended_labels(vol: Volume, name: str, placement: str, oversample: float,
                           values: str | None) -> None:
    """Refuse a label map's capture on the spanning grid, which blends its ids for good.

    On the subdivision grid (the uniform placement, an integer oversample) a
    capture holds its input's samples, and ``warp`` takes a label map's
    capture for labels as it takes the map. On the spanning grid a warp of
    it could only average the ids (ids 1, 2, 7 gave 5 and 6, exit 0): refused
    as ``warp`` refuses such a spec for a label map (a usage error), unless
    ``values`` is ``"intensity"``.
    """
    from .bspline.lattice import subdivision_of
    from .warp.defaults import choose_values

    if values == "labels":  # (as warp refuses it: fractions are no ids; found now, not at
        choose_values(vol.data, "labels", name=name)  # every later warp of the file)
    if values == "intensity" or subdivision_of(oversample, placement):
        return
    how = "the tripled placement" if placement != "uniform" else f"oversample {oversample:g}"
    if values == "labels":
        raise BadUsage(f"{name}: --values labels needs the uniform placement and an integer "
                       f"--oversample (each domain voxel one input voxel's label); {how} "
                       "blends the ids")
    choice = choose_values(vol.data, meta=vol.meta)
    if choice.is_labels:
        raise BadUsage(f"{name} looks like a label map ({choice.labels} labels), and {how} "
                       "blends its ids (a warp of the capture would average them): capture it "
                       "with the uniform placement and an integer --oversample, or give "
                       "--values intensity to capture its samples as intensities")


def _finite(value, name: str, *, positive: bool = False) -> None:
    """A number option: finite (and positive), or None (a BadUsage, as the command's)."""
    import math
    import numbers

    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise BadUsage(f"{name} must be a finite number, got {value!r}")
    if positive and not value > 0:
        raise BadUsage(f"{name} must be positive, got {value!r}")


def _choice(value, choices, name: str) -> None:
    """A usage error for an option whose value is not one of ``choices`` (None: not given)."""
    if value is not None and value not in choices:
        raise BadUsage(f"{name} must be one of {', '.join(map(str, choices))}, got {value!r}")


def _three_ints(value, name: str) -> tuple[int, int, int]:
    """One int or three (x, y, z), as three ints."""
    import numbers

    try:
        sizes = ([int(value)] * 3 if isinstance(value, numbers.Integral)
                 else [int(v) for v in value])
    except (TypeError, ValueError):
        sizes = []
    if len(sizes) != 3:
        raise BadUsage(f"{name}: give one size or three (x y z), got {value!r}")
    return tuple(sizes)

