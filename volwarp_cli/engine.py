"""The Dask engine: which scheduler runs a block graph, and what it reports.

volwarp has no scheduler of its own. A chunked operation builds a Dask graph
whose last tasks each compute and write one output block; this module picks
who runs it, from ``--scheduler`` (else ``DASK_SCHEDULER_ADDRESS``, else the
threaded scheduler):

==================  ================================================================
``threads``         Dask's threaded scheduler in this process (the default: volwarp's
                    kernels release the GIL), ``--threads`` threads
``processes``       Dask's multiprocessing scheduler, ``--threads`` processes
``synchronous``     one task at a time in the calling thread (debugging, tests)
``local``           a ``distributed.LocalCluster`` of ``--workers`` processes with
                    ``--threads-per-worker`` threads each, the memory budget split
                    among them
``tcp://HOST:PORT`` an existing cluster's scheduler (also ``tls://``, ``ucx://``,
                    ``inproc://``)
``file:PATH``       an existing cluster whose scheduler wrote PATH (``dask
                    scheduler --scheduler-file PATH``)
==================  ================================================================

Every scheduler runs the same block tasks, so outputs are identical on all of
them. A block task runs its kernels on one thread (:func:`block_task`): the
scheduler's threads are the parallelism, not threads inside the tasks.

Nothing here is imported by the in-memory path; dask and distributed are the
``[scale]`` extra, imported when a graph is built.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from .errors import VolwarpError

#: Dask's own variable naming the scheduler of an existing cluster.
SCHEDULER_ENV = "DASK_SCHEDULER_ADDRESS"
#: The schedulers named by a word (the others are addresses or ``file:PATH``).
LOCAL_SCHEDULERS = ("threads", "processes", "synchronous", "local")
_ADDRESS_PREFIXES = ("tcp://", "tls://", "ucx://", "inproc://", "ws://", "wss://")


@dataclass(frozen=True)
class SchedulerChoice:
    """A parsed ``--scheduler``: its kind and, for a cluster, where it is."""

    kind: str  # threads | processes | synchronous | local | address | file
    where: str | None = None

    @property
    def distributed(self) -> bool:
        """True when the graph runs on a ``distributed`` cluster (local or remote)."""
        return self.kind in ("local", "address", "file")

    def describe(self) -> str:
        """The scheduler as a user names it."""
        return self.where if self.kind == "address" else (
            f"file:{self.where}" if self.kind == "file" else self.kind)


def parse_scheduler(value: str | None, environ=None) -> SchedulerChoice:
    """The scheduler ``value`` names (None: ``DASK_SCHEDULER_ADDRESS``, else threads)."""
    environ = os.environ if environ is None else environ
    if value is None or not str(value).strip():
        env = environ.get(SCHEDULER_ENV, "").strip()
        if not env:
            return SchedulerChoice("threads")
        value = env
    value = str(value).strip()
    word = value.lower()
    if word in ("sync", "single-threaded"):
        word = "synchronous"
    if word in LOCAL_SCHEDULERS:
        return SchedulerChoice(word)
    if word.startswith(_ADDRESS_PREFIXES):
        return SchedulerChoice("address", value)
    if word.startswith("file:"):
        path = value[5:]
        if not path:
            raise VolwarpError("--scheduler file: needs the scheduler file's path "
                               "(file:PATH)")
        return SchedulerChoice("file", path)
    raise VolwarpError(f"unknown scheduler {value!r} (known: {', '.join(LOCAL_SCHEDULERS)}, "
                       "tcp://HOST:PORT, file:PATH)")


# -- progress --------------------------------------------------------------------------
class JsonlProgress:
    """One JSON object per line, per block or scan event: start, done, failed.

    Each line has ``event``, ``kind`` (block or scan), ``id``, ``t`` (seconds
    since the run started) and, on done and failed, the task's own
    ``seconds`` and its process's ``peak_rss`` (bytes); failed lines add
    ``error``. Lines are written whole under a lock, so threads never mix them.
    """

    def __init__(self, stream=None):
        self.stream = stream
        self._start = time.perf_counter()
        self._lock = threading.Lock()

    def emit(self, event: str, kind: str, ident, **fields) -> None:
        """Write one event line."""
        record = {"event": event, "kind": kind, "id": ident,
                  "t": round(time.perf_counter() - self._start, 4)}
        record.update({k: v for k, v in fields.items() if v is not None})
        line = json.dumps(record, separators=(",", ":")) + "\n"
        stream = self.stream if self.stream is not None else sys.stderr
        with self._lock:
            stream.write(line)
            stream.flush()


def peak_rss() -> int:
    """The peak resident set of this process so far, in bytes (ru_maxrss is KiB on Linux)."""
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


@dataclass(frozen=True)
class BlockStats:
    """What a block task returns: its id, its seconds, its process's peak memory.

    ``value``: what the task's function returned, when it is kept
    (:meth:`Engine.map`; a block written to an output store returns nothing).
    """

    id: str
    seconds: float
    peak_rss: int
    value: object = None
    #: the warnings the task said in another process than the command's: ``(key, message)``
    said: tuple = ()
    #: what its casts noted there, judged with the command's (:func:`.samples.run_notes`)
    notes: tuple = ()


def block_task(fn: Callable, ident: str, *args, threads: int = 1, memory: int | None = None,
               keep: bool = False, origin: int | None = None, run: int | None = None,
               **kwargs) -> BlockStats:
    """Run ``fn(*args, **kwargs)`` as one block task; its :class:`BlockStats`.

    The task's kernels get ``threads`` threads (the scheduler's are the
    parallelism) and the memory budget ``memory`` (the command's, passed in:
    a worker process has no command line to read it from). ``keep``: return
    ``fn``'s result too, as the stats' ``value``. ``origin``: the command's
    process; in another one the task is a run of its own and its warnings go
    back in the stats (:meth:`Engine.run` says them once, as the block ends),
    not to the worker's stderr. ``run``: the command's run
    (:func:`~volwarp_cli.runscope.current_run_id`), entered in this process
    (a thread pool's task has no context of it).
    """
    from . import memory as memory_mod
    from . import parallel
    from .runscope import enter_run

    start = time.perf_counter()
    with enter_run(run if origin is None or os.getpid() == origin else None), \
            parallel.use_threads(threads), (memory_mod.use_memory_limit(
                memory, source="a block task's share of --memory-limit")
                if memory is not None else contextlib.nullcontext()), \
            _said_here(origin is not None and os.getpid() != origin) as said:
        try:
            value = fn(*args, **kwargs)
        except BaseException as exc:  # (its warnings go back with the failure)
            if said:
                exc.volwarp_said = tuple(said)
            raise
        notes = ()
        if origin is not None and os.getpid() != origin:  # (its own run: notes go back)
            from .samples import run_notes

            notes = run_notes()
    return BlockStats(ident, time.perf_counter() - start, peak_rss(),
                      value if keep else None, tuple(said), notes)


_capture = threading.local()


class _KeepSaid:
    """A filter of volwarp's log: warnings in a capturing thread kept (key, message), not shown.

    ``key``: the record's ``once`` (what a warning said once per run is
    keyed by), else its message.
    """

    def filter(self, record) -> bool:
        import logging

        said = getattr(_capture, "said", None)
        if said is None or record.levelno < logging.WARNING:
            return True
        message = record.getMessage()
        said.append((getattr(record, "once", None) or message, message))
        return False


@contextlib.contextmanager
def _said_here(capture: bool):
    """The warnings said inside, kept (a list) where ``capture``, in a run of its own."""
    if not capture:
        yield []
        return
    from .progress import log
    from .runscope import run_scope

    if not any(isinstance(f, _KeepSaid) for f in log.filters):
        log.addFilter(_KeepSaid())
    said: list = []
    _capture.said = said
    try:
        with run_scope():
            yield said
    finally:
        _capture.said = None


def say_once(results) -> None:
    """The warnings block tasks said in other processes, each key once per run.

    Their casts' notes are merged into the run's (judged at its end).
    ``results``: :class:`BlockStats`, or a failed task's exception (its
    ``volwarp_said``: what the block said before it failed).
    """
    from .progress import log
    from .runscope import run_files
    from .samples import merge_notes

    done = run_files().said
    for stats in results:
        merge_notes(getattr(stats, "notes", ()))
        for key, message in getattr(stats, "said", getattr(stats, "volwarp_said", ())):
            if key not in done:
                done.add(key)
                log.warning("%s", message)


# -- running a graph -------------------------------------------------------------------
@dataclass
class Engine:
    """A scheduler opened for one command: :meth:`run` computes block tasks on it."""

    choice: SchedulerChoice
    workers: int
    client: object | None = None  # a distributed.Client for a cluster
    progress: JsonlProgress | None = None
    _cluster: object | None = field(default=None, repr=False)

    def run(self, tasks, *, label: str = "blocks") -> list[BlockStats]:
        """Compute ``tasks`` (dask delayed objects returning :class:`BlockStats`).

        Failures propagate as the task's own exception (a VolwarpError stays
        one); a bar is drawn on a terminal, JSON lines with ``progress``.
        """
        from .progress import progress

        tasks = list(tasks)
        if not tasks:
            return []
        try:
            with progress(len(tasks), label) as bar:
                results = self._run(tasks, bar)
        except BaseException as exc:  # (a failed block's warnings: said before its error)
            say_once((exc,))
            raise
        return results

    def _run(self, tasks: list, bar) -> list[BlockStats]:
        """:meth:`run`'s tasks on the client or on a local scheduler, advancing ``bar``."""
        import dask

        if self.client is not None:
            from distributed import as_completed

            futures = self.client.compute(tasks)
            keys = {f.key: i for i, f in enumerate(futures)}
            names = {f.key: _key_name(f.key) for f in futures}
            ordered: list[BlockStats | None] = [None] * len(futures)
            for fut in as_completed(futures):
                try:
                    stats = fut.result()
                except BaseException as exc:
                    self._failed(names[fut.key], exc)
                    for other in futures:
                        other.cancel()
                    raise
                ordered[keys[fut.key]] = stats
                self._done(stats)
                bar.advance()
            results = [s for s in ordered if s is not None]
        else:
            pool = _local_pool(self.choice.kind, self.workers)
            extra = {} if pool is None else {"pool": pool}
            try:
                with _LocalCallbacks(self, bar):
                    # the scheduler's function, not its name: a name makes dask import
                    # distributed (0.2 s) to look for a client
                    results = list(dask.compute(*tasks,
                                                scheduler=_local_get(self.choice.kind),
                                                num_workers=self.workers, **extra))
            finally:
                # (a failed task: the tasks still running finish before the error goes
                # on, so that no late block writes into an output being removed)
                if pool is not None:
                    pool.shutdown(wait=True, cancel_futures=True)
        return results

    @staticmethod
    def block_delayed(fn: Callable, ident: str, *args, **kwargs):
        """:func:`block_delayed` (a task for :meth:`run`)."""
        return block_delayed(fn, ident, *args, **kwargs)

    def map(self, fn: Callable, items, *, label: str, memory: int | None = None) -> list:
        """``[fn(item) for item in items]``, one block task per item, on this engine.

        For block results gathered in the caller (a mesh's parts), not
        written to a store. Items are numbered in the progress lines.
        """
        tasks = [block_delayed(fn, f"{label}-{i}", item, memory=memory, keep=True)
                 for i, item in enumerate(items)]
        by_id = {s.id: s.value for s in self.run(tasks, label=label)}
        return [by_id[f"{label}-{i}"] for i in range(len(tasks))]

    def _done(self, stats: BlockStats) -> None:
        say_once((stats,))  # (as each block ends: a later block's failure loses none)
        if self.progress is not None:
            self.progress.emit("done", "block", stats.id, seconds=round(stats.seconds, 4),
                               peak_rss=stats.peak_rss)

    def _failed(self, ident: str, exc: BaseException) -> None:
        if self.progress is not None:
            self.progress.emit("failed", "block", ident, error=_one_line(exc))

    def close(self) -> None:
        """Close the client and the cluster this engine started (not a remote one)."""
        if self.client is not None:
            self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def _local_get(kind: str):
    """The ``get`` function of a local Dask scheduler."""
    if kind == "threads":
        from dask.threaded import get
    elif kind == "processes":
        from dask.multiprocessing import get
    else:
        from dask.local import get_sync as get
    return get


