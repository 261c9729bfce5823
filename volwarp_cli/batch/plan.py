"""What each scan's steps are, concretely, and whether they are up to date (by content).

A step's plan is its command line (``volwarp RUN INPUT [--spec S] -o OUT -q
OPTIONS``), its input (the scan, or an earlier step's output) and its
outputs: ``-o`` and every option value holding a placeholder (a mesh's
``--render {stem}.png``), all under the output folder, and the output
options' values without one (``--camera-to cam.json``: one file, in the
manifest's folder, which :func:`check_outputs` allows for one scan only).
The outputs are the files the command writes, named as it names them
(:func:`written_files`): ``--render {stem}.png --turntable 4`` writes
``{stem}-000.png`` ... ``{stem}-003.png``, not ``{stem}.png``. A name that
is still a pattern once its placeholders are filled (``--frames-to
'{stem}_{{frame:03d}}.nrrd'``: a file per frame) is refused: its files
are known only once the step has run.
An option value ``{COLUMN}`` is the scan's file in that column of its table
row (``{reference}``: its series; ``{transform}``: its registration): a file
the step reads for that scan, not an output (an elastix parameter file with
the initial transforms it names).

A step is up to date when what its outputs were made from is what it would
be made from now, and its outputs are still what it made. "Made from" is
volwarp's version and code (:func:`source_digest`), the libraries it runs on
(:func:`library_versions`), the step as the manifest
defines it (its options) and the sha256 of every file it reads (its input
with the data files its header names, its spec, the files its options
name): :func:`made_from`. The record
(:class:`CommandRecord`, ``OUT/.volwarp-batch/state.json``) keeps that for
each output with the output's own sha256. Dates decide nothing: a scan
replaced by an older-dated one (``rsync -a``, ``cp -p``) is redone, a touched
one is not. Hashes are cached by each file's inode, size, mtime and ctime
(:mod:`.content`), so an unchanged tree is not read again.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from .. import __version__
from .content import (
    FileHashes,
    age_words,
    content_digest,
    content_stamp,
    input_last_change,
)
from .lock import BOOK_DIR
from .manifest import (
    SCAN,
    Manifest,
    Scan,
    Step,
    fill,
    fill_column,
    option_value,
    placeholders,
    row_column,
)

#: in the output folder: what each output was made from, and the file hash cache
STATE_NAME = f"{BOOK_DIR}/state.json"
#: held while the state file is merged and rewritten (shards share the file)
STATE_LOCK_NAME = f"{BOOK_DIR}/state.lock"
#: the state file's format (an older one is ignored: its outputs are made again)
STATE_VERSION = 2
#: seconds between rewrites of the state file during a run (and once at its end)
FLUSH_SECONDS = 1.0
#: compiled files left out of :func:`source_digest` (built from the sources beside them)
_COMPILED = (".so", ".pyd", ".dylib", ".dll", ".pyc", ".pyo", ".o")
#: the parsed options that change which files an output option writes, by command
#: (each step's dry run keeps their values: :attr:`.manifest.Step.params`)
FILE_PARAMS = {"mesh": ("turntable", "labels")}


@dataclass
class StepPlan:
    """One step for one scan, concretely: its input, its outputs and its command line."""

    step: Step
    input: Path
    output: Path
    extra_outputs: list[Path] = field(default_factory=list)
    argv: list[str] = field(default_factory=list)  # after ``volwarp``
    extra_options: list[str] = field(default_factory=list)  # the option of each extra output
    #: ``(option, path)`` of each output option without a placeholder (one name for all
    #: scans, in the manifest's folder: ``--camera-to cam.json``); not in :attr:`outputs`
    fixed_outputs: list[tuple[str, Path]] = field(default_factory=list)
    #: the files this scan's step reads besides its input and the step's own files (the
    #: scan's ``{reference}`` series, ``{transform}``...)
    reads: list[Path] = field(default_factory=list)

    @property
    def outputs(self) -> list[Path]:
        """The files the step makes per scan: ``-o`` first, then those of the placeholder options."""
        return [self.output, *self.extra_outputs]

    @property
    def output_options(self) -> list[str]:
        """The option naming each of :attr:`outputs` (``-o``, ``--render``...)."""
        return ["-o", *self.extra_options]

    @property
    def made(self) -> list[Path]:
        """Every file the step makes: :attr:`outputs` and the fixed outputs.

        Each recorded and checked: one deleted or changed by hand makes the step run again.
        """
        return [*self.outputs, *(p for _, p in self.fixed_outputs)]

    @property
    def writes(self) -> list[tuple[str, Path]]:
        """``(option, path)`` of every file the step writes: :attr:`outputs`, fixed outputs."""
        return [*zip(self.output_options, self.outputs, strict=True), *self.fixed_outputs]


def output_path(manifest: Manifest, scan: Scan, pattern: str) -> Path:
    """A pattern filled for ``scan``, under the output folder.

    The scan's folder is mirrored there, unless the pattern places ``{relpath}`` itself.
    """
    filled = fill(pattern, scan)
    if ".." in Path(filled).parts or Path(filled).is_absolute():
        from ..errors import BadUsage  # (a scan named "...nrrd": its stem is "..")

        raise BadUsage(f"scan {scan.id!r} ({scan.path}) fills output pattern {pattern!r} as "
                       f"{filled!r}, which leaves output_dir (the folder this batch locks): "
                       "rename the scan, or leave it out of inputs")
    if "relpath" in (placeholders(pattern) or ()):
        return manifest.output_dir / filled
    return manifest.output_dir / scan.relpath / filled


def written_files(step: Step, option: str, path: Path) -> list[Path]:
    """The files ``step``'s command writes for its output ``option`` given ``path``.

    Named by the command's own function, so that what batch records and checks
    is what the step writes (``--render`` with ``--turntable``: only the frames).
    """
    if step.run == "mesh" and option == "--render":
        from ..cli.mesh import render_files

        return render_files(path, dict(step.params).get("turntable"))
    return [path]


def plan_scan(manifest: Manifest, scan: Scan) -> list[StepPlan]:
    """The plans of the manifest's steps for ``scan``, in step order (absolute paths)."""
    plans: dict[str, StepPlan] = {}
    for step in manifest.steps:
        source = scan.path if step.input == SCAN else plans[step.input].output
        output = output_path(manifest, scan, step.output)
        options, extra, flags, reads = [], [], [], []
        for k, value in enumerate(step.options):
            if row_column(value) is not None:
                text, path = fill_column(value, scan)
                options.append(text)
                reads += [path, *linked_files(path, manifest.base)]
            elif placeholders(value):
                path = output_path(manifest, scan, value)
                flag = (step.options[k - 1] if k and step.options[k - 1].startswith("-")
                        else "an output")
                files = written_files(step, flag, path)
                extra += files
                flags += [flag] * len(files)
                options.append(str(path.absolute()))
            else:
                options.append(value)
        argv = [step.run, str(Path(source).absolute())]
        if step.spec is not None:
            argv += ["--spec", str(step.spec.absolute())]
        # (no -q: the step's warnings are kept for the report, run.step_warnings)
        argv += ["-o", str(output.absolute()), *options]
        plans[step.name] = StepPlan(step, Path(source), output, extra, argv, flags,
                                    _fixed_outputs(manifest, step), reads)
    return list(plans.values())


