"""What one run of a command knows about its files: its inputs and the permissions it was given.

A command must not write an output over one of its own inputs, nor rename
an output made from a mapped input that another program changed meanwhile
(:mod:`.io.mapped`), and ``--allow-outside-data`` lets its readers open a
detached header's data file elsewhere. These facts belong to one run, not
to the process: a caller that runs several commands (a test session, a Dask
worker, a library user's threads) must not carry one run's inputs or
permission into the next. :func:`run_scope` gives a run its own
:class:`RunFiles`, in a context variable; code outside any scope shares the
process's (a library call that reads and writes volumes directly).

Standard library only: the command line enters a scope before it imports
numpy.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
from dataclasses import dataclass, field


class Outputs(dict):
    """Each output (its real path) -> who writes it; ``holding``: each folder above one -> it.

    So that an output folder (an OME-Zarr store) holding an output named
    before it is found by one lookup (:func:`volwarp_cli.io.inputs.nested_outputs`),
    not a pass over every output (a batch's thousands).
    """

    def __init__(self) -> None:
        super().__init__()
        self.holding: dict[str, str] = {}

    def __setitem__(self, real: str, who) -> None:
        super().__setitem__(real, who)
        folder, parent = real, os.path.dirname(real)
        while parent not in self.holding and parent != folder:  # (its own are there already)
            self.holding[parent] = real
            folder, parent = parent, os.path.dirname(parent)

    def setdefault(self, real: str, who=None):
        """As dict's, through :meth:`__setitem__` (dict's own would go round it)."""
        if real not in self:
            self[real] = who
        return self[real]


@dataclass
class RunFiles:
    """The files of one run.

    ``inputs``: (device, inode) of every file read as an input; ``declared``:
    the input paths the command line and the specs named, before any was
    read (:mod:`volwarp_cli.io.inputs`), and ``expanded``: each one's files;
    ``mapped``: path -> ((size, mtime_ns, inode), ctime_ns, a hash of sampled
    pieces) of each input read as the work goes (by ``pread`` or a memory map),
    when it was opened (:mod:`.io.mapped`), and ``folders``: name -> (folder,
    the folder read under it, their identity) of each folder input read file by
    file as the work goes (an OME-Zarr store); ``allow_outside_data``: detached headers
    may read data files outside their own folder; ``dry_run``: the command runs
    its checks only, and stops at its first read of an input
    (:func:`stop_if_dry_run`); ``said``: the warnings a run says once;
    ``ends``: what the run removes when it ends (:func:`at_run_end`); ``copies``:
    its inputs' scratch copies (:mod:`volwarp_cli.io.inflated`), by file;
    ``decided``: choices the run makes once and must keep (an OME-Zarr output's
    staging, weighed before its blocks run and taken when it is opened);
    ``folder``: where the run's relative names inside files are taken from
    (an elastix file's initial transform: where elastix ran), None for the
    process's folder (a batch's dry run of a step stands in for the step,
    which runs in the manifest's folder).
    """

    inputs: set[tuple[int, int]] = field(default_factory=set)
    declared: dict[str, None] = field(default_factory=dict)
    expanded: dict[str, list] = field(default_factory=dict)
    #: each output file (links followed) and the option that named it, as checked
    claimed: Outputs = field(default_factory=Outputs)
    mapped: dict[str, tuple] = field(default_factory=dict)
    folders: dict[str, tuple] = field(default_factory=dict)
    allow_outside_data: bool = False
    dry_run: bool = False
    said: set = field(default_factory=set)
    ends: list = field(default_factory=list)
    copies: dict = field(default_factory=dict)
    decided: dict = field(default_factory=dict)
    #: the glob patterns of the run's inputs (a sweep's template frames ``fr_*.png``)
    globs: list = field(default_factory=list)
    #: the numbered output patterns (``--frames-to``, a morph's frames) and their options
    patterns: list = field(default_factory=list)
    #: the outputs renamed into place, in order (``io.atomic.outputs_together``)
    committed: list = field(default_factory=list)
    folder: str | None = None


class DryRunStop(BaseException):  # noqa: N818 - a stop, not an error
    """A dry run reached its first read of an input: every check before it passed.

    A BaseException, so that no ``except Exception`` of a command takes it for
    a failure of the read (``volwarp batch`` checks each step this way).
    """


def stop_if_dry_run(path) -> None:
    """At each reader's entry: a dry run ends here, before anything is read.

    So a command run for its checks only (its options' cross-checks, its
    outputs' names) never reads a volume, and never gets to write one.
    """
    if run_files().dry_run:
        raise DryRunStop(str(path))


_process = RunFiles()
_current: contextvars.ContextVar[RunFiles | None] = contextvars.ContextVar(
    "volwarp_run_files", default=None)


def run_files() -> RunFiles:
    """The current run's files (the process's outside any :func:`run_scope`)."""
    return _current.get() or _process


#: the runs under way in this process, by :func:`current_run_id` (a block task of a
#: thread pool has no context of its run: it enters it by this number, :func:`enter_run`)
_runs: dict[int, RunFiles] = {}


@contextlib.contextmanager
def run_scope():
    """A fresh :class:`RunFiles` for the code inside (and the threads it hands its context to)."""
    token = _current.set(RunFiles())
    files = _current.get()
    _runs[id(files)] = files
    try:
        yield files
    finally:
        _current.reset(token)
        _runs.pop(id(files), None)
        _run_ends(files)


def current_run_id() -> int | None:
    """A number naming the current run in this process (None outside any :func:`run_scope`)."""
    files = _current.get()
    return None if files is None else id(files)


@contextlib.contextmanager
def enter_run(run_id: int | None):
    """Inside, :func:`run_files` is the run ``run_id`` names, where it is under way here.

    For a block task that a thread pool runs outside its run's context (Dask's
    threads): its warnings are said once a run, its notes gathered with the
    run's. Yields whether it entered (not in another process, nor outside a run).
    """
    files = _runs.get(run_id) if run_id is not None else None
    if files is None or _current.get() is files:
        yield files is not None
        return
    token = _current.set(files)
    try:
        yield True
    finally:
        _current.reset(token)


def at_run_end(end) -> None:
    """Call ``end()`` when the current run ends (outside any :func:`run_scope`: at exit).

    For what a run makes for itself and must not outlive it (an input
    inflated to a scratch file): a batch that runs many scans in one process
    removes each one's when that scan's run ends.
    """
    files = _current.get()
    if files is None:
        import atexit

        atexit.register(end)
    else:
        files.ends.append(end)


def in_run() -> bool:
    """Whether the code runs inside a :func:`run_scope` (a command's run, a batch scan)."""
    return _current.get() is not None


#: a library call's warnings outside any run (:func:`call_scope`)
_call: contextvars.ContextVar[RunFiles | None] = contextvars.ContextVar("volwarp_call",
                                                                         default=None)


@contextlib.contextmanager
def call_scope():
    """A library call (:mod:`volwarp_cli.api`) outside any run: its warnings said as a command's.

    A command says a warning once a run (:func:`first_said`) and the notes
    gathered over its blocks (:mod:`volwarp_cli.samples`: a cast's reach, an
    output all background) when it ends. Outside a run these were said at
    every block, or never: a warp cast to uint8 said its clipping once a plane
    group, a sweep beside its grid returned zeros without a word. Inside, they
    are the call's (:func:`said_files`), its notes said when it returns (not
    when it raises: its error is what it says). Its files stay the process's
    (:func:`run_files`): what one call read, the next does not overwrite. A
    call inside a run, or inside another call, is theirs.
    """
    if _current.get() is not None or _call.get() is not None:
        yield
        return
    call = RunFiles()
    token = _call.set(call)
    try:
        yield
    finally:
        _call.reset(token)
    call.committed.append(None)  # (its outputs: the values it returns)
    _run_ends(call)


def said_files() -> RunFiles | None:
    """Where warnings are said once and notes gathered: the run's, a library call's, or None."""
    return _current.get() or _call.get()


def first_said(key) -> bool:
    """True the first time ``key`` is asked in this run or library call (said once).

    Always True outside both: a script's every call says it.
    """
    files = said_files()
    if files is None:
        return True
    if key in files.said:
        return False
    files.said.add(key)
    return True


def _run_ends(files: RunFiles) -> None:
    ends, files.ends = files.ends, []
    for end in reversed(ends):
        with contextlib.suppress(Exception):  # (a failed cleanup must not hide the result)
            end()
