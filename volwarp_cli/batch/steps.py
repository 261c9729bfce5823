"""Each step checked by its own command before any scan runs: options, spec, and cross-checks.

A typo in a step's options (``--isoo 50``), or options that do not go together
(``--crop --grid grow``), would otherwise surface once per scan, as each
scan's step process failed, after the earlier steps of every scan had run.
Here each step's command runs once, in this process, as a **dry run**: its
command line parsed by its click command (options, types, callbacks), its
spec checked against its schema, then its body run up to its first read of an
input, where :func:`..runscope.stop_if_dry_run` stops it (every reader's
entry checks the run's ``dry_run`` flag). What a command refuses before it
reads (a usage error, a bad spec) is one error (exit 2) naming the manifest's
line, before any work; anything else it raises is left to the real run, which
reports it per scan. Options are the same for every scan but for ``{stem}``
and ``{relpath}``, which only change names, so one dry run per step suffices.

The dry run sees what the real run will: the first scan as the input (an
earlier step's output does not exist yet: its reader stops first), outputs
in a fresh temporary folder (nothing is written; the batch makes its output
folders), and every relative file name of the step's options taken from the
manifest's folder, where the step will run; this process's working folder is
never changed.

The files the step reads for every scan besides its input (its spec, the
files of its input options, ``--reference``, ``-t``, ``--points-in``..., and
the initial transforms an elastix file names) come from its options
(:func:`_own_files`), not from what the dry run on the first scan read: a
file that is also the first scan is every scan's file all the same. They go
into what the step's outputs are made from (:mod:`.plan`), and no output may
replace them.
"""

from __future__ import annotations

import contextvars
import dataclasses
import importlib
import re
import tempfile
from pathlib import Path
from typing import NamedTuple

import click

from .manifest import (
    RESERVED_OPTIONS,
    Manifest,
    Scan,
    Step,
    placeholders,
    reserved_message,
    row_column,
)

#: spec files a step's command reads, by command and parameter: the schema they follow
SPEC_PARAMS = {"warp": {"spec_path": "warp"}, "distance": {"transform": "transform"}}
#: the stand-in for the scan when the manifest finds none (its reader is never reached)
_STAND_IN = "volwarp-batch-step-input.nrrd"
#: options that print and end the command instead of running it
_ENDING = ("-h", "--help", "-V", "--version")
#: options whose product is the step's console output, which the batch does not keep (its
#: stdout goes nowhere, its stderr to its warnings and a failure's last line): the report
#: says what each step made and how long it took
_CONSOLE = ("--json", "--stats", "-v", "--verbose", "--progress")
#: long options writing a file whose type is not a click.Path (besides every ``--*-to``)
_OUTPUT_NAMES = ("--sheet",)
#: an input option's ``[FILE,0|1]`` (apply's -t: a transform or its inverse)
_BRACKETS = re.compile(r"^\[\s*(.+?)\s*,\s*([01])\s*\]$")


def check_steps(manifest: Manifest) -> list[Step]:
    """The manifest's steps, each dry-run by its command, with the files it reads and writes."""
    from .plan import FILE_PARAMS, plan_scan

    sample = _sample_scan(manifest)
    steps = []
    with tempfile.TemporaryDirectory(prefix="volwarp-batch-check-") as tmp:
        dry = dataclasses.replace(manifest, output_dir=Path(tmp))
        for plan in plan_scan(dry, sample):
            step = plan.step
            command = importlib.import_module(f"volwarp_cli.cli.{step.run}").command
            values = option_values(command, step.options)
            _check_tokens(manifest, step, values)
            argv = _absolute(manifest, _apart(plan, Path(tmp)), step.options, values)
            params, problem, quiet = _dry_run(manifest, step, command, argv)
            inputs = _own_files(manifest, step, values)
            _check_inputs_exist(manifest, step, inputs)
            _check_specs(manifest, step, params)
            if problem is not None:
                raise problem
            if quiet:  # (the batch runs its steps at the default verbosity: warnings only)
                from ..progress import log

                log.warning("%s", manifest.doc.error(
                    ("steps", step.index, "options"),
                    "-q (--quiet) hides the step's warnings (an output written all "
                    "background, a label lost), which the batch says and reports"))
            writes = tuple((v.index, v.option) for v in values if v.kind == "output")
            kept = tuple((name, params.get(name)) for name in FILE_PARAMS.get(step.run, ()))
            steps.append(dataclasses.replace(step, inputs=tuple(inputs), writes=writes,
                                             params=kept))
    return steps


