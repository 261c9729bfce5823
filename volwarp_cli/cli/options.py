"""Options shared by several subcommands, each defined once (rasterio's habit).

Decorators add the options; callbacks validate them (``click.BadParameter``,
exit 2) and hand the command typed values. A renamed option keeps its old
spelling as a hidden alias (:func:`option`'s ``was``) that still works and
says, on stderr, ``volwarp: warning: --size is now --render-size``.

Every option, and the commands that take it (``tests/test_cli_help.py``
checks this list against the commands; ``(every command)``: from
:func:`common_options`; the ``--raw-*``, DICOM (``--series`` ... ``--keep-phi``, and
the segmentation inputs' ``--reference``, ``--segment``, ``--structure``),
``--volume-index`` and ``--allow-outside-data`` options from :func:`input_options`; ``--dtype``,
``--compress``, ``--byte-order``, ``--ome-zarr-version`` and ``--pyramid`` from
:func:`write_options`)::

    --allow-empty             mesh
    --allow-growth            warp
    --allow-outside-data      capture warp apply distance mesh info convert
    --allow-outside-field     apply
    --background-color        mesh
    --background-value        warp apply
    --block                   warp apply morph sweep distance mesh
    --byte-order              warp apply morph sweep distance convert
    --camera-from             morph sweep mesh
    --camera-to               morph sweep mesh
    --cap                     mesh
    --chunked/--no-chunked    warp apply morph sweep distance mesh
    --color                   mesh
    --compress/--no-compress  warp apply morph sweep distance convert
    --contours                convert
    --crop                    warp
    --debug                   (every command)
    --decimate                mesh
    --density                 morph
    --dicom-type              convert
    --displacement-to         warp
    --dtype                   warp apply morph sweep distance convert
    --duplicates              capture warp apply distance mesh info convert
    --evaluator               warp
    --fail-fast               batch
    --force                   batch
    --forward-field-to        warp
    --frames                  morph
    --frames-to               warp
    --grid                    warp morph
    --inside                  morph distance mesh
    --interpolation           apply
    --irregular               capture warp apply distance mesh info convert
    --iso                     morph distance mesh
    --jacobian-to             warp
    -j/--jobs                 batch
    --json                    warp mesh info
    --keep-phi                capture warp apply distance mesh info convert
    --keep-shear              capture warp apply distance mesh info convert
    --label                   morph distance mesh
    --labels                  warp apply mesh
    --largest-component       mesh
    --lattice                 capture
    --max-distance            morph distance
    --memory-limit            (every command)
    --mesh-in                 warp apply
    --mesh-to                 warp apply morph
    --method                  sweep
    --metric                  morph distance
    --multi                   sweep
    --ome-zarr-version        warp apply morph sweep distance convert
    --orientation-labels/--no-orientation-labels  morph sweep mesh
    -o/--output               capture warp apply morph sweep distance mesh convert
    --oversample              capture
    --pad                     capture
    --placement               capture
    --points-in               warp apply
    --points-to               warp apply
    --preserve-labels         warp
    --progress                warp apply morph sweep distance mesh batch
    --pushforward             warp
    --pyramid                 warp apply morph sweep distance convert
    --pyramid-method          convert
    -q/--quiet                (every command)
    --raw-dtype               capture warp apply distance mesh info convert
    --raw-endian              capture warp apply distance mesh info convert
    --raw-header-bytes        capture warp apply distance mesh info convert
    --raw-origin              capture warp apply distance mesh info convert
    --raw-shape               capture warp apply distance mesh info convert
    --raw-spacing             capture warp apply distance mesh info convert
    --reference               capture warp apply distance mesh info convert
    --reference-series        apply
    --render                  sweep mesh
    --render-size             morph sweep mesh
    --render-to               morph
    --report                  batch
    --report-json             batch
    --retries                 batch
    --sampling                capture
    --scheduler               warp apply morph sweep distance mesh batch
    --segment                 capture warp apply distance mesh info convert
    --segments                convert
    --series                  capture warp apply distance mesh info convert
    --settle                  batch
    --shape                   sweep
    --shard                   batch
    --sheet                   morph
    --smooth                  mesh
    --spacing                 sweep
    --spec                    warp morph
    --stats                   mesh
    --structure               capture warp apply distance mesh info convert
    --surface                 distance
    --tau                     sweep
    --threads                 (every command)
    --threads-per-worker      warp apply morph sweep distance mesh batch
    --times                   morph
    --transform               distance
    -t/--transform            apply
    --transform-to            warp
    --turntable               mesh
    --unsigned                distance
    --update                  distance
    --values                  capture warp apply morph distance mesh convert
    -v/--verbose              (every command)
    --view                    morph sweep mesh
    --volume-index            capture warp apply distance mesh info convert
    --wait                    batch
    --workers                 warp apply morph sweep distance mesh batch

Old spellings, hidden, still accepted with a warning::

    --size                    --render-size: mesh morph
    --background              --background-value: warp (a number: the space around the
                              model); --background-color: mesh (the render's colour)
"""

