"""Running the scans on a Dask cluster: one task per scan, the same scan runner on the worker.

Each scan is one ``distributed`` task (:func:`scan_task`) that runs the
scan's steps as child processes on its worker with :class:`.run.ScanRunner`,
the local pool's code, and returns the picklable :class:`.run.ScanResult`.
The batch process stays the only writer of the record: a task reads a
snapshot of the record's entries for its scan (and of the file hash cache),
and what the steps it ran made, with the hashes it computed, is kept when
its result arrives.

- A worker that dies (killed, out of memory, its machine gone) loses its
  tasks; the scheduler runs them again elsewhere, up to its
  ``distributed.scheduler.allowed-failures`` times (``--retries`` for a
  ``--scheduler local`` cluster; an existing cluster's own setting). A scan
  whose worker died once more than that is failed with the error
  ``worker died``; the batch goes on. (A task only queued on a worker that
  died, never started, the scheduler counts too: such a scan is submitted
  again. A ``local`` cluster sends a worker no more scans than its threads,
  ``worker-saturation`` 1.0, so none waits behind a long one there.) The rerun redoes the scan's steps that
  are not up to date; a killed step left no partial output (each step is a
  volwarp command: atomic outputs, and it is stopped with its worker).
- ``attempts`` of a scan (the report's) are its task's runs, counted by
  the events each run sends as it starts (else the scheduler's count of
  workers that died holding the task, plus one).
- Each task says when it starts (a worker event on the topic
  ``volwarp-batch-RUN``): the ``start`` line of ``--progress jsonl``, with
  the worker's address and process id.
- ``--fail-fast``: after a failure the scans not started are cancelled.
  SIGINT / SIGTERM: the scans not started are cancelled, the running ones'
  step processes on every worker get the signal (their old outputs stay),
  and their tasks end as ``stopped``; a second stop kills them.
"""

from __future__ import annotations

import os
import signal
import threading
import time
import uuid
from dataclasses import KW_ONLY, dataclass

from .manifest import Manifest, Scan
from .plan import CommandRecord, RecordSnapshot, plan_scan
from .run import (
    STOP_GRACE,
    Children,
    ScanResult,
    ScanRunner,
    StepResult,
    install_stop_handlers,
    restore_handlers,
)

#: the error of a scan whose worker died more often than the scheduler allows
WORKER_DIED = "worker died"
TOPIC = "volwarp-batch"
#: times a scan whose task was lost, never started, with a dying worker is submitted again
MAX_REQUEUES = 5

# -- on the worker -------------------------------------------------------------------------
_runs: dict[str, Children] = {}  # run id -> the children of that run in this worker process
_runs_lock = threading.Lock()


def _children(run_id: str) -> Children:
    with _runs_lock:
        return _runs.setdefault(run_id, Children())