def _apart(plan, tmp: Path) -> list[str]:
    """The plan's command line with each output in a folder of its own under ``tmp``.

    No output of the dry run is then its input or another's: those clashes are
    the batch's to name, with the real names (:func:`..plan.check_outputs`).
    """
    argv = list(plan.argv)
    options = plan.step.options
    start = len(argv) - len(options)
    where = [argv.index("-o") + 1] + [start + k for k, v in enumerate(options) if placeholders(v)]
    for k, i in enumerate(where):  # (by the values: an option may write several files)
        folder = tmp / f"{plan.step.index}-{k}"
        folder.mkdir()
        argv[i] = str(folder / Path(argv[i]).name)
    return argv


def _sample_scan(manifest: Manifest) -> Scan:
    """The first scan (its outputs at the top of the output folder), or a stand-in."""
    from ..errors import VolwarpError
    from .manifest import find_scans

    try:
        scans = find_scans(manifest)
    except VolwarpError:  # (said again, with its key, when the batch looks for its scans)
        scans = []
    if scans:
        return dataclasses.replace(scans[0], relpath="")
    return Scan(id="scan", path=manifest.base / _STAND_IN, stem="scan", relpath="",
                files=tuple((c, manifest.base / _STAND_IN) for c in manifest.columns))


def path_kind(param: click.Parameter) -> str | None:
    """``"input"``, ``"output"`` or None: what a value of the option ``param`` names.

    An input is declared by its type (:class:`..cli.options.InputPath`); an
    output is any other file name (a ``click.Path``), or the value of a
    ``--*-to`` option (``--frames-to``, ``--points-to``...).
    """
    from ..cli.options import InputPath

    if isinstance(param.type, InputPath):
        return "input"
    names = [o for o in (*param.opts, *param.secondary_opts) if o.startswith("--")]
    if isinstance(param.type, click.Path) or any(
            o.endswith("-to") or o in _OUTPUT_NAMES for o in names):
        return "output"
    return None


class OptionValue(NamedTuple):
    """One value in a step's options: the item holding it, its option, what it names."""

    index: int  # in the step's options
    option: str  # as the parse knows it: ``-t``, ``--reference``
    kind: str | None  # :func:`path_kind`
    start: int = 0  # where the value starts in its item (``--opt=VALUE``, ``-tVALUE``)

    def value(self, options) -> str:
        """The value itself, from the step's ``options``."""
        return options[self.index][self.start:]


def option_values(command: click.Command, options) -> list[OptionValue]:
    """Each option value in a step's ``options``, as click's parser reads them.

    ``--opt VALUE``, ``--opt=VALUE``, a short option's ``-tVALUE`` (after any
    flags: ``-qtVALUE``), flags taking none, ``nargs`` values taking several;
    ``--`` ends the options. An unknown option is left to the parse.
    """
    table = {o: p for p in command.params if isinstance(p, click.Option)
             for o in (*p.opts, *p.secondary_opts)}
    out, k = [], 0
    while k < len(options) and options[k] != "--":
        param, option, start = _option_in(table, options[k])
        takes = 0 if param is None or param.is_flag or param.count else param.nargs
        if takes and start:  # (its first value in its own item)
            out.append(OptionValue(k, option, path_kind(param), start))
            takes -= 1
        count = min(takes, len(options) - k - 1)  # (a value missing: the parse says so)
        out += [OptionValue(k + 1 + j, option, path_kind(param)) for j in range(count)]
        k += count + 1
    return out