def _local_pool(kind: str, workers: int):
    """The executor a local Dask scheduler runs on, ours to wait for (None: synchronous).

    Made as dask makes its own (for processes: its context and worker
    initializer), so that the tasks run as before.
    """
    if kind == "threads":
        from concurrent.futures import ThreadPoolExecutor

        return ThreadPoolExecutor(workers)
    if kind == "processes":
        import functools
        import os
        from concurrent.futures import ProcessPoolExecutor

        from dask.multiprocessing import get_context, initialize_worker_process

        if os.environ.get("PYTHONHASHSEED") in (None, "0"):
            os.environ["PYTHONHASHSEED"] = "6640"  # (dask's own choice, for its hashing)
        return ProcessPoolExecutor(workers, mp_context=get_context(), initializer=functools.partial(
            initialize_worker_process, user_initializer=None))
    return None


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[-1] if text else type(exc).__name__


class _LocalCallbacks:
    """Dask callbacks of the local schedulers: start lines and the bar, per block task."""

    def __init__(self, engine: Engine, bar):
        from dask.callbacks import Callback

        self.engine = engine
        outer = self

        class _Cb(Callback):
            def _pretask(self, key, dsk, state):
                if outer.engine.progress is not None and _is_block_key(key):
                    outer.engine.progress.emit("start", "block", _key_name(key))

            def _posttask(self, key, result, dsk, state, worker_id):
                if isinstance(result, BlockStats):
                    outer.engine._done(result)
                    bar.advance()

        self._cb = _Cb()

    def __enter__(self):
        self._cb.__enter__()
        return self

    def __exit__(self, *exc):
        return self._cb.__exit__(*exc)