from __future__ import annotations

import functools
import math
import os

import click
from click.core import ParameterSource

from ..errors import VolwarpError
from ..io import FOLDER_FORMATS, SUPPORTED_DTYPES
from ..io.common import dicom_read_options
from ..progress import configure, log
from ..runscope import run_files
from .view_options import VIEW_HELP  # noqa: F401  (--view's help, for every command)


def _configure_verbosity(ctx, param, value):
    # --quiet and --verbose each arrive here; keep the combined level on ctx.
    level = ctx.meta.get("volwarp.verbosity", 0)
    if param.name == "quiet" and value:
        level = -1
    elif param.name == "verbose" and value:
        level = max(level, 0) + value if level >= 0 else level
    ctx.meta["volwarp.verbosity"] = level
    configure(level)
    return value


def common_options(f):
    """--quiet, --verbose, --debug, --threads and --memory-limit, on every subcommand."""
    from .resources import resource_options

    f = resource_options(f)
    f = click.option("-q", "--quiet", is_flag=True, expose_value=False, is_eager=True,
                     callback=_configure_verbosity,
                     help="No progress bar; errors only.")(f)
    f = click.option("-v", "--verbose", count=True, expose_value=False, is_eager=True,
                     callback=_configure_verbosity,
                     help="Log each step and its time (-vv for more).")(f)
    f = click.option("--debug", is_flag=True, expose_value=False,
                     help="Show a traceback on errors.")(f)
    return f


class Command(click.Command):
    """A subcommand (every one is this class): what click takes silently, refused.

    An option of one value given twice: click keeps the last (``-o a.nrrd -o
    b.nrrd`` wrote b.nrrd alone, ``--threads 1 --threads 4`` ran on 4), and in a
    command line put together from a Makefile's variables one of the two places
    was overruled without a word. Two different values (``--compress
    --no-compress`` too) are a usage error; the same value twice is harmless and
    taken once. ``multiple`` options (apply's ``-t``) and counts (``-vv``) take
    every one; an environment variable is no value given.

    An empty (or blank) value, ``--threads=$(N)`` with N unset: ``--threads=``
    ran on every core, ``--scheduler=`` on the default, ``--frames-to=`` wrote no
    frames, ``--reference=`` named the working folder. No option takes an empty
    value: a usage error, for every option.

    Both are said as the parser meets the value, before any option's callback
    and any work.
    """

    def make_parser(self, ctx):
        """Click's parser, each value checked as it is stored."""
        parser = super().make_parser(ctx)
        # (click's parser has no hook for this: its options are wrapped where it keeps them)
        for stored in {*parser._long_opt.values(), *parser._short_opt.values()}:
            if stored.action in ("store", "store_const", "append"):
                stored.process = _checked(stored, ctx)
        return parser