def _option_in(table: dict, text: str) -> tuple[click.Option | None, str, int]:
    """``(param, option, start)`` of the option an options item gives (click's rules).

    ``start``: where a value attached to it begins in the item (0: none, its
    values are the next items). A long option (or one of several letters)
    takes ``=VALUE``; a one-letter option after ``-`` takes the rest of the
    item, after the flags before it (``-qtVALUE``). ``(None, text, 0)`` for
    anything else.
    """
    name, eq, _ = text.partition("=")
    if name in table and not _is_short(name):
        return table[name], name, len(name) + 1 if eq else 0
    if len(text) < 2 or text[0] != "-" or text.startswith("--"):
        return None, text, 0
    for i in range(1, len(text)):
        option = "-" + text[i]
        param = table.get(option)
        if param is None:
            break
        if not (param.is_flag or param.count):
            return param, option, i + 1 if i + 1 < len(text) else 0
    return None, text, 0


def _is_short(option: str) -> bool:
    """``-t``: one letter after one dash (click parses ``-tVALUE``, never ``-t=VALUE``)."""
    return len(option) == 2 and option[0] == "-" and option[1] != "-"


def _check_tokens(manifest: Manifest, step: Step, values) -> None:
    """Options that would end the command (``--help``), placeholders where no output is named."""
    taken = {v.index: v.kind for v in values}
    for k, text in enumerate(step.options):
        key = ("steps", step.index, "options", k)
        if k not in taken and text.split("=", 1)[0] in _ENDING:
            raise manifest.doc.error(key, f"{text} prints and ends the command instead of "
                                          "running it: not a step's option")
        if k not in taken and (text.split("=", 1)[0] in _CONSOLE
                               or re.fullmatch(r"-[a-zA-Z]*v[a-zA-Z]*", text)):  # (-vv, -qv)
            raise manifest.doc.error(key, f"{text} writes to the step's console, which the "
                                          "batch does not keep (--report-json has each "
                                          "step's outputs and times; -v and --progress "
                                          "jsonl on the batch itself): not a step's option")
        column = row_column(text)
        if column is not None and taken.get(k) != "input":
            raise manifest.doc.error(key, f"{{{column}}} (each scan's file, from its "
                                          f"{column!r} cell) is the value of an input option, "
                                          "e.g. --reference {reference}, -t {transform}")
    for v in values:
        key = ("steps", step.index, "options", v.index)
        if v.option in RESERVED_OPTIONS:  # (attached: -oNAME; the manifest refuses -o NAME)
            raise manifest.doc.error(key, reserved_message(v.option))
        if v.kind != "output" and placeholders(v.value(step.options)):
            raise manifest.doc.error(
                key, f"{v.option} {v.value(step.options)!r}: {{stem}} and {{relpath}} name "
                     "outputs (placed under output_dir); only an output option (-o, --render, "
                     "--*-to) holds them")


def _absolute(manifest: Manifest, argv: list[str], options, values) -> list[str]:
    """``argv`` with each relative file name of the step's options taken from the manifest's folder.

    The step runs there; the dry run runs here, with this process's working
    folder left alone. (Placeholder names are absolute already: under output_dir.)
    """
    argv = list(argv)
    start = len(argv) - len(options)
    for v in values:
        value = v.value(options)
        inverse = _BRACKETS.match(value) if v.kind == "input" else None
        path = inverse.group(1) if inverse else value  # (apply's -t '[FILE,1]')
        if v.kind is None or placeholders(value) or row_column(value) is not None or \
                Path(path).is_absolute() or not path:
            continue  # (placeholders are filled with absolute names already)
        resolved = str(manifest.base / path)
        if inverse:
            resolved = f"[{resolved},{inverse.group(2)}]"
        argv[start + v.index] = options[v.index][:v.start] + resolved
    return argv