def linked_files(path: Path, folder: Path) -> list[Path]:
    """The files a scan's own file names: an elastix parameter file's initial transforms.

    They are what the step reads too (a changed initial transform redoes the
    scan), found as the step finds them: it runs in the manifest's ``folder``.
    One that cannot be found is the step's to report.
    """
    from ..errors import VolwarpError
    from ..transforms.elastix import initial_files

    try:
        return [Path(p) for p in initial_files(str(path), str(folder))]
    except (OSError, VolwarpError):
        return []


def _fixed_outputs(manifest: Manifest, step: Step) -> list[tuple[str, Path]]:
    """The output option values of ``step`` without a placeholder, from the manifest's folder."""
    out = []
    for k, option in step.writes:
        text = step.options[k]
        value = option_value(text)
        if not placeholders(value):
            p = Path(value)
            out += [(option, f) for f in written_files(step, option, p if p.is_absolute()
                                                      else manifest.base / p)]
    return out


def command_digest(manifest: Manifest, plan: StepPlan) -> str:
    """The step as the manifest defines it (run, input, output pattern, spec, options), hashed.

    Paths are relative to the manifest, so a tree moved elsewhere is still up to date.
    """
    step = plan.step
    spec = None if step.spec is None else os.path.relpath(step.spec, manifest.base)
    text = json.dumps([step.run, step.input, step.output, spec, list(step.options)])
    return hashlib.sha256(text.encode()).hexdigest()


