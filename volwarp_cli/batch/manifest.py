"""The batch manifest: loaded, checked against its schema and against itself, before any work.

A manifest (``specs/manifest.schema.json``) names the scans (a glob, a list or a
CSV column), the output folder and the chain of volwarp steps each scan goes
through. Everything that can be wrong with it is a :class:`SpecError` (exit 2)
naming the key path and its line: an unknown subcommand, a step reading a
step that does not come before it, a missing output pattern, an unknown
placeholder, an option the manifest sets itself (``-o``, ``--spec``), an
output extension the step cannot write, an option or a spec the step's own
command refuses (:mod:`.steps`). A scans' table (``inputs.csv``) may give each
scan files of its own in columns, which a step's input option takes as
``{COLUMN}``, its whole value: the image series it lies on in a ``reference``
column (``--reference {reference}``: a DICOM SEG or RTSTRUCT read on its
series), its registration in a ``transform`` column (``apply -t
{transform}``), any column so named (``-t {warp} -t {affine}``). The scans
are found here too (:func:`find_scans`), so two scans that would share
outputs are refused before anything runs.
"""

from __future__ import annotations

import csv
import glob
import hashlib
import os
import re
import string
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import SpecError, VolwarpError
from ..spec.loader import SpecDoc, load_spec

#: where a step's input is the scan itself
SCAN = "scan"
#: the placeholders of output patterns and option values
PLACEHOLDERS = ("stem", "relpath")
#: an input option's whole value naming a column of the scans' table: that row's file
_COLUMN = re.compile(r"^\{([A-Za-z_][A-Za-z0-9_]*)\}$")
#: extensions a single extension's worth of stem stripping treats as one
DOUBLE_EXTENSIONS = (".nii.gz", ".raw.gz")
#: options the manifest's own keys set (given in ``options`` they would clash)
RESERVED_OPTIONS = ("-o", "--output", "--spec")
_MESH_EXTENSIONS = (".ply", ".stl", ".obj", ".vtp", ".vtk")
#: seconds a folder scan's newest file must be old before it is read (``inputs.settle``):
#: a PACS's own (Orthanc calls a series stable after 60 s without a new instance)
DEFAULT_SETTLE = 60.0


@dataclass(frozen=True)
class Step:
    """One step of the manifest's chain: the subcommand it runs, on what, into which pattern."""

    index: int
    name: str
    run: str
    input: str  # SCAN or an earlier step's name
    output: str  # the pattern
    spec: Path | None
    options: tuple[str, ...]
    #: the files the step reads besides its input (its spec, its options' files), absolute
    inputs: tuple[Path, ...] = ()
    #: ``(index in options, option)`` of each option value naming a file the step writes
    writes: tuple[tuple[int, str], ...] = ()
    #: ``(parameter, parsed value)`` of the options that change which files an output
    #: option writes (mesh's ``turntable``: :data:`.plan.FILE_PARAMS`)
    params: tuple[tuple[str, object], ...] = ()


@dataclass(frozen=True)
class Scan:
    """One input scan: its file, and the stem and folder its outputs are named by."""

    id: str  # relpath/stem, posix: the scan's name in progress lines and the report
    path: Path
    stem: str
    relpath: str  # "" at the root
    #: ``(column, file)`` of the table's cells the steps take (``{reference}``, ``{transform}``)
    files: tuple[tuple[str, Path], ...] = ()

    def file(self, column: str) -> Path | None:
        """The scan's file in the table's ``column`` (None: not taken, or no table)."""
        return dict(self.files).get(column)


@dataclass
class Manifest:
    """A loaded, checked manifest: its steps, output folder, and the sha256 of it and its specs."""

    path: Path
    base: Path  # the manifest's folder
    output_dir: Path
    steps: list[Step]
    doc: SpecDoc
    sha256: str = ""
    specs: dict[str, str] = field(default_factory=dict)  # spec path -> sha256
    #: seconds a folder scan's newest file must be old before the scan is read
    #: (``inputs.settle``, ``--settle``; 0: read at once), :func:`.plan.still_arriving`
    settle: float = DEFAULT_SETTLE
    #: the scans :func:`find_scans` found (looked for once; not sent with cluster tasks)
    scans: list[Scan] | None = field(default=None, repr=False, compare=False)

    @property
    def columns(self) -> tuple[str, ...]:
        """The table columns the steps' options take (``{reference}``...): each scan's files."""
        return tuple(sorted({c for step in self.steps for v in step.options
                             if (c := row_column(v)) is not None}))

    def __getstate__(self) -> dict:
        """Pickled for a cluster task without the scan list (a task gets its own scan)."""
        return {**self.__dict__, "scans": None}


