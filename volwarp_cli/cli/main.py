"""The ``volwarp`` command group and its error handling.

Errors become one line on stderr, ``volwarp: error: ...``, and an exit code:
0 success, 2 usage or spec error, 1 anything else (bad volume, I/O, a
computation that cannot be done). ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import os
import sys
import warnings

import click

from .. import __version__
from ..errors import BadUsage, SpecError, VolwarpError
from ..progress import log
from ..runscope import run_files, run_scope
from ..signals import Interrupted, stop_requested
from ..signals import cancel_deferred as cancel_deferred_stop
from ..signals import install as install_signal_handlers
from ..signals import settle as settle_signals

# the subcommands, each the module of its name under volwarp_cli.cli; imported when
# used, so that `volwarp --help` stays fast and one broken command cannot break the others.
COMMANDS = ("capture", "warp", "apply", "morph", "sweep", "distance", "mesh", "info",
            "convert", "batch")
_SHORT_HELP = {
    "capture": "Capture a volume into a B-spline domain voxmap (.vwc).",
    "warp": "Warp a volume by moving B-spline control points or dragging handles.",
    "apply": "Resample a volume, points or a mesh through ITK/ANTs transforms.",
    "morph": "Morph one shape into another through signed distance fields.",
    "sweep": "Sweep 2-D image templates along a trajectory into volumes.",
    "distance": "Signed distance field of a shape (euclidean or min-norm).",
    "mesh": "Isosurface a volume to PLY/STL/OBJ/VTP/VTK and render it to PNG.",
    "info": "Print a volume's format, geometry and statistics.",
    "convert": "Convert a volume between NRRD, NIfTI, MetaImage, TIFF, OME-Zarr and raw (DICOM in).",
    "batch": "Run a manifest of scans through a chain of volwarp steps, in parallel.",
}


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


#: whether this command-line run has printed its error line (one line, never two)
_reported: list[bool] = []


def _fail(message: str, code: int) -> int:
    click.echo(f"volwarp: error: {_one_line(message)}", err=True)
    _reported.append(True)
    return code


def _stopped(signum: int) -> int:
    return _fail(str(Interrupted(signum)), 128 + signum)


class VolwarpGroup(click.Group):
    """A group that loads subcommands lazily and maps errors to exit codes."""

    def list_commands(self, ctx):
        """The subcommands, in the order of ``COMMANDS``."""
        return list(COMMANDS)

    def get_command(self, ctx, name):
        """Subcommand ``name``, its module imported only now (None if there is none)."""
        if name not in COMMANDS:
            return None
        import importlib

        module = importlib.import_module(f"volwarp_cli.cli.{name}")
        return module.command

    def format_commands(self, ctx, formatter):
        """The commands' list in ``--help``, without importing them."""
        rows = [(name, _SHORT_HELP[name]) for name in COMMANDS]
        with formatter.section("Commands"):
            formatter.write_dl(rows)

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        """Run the command line; returns (or exits with) the exit code of DESIGN.md."""
        if args is None:
            args = sys.argv[1:]
        args = list(args)
        debug = "--debug" in args
        code = self._run(args, prog_name or "volwarp", debug, extra)
        if standalone_mode:
            sys.exit(code)
        return code

    def _run(self, args, prog_name, debug, extra) -> int:
        # the run's own inputs and permissions, and its warning filters, end with it (a
        # caller may run several commands in one process)
        with run_scope(), warnings.catch_warnings():
            return self._run_scoped(args, prog_name, debug, extra)

    def _run_scoped(self, args, prog_name, debug, extra) -> int:
        if not debug:
            # numpy's "overflow encountered in multiply" and the like are not messages for
            # the user (the contract is one line, and volwarp checks what it computes for
            # finiteness itself); --debug shows them
            warnings.filterwarnings("ignore", category=RuntimeWarning)
            # pydicom warns about every odd element it reads past (a bad VR, a missing
            # preamble): the reader's own errors say what matters
            warnings.filterwarnings("ignore", module=r"pydicom(\..*)?$")
        try:
            with _outputs_of(args):
                result = super().main(args=args, prog_name=prog_name, standalone_mode=False,
                                      **extra)
            if run_files().patterns:  # (an earlier run's frames beyond this run's; the
                from ..io.inputs import say_earlier_pattern_files  # io package loads numpy)

                say_earlier_pattern_files()
            code = result if isinstance(result, int) else 0
            cancel_deferred_stop()  # the work is over: a deferred stop is reported below
        except BaseException as exc:
            cancel_deferred_stop()
            stop = stop_requested()
            if stop is not None and not debug:
                # whatever the stop became on its way out (a reader's "file damaged",
                # an error of a library that caught it): it is a stop
                return _stopped(stop)
            code = self._failure(exc, debug)
        stop = stop_requested()
        if stop is not None:  # asked during the run and swallowed: the run did not finish
            return _stopped(stop)
        return code

    @staticmethod
    def _failure(exc: BaseException, debug: bool) -> int:
        """The exit code of a run that raised ``exc`` (its message printed)."""
        try:
            raise exc
        except click.exceptions.Exit as exc:
            return exc.exit_code
        except click.exceptions.Abort:
            return _fail("aborted", 1)
        except click.exceptions.NoArgsIsHelpError as exc:
            # bare `volwarp` (or a group without its command): the help itself, on stdout
            # (`volwarp | less` shows it), exit 2 (a script that lost its arguments fails)
            click.echo(exc.ctx.get_help())
            return exc.exit_code
        except click.ClickException as exc:
            hint = ""
            ctx = getattr(exc, "ctx", None)
            if isinstance(exc, click.UsageError) and ctx is not None:
                hint = f" (see '{ctx.command_path} --help')"
            return _fail(exc.format_message() + hint, exc.exit_code)
        except Interrupted as exc:
            if debug:
                raise
            return _fail(str(exc), 128 + exc.signum)
        except (SpecError, BadUsage) as exc:
            if debug:
                raise
            return _fail(str(exc), 2)
        except VolwarpError as exc:
            if debug:
                raise
            return _fail(str(exc), 1)
        except MemoryError:
            if debug:
                raise
            return _fail("out of memory (the volume is too large for this machine)", 1)
        except OSError as exc:
            if debug:
                raise
            name = f"{exc.filename}: " if exc.filename else ""
            return _fail(f"{name}{exc.strerror or exc}", 1)
        except Exception as exc:  # a bug: say so, in one line, unless --debug
            if debug:
                raise
            return _fail(f"internal error: {type(exc).__name__}: {exc} "
                         "(run with --debug for a traceback)", 1)