def step_files(manifest: Manifest, plan: StepPlan) -> list[tuple[str, Path]]:
    """``(name, path)`` of every file the step reads: its input, then its spec and option files.

    The input is named by its file name (as its outputs' provenance names it),
    the others relative to the manifest (a moved tree keeps its names).
    """
    out = [(plan.input.name, plan.input)]
    out += [(os.path.relpath(p, manifest.base), Path(p)) for p in [*plan.step.inputs, *plan.reads]
            if Path(p).absolute() != plan.input.absolute()]
    return out


@functools.cache
def source_digest() -> str:
    """The sha256 of volwarp's own code: every file of its package but compiled ones.

    A commit may change what a command writes without a version bump: an
    output made by other code is made again (any change, the safe side).
    Relative names and bytes, sorted by name; ``__pycache__`` and extension
    binaries left out. Once per process (a few milliseconds).
    """
    root = Path(__file__).parent.parent
    files = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = [d for d in dirnames if d != "__pycache__"]
        files += [os.path.join(dirpath, f) for f in filenames if not f.endswith(_COMPILED)]
    digest = hashlib.sha256()
    for path in sorted(files, key=lambda f: os.path.relpath(f, root)):
        with open(path, "rb") as fh:
            data = fh.read()
        digest.update(f"{os.path.relpath(path, root)}\0{len(data)}\0".encode() + data)
    return digest.hexdigest()


#: volwarp's extras whose libraries read or write what a step does (DICOM, stores)
_OUTPUT_EXTRAS = ("dicom", "scale")


@functools.lru_cache(maxsize=1)
def library_versions() -> dict[str, str | None]:
    """The versions of the libraries volwarp runs on: its requirements, Python's, zlib's.

    Part of what an output is made from: an upgraded scipy, vtk, isal or
    OpenImageIO can change the bytes a command writes (an interpolation, a
    render, a gzip stream), so an output made with other libraries is made
    again, as one made by other code is. volwarp's own requirements and
    those of its ``dicom`` and ``scale`` extras, as installed (None: not);
    once per process (~20 ms).
    """
    import importlib.metadata as metadata
    import platform
    import zlib

    versions: dict[str, str | None] = {"python": platform.python_version(),
                                       "zlib": zlib.ZLIB_RUNTIME_VERSION}
    try:
        wanted = metadata.requires("volwarp-cli") or []
    except metadata.PackageNotFoundError:  # (run from a source tree that is not installed)
        wanted = []
    for requirement in wanted:
        spec, _, marker = requirement.partition(";")
        extra = re.search(r"""extra\s*==\s*["']([^"']+)["']""", marker)
        if extra is not None and extra.group(1) not in _OUTPUT_EXTRAS:
            continue
        name = re.match(r"[A-Za-z0-9._-]+", spec.strip()).group(0)
        if name.lower() == "volwarp-cli":
            continue
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return dict(sorted(versions.items()))


def made_from(manifest: Manifest, plan: StepPlan, hashes: FileHashes) -> dict:
    """What the step's outputs would be made from now (raises OSError for a missing input)."""
    return {"volwarp": __version__, "source": source_digest(),
            "libraries": library_versions(),
            "command": command_digest(manifest, plan),
            "inputs": [[name, content_digest(path, hashes)]
                       for name, path in step_files(manifest, plan)]}


def read_stamps(manifest: Manifest, plan: StepPlan) -> list:
    """The identity of every file the step reads (:func:`.content.content_stamp`), by name.

    Taken before :func:`made_from` hashes them, and compared once the step has
    run (:func:`changed_while_run`).
    """
    return [[name, content_stamp(path)] for name, path in step_files(manifest, plan)]