def _checked(stored, ctx):
    """``stored.process`` (a parser option's), refusing an empty value and a second, other one."""
    process = stored.process
    spelling = (stored._long_opts or stored._short_opts)[0]
    name = max(stored.obj.opts, key=len)
    flag = stored.action == "store_const"
    once = stored.action != "append"

    def check(value, state):
        for v in value if isinstance(value, tuple) else (value,):
            if isinstance(v, str) and not v.strip():
                raise click.BadOptionUsage(
                    name, f"Invalid value for {name!r}: {v!r} is "
                          f"{'blank' if v else 'empty'} (an unset variable?): give a value, "
                          f"or leave {name} out", ctx=ctx)
        process(value, state)
        if not once:
            return
        # what was stored (a flag's constant: --compress True, --no-compress False; what an
        # option class of its own made of its values: capture's --lattice 9 7 9)
        now = state.opts[stored.dest]
        shown = spelling if flag else repr(" ".join(now) if isinstance(now, tuple) else now)
        first = vars(state).setdefault("volwarp_given", {}).setdefault(stored.dest,
                                                                        (now, shown))
        if first[0] != now:
            message = (f"{first[1]} and {shown} both given: give one" if flag else
                       f"{name} given twice, as {first[1]} and as {shown}: give it once")
            raise click.BadOptionUsage(name, message, ctx=ctx)

    return check


#: ``ctx.meta`` key: values given with an old spelling, by the new option's name
_RENAMED = "volwarp.renamed"
_NOT_GIVEN = object()


def _given(name: str) -> bool:
    """Whether the running command's option ``name`` was given (not its default)."""
    from .view_options import option_given

    return option_given(click.get_current_context(silent=True), name)


#: ``ctx.meta`` key: the options given by their old spelling (:func:`option`'s ``was``)
RENAMED_GIVEN = "volwarp_renamed_given"


def option(*decls, was: str | None = None, **attrs):
    """``click.option(*decls, **attrs)``; ``was``: the option's old spelling, still accepted.

    The old spelling is a hidden option of the same type whose value goes to the new
    one (through the new one's callback, so its errors name the spelling used) with
    one line on stderr, ``volwarp: warning: OLD is now NEW`` (silenced by -q). Both
    spellings at once are a usage error.
    """
    if was is None:
        return click.option(*decls, **attrs)
    name = click.Option(list(decls)).name
    new = max((d for d in decls if d.startswith("-")), key=len)
    callback = attrs.pop("callback", None)

    def new_callback(ctx, param, value):
        given = ctx.meta.get(_RENAMED, {}).pop(name, _NOT_GIVEN)
        if given is not _NOT_GIVEN:
            if ctx.get_parameter_source(name) is ParameterSource.COMMANDLINE:
                raise click.UsageError(f"{was} is the old name of {new}: give {new} only",
                                       ctx=ctx)
            # (given, as the new spelling would be: the checks of what was given see it)
            ctx.meta.setdefault(RENAMED_GIVEN, set()).add(name)
            return given
        return value if callback is None else callback(ctx, param, value)

    def old_callback(ctx, param, value):
        if value is None:
            return None
        if ctx.get_parameter_source(name) is ParameterSource.COMMANDLINE:
            raise click.UsageError(f"{was} is the old name of {new}: give {new} only", ctx=ctx)
        log.warning("warning: %s is now %s", was, new)
        value = value if callback is None else callback(ctx, param, value)
        ctx.meta.setdefault(_RENAMED, {})[name] = value
        return value

    alias = {k: v for k, v in attrs.items() if k in ("type", "nargs", "metavar")}

    def decorator(f):
        f = click.option(*decls, callback=new_callback, **attrs)(f)
        return click.option(was, f"renamed_{name}", hidden=True, expose_value=False,
                            default=None, callback=old_callback, **alias)(f)
    return decorator


def examples(*lines: str) -> str:
    """A command's epilog: the example command lines that end its ``--help``.

    ``tests/test_cli_help.py`` parses each against the command.
    """
    body = "\n".join(f"  {line}" for line in lines)
    return f"Examples:\n\n\b\n{body}"


def finite(ctx, param, value):
    """Callback: a float option (or each of a tuple of them) must be a finite number."""
    values = value if isinstance(value, tuple) else (value,)
    for v in values:
        if v is not None and not math.isfinite(v):
            raise click.BadParameter(f"must be a finite number, got {v}", ctx=ctx, param=param)
    return value


def band(ctx, param, value):
    """Callback: ``--max-distance``, finite and a band a float32 field holds."""
    finite(ctx, param, value)
    from ..distance.field import band_problem

    if value is not None and band_problem(value):
        raise click.BadParameter(band_problem(value), ctx=ctx, param=param)
    return value


