"""Running the scans: one scan's steps (the same code on a local pool and on a cluster).

A scan's steps are run by a :class:`ScanRunner`: every step as ``python -P -m
volwarp_cli RUN ...`` in a child process (in the manifest's folder, so relative
paths in options are the manifest's), so a crash, a memory blow-up or a stop of
one scan cannot take the others down. The last line of a failed step's stderr is
its error; the child's peak resident memory comes from ``wait4`` (its own
``ru_maxrss``). A child is asked to stop (SIGTERM: it removes its temporaries)
when the thread that started it dies with its process (``PR_SET_PDEATHSIG``):
a killed batch or a killed cluster worker leaves no step running on and no
partial file.

:class:`Batch` is the local pool: each scan one task of a pool of ``jobs``
threads of the batch process, each waiting on its own child. The cluster form
(:mod:`.cluster`) submits each scan as one task whose worker runs the same
:class:`ScanRunner`.

- A scan whose folder is still arriving (:func:`..plan.still_arriving`: its newest
  file younger than the manifest's settle time) is not read: its status says
  so (:data:`ARRIVING`), nothing is recorded, and the next run takes it.
- Up-to-date steps are skipped (:func:`..plan.stale_reason`: by the content of
  what they read, never by dates) unless ``force``; a step whose input step ran
  runs when that input's bytes changed. A step during which a file it reads
  was replaced or rewritten (:func:`..plan.changed_while_run`) fails, its
  outputs not recorded: hashed before it ran, they may not be what it read.
- A failed step fails its scan; the steps that depend on it are not run, the
  scan's other steps are (``make -k``). ``fail_fast``: no new scan starts after a
  failure; running ones finish.
- ``retries``: a step whose process died of a signal (exit code < 0: SIGKILL from
  the out-of-memory killer, SIGSEGV) is run again, up to that many times; a
  step that failed (exit 1, 2) or was stopped never is.
- SIGINT / SIGTERM (SIGHUP, SIGQUIT, SIGUSR1, ...: :data:`~volwarp_cli.signals.STOPS`) to the
  batch: no new step starts, the running ones get the
  same signal (each leaves its old outputs, as every volwarp command
  guarantees), and :meth:`Batch.run` returns with the signal number. A second
  stop kills the children at once.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field

from ..io.atomic import COMMITTED_LOG, committed_in
from ..memory import MEMORY_ENV
from ..parallel import THREADS_ENV
from ..signals import STOPS, stops
from .manifest import SCAN, Manifest, Scan
from .plan import (
    CommandRecord,
    Replaced,
    StepPlan,
    changed_while_run,
    made_from,
    plan_scan,
    read_stamps,
    stale_reason,
    still_arriving,
)

#: seconds a stopped child is given before it is killed
STOP_GRACE = 20.0
_STOP_CODES = tuple(128 + s for s in STOPS)
#: the status of a scan whose folder is still arriving (read by a later run)
ARRIVING = "still arriving"
#: Linux's prctl option asking for a signal when the parent (thread) dies
_PR_SET_PDEATHSIG = 1
#: Python's option leaving the working folder off ``sys.path`` (3.11+: ``PYTHONSAFEPATH``)
_SAFE_PATH = "-P"
#: the child's first lines: SIGTERM when its parent dies, then ``volwarp`` itself
_BOOT = (
    "import ctypes, os, signal, sys\n"
    "ppid = int(sys.argv.pop(1))\n"
    "ctypes.CDLL(None, use_errno=True).prctl(" + str(_PR_SET_PDEATHSIG) + ", signal.SIGTERM)\n"
    "if os.getppid() != ppid: os.kill(os.getpid(), signal.SIGTERM)\n"
    "import runpy\n"
    "runpy.run_module({module!r}, run_name='__main__', alter_sys=True)\n"
)


@dataclass
class StepResult:
    """How one step of one scan went: status, time, attempts, exit code, error line, command."""

    name: str
    run: str
    status: str  # ok | skipped | failed | not run | stopped
    seconds: float = 0.0
    error: str | None = None
    attempts: int = 0
    exit_code: int | None = None
    command: list[str] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)
    reason: str | None = None  # why it ran (or None: forced, or skipped)
    peak_rss: int | None = None  # bytes: the step process's peak resident memory
    made: dict | None = None  # the record of its outputs, when it ran and made them all
    #: its warning lines (``volwarp: warning:`` taken off); a skipped step's: those of the
    #: run that made its outputs, kept in the record
    warnings: list[str] = field(default_factory=list)


@dataclass
class ScanResult:
    """How one scan went: its status, time and the result of each of its steps."""

    scan: Scan
    status: str  # ok | skipped | failed | stopped | not started | still arriving
    seconds: float = 0.0
    steps: list[StepResult] = field(default_factory=list)
    attempts: int = 1  # runs of the scan's task (more than one: its worker died)
    worker: str | None = None  # the cluster worker that ran it (None: the local pool)
    #: ``{"input": PNG bytes or None, "outputs": [(name, PNG bytes), ...]}`` (--report html)
    thumbnails: dict | None = None
    #: file hashes computed on a cluster worker, for the batch process's cache
    hashed: dict | None = None
    #: why a scan still arriving was not read (``newest file 3 s old, settle 60 s``)
    reason: str | None = None

    @property
    def error(self) -> str | None:
        """The error line of the scan's first failed step, or None."""
        return next((s.error for s in self.steps if s.status == "failed"), None)

    @property
    def peak_rss(self) -> int | None:
        """The largest peak resident memory of the scan's step processes (bytes), or None."""
        peaks = [s.peak_rss for s in self.steps if s.peak_rss is not None]
        return max(peaks) if peaks else None