def stem_of(name: str) -> str:
    """``p01.nii.gz`` -> ``p01``; ``p01.nrrd`` -> ``p01``; one extension only."""
    lower = name.lower()
    for ext in DOUBLE_EXTENSIONS:
        if lower.endswith(ext) and len(name) > len(ext):
            return name[:-len(ext)]
    return Path(name).stem


def placeholders(text: str) -> list[str] | None:
    """The placeholder names in ``text``, or None if it is not a valid pattern."""
    try:
        parsed = list(string.Formatter().parse(text))
    except ValueError:
        return None
    names = []
    for _, name, spec, conversion in parsed:
        if name is None:
            continue
        if spec or conversion or name not in PLACEHOLDERS:
            return None
        names.append(name)
    return names


def reserved_message(option: str) -> str:
    """Why ``option`` (one of :data:`RESERVED_OPTIONS`) is not a step's option."""
    return (f"{option} is set by the step's {'spec' if option == '--spec' else 'output'} key, "
            "not options")


def option_value(text: str) -> str:
    """The value of an options item: ``--opt=VALUE`` -> ``VALUE``; else the item."""
    name, eq, value = text.partition("=")
    return value if eq and name.startswith("--") else text


def row_column(text: str) -> str | None:
    """The table column whose file an options item takes (``{transform}`` -> ``transform``).

    The item's whole value (``VALUE`` or ``--opt=VALUE``) is ``{COLUMN}``,
    COLUMN not an output placeholder; None otherwise.
    """
    m = _COLUMN.match(option_value(text))
    return m.group(1) if m and m.group(1) not in PLACEHOLDERS else None


def _embedded_column(text: str) -> str | None:
    """A column placeholder inside a longer value (``x/{reference}``), or None."""
    try:
        fields = [f for _, f, _, _ in string.Formatter().parse(option_value(text))]
    except ValueError:
        return None
    return next((f for f in fields if f and _COLUMN.match("{" + f + "}")
                 and f not in PLACEHOLDERS), None)


def fill_column(text: str, scan: Scan) -> tuple[str, Path]:
    """An options item with ``{COLUMN}`` replaced by the scan's file (absolute), and the file."""
    column = row_column(text)
    path = scan.file(column)
    if path is None:  # (find_scans refuses an empty cell when a step needs it)
        raise VolwarpError(f"scan {scan.id}: no file in the {column!r} column")
    return text.replace("{" + column + "}", str(path.absolute())), path


def fill(text: str, scan: Scan) -> str:
    """``text`` with ``{stem}`` and ``{relpath}`` (``.`` at the root) of ``scan`` filled in."""
    return text.format(stem=scan.stem, relpath=scan.relpath or ".")


def _number_text(value) -> str:
    """A YAML number as the command line gets it: every digit written (``180.1234``).

    ``{:g}`` kept 6 significant digits: ``--iso 180.1234`` ran as 180.123, and an edit
    to 180.1231 was taken for no change (the step skipped, its output stale). A whole
    float is written as an integer (``3.0`` as ``3``: integer options take it).
    """
    if isinstance(value, float):
        if value.is_integer() and abs(value) < 1e16:
            return str(int(value))
        return repr(value)
    return str(value)


def _check_pattern(doc: SpecDoc, path: tuple, text: str, *, output: bool = False) -> list[str]:
    """The placeholders of ``text``; a per-scan output's pattern must stay in output_dir.

    ``output``: the step's ``output`` (an option with a placeholder is one too).
    Such a path lands under output_dir, the folder the batch's lock holds: a
    '../' or absolute pattern wrote beside the scans (taken for a scan by the
    next run) or into another batch's folder, unlocked.
    """
    names = placeholders(text)
    if names is None:
        raise doc.error(path, f"bad pattern {text!r}: the placeholders are "
                              + ", ".join("{" + p + "}" for p in PLACEHOLDERS)
                              + " (write {{ and }} for braces)")
    if (output or names) and (os.path.isabs(text) or ".." in Path(text).parts):
        inside = not os.path.isabs(text) and not os.path.normpath(text).startswith("..")
        raise doc.error(path, (f"{text!r} has '..' in it: a scan's name or a placeholder "
                               "could take it out of output_dir; write it without "
                               f"('{os.path.normpath(text)}')") if inside else
                        (f"{text!r} leaves output_dir: a scan's outputs land in it (the "
                         "folder this batch locks); write a path inside it"))
    return names