def _outputs_of(args):
    """The command's outputs renamed into place together at its end (all new or all old).

    :func:`volwarp_cli.io.atomic.outputs_together`; not for ``batch``, whose
    steps are commands of their own (each its own set) and whose reports are
    written as it goes; nothing for ``--help`` and ``--version``.
    """
    import contextlib

    name = next((a for a in args if not a.startswith("-")), None)
    if name is None or name == "batch" or name not in COMMANDS:
        return contextlib.nullcontext()
    from ..io.atomic import outputs_together

    return outputs_together()


@click.group(cls=VolwarpGroup, context_settings={"help_option_names": ["-h", "--help"]},
             epilog="'volwarp COMMAND --help' lists a command's options and ends with "
                    "example command lines.")
@click.version_option(__version__, "-V", "--version", prog_name="volwarp")
@click.option("--debug", is_flag=True, help="Show a traceback on errors.")
def cli(debug):
    """volwarp: modelling with sampled volumes, in batch.

    Volumes are NRRD, NIfTI, MetaImage, TIFF, OME-Zarr or raw files, or DICOM
    (a file, a folder or a DICOMDIR; SEG and RTSTRUCT as label maps); geometry
    on the command line and in specs is always (x, y, z) in world units
    unless a spec says `units: voxel`. The world frame is LPS millimetres
    (x to the patient's left, y posterior, z superior, as ITK and 3D Slicer
    have it), whatever frame a file stores: a RAS point (FSL, SPM, MNI) is
    (-x, -y, z). Exit codes: 0 success, 2 usage or spec error, 1 other
    failures, 128+N when stopped by signal N (130 Ctrl-C, 143 SIGTERM); batch:
    75 when another batch holds its output folder.
    """


@cli.result_callback()
def _after_command(result, **_):
    """A command's options for work by blocks that it never used: said, not silently ignored."""
    from .resources import scale_settings

    settings = scale_settings()
    unused = settings.unused()
    if unused:
        advice = ("" if settings.chunked else
                  " (give --chunked to run it by blocks, where the command can)")
        log.warning("warning: %s not used: they apply to work by blocks, and this command "
                    "ran in memory%s", ", ".join(unused), advice)
    return result


def main(argv=None) -> int:
    """Run ``volwarp`` with ``argv`` (default: the process's); ends the process when run from it."""
    try:
        install_signal_handlers()
        _reported.clear()
        code = cli.main(args=argv, prog_name="volwarp", standalone_mode=False)
    except Interrupted as exc:  # a second stop while the first was being reported
        code = 128 + exc.signum
        if not _reported:  # (or a deferred one landing before the report)
            _stopped(exc.signum)
    while argv is None:  # a command-line run, not a call from Python: end the process
        try:
            _end_process(code)  # (never returns)
        except Interrupted:  # a stop landing on the way out: the code is decided
            continue
    return code


def _end_process(code: int) -> None:
    """End a command-line run: every output is written, closed and renamed by now.

    The interpreter's tear-down would free every array, module and object one
    by one for nothing (about 4% of a 256^3 `warp`, numba's ~100,000 registry
    objects in a `distance`), and OpenImageIO's nanobind bindings would print a
    "leaked" report for each of their objects still alive.
    """
    # the run is over (its code decided): a stop arriving now changes nothing, and a
    # stop deferred by an import (its re-check timer) must not raise out of the exit
    for _ in range(100):
        try:
            settle_signals()
            break
        except Interrupted:
            continue
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more to say
            pass
    if "logging" in sys.modules:  # (imported when a record was emitted: progress.log)
        sys.modules["logging"].shutdown()
    from .. import dataclass_code

    dataclass_code.save()  # (a class's methods compiled this run, for the next runs)
    os._exit(code)