def _scan_status(steps: list[StepResult]) -> str:
    """A scan's status from its steps': failed, stopped, ok (one ran) or skipped."""
    statuses = {s.status for s in steps}
    for status in ("failed", "stopped", "ok"):
        if status in statuses:
            return status
    return "skipped"


def volwarp_argv(argv: list[str]) -> list[str]:
    """The command line that runs ``volwarp ARGV`` with this interpreter (see :func:`child_argv`)."""
    return [sys.executable, _SAFE_PATH, "-m", "volwarp_cli", *argv]


def child_argv(argv: list[str], module: str = "volwarp_cli") -> list[str]:
    """``python -P -m MODULE ARGV``, made to stop (SIGTERM) if this process dies first (Linux).

    ``-P``: a step runs in the manifest's folder, and ``-c``/``-m`` would put
    that folder first on ``sys.path``, so a ``numpy.py`` or a ``volwarp_cli/``
    lying beside the manifest would run instead of the real one (its output
    recorded as the step's). ``PYTHONPATH`` still counts.
    """
    if not sys.platform.startswith("linux"):
        return [sys.executable, _SAFE_PATH, "-m", module, *argv]
    return [sys.executable, _SAFE_PATH, "-c", _BOOT.replace("{module!r}", repr(module)),
            str(os.getpid()), *argv]


#: how a step's warning lines start (:mod:`volwarp_cli.progress`'s formatter)
WARNING_PREFIX = "volwarp: warning: "


def step_warnings(text: str) -> list[str]:
    """The warning lines of a step's stderr, their prefix taken off, each once, in order.

    A step warns where its output is written but may not be what was meant
    (every voxel the background, a label in no output voxel, samples clipped):
    the batch ran its steps with ``-q`` and said nothing of them, "2 ok".
    """
    out: list[str] = []
    for line in text.splitlines():
        line = line.strip()
        if line.startswith(WARNING_PREFIX) and line[len(WARNING_PREFIX):] not in out:
            out.append(line[len(WARNING_PREFIX):])
    return out


def last_line(text: str) -> str | None:
    """The last non-blank line of ``text`` that is no warning (a failed step's error), or None.

    A step killed (the out-of-memory killer) after a warning writes no error
    line: its warning is not why it failed, and is kept as a warning.
    """
    lines = [line.strip() for line in text.splitlines()
             if line.strip() and not line.strip().startswith(WARNING_PREFIX)]
    return lines[-1] if lines else None