#: key-name prefix of block tasks (see :func:`block_delayed`)
BLOCK_PREFIX = "volwarp-block-"
#: between a block task's name and what makes its key unique (see :func:`block_delayed`)
KEY_MARK = "@@"
_KEY_TOKEN = f"{os.getpid()}-{os.urandom(6).hex()}"  # (this process's, beside a counter)
_key_counter = itertools.count()


def _key_name(key) -> str:
    name = key[0] if isinstance(key, tuple) else key
    name = str(name)
    if not name.startswith(BLOCK_PREFIX):
        return name
    return name[len(BLOCK_PREFIX):].rsplit(KEY_MARK, 1)[0]


def _is_block_key(key) -> bool:
    name = key[0] if isinstance(key, tuple) else key
    return str(name).startswith(BLOCK_PREFIX)


def block_delayed(fn: Callable, ident: str, *args, threads: int = 1,
                  memory: int | None = None, **kwargs):
    """A dask delayed :func:`block_task` named after the block (its progress lines' id).

    Its key is unique to this call: the block's name, then :data:`KEY_MARK`, this
    process's token and a count. A scheduler hands back the result it holds for
    a key without running the task again: named by the block alone, a morph's
    second frame got its first frame's blocks (a LocalCluster kept them: frames
    of zeros, exit 0) and a mesh's pieces its counting pass's results.
    """
    import dask

    from .runscope import current_run_id

    key = f"{BLOCK_PREFIX}{ident}{KEY_MARK}{_KEY_TOKEN}-{next(_key_counter)}"
    return dask.delayed(block_task, pure=False)(
        fn, ident, *args, threads=threads, memory=memory, origin=os.getpid(),
        run=current_run_id(), dask_key_name=key, **kwargs)