def _positive(ctx, param, value):
    finite(ctx, param, value)
    if value is not None and any(v <= 0 for v in value):
        raise click.BadParameter(f"must be positive, got {' '.join(map(str, value))}",
                                 ctx=ctx, param=param)
    return value


class InputPath(click.Path):
    """An input path, declared as the run's input as it is parsed.

    No checks by click (whose "not readable" or "is a directory" would exit
    2): the readers report a missing, unreadable or folder input as a file
    error (exit 1). Declared (:func:`volwarp_cli.io.inputs.declare_input`)
    so that every output check of the run, made before any work, refuses an
    output that would replace it or a data file its header names.

    A named pipe or a device is refused here, before anything opens it
    (:func:`volwarp_cli.io.inputs.refuse_stream_input`), unless ``once``:
    an input read once from start to end (a spec, a CSV file), which
    ``--spec /dev/stdin`` or ``<(...)`` may give. An empty name (a positional
    input's: an option's is :class:`Command`'s) is refused, never the working folder.
    """

    def __init__(self, *, once: bool = False, **kwargs):
        super().__init__(readable=False, **kwargs)
        self.once = once

    def convert(self, value, param, ctx):
        """The path, declared as an input of this run."""
        from ..io.inputs import declare_input, refuse_stream_input

        value = super().convert(value, param, ctx)
        if value is not None and not str(value).strip():
            # (an unset variable, `volwarp convert "$(SCAN)"`: read as the working folder, a
            # DICOM series there was converted, exit 0; an option's is refused by the parser)
            self.fail("an empty name: give the file to read", param, ctx)
        if value is not None and self.once and os.path.isdir(value):
            # (declared, a folder is an input folder: "-o out.nrrd would overwrite the input
            # folder", said of a folder, blamed the output)
            self.fail(f"{value!r} is a folder: give the file to read", param, ctx)
        if value is not None:
            if not self.once:
                refuse_stream_input(value)
            declare_input(value)
        return value


#: An input path (see :class:`InputPath`).
INPUT_PATH = InputPath()
#: An input read once, start to end (a spec, a CSV file): a pipe will do.
READ_ONCE_PATH = InputPath(once=True)


def _volume_output(ctx, param, value):
    # an unknown extension is a usage error, found before any work
    from ..io import volume_format

    if value is not None:
        try:
            fmt = volume_format(value)
        except VolwarpError as exc:
            raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
        if fmt not in FOLDER_FORMATS and os.path.isdir(value):  # (a store may be replaced)
            raise click.BadParameter(f"{value!r} is a directory.", ctx=ctx, param=param)
    return value


def file_name_checked(callback):
    """``callback`` after a check that the output names a file, not a folder (``out.nrrd/``).

    A trailing slash says a folder: ``-o out.nrrd/`` wrote the file ``out.nrrd``
    without a word, and ``-o scans/`` a file named ``scans``. An OME-Zarr store
    is a folder: its name may end in one.
    """
    from ..io import volume_format

    def check(ctx, param, value):
        if isinstance(value, str) and value.endswith(("/", os.sep)):
            try:
                folder = volume_format(value.rstrip("/" + os.sep)) in FOLDER_FORMATS
            except VolwarpError:
                folder = False
            if not folder:
                raise click.BadParameter(f"{value!r} ends in a slash, which names a folder: "
                                         "give the output file's name", ctx=ctx, param=param)
        return callback(ctx, param, value) if callback is not None else value

    return check


def output_option(help_text: str = "Output file (format by extension).", volume: bool = True,
                  callback=None, required: bool = True, folders: bool | None = None):
    """-o/--output; ``volume``: a volume file, its extension checked at once.

    ``callback``: a check of its own instead (e.g. of a pattern of volume files);
    ``required``: False where the command has other outputs (``warp``'s exports);
    ``folders``: whether an existing folder may be given (default: for a volume,
    an OME-Zarr store being replaced; the callback refuses other folders).
    """
    if callback is None and volume:
        callback = _volume_output
    if folders is None:
        folders = callback is _volume_output
    kind = click.Path(dir_okay=folders)
    callback = file_name_checked(callback)
    # (click 8.2+: an explicit default, even None, satisfies `required`: none when required)
    extra = {} if required else {"default": None}
    return click.option("-o", "--output", required=required, type=kind, callback=callback,
                        help=help_text, **extra)