class Children:
    """The child processes of one batch (or of one run on one cluster worker), to stop them.

    A child is reaped with ``wait4`` for its peak memory; it leaves the set of
    running children before it is reaped, so a stop never signals a reused pid.
    """

    def __init__(self):
        self.lock = threading.Lock()
        self.running: set[subprocess.Popen] = set()
        self.stopping: int | None = None

    def start(self, cmd: list[str], **popen) -> subprocess.Popen | None:
        """Start ``cmd`` (stdin and stdout closed, stderr piped), or None when stopping."""
        with self.lock:
            if self.stopping is not None:
                return None
            popen.setdefault("stdout", subprocess.DEVNULL)
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                    **popen)
            self.running.add(proc)
        return proc

    def finish(self, proc: subprocess.Popen) -> tuple[int, bytes, bytes, int | None]:
        """Wait for ``proc``: ``(exit code, stdout, stderr, peak resident bytes)``."""
        try:
            out = b""
            if proc.stdout is not None:  # (communicate would reap the child itself)
                got: list[bytes] = []
                reader = threading.Thread(target=lambda: got.append(proc.stderr.read()),
                                          daemon=True)
                reader.start()
                out = proc.stdout.read()
                reader.join()
                err = got[0] if got else b""
            else:
                err = proc.stderr.read()
            os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOWAIT)
        finally:
            with self.lock:
                self.running.discard(proc)
        peak = None
        try:
            _, status, usage = os.wait4(proc.pid, 0)
            proc.returncode = os.waitstatus_to_exitcode(status)
            peak = int(usage.ru_maxrss) * 1024  # KiB on Linux
        except ChildProcessError:  # reaped elsewhere
            proc.wait()
        for pipe in (proc.stdout, proc.stderr):
            if pipe is not None:
                pipe.close()
        return proc.returncode, out or b"", err or b"", peak

    def signal(self, signum: int) -> None:
        """Send ``signum`` to every running child."""
        with self.lock:
            for proc in self.running:
                try:
                    os.kill(proc.pid, signum)
                except OSError:  # already gone
                    pass

    def stop(self, signum: int) -> None:
        """No new child starts; the running ones get ``signum``."""
        with self.lock:
            if self.stopping is None:
                self.stopping = signum
        self.signal(signum)