def _produces(run: str) -> str:
    return {"mesh": "mesh", "capture": "capture"}.get(run, "volume")


def _check_output_extension(doc: SpecDoc, path: tuple, run: str, pattern: str) -> None:
    from ..io import volume_format

    name = pattern.lower()
    if run == "mesh":
        if not name.endswith(_MESH_EXTENSIONS):
            raise doc.error(path, f"a mesh output must end in {' '.join(_MESH_EXTENSIONS)}, "
                                  f"not {pattern!r}")
    elif run == "capture":
        if not name.endswith(".vwc"):
            raise doc.error(path, f"a capture output must end in .vwc, not {pattern!r}")
    else:
        try:
            volume_format(pattern)
        except VolwarpError as exc:
            raise doc.error(path, str(exc)) from None


def _what(column: str) -> str:
    """What a column's file is to a scan, for messages."""
    return {"reference": "each scan's series", "transform": "each scan's transform"}.get(
        column, "each scan's file")


def _check_column_source(doc: SpecDoc, key: tuple, column: str) -> None:
    """``{COLUMN}`` needs scans listed in a table (``inputs.csv``) with that column."""
    if "csv" not in doc.data["inputs"]:
        raise doc.error(key, f"{{{column}}} is {_what(column)} from the scans' table: list "
                             f"the scans in inputs.csv with a {column!r} column")
    table = doc.resolve(doc.data["inputs"]["csv"])
    try:
        with open(table, newline="", encoding="utf-8-sig") as fh:
            columns = next(csv.reader(fh), [])
    except (OSError, UnicodeDecodeError):  # (said with its key when the scans are read)
        return
    if column not in columns:
        raise doc.error(key, f"{{{column}}}: {table.name} has no {column!r} column "
                             f"(columns: {', '.join(columns) or 'none'})")


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a manifest (every error a :class:`SpecError` with key and line)."""
    path = Path(path)
    doc = load_spec(path, "manifest")
    base = path.parent
    steps: list[Step] = []
    by_name: dict[str, Step] = {}
    for i, raw in enumerate(doc.data["steps"]):
        key = ("steps", i)
        name, run = raw["name"], raw["run"]
        if name == SCAN:
            raise doc.error(key + ("name",), f"{SCAN!r} names the scan itself; "
                                             "choose another step name")
        if name in by_name:
            raise doc.error(key + ("name",), f"duplicate step name {name!r} "
                                             f"(also steps[{by_name[name].index}])")
        source = raw.get("input", SCAN)
        if source != SCAN:
            if source not in by_name:
                later = [j for j, s in enumerate(doc.data["steps"]) if s.get("name") == source]
                known = ", ".join([SCAN] + list(by_name))
                why = (f"step {source!r} comes later (steps[{later[0]}]); a step reads "
                       "the scan or an earlier step" if later else f"unknown step {source!r}")
                raise doc.error(key + ("input",), f"{why} (known here: {known})")
            made = _produces(by_name[source].run)
            if made == "mesh":
                raise doc.error(key + ("input",), f"step {source!r} writes a mesh, which "
                                                  f"{run} cannot read")
            if made == "capture" and run != "warp":
                raise doc.error(key + ("input",), f"step {source!r} writes a capture file "
                                                  f"(.vwc), which only warp reads")
        spec = raw.get("spec")
        if run == "warp" and spec is None:
            raise doc.error(key, "a warp step needs 'spec' (its warp spec)")
        if run != "warp" and spec is not None:
            raise doc.error(key + ("spec",), f"{run} takes no spec (only warp steps do)")
        spec_path = doc.resolve(spec) if spec is not None else None
        if spec_path is not None and not spec_path.is_file():
            raise doc.error(key + ("spec",), f"{spec_path} is a folder, not a spec file"
                            if spec_path.is_dir() else f"no such spec file: {spec_path}")
        _check_pattern(doc, key + ("output",), raw["output"], output=True)
        _check_output_extension(doc, key + ("output",), run, raw["output"])
        options = []
        for k, value in enumerate(raw.get("options", [])):
            if isinstance(value, bool):
                raise doc.error(key + ("options", k), "an option value must be a string or "
                                                      f"a number, not {value!r}")
            text = value if isinstance(value, str) else _number_text(value)
            flag = text.split("=", 1)[0]
            if "=" in text and flag.startswith("-") and placeholders(text.split("=", 1)[1]):
                raise doc.error(key + ("options", k),
                                f"write {flag} and its output name as two items "
                                f"([{flag!r}, {text.split('=', 1)[1]!r}]): the name is placed "
                                "under output_dir")
            if flag in RESERVED_OPTIONS:
                raise doc.error(key + ("options", k), reserved_message(flag))
            column = row_column(text)
            embedded = _embedded_column(text)
            if column is not None:
                _check_column_source(doc, key + ("options", k), column)
            elif embedded is not None:
                raise doc.error(key + ("options", k),
                                f"{text!r}: {{{embedded}}} is a whole option value "
                                f"({_what(embedded)}, e.g. --reference {{reference}}, "
                                "-t {transform})")
            else:
                _check_pattern(doc, key + ("options", k), text)
            options.append(text)
        step = Step(i, name, run, source, raw["output"], spec_path, tuple(options))
        steps.append(step)
        by_name[name] = step
    manifest = Manifest(path=path, base=base,
                        output_dir=doc.resolve(doc.data["output_dir"]).absolute(),
                        steps=steps, doc=doc,
                        settle=float(doc.data["inputs"].get("settle", DEFAULT_SETTLE)))
    from .steps import check_steps

    manifest.steps = check_steps(manifest)  # each step's options and spec, by its command
    manifest.sha256 = hashlib.sha256(path.read_bytes()).hexdigest()
    for step in steps:
        if step.spec is not None and str(step.spec) not in manifest.specs:
            manifest.specs[str(step.spec)] = hashlib.sha256(step.spec.read_bytes()).hexdigest()
    return manifest


def _glob_root(pattern: str) -> str:
    """The folder of a glob pattern before its first wildcard: ``scans/**/*.nrrd`` -> ``scans``."""
    parts = Path(pattern).parts
    fixed = []
    for part in parts[:-1]:
        if glob.has_magic(part):
            break
        fixed.append(part)
    return str(Path(*fixed)) if fixed else "."


def glob_pattern(manifest: Manifest) -> str | None:
    """The manifest's ``inputs.glob``, resolved (None: its scans are listed or tabled)."""
    inputs = manifest.doc.data["inputs"]
    return str(manifest.doc.resolve(inputs["glob"])) if "glob" in inputs else None


