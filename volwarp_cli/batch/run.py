"""Running the scans: a local pool, one subprocess per step, stops and retries.

Each scan is one task of a pool of ``jobs`` workers (threads of the batch
process, each waiting on its own child): every step runs as ``python -m
volwarp_cli RUN ...`` in a child process (in the manifest's folder, so relative
paths in options are the manifest's), so a crash, a memory blow-up or a stop of
one scan cannot take the others down. The last line of a failed step's stderr is
its error.

- Up-to-date steps are skipped (:func:`..plan.stale_reason`) unless ``force``; a
  step whose input step ran, runs.
- A failed step fails its scan; the steps that depend on it are not run, the
  scan's other steps are (``make -k``). ``fail_fast``: no new scan starts after a
  failure; running ones finish.
- ``retries``: a step whose process died of a signal (exit code < 0: SIGKILL from
  the out-of-memory killer, SIGSEGV) is run again, up to that many times; a
  step that failed (exit 1, 2) or was stopped never is.
- SIGINT / SIGTERM to the batch: no new step starts, the running ones get the
  same signal (each leaves its old outputs, as every volwarp command
  guarantees), and :meth:`Batch.run` returns with the signal number. A second
  stop kills the children at once.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field

from ..parallel import THREADS_ENV
from .manifest import SCAN, Manifest, Scan
from .plan import CommandRecord, StepPlan, plan_scan, stale_reason

#: seconds a stopped child is given before it is killed
STOP_GRACE = 20.0
_STOP_CODES = (128 + signal.SIGINT, 128 + signal.SIGTERM)


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


@dataclass
class ScanResult:
    """How one scan went: its status, time and the result of each of its steps."""

    scan: Scan
    status: str  # ok | skipped | failed | stopped | not started
    seconds: float = 0.0
    steps: list[StepResult] = field(default_factory=list)

    @property
    def error(self) -> str | None:
        """The error line of the scan's first failed step, or None."""
        return next((s.error for s in self.steps if s.status == "failed"), None)


def volwarp_argv(argv: list[str]) -> list[str]:
    """The command line that runs ``volwarp ARGV`` with this interpreter."""
    return [sys.executable, "-m", "volwarp_cli", *argv]


def last_line(text: str) -> str | None:
    """The last non-blank line of ``text`` (stripped; a failed step's error), or None."""
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else None