def _dry_run(manifest: Manifest, step: Step, command, argv: list[str]):
    """Parse and run ``volwarp ARGV`` up to its first read: ``(params, problem, quiet)``.

    ``problem``: the usage or spec error the command raised before it read,
    as the manifest's error (None: none). A parse error is raised at once.
    ``quiet``: the options hold ``-q`` (in any form: ``--quiet``, ``-qtFILE``).
    In a run scope of its own, in a copy of this context, with the log level
    put back: the run's side effects (``-q`` sets the level, ``--threads`` a
    context variable) stay there.
    """
    from ..progress import log
    from ..runscope import run_scope

    level = log.level

    def run():
        with run_scope() as files:
            files.dry_run = True
            files.folder = str(manifest.base)  # (where the step will run)
            try:
                ctx = command.make_context(f"volwarp {step.run}", argv[1:],
                                           resilient_parsing=False)
            except click.exceptions.Exit:  # (an eager option that prints and ends)
                raise manifest.doc.error(("steps", step.index, "options"),
                                         f"{step.run}: its options end the command before "
                                         "it runs") from None
            params = dict(ctx.params)
            quiet = ctx.meta.get("volwarp.verbosity", 0) < 0
            problem = _invoke(manifest, step, command, ctx)
            return params, problem, quiet

    try:
        return contextvars.copy_context().run(run)
    except click.ClickException as exc:
        raise _options_error(manifest, step, exc) from None
    finally:
        log.setLevel(level)


def _invoke(manifest: Manifest, step: Step, command, ctx):
    """Run the parsed command until its first read; its usage or spec error, or None."""
    from ..errors import BadUsage, SpecError
    from ..runscope import DryRunStop

    try:
        with ctx:
            command.invoke(ctx)
    except DryRunStop:
        return None
    except click.ClickException as exc:  # (UsageError, BadParameter)
        return _options_error(manifest, step, exc)
    except BadUsage as exc:
        return _options_error(manifest, step, exc)
    except SpecError as exc:  # a spec's own error: its file and line, and the step's
        return SpecError(f"{exc.message} (step {step.name!r} of {manifest.path.name})",
                         file=exc.file, key=exc.key, line=exc.line)
    except Exception:  # noqa: BLE001 - not the options': the real run says it, per scan
        return None
    return None  # (a command that read nothing: the checks passed)


def _options_error(manifest: Manifest, step: Step, exc: Exception):
    """An error of the step's options, at ``steps[i].options`` of the manifest."""
    text = exc.format_message() if isinstance(exc, click.ClickException) else str(exc)
    return manifest.doc.error(("steps", step.index, "options"),
                              f"{step.run}: {_one_line(text)}")


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _own_files(manifest: Manifest, step: Step, values: list[OptionValue]) -> list[Path]:
    """The files the step reads for every scan: its spec, its input options' files, what they name.

    From the manifest's options, never from what the dry run (on the first
    scan) declared: a reference or a transform that is also the first scan,
    or one of its table's cells, is every scan's file all the same. A
    ``{COLUMN}`` value is each scan's own (:attr:`.plan.StepPlan.reads`).
    """
    from .plan import linked_files

    files = [] if step.spec is None else [step.spec]
    for v in values:
        value = v.value(step.options)
        inverse = _BRACKETS.match(value)
        path = inverse.group(1) if inverse else value  # (apply's -t '[FILE,1]')
        if v.kind == "input" and row_column(value) is None and path:
            file = manifest.base / path
            files += [file, *linked_files(file, manifest.base)]
    return files


def _check_inputs_exist(manifest: Manifest, step: Step, inputs: list[Path]) -> None:
    """A file the step reads that is missing: one error now, not one per scan later."""
    for path in inputs:
        if not path.exists():
            raise manifest.doc.error(("steps", step.index, "options"),
                                     f"{step.run}: {path}: no such file (the step reads it)")


def _resolve(manifest: Manifest, path: str) -> Path:
    """A path as the step's process sees it (it runs in the manifest's folder)."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else manifest.base / p


def _check_specs(manifest: Manifest, step: Step, params: dict) -> None:
    """Each spec the step reads, against its schema (and a warp spec read as warp reads it)."""
    from ..spec.loader import load_spec

    for param, kind in SPEC_PARAMS.get(step.run, {}).items():
        path = params.get(param)
        if not path:
            continue
        doc = load_spec(_resolve(manifest, str(path)), kind)
        if kind == "warp":
            from ..bspline.plan import read_warp_spec

            read_warp_spec(doc)