def changed_while_run(manifest: Manifest, plan: StepPlan, stamps: list) -> str | None:
    """Why the step's outputs may not be made from what :func:`made_from` hashed, or None.

    A file it reads was replaced or rewritten after ``stamps`` were taken: the
    step may have read the other bytes (or a file half written), and a record
    naming the hashed ones would skip that output for good once the file is
    put back (a sync rewriting a scan in place with the same bytes).
    """
    for (name, then), (_, now) in zip(stamps, read_stamps(manifest, plan), strict=True):
        if then != now:
            return (f"{name} changed while the step ran: its outputs are not recorded, "
                    "made again next run")
    return None


def _difference(old: dict, new: dict) -> str | None:
    """Why an output made from ``old`` is stale now that it would be made from ``new``."""
    if old.get("volwarp") != new["volwarp"]:
        return f"volwarp's version changed ({old.get('volwarp')} -> {new['volwarp']})"
    if old.get("source") != new["source"]:
        return "volwarp's code changed (same version)"
    if old.get("libraries") != new["libraries"]:
        then = old.get("libraries") or {}
        moved = [f"{k} {then.get(k)} -> {v}" for k, v in new["libraries"].items()
                 if then.get(k) != v]
        return ("the libraries it runs on changed (" + ", ".join(moved[:3])
                + (", ..." if len(moved) > 3 else "") + ")")
    if old.get("command") != new["command"]:
        return "its options changed"
    now = [(name, digest) for name, digest in new["inputs"]]
    then = [(name, digest) for name, digest in old.get("inputs", [])]
    if now == then:  # (in order: -t A -t B is not -t B -t A, nor -t A -t A)
        return None
    before = dict(then)
    for name, digest in now:
        if before.get(name) != digest:
            return f"{name} changed" if name in before else f"it reads {name} now"
    if sorted(now) == sorted(then):
        return "it reads its files in another order now"
    return "it reads other files now"


def stale_reason(manifest: Manifest, plan: StepPlan, record: CommandRecord, made: dict
                 ) -> str | None:
    """Why ``plan``'s outputs must be (re)made from ``made``, or None when they are up to date."""
    for out in plan.made:
        entry = record.entry(out)
        if entry is None:
            return f"{out.name}: not made by this batch before"
        why = _difference(entry, made)
        if why is not None:
            return why
        try:
            now = content_digest(out, record.hashes)
        except OSError:
            return f"{out.name} is missing"
        if now != entry.get("sha256"):
            return f"{out.name} was changed since it was made"
    return None


def _now() -> float:
    """The clock a folder's age is taken against (seconds since the epoch)."""
    return time.time()


def still_arriving(manifest: Manifest, scan: Scan) -> str | None:
    """Why ``scan`` is not read this run (its folder still arriving), or None.

    No DICOM tag says how many slices a classic series has: a series folder
    read while a PACS, rsync or a scanner's export is still storing its
    slices gives a volume short of them (and an OME-Zarr store its missing
    chunks' fill value), exit 0. A folder (the scan's, a table cell's
    ``{reference}`` series) whose newest file (:func:`.content.last_change`)
    is younger than ``manifest.settle`` seconds is left to the next run.
    A file scan is not held back: its reader knows its length from its header,
    and rsync renames a file into place whole.
    """
    if manifest.settle <= 0:
        return None
    now = _now()
    for column, path in [("", scan.path), *scan.files]:
        if not Path(path).is_dir():
            continue
        newest = input_last_change(path, now)
        if newest is None or now - newest >= manifest.settle:
            continue
        where = f"{{{column}}} {os.path.relpath(path, manifest.base)}: " if column else ""
        return f"{where}newest file {age_words(now - newest)}, settle {manifest.settle:g} s"
    return None


def _read_state(path: Path) -> tuple[dict, dict]:
    """``(outputs, files)`` of a state file; empty for a missing, damaged or older one."""
    try:
        data = json.loads(path.read_text())
        if data.get("version") == STATE_VERSION:
            return dict(data["outputs"]), dict(data["files"])
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        pass
    return {}, {}


class Replaced(Exception):
    """A step's output was replaced by another writer's before the batch recorded it."""