#: --reference's help in every command reading a volume (convert adds its output's meaning)
REFERENCE_HELP = ("DICOM SEG or RTSTRUCT input: the image series (folder, DICOMDIR or file) it "
                  "lies on. RTSTRUCT: required, its ROIs are rasterised on that grid; SEG: "
                  "the label map is put on that whole grid (default: the SEG's own frames' "
                  "grid).")


def input_options(f=None, *, reference_help: str = REFERENCE_HELP,
                  reference_metavar: str = "SERIES"):
    """Options describing how to read a volume input.

    Headerless raw inputs (``--raw-*``, combined into ``raw: RawLayout``),
    ``--volume-index``, and the DICOM choices (combined into ``dicom``: the
    keyword arguments of ``read_dicom``, or None). A DICOM SEG or RTSTRUCT is
    a label map input of every command: ``--reference SERIES`` (the image
    series it lies on; an RTSTRUCT needs it), ``--segment N`` and ``--structure
    NAME`` (one segment or ROI as a 0/1 mask) go into ``dicom`` too, so that
    :func:`~volwarp_cli.cli.common.load_input` and
    :func:`~volwarp_cli.cli.chunked.lazy_input` read them for every command.

    ``@input_options``, or ``@input_options(reference_help=..., reference_metavar=...)``
    (``apply``'s ``--reference`` is the output grid's image: ``REF``). A command
    whose function takes ``reference`` itself (``convert``: also the series a
    written SEG or RTSTRUCT references) gets ``--reference`` as that keyword
    instead, and decides.
    """
    import inspect

    if f is None:
        return functools.partial(input_options, reference_help=reference_help,
                                 reference_metavar=reference_metavar)
    takes_reference = "reference" in inspect.signature(f).parameters

    @functools.wraps(f)
    def wrapper(*args, raw_shape, raw_dtype, raw_endian, raw_spacing, raw_origin,
                raw_header_bytes, volume_index, series, irregular, duplicates, keep_shear,
                keep_phi, allow_outside_data, reference, segment, structure, **kwargs):
        if takes_reference:
            kwargs["reference"] = reference
        dicom = dicom_read_options(series, irregular, duplicates, keep_shear, keep_phi,
                                   None if takes_reference else reference, segment, structure)
        if allow_outside_data:  # this run's readers may open such data files (io.common)
            run_files().allow_outside_data = True
        layout = None
        if raw_shape is not None or raw_dtype is not None:
            if raw_shape is None or raw_dtype is None:
                raise click.UsageError("--raw-shape and --raw-dtype go together")
            from ..io.raw import RawLayout

            layout = RawLayout(shape=tuple(raw_shape), dtype=raw_dtype, endian=raw_endian,
                               spacing=tuple(raw_spacing) if raw_spacing else (1.0, 1.0, 1.0),
                               origin=tuple(raw_origin) if raw_origin else (0.0, 0.0, 0.0),
                               header_bytes=raw_header_bytes)
        elif raw_spacing or raw_origin or raw_header_bytes or _given("raw_endian"):
            raise click.UsageError("--raw-spacing/--raw-origin/--raw-header-bytes/--raw-endian "
                                   "need --raw-shape and --raw-dtype")
        return f(*args, raw=layout, volume_index=volume_index, dicom=dicom, **kwargs)

    opts = [
        click.option("--raw-shape", nargs=3, type=click.IntRange(min=1), default=None,
                     metavar="X Y Z", help="Raw input: samples along x, y, z."),
        click.option("--raw-dtype", type=click.Choice(SUPPORTED_DTYPES), default=None,
                     help="Raw input: sample type."),
        click.option("--raw-endian", type=click.Choice(["little", "big"]), default="little",
                     show_default=True, help="Raw input: byte order."),
        click.option("--raw-spacing", nargs=3, type=float, default=None, metavar="SX SY SZ",
                     callback=_positive, help="Raw input: voxel spacing (x, y, z)."),
        click.option("--raw-origin", nargs=3, type=float, default=None, metavar="OX OY OZ",
                     callback=finite,
                     help="Raw input: world position of the first voxel's centre."),
        click.option("--raw-header-bytes", type=click.IntRange(min=0), default=0,
                     help="Raw input: bytes to skip before the samples."),
        click.option("--volume-index", type=click.IntRange(min=0), default=None,
                     help="4-D NIfTI or MetaImage input: which volume to read; "
                          "multi-component NRRD or MetaImage: which component; TIFF "
                          "holding several images (OME-TIFF images, tifffile series): "
                          "which image."),
        click.option("--series", default=None, metavar="UID|N",
                     help="DICOM input holding several volumes: which one, by "
                          "SeriesInstanceUID or by its number in `volwarp info`'s list."),
        click.option("--irregular", type=click.Choice(["resample"]), default=None,
                     help="DICOM input whose slice gaps differ: resample it onto a uniform "
                          "grid (default: an error naming the gap)."),
        click.option("--duplicates", type=click.Choice(["first", "last"]), default=None,
                     help="DICOM input with several images at one position: keep the first "
                          "or last in file order (default: an error)."),
        click.option("--keep-shear", is_flag=True, default=False,
                     help="Gantry-tilted DICOM input: keep the exact sheared geometry "
                          "(NRRD and MetaImage outputs only) instead of resampling onto an "
                          "orthogonal grid."),
        click.option("--allow-outside-data", is_flag=True, default=False,
                     help="Let a detached header (.nhdr, .mhd) read data files outside its "
                          "own folder (default: refused; also VOLWARP_ALLOW_OUTSIDE_DATA=1)."),
        click.option("--keep-phi", is_flag=True, default=False,
                     help="DICOM input: keep identifying tags (patient name, ID, birth "
                          "date, ...) in the output's key/values (default: left out)."),
        click.option("--reference", type=INPUT_PATH, default=None,
                     metavar=reference_metavar, help=reference_help),
        click.option("--segment", type=click.IntRange(min=1), default=None, metavar="N",
                     help="DICOM SEG input: segment N alone, as a 0/1 mask (default: every "
                          "segment, valued by its number; overlapping segments need this)."),
        click.option("--structure", default=None, metavar="NAME",
                     help="DICOM RTSTRUCT input: the ROI named NAME alone, as a 0/1 mask "
                          "(default: every ROI, valued by its ROI Number; see "
                          "docs/segmentations.md for overlapping ROIs)."),
    ]
    for opt in reversed(opts):
        wrapper = opt(wrapper)
    return wrapper