class ScanRunner:
    """One scan's steps, run in order as child processes (the local pool's and a worker's).

    ``record`` tells what each output was made from and keeps the file hash
    cache (:class:`..plan.CommandRecord`, or a snapshot of it on a worker),
    and notes each step that ran; ``ships_hashes``: the result carries the
    hashes this runner computed (a cluster task's, for the batch process's
    cache); ``thumbnails``: after the steps, small PNG
    renders of the scan and of its outputs for the HTML report (in a child
    process too, see :mod:`.thumbs`); ``on_start``: called with the scan as
    its first step is considered.
    """

    def __init__(self, manifest: Manifest, *, force: bool = False, retries: int = 0,
                 child_threads: int = 1, child_memory: int | None = None,
                 memory_from: str = "memory limit", record: CommandRecord | None = None,
                 children: Children | None = None, thumbnails: bool = False, on_start=None,
                 ships_hashes: bool = False):
        self.manifest = manifest
        self.ships_hashes = ships_hashes  # (a cluster task: its result carries its hashes)
        self.force = force
        self.retries = retries
        self.child_threads = child_threads
        self.child_memory = child_memory
        self.memory_from = memory_from  # (what child_memory is a share of, for messages)
        self.record = record if record is not None else CommandRecord(manifest)
        self.children = children if children is not None else Children()
        self.thumbnails = thumbnails
        self.on_start = on_start

    @property
    def stopping(self) -> int | None:
        """The stop's signal number, once the batch is stopping."""
        return self.children.stopping

    def run(self, scan: Scan) -> ScanResult:
        """Run (or skip) each of the scan's steps; the scan's :class:`ScanResult`."""
        if self.stopping is not None:
            return ScanResult(scan, "not started")
        if self.on_start is not None:
            self.on_start(scan)
        start = time.monotonic()
        arriving = still_arriving(self.manifest, scan)
        if arriving is not None:
            return ScanResult(scan, ARRIVING, time.monotonic() - start, reason=arriving,
                              hashed={} if self.ships_hashes else None)
        plans = plan_scan(self.manifest, scan)
        results: dict[str, StepResult] = {}
        for plan in plans:
            step = plan.step
            res = StepResult(step.name, step.run, "not run", command=["volwarp", *plan.argv],
                             outputs=[str(p) for p in plan.made])
            results[step.name] = res
            upstream = results.get(step.input) if step.input != SCAN else None
            if upstream is not None and upstream.status in ("failed", "not run", "stopped"):
                continue  # its input was not made
            if self.stopping is not None:
                res.status = "stopped"
                continue
            stamps = read_stamps(self.manifest, plan)  # (before the hashes they vouch for)
            made = self._consider(plan, res)
            if res.status == "skipped":
                continue
            committed = self._run_step(plan, res)
            if res.status == "ok" and made is not None:
                changed = changed_while_run(self.manifest, plan, stamps)
                try:
                    if changed is None:
                        res.made = self.record.entries(plan, made, committed, res.warnings)
                    else:  # (what it read is unknown: the next run makes it again)
                        res.status, res.error = "failed", changed
                except Replaced as exc:
                    res.status, res.error = "failed", str(exc)
                if res.made is not None:
                    self.record.keep(res.made)
        steps = list(results.values())
        result = ScanResult(scan, _scan_status(steps), time.monotonic() - start, steps)
        if self.thumbnails and result.status != "stopped" and self.stopping is None:
            result.thumbnails = self._thumbnails(scan, plans)
        result.hashed = dict(self.record.hashes.fresh) if self.ships_hashes else None
        return result

    def _consider(self, plan: StepPlan, res: StepResult) -> dict | None:
        """What the step would be made from (None: an input is missing); skips it when current."""
        try:
            made = made_from(self.manifest, plan, self.record.hashes)
        except OSError as exc:  # the step runs, and says what is wrong
            res.reason = f"{exc.filename or exc}: {exc.strerror or 'cannot be read'}"
            return None
        if not self.force:
            res.reason = stale_reason(self.manifest, plan, self.record, made)
            if res.reason is None:
                res.status = "skipped"
                entry = self.record.entry(plan.made[0]) if plan.made else None
                res.warnings = list((entry or {}).get("warnings", []))
        return made

    def _run_step(self, plan: StepPlan, res: StepResult) -> dict:
        """Run the step (retried where it was killed): the outputs it renamed into place.

        Their identities by absolute path (the last attempt's), as :meth:`_call` gives them.
        """
        committed: dict = {}
        for out in plan.outputs:
            try:
                out.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                res.status, res.error = "failed", f"{out.parent}: {exc.strerror or exc}"
                return committed
        start = time.monotonic()
        while True:
            res.attempts += 1
            code, stderr, peak, committed = self._call(plan.argv)
            res.exit_code = code
            res.warnings = step_warnings(stderr)
            res.seconds = time.monotonic() - start
            if peak is not None:
                res.peak_rss = max(peak, res.peak_rss or 0)
            if code is None:  # not started: the batch is stopping
                res.status = "stopped"
                return committed
            if code == 0:
                res.status, res.error = "ok", None
                return committed
            if code in _STOP_CODES or code < 0:
                # a terminal's Ctrl-C reaches the children with the batch: give the
                # batch's own handler a moment to say it was a stop
                for _ in range(20):
                    if self.stopping is not None:
                        res.status, res.error = "stopped", None
                        return committed
                    time.sleep(0.01)
            res.error = last_line(stderr)
            if code < 0:
                name = signal.Signals(-code).name if -code in signal.valid_signals() else -code
                res.error = f"killed by {name}" + (f" ({res.error})" if res.error else "")
                if res.attempts <= self.retries:
                    continue
            res.status = "failed"
            if res.error is None:
                res.error = f"exit code {code}"
            return committed

    def _env(self, threads: int) -> dict:
        """A child's environment: its threads, and this scan's share of the batch's limit.

        The share only lowers a limit the environment already sets (a cluster
        worker's own ``VOLWARP_MEMORY_LIMIT``: its host's), never raises it.
        """
        from ..memory import MEMORY_FROM_ENV, parse_size

        env = dict(os.environ, **{THREADS_ENV: str(threads)})
        if self.child_memory is not None:
            own = env.get(MEMORY_ENV, "").strip()
            try:
                own = parse_size(own) if own else None
            except ValueError:
                return env  # (kept as it is: the step refuses it itself, naming it)
            if own is None or self.child_memory < own:
                env[MEMORY_ENV] = str(self.child_memory)
                env[MEMORY_FROM_ENV] = (f"{MEMORY_ENV}, this scan's share of the batch's "
                                        f"{self.memory_from}")
        return env

    def _call(self, argv: list[str]) -> tuple[int | None, str, int | None, dict]:
        """Run ``volwarp ARGV``: ``(exit code or None if not started, stderr, peak, renamed)``.

        ``peak``: its peak resident bytes; ``renamed``: the identities of the
        outputs it renamed into place (:func:`~volwarp_cli.io.atomic.note_committed`),
        by absolute path.
        """
        import tempfile

        env = self._env(self.child_threads)
        log = None
        with contextlib.suppress(OSError):  # (none to be had: outputs recorded as they are)
            fd, log = tempfile.mkstemp(prefix=".volwarp-committed-", suffix=".jsonl")
            os.close(fd)
            env[COMMITTED_LOG] = log
        try:
            proc = self.children.start(child_argv(argv), cwd=self.manifest.base, env=env)
            if proc is None:
                return None, "", None, {}
            code, _, err, peak = self.children.finish(proc)
            return code, err.decode("utf-8", "replace"), peak, committed_in(log)
        finally:
            if log is not None:
                with contextlib.suppress(OSError):
                    os.unlink(log)

    def _thumbnails(self, scan: Scan, plans: list[StepPlan]) -> dict | None:
        from . import thumbs

        files = [str(scan.path.absolute())]
        names = []
        for plan in plans:
            for out in plan.outputs:
                if thumbs.can_preview(out) and out.is_file():
                    files.append(str(out.absolute()))
                    names.append(os.path.relpath(out, self.manifest.output_dir))
        env = self._env(1)  # (its reads held to the scan's share too)
        proc = self.children.start(thumbs.command(files), cwd=self.manifest.base, env=env,
                                   stdout=subprocess.PIPE)
        if proc is None:
            return None
        code, out, _, _ = self.children.finish(proc)
        pngs = thumbs.parse_output(out) if code == 0 else [None] * len(files)
        return {"input": pngs[0], "outputs": [(n, p) for n, p in zip(names, pngs[1:],
                                                                    strict=True)]}