def glob_would_match(pattern: str, path) -> bool:
    """Whether ``glob.glob(pattern, recursive=True)`` would list the file ``path`` were it there.

    (Relative ones: of the working folder.) Component by component, as glob matches them: ``**`` any
    number of folders (none too), the others by fnmatch's rules (case counts),
    a wildcard never matching a name that starts with a dot (glob's hidden
    files); a folder that exists is matched as glob would (it lists ``path``
    only where every folder on the way matches).
    """
    import fnmatch

    want = Path(os.path.normpath(os.path.abspath(pattern))).parts
    have = Path(os.path.normpath(os.path.abspath(path))).parts

    def match(i: int, j: int) -> bool:
        if i == len(want):
            return j == len(have)
        part = want[i]
        if part == "**":  # (last: the file and the folders above it, one at least)
            if i == len(want) - 1:
                return j < len(have) and not any(h.startswith(".") for h in have[j:])
            if match(i + 1, j):
                return True
            return j < len(have) and not have[j].startswith(".") and match(i, j + 1)
        if j == len(have):
            return False
        if glob.has_magic(part):
            if have[j].startswith(".") and not part.startswith("."):
                return False
            if not fnmatch.fnmatchcase(have[j], part):
                return False
        elif part != have[j]:
            return False
        return match(i + 1, j + 1)

    return match(0, 0)


def find_scans(manifest: Manifest) -> list[Scan]:
    """The manifest's scans, sorted by id; two scans with one id are a spec error.

    Looked for once per manifest (the step checks need the first scan, the
    batch all of them): a second call gives the same list.
    """
    if manifest.scans is None:
        manifest.scans = _find_scans(manifest)
    return list(manifest.scans)