def share_of_cores(cores: int, host: str, host_threads: dict | None, nthreads: int) -> int:
    """Threads for one scan's steps on a worker: its host's cores over the scans run there at once.

    ``host_threads``: the cluster's worker threads per host (several worker
    processes on one machine share its cores: ``dask worker --nworkers 4``);
    a host not in it (a worker that joined later) counts its own ``nthreads``.
    """
    return max(1, int(cores) // scans_at_once(host, host_threads, nthreads))


def scans_at_once(host: str, host_threads: dict | None, nthreads: int) -> int:
    """The scans a host runs at once: its workers' threads (:func:`share_of_cores`)."""
    return max(1, int((host_threads or {}).get(host) or nthreads))


def host_threads(scheduler_info: dict) -> dict[str, int]:
    """Worker threads per host, from ``client.scheduler_info()``."""
    out: dict[str, int] = {}
    for w in scheduler_info.get("workers", {}).values():
        host = w.get("host")
        if host:
            out[host] = out.get(host, 0) + int(w.get("nthreads", 1))
    return out


def scan_task(manifest: Manifest, scan: Scan, made: tuple[dict, dict], run_id: str, *,
              force: bool, step_retries: int, child_threads: int | None,
              thumbnails: bool, hosts: dict | None = None,
              memory_limit: int | None = None) -> ScanResult:
    """One scan's steps on this worker (a distributed task); its :class:`ScanResult`.

    ``memory_limit``: the batch's explicit limit, which the scans its host runs
    at once share (each step process gets its share as ``VOLWARP_MEMORY_LIMIT``).
    """
    from distributed import get_worker
    from distributed.comm import get_address_host

    from .. import parallel

    worker = get_worker()
    children = _children(run_id)
    if children.stopping is not None:
        return ScanResult(scan, "not started", worker=worker.address)
    nthreads = getattr(getattr(worker, "state", None), "nthreads", None) or getattr(
        worker, "nthreads", 1)
    host = get_address_host(worker.address)
    if child_threads is None:  # the host's cores shared by the scans it runs at once
        child_threads = share_of_cores(parallel.threads(), host, hosts, nthreads)
    child_memory, memory_from = None, "memory limit"
    if memory_limit is not None:  # (and the batch's memory limit)
        from ..memory import human_bytes

        at_once = scans_at_once(host, hosts, nthreads)
        child_memory = max(1, int(memory_limit) // at_once)
        memory_from = f"memory limit {human_bytes(memory_limit)}, {at_once} scans at once on {host}"

    def started(scan):
        worker.log_event(f"{TOPIC}-{run_id}", {"scan": scan.id, "worker": worker.address,
                                                "pid": os.getpid()})

    runner = ScanRunner(manifest, force=force, retries=step_retries,
                        child_threads=child_threads, child_memory=child_memory,
                        memory_from=memory_from,
                        record=RecordSnapshot(manifest, made), children=children,
                        thumbnails=thumbnails, on_start=started, ships_hashes=True)
    result = runner.run(scan)
    result.worker = worker.address
    return result


def stop_run(run_id: str, signum: int) -> None:
    """On a worker: no new step of run ``run_id`` starts; its running ones get ``signum``."""
    _children(run_id).stop(signum)


def forget_run(run_id: str) -> None:
    """On a worker: drop the run's bookkeeping (the batch is over)."""
    with _runs_lock:
        _runs.pop(run_id, None)


def _worker_deaths(keys: list[str], dask_scheduler=None) -> dict[str, int]:
    """On the scheduler: how many workers died running each task (``suspicious``)."""
    out = {}
    for key in keys:
        ts = dask_scheduler.tasks.get(key)
        if ts is not None:
            out[key] = int(getattr(ts, "suspicious", 0))
    return out


# -- in the batch process --------------------------------------------------------------------
@dataclass(eq=False)
class ClusterBatch:
    """The scans of a manifest, one task each on the cluster of ``client``.

    ``on_start``: called with (scan, worker address, worker pid);
    ``memory_limit``: the batch's explicit limit, shared by the scans each host
    runs at once (:func:`scan_task`).
    """

    manifest: Manifest
    scans: list[Scan]
    _: KW_ONLY
    client: object
    force: bool = False
    fail_fast: bool = False
    retries: int = 0
    child_threads: int | None = None
    memory_limit: int | None = None
    thumbnails: bool = False
    on_scan: object = None
    on_start: object = None

    def __post_init__(self):
        self.run_id = uuid.uuid4().hex[:12]
        self.record = CommandRecord(self.manifest)
        self._signals: list[int] = []
        self._stopping: int | None = None
        self._lock = threading.Lock()
        self._started: dict[str, int] = {}  # scan id -> start events seen

    def run(self) -> tuple[list[ScanResult], int | None]:
        """Run every scan; ``(results in scan order, the stop's signal number or None)``."""
        handlers = install_stop_handlers(self._signals)
        topic = f"{TOPIC}-{self.run_id}"
        self.client.subscribe_topic(topic, self._event)
        try:
            results = self._run()
        finally:
            restore_handlers(handlers)
            self.record.flush()
            try:
                self.client.unsubscribe_topic(topic)
                self.client.run(forget_run, self.run_id)
            except Exception:  # noqa: BLE001 - a cluster going away at the end changes nothing
                pass
        return results, self._stopping

    def _event(self, event) -> None:
        msg = event[1] if isinstance(event, tuple) and len(event) == 2 else event
        if not isinstance(msg, dict) or "scan" not in msg:
            return
        with self._lock:
            self._started[msg["scan"]] = self._started.get(msg["scan"], 0) + 1
        if self.on_start is not None:
            scan = self._by_id.get(msg["scan"])
            if scan is not None:
                self.on_start(scan, msg.get("worker"), msg.get("pid"))

    def _submit(self, i: int, again: int = 0):
        scan = self.scans[i]
        plans = plan_scan(self.manifest, scan)
        return self.client.submit(
            scan_task, self.manifest, scan, self.record.snapshot(plans), self.run_id,
            force=self.force, step_retries=self.retries, child_threads=self.child_threads,
            thumbnails=self.thumbnails, hosts=self._hosts, memory_limit=self.memory_limit,
            key=f"volwarp-scan-{self.run_id}-{i:06d}-{again}",
            priority=-i, pure=False)

    def _never_ran(self, i: int, future) -> bool:
        """True for a task lost with a worker it was only queued on (it never started)."""
        from distributed import KilledWorker

        if future.status != "error" or self._stopping is not None:
            return False
        with self._lock:
            started = self.scans[i].id in self._started
        return not started and isinstance(future.exception(), KilledWorker)

    def _run(self) -> list[ScanResult]:
        self._by_id = {s.id: s for s in self.scans}
        self._hosts = None
        if self.child_threads is None or self.memory_limit is not None:
            try:
                self._hosts = host_threads(self.client.scheduler_info())
            except Exception:  # noqa: BLE001 - then each worker counts its own threads
                self._hosts = None
        futures = [self._submit(i) for i in range(len(self.scans))]
        results: list[ScanResult | None] = [None] * len(futures)
        again = [0] * len(futures)
        pending = set(range(len(futures)))
        stop_deadline = None
        failed = False
        while pending:
            done = [i for i in pending if futures[i].done()]
            for i in done:
                if again[i] < MAX_REQUEUES and self._never_ran(i, futures[i]):
                    again[i] += 1  # queued on a worker that died: it is no failure of its own
                    futures[i].release()
                    futures[i] = self._submit(i, again[i])
                    continue
                pending.discard(i)
                results[i] = self._collect(self.scans[i], futures[i])
                if results[i].status == "failed" and self.fail_fast and not failed:
                    failed = True
                    self._cancel_unstarted(futures, pending)
            if self._signals and self._stopping is None:
                self._stopping = self._signals[0]
                self._cancel_unstarted(futures, pending)
                self._stop_workers(self._stopping)
                stop_deadline = time.monotonic() + STOP_GRACE
            if self._stopping is not None and (
                    len(self._signals) > 1 or time.monotonic() > stop_deadline):
                self._stop_workers(signal.SIGKILL)
                for i in list(pending):
                    futures[i].cancel()
                    results[i] = ScanResult(self.scans[i], "stopped")
                    pending.discard(i)
            if pending and not done:
                time.sleep(0.02)
        self._count_attempts(futures, results)
        for f in futures:
            f.release()
        return [r for r in results if r is not None]

    def _cancel_unstarted(self, futures, pending) -> None:
        with self._lock:
            started = set(self._started)
        for i in list(pending):
            if self.scans[i].id not in started:
                futures[i].cancel()

    def _stop_workers(self, signum: int) -> None:
        try:
            self.client.run(stop_run, self.run_id, signum)
        except Exception:  # noqa: BLE001 - workers gone: nothing left to stop there
            pass

    def _collect(self, scan: Scan, future) -> ScanResult:
        from distributed import KilledWorker

        status = future.status
        if status == "finished":
            try:
                result = future.result()
            except Exception as exc:  # noqa: BLE001 - lost between done and result
                result = _failed(scan, f"internal error: {type(exc).__name__}: {exc}")
        elif status == "cancelled":
            started = scan.id in self._started
            result = ScanResult(scan, "stopped" if started and self._stopping else "not started")
        else:
            exc = future.exception()
            if isinstance(exc, KilledWorker):
                result = _failed(scan, WORKER_DIED)
            else:
                result = _failed(scan, f"internal error: {type(exc).__name__}: {exc}")
        made = {k: v for step in result.steps if step.status == "ok" and step.made
                for k, v in step.made.items()}
        self.record.keep(made, result.hashed)
        if self.on_scan is not None:
            self.on_scan(result)
        return result

    def _count_attempts(self, futures, results) -> None:
        keys = [f.key for f in futures]
        try:
            deaths = self.client.run_on_scheduler(_worker_deaths, keys)
        except Exception:  # noqa: BLE001 - then the start events are all there is
            deaths = {}
        for f, r in zip(futures, results, strict=True):
            if r is None:
                continue
            starts = self._started.get(r.scan.id, 0)
            if starts:  # each run of the task said so as it started
                r.attempts = starts
            elif r.status == "not started":
                r.attempts = 0
            else:  # (no event arrived: the scheduler's count, which also counts a task
                # merely queued on a worker that died)
                r.attempts = deaths.get(f.key, 0) + (r.error != WORKER_DIED)


def _failed(scan: Scan, error: str) -> ScanResult:
    return ScanResult(scan, "failed", steps=[StepResult("-", "-", "failed", error=error)])


def run_on_cluster(manifest: Manifest, scans: list[Scan], where, **options):
    """Run the scans on the cluster ``where`` names: ``(results, stop, scans at once)``.

    ``where``: a :class:`.run.Where` with a scheduler; ``options``:
    :class:`ClusterBatch`'s. A ``local`` cluster is started for the batch,
    with the scheduler's ``allowed-failures`` set to ``retries`` and a
    worker sent no more scans than it has threads (an existing cluster
    keeps its own settings).
    """
    import contextlib

    import dask
    import distributed  # noqa: F401 - its config defaults in place before the set below

    from .. import memory, parallel
    from ..engine import open_engine

    local = where.scheduler.kind == "local"
    per = where.threads_per_worker or 1
    config = ({"distributed.scheduler.allowed-failures": options.get("retries", 0),
               "distributed.scheduler.worker-saturation": 1.0} if local else {})
    # (a scan's memory is its steps' processes', which a worker's memory monitor never
    # sees: no limit, and no monitor polling every 100 ms beside the steps)
    with dask.config.set(config), open_engine(where.scheduler, workers=where.workers,
                                              threads_per_worker=per,
                                              memory_limit=0 if local else None) as engine:
        if local:
            at_once = engine.workers * per
            child = max(1, parallel.threads() // at_once)
        else:
            at_once, child = engine.workers, None  # (each host shares its cores: share_of_cores)
        with contextlib.suppress(Exception):
            engine.client.wait_for_workers(1, timeout=60)
        limit = memory.explicit_limit()  # (each host's scans at once share it)
        if limit is not None and local:  # (on this machine: less what the batch holds)
            from .run import child_memory

            limit, _ = child_memory(1)
            limit = less_local_workers(engine.client, limit)
        results, stop = ClusterBatch(manifest, scans, client=engine.client,
                                     child_threads=child, memory_limit=limit, **options).run()
    return results, stop, at_once


def less_local_workers(client, limit: int) -> int:
    """``limit`` less what a local cluster's worker and nanny processes hold now.

    They run on this machine beside the batch and its steps (about 120 MiB a
    worker with its nanny): a batch under ``--memory-limit`` shared the whole
    of what the batch process left among the steps, and the machine held the
    workers on top. An :class:`~volwarp_cli.errors.OutOfMemoryError` where
    they leave the steps nothing.
    """
    from .. import memory
    from ..errors import OutOfMemoryError

    held = sum(sum(client.run(memory.process_rss, nanny=nanny).values())
               for nanny in (False, True))
    if limit <= held:
        raise OutOfMemoryError(f"the memory limit leaves nothing for the scans' steps: the "
                               f"local cluster's workers hold {memory.human_bytes(held)} of "
                               f"the {memory.human_bytes(limit)} the batch process leaves")
    return limit - held