class CommandRecord:
    """What each output was made from, and the file hash cache (``STATE_NAME``).

    One writer per process; shards of one folder merge theirs under a lock
    (:meth:`flush`). Written at most every :data:`FLUSH_SECONDS` and at the
    end of the run: a batch killed outright loses a second of records at most,
    whose steps run again next time.
    """

    def __init__(self, manifest: Manifest):
        self.manifest = manifest
        self.path = manifest.output_dir / STATE_NAME
        self.lock = threading.Lock()
        self.outputs, files = _read_state(self.path)
        self.hashes = FileHashes(files)
        self._dirty: dict[str, dict] = {}
        self._flushed = time.monotonic()

    def _key(self, path: Path) -> str:
        return os.path.relpath(Path(path).absolute(), self.manifest.output_dir)

    def entry(self, path: Path) -> dict | None:
        """What the output ``path`` was recorded as made from, or None."""
        with self.lock:
            entry = self.outputs.get(self._key(path))
        return entry if isinstance(entry, dict) else None

    def entries(self, plan: StepPlan, made: dict, committed: dict | None = None,
                warnings: list[str] | None = None) -> dict[str, dict] | None:
        """The record of ``plan``'s outputs just made from ``made`` (None: one is missing).

        ``warnings``: what the step warned, kept so that a later run that skips
        it reports them again (an output made with a warning stays that output).

        ``committed``: the identity of each output as the step renamed it into
        place, by absolute path (:func:`~volwarp_cli.io.atomic.note_committed`).
        An output whose file is no longer that one (another writer put its own
        there after the step) raises :class:`Replaced`: its bytes are not the
        step's.
        """
        from ..io.atomic import file_identity
        from ..io.inputs import output_files

        def identity(file):
            try:
                return file_identity(os.stat(file))
            except FileNotFoundError:
                return None

        out = {}
        for path in plan.made:
            # the output and the data file a detached header writes: either replaced makes
            # the recorded digest another writer's (the header alone was checked)
            files = [(f, (committed or {}).get(os.path.abspath(f))) for f in output_files(path)]
            files = [(f, want) for f, want in files if want is not None or f == Path(path)]
            try:
                before = [identity(f) for f, _ in files]
                out[self._key(path)] = {**made, "sha256": content_digest(path, self.hashes),
                                        **({"warnings": list(warnings)} if warnings else {})}
                after = [identity(f) for f, _ in files]
            except OSError:
                return None
            if before[0] is None:
                return None
            for (file, want), b, a in zip(files, before, after, strict=True):
                if want is not None and not b == a == want:
                    raise Replaced(f"{file} was replaced by another writer after this step made "
                                   "it (another batch or command writing the same file): not "
                                   "recorded, made again next run")
        return out

    def keep(self, entries: dict[str, dict], files: dict[str, list] | None = None) -> None:
        """Note ``entries`` (and hashes a cluster task computed); written now and then."""
        with self.lock:
            self.outputs.update(entries)
            self._dirty.update(entries)
            if files:
                self.hashes.entries.update(files)
                self.hashes.fresh.update(files)
            due = time.monotonic() - self._flushed >= FLUSH_SECONDS
        if due:
            self.flush()

    def flush(self) -> None:
        """Write the state file, merged with what other shards wrote meanwhile."""
        import fcntl

        from ..io.atomic import write_bytes_atomic

        with self.lock:
            if not self._dirty and not self.hashes.fresh:
                return
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.manifest.output_dir / STATE_LOCK_NAME,
                         os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
                outputs, files = _read_state(self.path)
                outputs.update(self._dirty)
                files.update(self.hashes.fresh)
                write_bytes_atomic(self.path, json.dumps(
                    {"version": STATE_VERSION, "outputs": outputs, "files": files},
                    sort_keys=True, separators=(",", ":")).encode())
            finally:
                os.close(fd)
            self._dirty.clear()
            self.hashes.fresh.clear()
            self._flushed = time.monotonic()

    def snapshot(self, plans: list[StepPlan]) -> tuple[dict, dict]:
        """The record's entries for ``plans``' outputs and files (what a cluster task needs)."""
        keys = {self._key(p) for plan in plans for p in plan.made}
        roots = [os.path.abspath(path) for plan in plans
                 for path in [*plan.made, *(p for _, p in step_files(self.manifest, plan))]]
        roots += [str(f) for plan in plans for f in _data_files(plan.input)]
        with self.lock:
            outputs = {k: v for k, v in self.outputs.items() if k in keys}
        return outputs, self.hashes.subset(roots)