class Batch:
    """The scans of a manifest run through its steps by a local pool of ``jobs`` workers."""

    def __init__(self, manifest: Manifest, scans: list[Scan], *, jobs: int, force: bool = False,
                 fail_fast: bool = False, retries: int = 0, on_scan=None, on_start=None,
                 thumbnails: bool = False):
        self.manifest = manifest
        self.scans = scans
        self.jobs = max(1, jobs)
        self.fail_fast = fail_fast
        self.on_scan = on_scan  # called with each ScanResult as it ends (any thread)
        self._children = Children()
        self._failed = False
        self._signals: list[int] = []  # appended by the signal handler only
        # VOLWARP_THREADS of each scan's commands (a step's own --threads wins), and their
        # memory: shared by the scans that run at once
        at_once = min(self.jobs, max(1, len(scans)))
        memory, memory_from = child_memory(at_once)
        self.runner = ScanRunner(manifest, force=force, retries=retries,
                                 child_threads=child_threads(at_once),
                                 child_memory=memory, memory_from=memory_from,
                                 record=CommandRecord(manifest), children=self._children,
                                 thumbnails=thumbnails, on_start=on_start)

    @property
    def _stopping(self) -> int | None:
        return self._children.stopping

    # --- the main thread -----------------------------------------------------------------

    def run(self) -> tuple[list[ScanResult], int | None]:
        """Run every scan; ``(results in scan order, the stop's signal number or None)``."""
        handlers = install_stop_handlers(self._signals)
        try:
            results = self._pool()
        finally:
            restore_handlers(handlers)
            self.runner.record.flush()
        return results, self._stopping

    def _pool(self) -> list[ScanResult]:
        killed_at = None
        with ThreadPoolExecutor(max_workers=min(self.jobs, max(1, len(self.scans))),
                                thread_name_prefix="volwarp-batch") as pool:
            # (each in the batch's own context: its run's files, not the process's, so that
            # what other code of this process read never stands in the way of state.json)
            futures = [pool.submit(contextvars.copy_context().run, self._guarded, scan)
                       for scan in self.scans]
            pending = set(futures)
            while pending:
                _, pending = wait(pending, timeout=0.05)
                if self._signals and self._stopping is None:
                    self._children.stop(self._signals[0])
                    killed_at = time.monotonic() + STOP_GRACE
                if self._stopping is not None and (
                        len(self._signals) > 1 or time.monotonic() > killed_at):
                    self._children.signal(signal.SIGKILL)
        return [f.result() for f in futures]

    # --- the workers -----------------------------------------------------------------------

    def _guarded(self, scan: Scan) -> ScanResult:
        try:
            if self.fail_fast and self._failed:
                result = ScanResult(scan, "not started")
            else:
                result = self.runner.run(scan)
        except Exception as exc:  # a bug of the batch itself: that scan fails, not the batch
            result = ScanResult(scan, "failed", steps=[StepResult(
                "-", "-", "failed", error=f"internal error: {type(exc).__name__}: {exc}")])
        if result.status == "failed":
            self._failed = True
        if self.on_scan is not None:
            self.on_scan(result)
        return result