def _glob_scans(manifest: Manifest, pattern: str) -> list[tuple[Path, tuple]]:
    """The files a glob matches, but for those under the output folder (outputs are not scans).

    An output folder that is the scans' folder, or holds it, is refused: every
    scan would be taken for an output (and its outputs, beside the scans, for
    scans the next time).
    """
    out = manifest.output_dir.resolve()
    folder = Path(_glob_root(pattern)).resolve()
    if folder.is_relative_to(out):
        how = "is" if folder == out else "holds"
        raise manifest.doc.error(("output_dir",), (
            f"outputs there would be taken for scans: it {how} the folder inputs.glob "
            "searches; choose an output_dir outside it (a folder inside it is fine: it is "
            f"left out of the glob) ({folder})"))
    paths = []
    batches: dict[Path, Path | None] = {}  # folder -> the batch output folder it lies in
    others: dict[Path, int] = {}
    own: list[Path] = []  # matched in our output folder
    folders: list[Path] = []  # matched folders (a DICOM series, a store): left out, said
    for name in sorted(glob.glob(pattern, recursive=True)):
        p = Path(name)
        if not p.is_file():  # (DICOM folders: convert them first, or list them)
            if p.is_dir() and not p.resolve().is_relative_to(out):
                folders.append(p)
            continue
        real = p.resolve()
        if real.is_relative_to(out):  # our own outputs are not scans
            own.append(real)
            continue
        other = _batch_output_folder(real.parent, folder, batches)
        if other is not None:  # another batch's outputs: not scans either
            others[other] = others.get(other, 0) + 1
            continue
        paths.append((p, ("inputs", "glob")))
    for other, n in others.items():
        from ..progress import log

        log.warning("warning: %s: inputs.glob: %d file%s under %s, another batch's output "
                    "folder, left out (outputs are not scans)", manifest.path, n,
                    "" if n == 1 else "s", other)
    if folders:  # (a glob of `scans/*` over series folders ran "0 scans", exit 0)
        from ..progress import log

        log.warning("warning: %s: inputs.glob matches %d folder%s (%s%s), left out: a glob "
                    "takes files; a DICOM series or an OME-Zarr store is a scan by "
                    "inputs.list or inputs.csv", manifest.path, len(folders),
                    "" if len(folders) == 1 else "s",
                    os.path.relpath(folders[0], manifest.path.parent),
                    f" and {len(folders) - 1} more" if len(folders) > 1 else "")
    _say_unrecorded(manifest, out, own)
    return paths


def _say_unrecorded(manifest: Manifest, out: Path, own: list[Path]) -> None:
    """Say the files the glob matches in the output folder that this batch never recorded.

    They are left out as outputs; scans placed there (an ``output_dir`` inside
    the scans' tree, ``scans/site-a``) were never processed, without a word.
    Not refused: a batch stopped before its first record leaves outputs of
    its own unrecorded, and refusing them would stop every later run.
    """
    if not own:
        return
    from ..io.inputs import output_files
    from ..progress import log
    from .plan import STATE_NAME, _read_state

    recorded = {os.path.normpath(os.path.relpath(f, out)) for k in _read_state(out / STATE_NAME)[0]
                for f in output_files(out / k)}  # (a recorded .nhdr's data file too)
    strangers = [p for p in own if os.path.relpath(p, out) not in recorded]
    if strangers:
        more = f" and {len(strangers) - 1} more" if len(strangers) > 1 else ""
        log.warning("warning: %s: inputs.glob: %s%s in the output folder %s left out as "
                    "outputs, though no run of this batch recorded writing them: if they are "
                    "scans, choose an output_dir outside the scans' folders", manifest.path,
                    os.path.relpath(strangers[0], out), more, out)


def _batch_output_folder(folder: Path, root: Path, seen: dict) -> Path | None:
    """The batch output folder (one holding ``.volwarp-batch``) ``folder`` lies in, below ``root``.

    A glob over a tree that holds an earlier batch's outputs took them for
    scans (a user-day review: ``scans/out/site-a/p01_warped.nii.gz``). The
    glob's own folder and those above it are not looked at: a glob in a
    batch's output folder asks for its outputs (a batch that goes on from
    another's).
    """
    from .lock import BOOK_DIR

    if folder in seen:
        return seen[folder]
    if folder == root or not folder.is_relative_to(root) or folder.parent == folder:
        found = None
    elif (folder / BOOK_DIR).is_dir():
        found = folder
    else:
        found = _batch_output_folder(folder.parent, root, seen)
    seen[folder] = found
    return found