def write_options(f=None, *, dtype_default: str = "the input's"):
    """--dtype, --compress, --byte-order, --ome-zarr-version and --pyramid for volume outputs.

    ``@write_options``, or ``@write_options(dtype_default="float32, ...")`` where
    the output's type is not the input's (its ``--help`` says so).

    The first three reach the command as ``dtype``, ``compress`` and
    ``byte_order``. The OME-Zarr ones reach it as one keyword, ``ome_zarr``:
    a dict of :func:`~volwarp_cli.io.write_volume`'s keyword arguments
    (``ome_zarr_version``, ``pyramid``) to pass on with ``**ome_zarr``. A
    command that does not take ``ome_zarr`` yet refuses values other than the
    defaults (a usage error) rather than ignore them.
    """
    import inspect

    if f is None:
        return functools.partial(write_options, dtype_default=dtype_default)
    takes = "ome_zarr" in inspect.signature(f).parameters

    @functools.wraps(f)
    def wrapper(*args, ome_zarr_version, pyramid, **kwargs):
        if takes:
            kwargs["ome_zarr"] = {"ome_zarr_version": ome_zarr_version, "pyramid": pyramid}
        elif ome_zarr_version != "0.5" or pyramid:
            raise click.UsageError("--ome-zarr-version and --pyramid are not passed on by "
                                   "this command yet")
        return f(*args, **kwargs)

    wrapper = click.option(
        "--pyramid", type=click.IntRange(min=0), default=0, show_default=True, metavar="N",
        help="OME-Zarr output: N extra levels, each half the size of the last (label "
             "maps by the most frequent label, others by the mean).")(wrapper)
    wrapper = click.option(
        "--ome-zarr-version", type=click.Choice(["0.4", "0.5"]), default="0.5",
        show_default=True,
        help="OME-Zarr output (.ome.zarr): NGFF 0.5 (Zarr v3, sharded) or 0.4 (Zarr v2, "
             "for older viewers).")(wrapper)
    wrapper = click.option("--dtype", type=click.Choice(SUPPORTED_DTYPES), default=None,
                           help=f"Output sample type (default: {dtype_default}). Integers are "
                                "rounded and clipped to the type's range.")(wrapper)
    wrapper = click.option("--compress/--no-compress", default=False, show_default=True,
                           help="gzip NRRD data, zlib MetaImage data and TIFF pages (.nii.gz "
                                "is always gzip; OME-Zarr always zstd).")(wrapper)
    wrapper = click.option("--byte-order", type=click.Choice(["little", "big"]),
                           default="little", show_default=True,
                           help="Byte order of NRRD, MetaImage, TIFF, raw and OME-Zarr outputs.")(wrapper)
    return wrapper