def install_stop_handlers(signals: list[int]):
    """The stops (:func:`volwarp_cli.signals.stops`) append their number to ``signals``.

    Main thread only; returns the old handlers.
    """
    if threading.current_thread() is not threading.main_thread():
        return None
    old = {s: signal.getsignal(s) for s in stops()}
    for s in old:
        signal.signal(s, lambda signum, frame: signals.append(signum))
    return old


def restore_handlers(handlers) -> None:
    """Put back the handlers :func:`install_stop_handlers` replaced."""
    for s, h in (handlers or {}).items():
        signal.signal(s, h)


def default_jobs() -> int:
    """The threads in effect, one scan per thread.

    That is ``--threads``, ``VOLWARP_THREADS``, else the cores this process may use:
    its affinity and cgroup quota.
    """
    from .. import parallel

    return parallel.threads()


def child_memory(at_once: int) -> tuple[int | None, str]:
    """Each scan's step processes' memory limit: an explicit limit shared by the scans at once.

    ``(bytes or None, what they are a share of)``. None without an explicit
    limit (``--memory-limit``, ``VOLWARP_MEMORY_LIMIT``): each step then weighs
    what the machine and its cgroup leave when it starts. Given, the batch's
    limit is the machine's for every scan running at once (what this process
    holds taken off first), never each step's whole (a pool of four scans
    under 8G: 2G each, less the batch's own share); an
    :class:`~volwarp_cli.errors.OutOfMemoryError` where this process alone
    holds it all.
    """
    from .. import memory
    from ..errors import OutOfMemoryError

    limit = memory.explicit_limit()
    if limit is None:
        return None, ""
    held = memory.process_rss()
    if limit <= held:
        raise OutOfMemoryError(f"the memory limit ({memory.human_bytes(limit)}) leaves nothing "
                               f"for the scans' steps: this batch process holds "
                               f"{memory.human_bytes(held)}")
    what = (f"memory limit {memory.human_bytes(limit)}, {at_once} "
            f"scan{'s' if at_once > 1 else ''} at once")
    return max(1, (limit - held) // max(1, at_once)), what


def child_threads(jobs: int) -> int:
    """Threads each scan's command gets: the threads in effect shared by ``jobs`` scans at once.

    At least one, so that a batch never runs more threads than it was given.
    """
    from .. import parallel

    return max(1, parallel.threads() // max(1, jobs))


@dataclass(frozen=True)
class Where:
    """Where a batch's scans run.

    ``scheduler`` None: the local pool of ``jobs`` threads (default
    :func:`default_jobs`); else the cluster's
    :class:`~volwarp_cli.engine.SchedulerChoice`, ``workers`` and
    ``threads_per_worker`` those of a ``local`` one (:func:`.cluster.run_on_cluster`).
    """

    scheduler: object = None
    jobs: int | None = None
    workers: int | None = None
    threads_per_worker: int | None = None


def run_batch(manifest: Manifest, scans: list[Scan], where: Where, progress, *,
              shard: tuple[int, int, int] | None = None, **options):
    """Run ``scans`` where ``where`` says: the run's :class:`.report.Report`.

    ``progress``: the :class:`.report.ScanProgress` told as scans start and
    end (closed here); ``shard``: ``(I, N, scans in all)``, for the report;
    ``options``: :class:`Batch`'s ``force``, ``fail_fast``, ``retries``,
    ``thumbnails``.
    """
    from .report import Report

    options = dict(options, on_scan=progress.end)
    try:
        if where.scheduler is None:
            jobs = where.jobs or default_jobs()
            results, stop = Batch(manifest, scans, jobs=jobs, on_start=progress.start,
                                  **options).run()
            scheduler = "pool"
        else:
            from .cluster import run_on_cluster

            results, stop, jobs = run_on_cluster(manifest, scans, where,
                                                 on_start=progress.start, **options)
            scheduler = where.scheduler.describe()
    finally:
        progress.close()
    return Report(results, stop, jobs=jobs, scheduler=scheduler, shard=shard)