def _find_scans(manifest: Manifest) -> list[Scan]:
    doc = manifest.doc
    inputs = doc.data["inputs"]
    paths: list[tuple[Path, tuple]] = []  # (file, the key that named it)
    cells: dict[int, tuple] = {}  # (the table's files the steps take, by row)
    if "glob" in inputs:
        pattern = str(doc.resolve(inputs["glob"]))
        # (the pattern is resolved already: its root is not resolved again)
        root = doc.resolve(inputs["root"]) if "root" in inputs else Path(_glob_root(pattern))
        paths = _glob_scans(manifest, pattern)
        if not paths:
            raise VolwarpError(f"{manifest.path}: inputs.glob: no scan matches {pattern!r} "
                               "(empty or not mounted?)")
    elif "list" in inputs:
        root = doc.resolve(inputs.get("root", "."))
        paths = [(doc.resolve(p), ("inputs", "list", i)) for i, p in enumerate(inputs["list"])]
    else:
        table = doc.resolve(inputs["csv"])
        column = inputs.get("column", "path")
        root = doc.resolve(inputs["root"]) if "root" in inputs else table.parent
        try:
            with open(table, newline="", encoding="utf-8-sig") as fh:
                reader = csv.DictReader(fh)
                if column not in (reader.fieldnames or []):
                    raise doc.error(("inputs", "column"),
                                    f"{table.name} has no column {column!r} (columns: "
                                    f"{', '.join(reader.fieldnames or []) or 'none'})")
                wants = manifest.columns
                for name in wants:
                    if name not in (reader.fieldnames or []):
                        raise doc.error(("inputs", "csv"),
                                        f"{table.name} has no {name!r} column, and a step's "
                                        f"options take {{{name}}} ({_what(name)})")
                for row in reader:
                    cell = (row.get(column) or "").strip()
                    if not cell:
                        raise SpecError(f"{column}: empty cell", file=str(table),
                                        line=reader.line_num)
                    p = Path(cell).expanduser()
                    files = []
                    for name in wants:
                        text = (row.get(name) or "").strip()
                        if not text:
                            raise SpecError(f"{name}: empty cell (a step's options take "
                                            f"{{{name}}})", file=str(table),
                                            line=reader.line_num)
                        f = Path(text).expanduser()
                        files.append((name, f if f.is_absolute() else table.parent / f))
                    cells[len(paths)] = tuple(files)
                    paths.append((p if p.is_absolute() else table.parent / p, ("inputs", "csv")))
        except OSError as exc:
            raise doc.error(("inputs", "csv"), f"cannot read {table}: "
                                               f"{exc.strerror or exc}") from None
        if not paths:
            raise VolwarpError(f"{table}: no scan listed")
    scans: dict[str, Scan] = {}
    for n, (p, key) in enumerate(paths):
        try:  # (lexically normal: '../x' is not under the root, though Path keeps its '..')
            rel = Path(os.path.normpath(Path(p).absolute().parent)).relative_to(
                os.path.normpath(Path(root).absolute()))
        except ValueError:
            raise doc.error(key, f"{p} is not under the inputs' root {root} (set inputs.root)"
                            ) from None
        relpath = "" if str(rel) == "." else rel.as_posix()
        stem = stem_of(Path(p).name)
        scan = Scan(id=f"{relpath}/{stem}" if relpath else stem, path=Path(p), stem=stem,
                    relpath=relpath, files=cells.get(n, ()))
        if scan.id in scans:
            raise doc.error(key, f"{scans[scan.id].path} and {p} would share outputs "
                                 f"(both are scan {scan.id!r})")
        scans[scan.id] = scan
    return [scans[k] for k in sorted(scans)]


def shard(scans: list[Scan], index: int, count: int) -> list[Scan]:
    """Shard ``index`` of ``count`` (0-based): every ``count``-th scan of the sorted list.

    The shards thus together hold every scan exactly once, and are of even size.
    """
    return scans[index::count]