@contextlib.contextmanager
def open_engine(scheduler: str | SchedulerChoice | None = None, *, workers: int | None = None,
                threads_per_worker: int | None = None, memory_limit: int | None = None,
                progress: str | None = None) -> Iterator[Engine]:
    """The engine for ``scheduler`` (see the module notes), closed on exit.

    ``workers``: threads or processes of a local scheduler, worker processes
    of a LocalCluster (default: the cores this process may use, divided by
    ``threads_per_worker``); ``memory_limit``: the LocalCluster's total,
    split among its workers (0: none, and no memory monitor in its workers, for
    tasks whose memory is their child processes'); ``progress``: ``"jsonl"``
    for JSON lines on stderr.
    """
    from . import parallel

    choice = scheduler if isinstance(scheduler, SchedulerChoice) else parse_scheduler(scheduler)
    reporter = JsonlProgress() if progress == "jsonl" else None
    if not choice.distributed:
        yield Engine(choice, workers=workers or parallel.threads(), progress=reporter)
        return
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - the [scale] extra is installed with volwarp's tests
        raise VolwarpError(f"--scheduler {choice.describe()} needs the 'distributed' package "
                           "(pip install 'volwarp-cli[scale]')") from None
    cluster = None
    if choice.kind == "local":
        import dask
        from distributed import LocalCluster

        per = threads_per_worker or 1
        n = workers or max(1, parallel.threads() // per)
        if memory_limit and memory_limit // n < LOCAL_WORKER_MIN:
            raise VolwarpError(
                f"--scheduler local: {n} worker process(es) would share "
                f"{memory_limit / 2**20:.0f} MiB of the memory limit (--memory-limit, or the "
                f"machine's or cgroup's), "
                f"{memory_limit // n / 2**20:.0f} MiB each; a Dask worker holds about 70 MiB "
                f"before its first block and pauses at 80% of its share (the run never ends): "
                f"give each at least {LOCAL_WORKER_MIN >> 20} MiB (more memory, or fewer "
                "--workers), or leave --scheduler local out")
        # the workers' statistical profiler samples every thread's stack every 10 ms, the
        # event loops' blocking check ticks every 20 ms and the system monitor (for a
        # dashboard) every 0.5 s: costs on every process, read by nothing volwarp runs
        # (on 2 cores their ticks alone took 3-4% of one core while the cluster idled)
        with dask.config.set({"distributed.worker.profile.enabled": False,
                              "distributed.admin.tick.interval": "1s",
                              "distributed.admin.system-monitor.interval": "5s"}):
            # (no dashboard; the scheduler's HTTP server, which it starts anyway, on a free
            # port of this host only: on 8787, a second cluster of another run at the
            # same time printed distributed's "Port 8787 is already in use" warning)
            cluster = LocalCluster(n_workers=n, threads_per_worker=per, processes=True,
                                   memory_limit=("auto" if memory_limit is None
                                                 else memory_limit // n),
                                   dashboard_address=None, silence_logs=50,
                                   scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
        client = Client(cluster)
    else:
        try:
            if choice.kind == "file":
                if not os.path.isfile(choice.where):
                    raise VolwarpError(f"{choice.where}: no such scheduler file")
                client = Client(scheduler_file=choice.where, timeout="30s")
            else:
                client = Client(choice.where, timeout="30s")
        except VolwarpError:
            raise
        except (OSError, TimeoutError) as exc:
            raise VolwarpError(f"cannot reach the Dask scheduler at {choice.describe()} "
                               f"({_one_line(exc)})") from None
        n = sum(w.get("nthreads", 1) for w in client.scheduler_info()["workers"].values())
    engine = Engine(choice, workers=n, client=client, progress=reporter, _cluster=cluster)
    try:
        yield engine
    finally:
        engine.close()


#: the least memory a LocalCluster worker may be given: a bare Dask worker with volwarp's
#: imports holds about 70 MiB, and Dask pauses a worker at 80% of its limit (paused from
#: the start, a run with 80 MiB a worker never ended; 105 MiB ran)
LOCAL_WORKER_MIN = 100 << 20


# -- graph pieces shared by the chunked operations ---------------------------------------
def dask_input(source, chunks):
    """``source`` (a sliceable array: a :class:`~volwarp_cli.io.lazy.LazySource`) in Dask."""
    import dask.array as da
    import numpy as np

    return da.from_array(source, chunks=chunks, asarray=True, lock=False,
                         meta=np.empty((0, 0, 0), dtype=source.dtype), name=False)


def _write(block, out, box):
    out.write(box, block)


def write_blocks(darr, out, engine, *, label: str, memory: int | None = None):
    """Compute Dask array ``darr`` block by block on ``engine``, each block written to ``out``.

    ``darr`` is rechunked to the output's block grid first, so every write is
    one aligned block; returns the tasks' stats.
    """
    import dask
    import numpy as np

    from .box import Box
    from .io.blockwrite import aligned_chunks

    darr = darr.rechunk(aligned_chunks(darr.shape, out))
    out_node = dask.delayed(out.writer(), pure=False)
    starts = [np.concatenate([[0], np.cumsum(c)[:-1]]).astype(int) for c in darr.chunks]
    tasks, boxes = [], []
    for index, part in zip(np.ndindex(*darr.numblocks), darr.to_delayed().ravel(),
                           strict=True):
        lo = [int(s[i]) for s, i in zip(starts, index, strict=True)]
        hi = [a + int(c[i]) for a, c, i in zip(lo, darr.chunks, index, strict=True)]
        box = Box(lo, hi)
        boxes.append(box)
        tasks.append(engine.block_delayed(_write, f"{label}-{'-'.join(map(str, lo))}", part,
                                          out_node, box, memory=memory))
    stats = engine.run(tasks, label=label)
    out.mark_written(boxes)  # (every task succeeded: a failure raised)
    return stats