def _data_files(path: Path) -> list[str]:
    from ..io.inputs import input_files

    return [os.path.abspath(f) for f in input_files(path)[1:]]


class RecordSnapshot(CommandRecord):
    """A :class:`CommandRecord` read from a snapshot (a cluster task's), writing nothing.

    The batch process keeps what a task made when its result arrives: one
    writer of the state file, however many workers.
    """

    def __init__(self, manifest: Manifest, snapshot: tuple[dict, dict]):
        self.manifest = manifest
        self.path = manifest.output_dir / STATE_NAME
        self.lock = threading.Lock()
        self.outputs = dict(snapshot[0])
        self.hashes = FileHashes(snapshot[1])
        self._dirty = {}
        self._flushed = time.monotonic()

    def keep(self, entries: dict[str, dict], files: dict[str, list] | None = None) -> None:
        """Only in memory: the batch process writes."""
        with self.lock:
            self.outputs.update(entries)

    def flush(self) -> None:
        """Nothing: the batch process writes."""


def _located(manifest: Manifest, key: tuple, message: str):
    """A spec error at ``key`` of the manifest, its message whole (both paths in it)."""
    from ..errors import SpecError
    from ..spec.loader import format_key

    return SpecError(message, file=manifest.doc.file, key=format_key(key),
                     line=manifest.doc.line(key))


def batch_reads(manifest: Manifest) -> dict[str, str]:
    """The files the batch reads besides its scans, each with who reads it.

    The steps' own files (specs, option files), the manifest, the scans' table.
    """
    files: dict[str, str] = {}
    for step in manifest.steps:
        for p in step.inputs:
            files.setdefault(str(p), f"read by step {step.name!r}, steps[{step.index}]")
    files.setdefault(str(manifest.path.absolute()), "the manifest")
    table = manifest.doc.data["inputs"].get("csv")
    if table is not None:
        files.setdefault(str(manifest.doc.resolve(table).absolute()), "the scans' table")
    return files


def _is_pattern(path: Path) -> bool:
    """Whether an output name still holds fields after its placeholders (``{frame:03d}``)."""
    import string

    try:
        return any(f is not None for _, f, _, _ in string.Formatter().parse(str(path)))
    except ValueError:
        return False


def _refuse_over(out: Path, option: str, inputs: list, readers: dict[str, str]) -> None:
    """:func:`..io.inputs.refuse_output_over_input` for one output.

    The message says who reads the input (``readers``: path -> who), when it is known.
    """
    from ..errors import BadUsage
    from ..io.inputs import refuse_output_over_input

    def refuse(given):
        refuse_output_over_input(out, inputs=given, option=option)

    try:
        refuse(inputs)
    except BadUsage as exc:
        for given in inputs:  # (on the way out only: which one it was)
            try:
                refuse([given])
            except BadUsage:
                if str(given) in readers:
                    raise BadUsage(f"{exc} ({readers[str(given)]})") from None
                break
        raise


@dataclass
class _Writer:
    """Who writes a file: a step of a scan through one of its options, or a report."""

    what: str  # "step 'conv' (steps[0])", "--report-json"
    step: Step | None = None
    scan: Scan | None = None
    option: str = ""


def _clash(path: Path, new: _Writer, old: _Writer) -> str:
    """Why two writers of one file are refused (one line)."""
    if new.step is not None and old.step is new.step and new.scan != old.scan:
        return (f"{new.option} {path} would be written by every scan ({old.scan.id}, "
                f"{new.scan.id}, ...): put {{stem}} in its name")
    if new.step is not None and old.step is new.step:
        return f"{new.option} {path} is also the step's {old.option} output"
    return f"{path} is also written by {old.what}"