class Batch:
    """The scans of a manifest run through its steps by a pool of ``jobs`` workers."""

    def __init__(self, manifest: Manifest, scans: list[Scan], *, jobs: int, force: bool = False,
                 fail_fast: bool = False, retries: int = 0, on_scan=None):
        self.manifest = manifest
        self.scans = scans
        self.jobs = max(1, jobs)
        #: VOLWARP_THREADS of each scan's commands (a step's own --threads wins)
        self.child_threads = child_threads(self.jobs)
        self.force = force
        self.fail_fast = fail_fast
        self.retries = retries
        self.on_scan = on_scan  # called with each ScanResult as it ends (any thread)
        self._lock = threading.Lock()
        self._running: set[subprocess.Popen] = set()
        self._stopping: int | None = None
        self._failed = False
        self._signals: list[int] = []  # appended by the signal handler only
        self._record = CommandRecord(manifest)

    # --- the main thread -----------------------------------------------------------------

    def run(self) -> tuple[list[ScanResult], int | None]:
        """Run every scan; ``(results in scan order, the stop's signal number or None)``."""
        handlers = self._install()
        try:
            results = self._pool()
        finally:
            self._restore(handlers)
        return results, self._stopping

    def _install(self):
        if threading.current_thread() is not threading.main_thread():
            return None
        old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        for s in old:
            signal.signal(s, lambda signum, frame: self._signals.append(signum))
        return old

    @staticmethod
    def _restore(handlers) -> None:
        for s, h in (handlers or {}).items():
            signal.signal(s, h)

    def _pool(self) -> list[ScanResult]:
        killed_at = None
        with ThreadPoolExecutor(max_workers=min(self.jobs, max(1, len(self.scans))),
                                thread_name_prefix="volwarp-batch") as pool:
            futures = [pool.submit(self._guarded, scan) for scan in self.scans]
            pending = set(futures)
            while pending:
                _, pending = wait(pending, timeout=0.05)
                if self._signals and self._stopping is None:
                    self._stop(self._signals[0])
                    killed_at = time.monotonic() + STOP_GRACE
                if self._stopping is not None and (
                        len(self._signals) > 1 or time.monotonic() > killed_at):
                    self._signal_children(signal.SIGKILL)
        return [f.result() for f in futures]

    def _stop(self, signum: int) -> None:
        with self._lock:
            self._stopping = signum
        self._signal_children(signum)

    def _signal_children(self, signum: int) -> None:
        with self._lock:
            children = list(self._running)
        for proc in children:
            try:
                proc.send_signal(signum)
            except OSError:  # already gone
                pass

    # --- the workers -----------------------------------------------------------------------

    def _guarded(self, scan: Scan) -> ScanResult:
        try:
            result = self._run_scan(scan)
        except Exception as exc:  # a bug of the batch itself: that scan fails, not the batch
            result = ScanResult(scan, "failed", steps=[StepResult(
                "-", "-", "failed", error=f"internal error: {type(exc).__name__}: {exc}")])
        if result.status == "failed":
            self._failed = True
        if self.on_scan is not None:
            self.on_scan(result)
        return result

    def _run_scan(self, scan: Scan) -> ScanResult:
        if self._stopping is not None or (self.fail_fast and self._failed):
            return ScanResult(scan, "not started")
        start = time.monotonic()
        plans = plan_scan(self.manifest, scan)
        results: dict[str, StepResult] = {}
        ran: set[str] = set()
        for plan in plans:
            step = plan.step
            res = StepResult(step.name, step.run, "not run", command=["volwarp", *plan.argv],
                             outputs=[str(p) for p in plan.outputs])
            results[step.name] = res
            upstream = results.get(step.input) if step.input != SCAN else None
            if upstream is not None and upstream.status in ("failed", "not run", "stopped"):
                continue  # its input was not made
            if self._stopping is not None:
                res.status = "stopped"
                continue
            if not self.force and step.input not in ran:
                res.reason = stale_reason(self.manifest, plan, self._record)
                if res.reason is None:
                    res.status = "skipped"
                    continue
            self._run_step(plan, res)
            if res.status == "ok":
                ran.add(step.name)
                self._record.record(plan)
        steps = list(results.values())
        statuses = {s.status for s in steps}
        if "failed" in statuses:
            status = "failed"
        elif "stopped" in statuses:
            status = "stopped"
        elif "ok" in statuses:
            status = "ok"
        else:
            status = "skipped"
        return ScanResult(scan, status, time.monotonic() - start, steps)

    def _run_step(self, plan: StepPlan, res: StepResult) -> None:
        for out in plan.outputs:
            try:
                out.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                res.status, res.error = "failed", f"{out.parent}: {exc.strerror or exc}"
                return
        start = time.monotonic()
        while True:
            res.attempts += 1
            code, stderr = self._call(plan.argv)
            res.exit_code = code
            res.seconds = time.monotonic() - start
            if code is None:  # not started: the batch is stopping
                res.status = "stopped"
                return
            if code == 0:
                res.status, res.error = "ok", None
                return
            if code in _STOP_CODES or code < 0:
                # a terminal's Ctrl-C reaches the children with the batch: give the
                # batch's own handler a moment to say it was a stop
                for _ in range(20):
                    if self._stopping is not None:
                        res.status, res.error = "stopped", None
                        return
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
            return

    def _call(self, argv: list[str]) -> tuple[int | None, str]:
        with self._lock:
            if self._stopping is not None:
                return None, ""
            env = dict(os.environ, **{THREADS_ENV: str(self.child_threads)})
            proc = subprocess.Popen(volwarp_argv(argv), cwd=self.manifest.base, env=env,
                                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE)
            self._running.add(proc)
        try:
            _, err = proc.communicate()
        finally:
            with self._lock:
                self._running.discard(proc)
        return proc.returncode, err.decode("utf-8", "replace")


def default_jobs() -> int:
    """The threads in effect, one scan per thread.

    That is ``--threads``, ``VOLWARP_THREADS``, else the cores this process may use:
    its affinity and cgroup quota.
    """
    from .. import parallel

    return parallel.threads()


def child_threads(jobs: int) -> int:
    """Threads each scan's command gets: the threads in effect shared by ``jobs`` scans at once.

    At least one, so that a batch never runs more threads than it was given.
    """
    from .. import parallel

    return max(1, parallel.threads() // max(1, jobs))