def moved_points_options(points: str, points_to: str, mesh: str, mesh_to: str):
    """--points-in/--points-to and --mesh-in/--mesh-to: points and a mesh the command moves.

    The four help texts say by which map (warp: the forward map; apply: the
    chain's inverse).
    """
    def decorate(f):
        for decls, kw in reversed([
                (("--points-in",), dict(type=READ_ONCE_PATH, metavar="P.csv", help=points)),
                (("--points-to",), dict(metavar="Q.csv", help=points_to)),
                (("--mesh-in",), dict(type=READ_ONCE_PATH, metavar="M.ply", help=mesh)),
                (("--mesh-to",), dict(metavar="M2.ply", help=mesh_to))]):
            f = click.option(*decls, default=None, **kw)(f)
        return f

    return decorate


def shape_values_options(label: str, values: str):
    """--label N and --values intensity|labels: how a shape is taken from its samples.

    ``distance`` and ``morph`` take a shape as the label rule says
    (:mod:`volwarp_cli.labelmap`); the two help texts say of which input.
    """
    from ..labelmap import VALUES

    def decorate(f):
        f = click.option("--values", "values", type=click.Choice(VALUES), default=None,
                         help=values)(f)
        return click.option("--label", "label", type=int, default=None, metavar="N",
                            help=label)(f)

    return decorate


#: --render-size's default, for every command that renders (mesh, morph, sweep)
DEFAULT_RENDER_SIZE = "800x600"


def render_size_option(parse=None, help_text: str = "Render size in pixels.",
                       was: str | None = "--size"):
    """--render-size WxH, the same default everywhere.

    ``parse``: the value's core parser (default :func:`parse_size`); ``was``: the
    command's old spelling (mesh and morph said --size).
    """
    return option("--render-size", "render_size", was=was, default=DEFAULT_RENDER_SIZE,
                  show_default=True, metavar="WxH", callback=core_parser(parse or parse_size),
                  help=help_text)


def core_parser(fn):
    """A click callback running ``fn`` (a core parser) on the option's value.

    Its ``VolwarpError`` becomes a usage error (exit 2) naming the option;
    ``None`` (an option not given) passes through.
    """
    def callback(ctx, param, value):
        if value is None:
            return None
        try:
            return fn(value)
        except VolwarpError as exc:
            raise click.BadParameter(str(exc)) from None
    return callback


# the render parsers, imported when an option is parsed (not at start-up)
def parse_view(value):
    """:func:`volwarp_cli.render.surface.parse_view`, imported when first used."""
    from ..render.surface import parse_view
    return parse_view(value)


def parse_size(value):
    """:func:`volwarp_cli.render.surface.parse_size`, imported when first used."""
    from ..render.surface import parse_size
    return parse_size(value)


def parse_color(value):
    """:func:`volwarp_cli.render.surface.parse_color`, imported when first used."""
    from ..render.surface import parse_color
    return parse_color(value)