def check_outputs(manifest: Manifest, scans: list[Scan],
                  reports: list[tuple[str, str]] = ()) -> None:
    """Refuse, before any work, an output over an input, or a file written twice.

    An output is every file a step writes (its ``-o``, every output option,
    as :func:`written_files` names them) and the batch's reports
    (``reports``: ``(option, path)``); a step's output its command fills per
    frame or label (:func:`_refuse_patterns`) is refused. An input is a
    scan (any scan's files, a detached header's data files too), a file a
    step reads (its spec, an option's file), the manifest, the scans' table;
    symbolic and hard links are followed
    (:func:`..io.inputs.refuse_output_over_input`). Two steps, two scans or a
    step and a report writing one file are refused too, and so is a detached
    header a scan's name would make unable to name its data file
    (:func:`..io.common.refuse_unnamable_data_file`).
    """
    from ..errors import BadUsage
    from ..io.common import refuse_unnamable_data_file
    from ..io.inputs import input_files
    from ..runscope import Outputs

    scan_files = {os.path.realpath(f): s for s in scans for f in input_files(s.path)}
    fixed = batch_reads(manifest)
    writers = Outputs()  # (real path -> _Writer)
    for step in manifest.steps:
        _refuse_patterns(manifest, step)
    plans = [(scan, plan_scan(manifest, scan)) for scan in scans]
    cells = _cell_reads(plans)
    for scan, scan_plans in plans:
        for plan in scan_plans:
            step = plan.step
            for option, out in plan.writes:
                key = ("steps", step.index, "output" if option == "-o" else "options")
                try:
                    _refuse_over(out, option, [str(scan.path), *map(str, plan.reads), *fixed],
                                 fixed)
                except BadUsage as exc:
                    fixed_name = (option, out) in plan.fixed_outputs  # (every scan's)
                    raise _located(manifest, key, f"{'' if fixed_name else f'scan {scan.id}: '}"
                                                  f"{exc}") from None
                _refuse_over_scans(manifest, key, out, option, scan_files)
                future = _future_scan(manifest, out, option)
                if future is not None:
                    raise _located(manifest, key, future)
                try:
                    refuse_unnamable_data_file(out, option)  # (a scan's name in a .nhdr's)
                    cells.refuse(out, option)
                except BadUsage as exc:
                    raise _located(manifest, key, f"scan {scan.id}: {exc}") from None
                inside = _in_records(manifest, out, option)
                if inside is not None:
                    raise _located(manifest, key, f"scan {scan.id}: {inside}")
                writer = _Writer(f"step {step.name!r} (steps[{step.index}])", step, scan, option)
                _refuse_twice(manifest, key, out, writer, writers)
    _check_reports(manifest, reports, fixed, scan_files, writers, cells)


def _cell_reads(plans):
    """Every file the scans' table cells name (``{reference}``, ``{transform}``), for every scan.

    An output is checked against all of them, not only its own scan's step's:
    scan b's output over scan a's reference, or one step's output over the
    file another step of the same scan reads through its cell, replaced that
    file with exit 0 (a cell naming a file some step writes would also make
    the scans' order matter).
    """
    from ..io.inputs import InputIndex

    index = InputIndex()
    for scan, scan_plans in plans:
        for plan in scan_plans:
            for path in plan.reads:
                index.add(path, f"read by step {plan.step.name!r} for scan {scan.id}")
    return index


def _refuse_patterns(manifest, step: Step) -> None:
    """An output the step's command fills per frame or label, given a pattern (``{{frame}}``).

    Warp's ``--frames-to`` and ``mesh --labels -o`` take patterns: a file per
    frame or label, which batch cannot name before the step runs, so it could
    neither record nor check them (the step ran every time, and a frame
    deleted by hand was never noticed). Only the manifest's value is looked
    at, its placeholders filled: braces in a scan's or a folder's name are
    names, and other options write the name given, braces and all.
    """
    params = dict(step.params)
    for k, option in ((-1, "-o"), *step.writes):
        if not ((step.run == "warp" and option == "--frames-to")
                or (step.run == "mesh" and option == "-o" and params.get("labels"))):
            continue
        value = step.output if k < 0 else step.options[k]
        named = value.format(stem="stem", relpath=".") if placeholders(value) is not None \
            else value
        if _is_pattern(named):
            key = ("steps", step.index, "output" if option == "-o" else "options")
            raise _located(manifest, key, (
                f"{option} {value}: a pattern, which the step fills per frame or label; batch "
                "records and checks every file a step writes and cannot name these before it "
                "runs (leave the option out, or run the command outside batch)"))


def _refuse_over_scans(manifest, key, out: Path, option: str, scan_files: dict) -> None:
    """An output over any scan's file (not only its own scan's)."""
    from ..io.inputs import output_files

    for target in output_files(out):
        other = scan_files.get(os.path.realpath(target))
        if other is not None:
            raise _located(manifest, key, f"{option} {out} would overwrite the scan "
                                          f"{other.id!r} ({other.path}); volwarp never "
                                          "replaces an input")


def _future_scan(manifest, out: Path, option: str) -> str | None:
    """Why ``out`` may not be written: ``inputs.glob`` matches it, outside the output folder.

    (The glob leaves the output folder out.) Written on the first run, it was
    a scan of every later one, and a step writing it was refused from then on
    ("would overwrite the scan"): refused on the first run instead.
    """
    from ..io.inputs import output_files
    from .manifest import glob_pattern, glob_would_match

    pattern = glob_pattern(manifest)
    if pattern is None:
        return None
    folder = os.path.realpath(manifest.output_dir)
    for target in output_files(out):
        real = os.path.realpath(target)
        if real == folder or real.startswith(folder + os.sep):
            continue
        if glob_would_match(pattern, target):
            return (f"{option} {out}: inputs.glob {pattern!r} matches it, so the next run "
                    "would take it for a scan; write it under output_dir (a name with {stem} "
                    "goes there) or name it so that the glob does not match it")
    return None


def _refuse_twice(manifest, key, out: Path, writer: _Writer, writers: dict) -> None:
    """Note ``writer`` of ``out`` (and of the data file it writes); refuse a second writer.

    And an output inside another's store (:func:`..io.inputs.nested_outputs`):
    a step's ``{stem}.ome.zarr/sdf.nrrd`` beside another's ``{stem}.ome.zarr``
    was replaced with the store, or changed the store's content, every step
    of the scan redone at every run.
    """
    from ..io.inputs import NESTED_WHY, nested_outputs, output_files

    for target in output_files(out):
        real = os.path.realpath(target)
        old = writers.get(real)
        if old is not None and not (old.step is writer.step and old.scan == writer.scan
                                    and old.option == writer.option):
            raise manifest.doc.error(key, _clash(target, writer, old))
        for how, path, old in nested_outputs(real, writers):
            raise manifest.doc.error(key, f"{writer.option} {out} {how} {path}, which "
                                          f"{old.what} writes: {NESTED_WHY}")
        writers[real] = writer


def _in_records(manifest, out: Path, option: str) -> str | None:
    """Why ``out`` may not be written: inside the batch's own records (its state, its locks)."""
    from .lock import book_dir

    book = os.path.realpath(book_dir(manifest.output_dir))
    if os.path.realpath(out) == book or os.path.realpath(out).startswith(book + os.sep):
        return (f"{option} {out} is inside the batch's own records ({book}): writing it "
                "would lose what the batch knows of its scans")
    return None


def _check_reports(manifest, reports, fixed, scan_files, writers, cells) -> None:
    """The batch's reports: never over an input, never a file a step (or another report) writes."""
    from ..errors import BadUsage
    from ..io.inputs import NESTED_WHY, InputIndex, nested_outputs

    scan_index = InputIndex()  # (a report inside a scan's folder, a DICOM series: one of it)
    for scan in {id(s): s for s in scan_files.values()}.values():
        scan_index.add(scan.path, f"the scan {scan.id!r}")
    for option, path in reports:
        out = Path(path).absolute()
        _refuse_over(out, option, list(fixed), fixed)
        cells.refuse(out, option)
        scan_index.refuse(out, option)
        for why in (_in_records(manifest, out, option), _future_scan(manifest, out, option)):
            if why is not None:
                raise BadUsage(why)
        other = scan_files.get(os.path.realpath(out))
        if other is not None:
            raise BadUsage(f"{option} {path} would overwrite the scan {other.id!r} "
                           f"({other.path}); volwarp never replaces an input")
        old = writers.get(os.path.realpath(out))
        if old is not None:
            raise BadUsage(f"{option} {path} is also written by {old.what}"
                           + (f" for scan {old.scan.id}" if old.scan is not None else ""))
        for how, held, old in nested_outputs(os.path.realpath(out), writers):
            raise BadUsage(f"{option} {path} {how} {held}, which {old.what} writes: "
                           f"{NESTED_WHY}")
        writers[os.path.realpath(out)] = _Writer(f"{option} {path}")
