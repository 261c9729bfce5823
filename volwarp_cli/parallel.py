"""How many threads volwarp's work runs on, and running block tasks over them.

The count comes from, in order: :func:`use_threads` (the CLI's ``--threads``),
``VOLWARP_THREADS``, then :func:`available_cores`, the cores this process may
use (its CPU affinity and its cgroup's CPU quota, not the machine's count:
inside a container or a cluster worker limited to 4 CPUs, 4).

The count lives in a context variable, not in a module global: a caller's
threads (a Dask worker's, a test's) each have their own, and :func:`run_blocks`
hands it to the tasks it runs. Every kernel sums exact integers or writes
disjoint blocks, so results do not depend on the count or the block sizes.

volwarp's numba kernels are ``nogil`` ones over ranges, run by
:func:`run_blocks` (none uses numba's ``prange`` pool). Libraries with thread
pools of their own are matched to the count when they run: VTK's SMP filters
by ``surface.isosurface``. BLAS is held to one thread: by the command
line's entry point (before numpy loads), or by :func:`library_threads` for a
library caller.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import os
import threading
from collections.abc import Callable, Iterable, Sequence

from .errors import SpecError

#: Environment variable giving the default thread count.
THREADS_ENV = "VOLWARP_THREADS"

_threads: contextvars.ContextVar[int | None] = contextvars.ContextVar("volwarp_threads",
                                                                       default=None)


def _read(path: str) -> str | None:
    try:
        with open(path) as fh:
            return fh.read().strip()
    except OSError:
        return None


def _cgroup_paths() -> dict[str, str]:
    """The cgroup of this process per controller (``""`` for the v2 unified hierarchy)."""
    out = {}
    text = _read("/proc/self/cgroup") or ""
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        for controller in parts[1].split(",") if parts[1] else [""]:
            out[controller] = parts[2]
    return out


def cgroup_levels(path: str) -> list[str]:
    """A cgroup and its ancestors, leaf first: ``/a/b`` -> ``/a/b``, ``/a``, ``/``."""
    parts = [p for p in path.split("/") if p]
    return ["/" + "/".join(parts[:n]) for n in range(len(parts), -1, -1)]


def _under(mount: str, path: str, name: str) -> str | None:
    """The file ``name`` of cgroup ``path`` under ``mount``, or at the mount's root.

    Inside a container the process's cgroup path is often not mounted below its
    own name (the container sees its cgroup as the root): try both.
    """
    for base in (os.path.join(mount, path.lstrip("/")), mount):
        text = _read(os.path.join(base, name))
        if text is not None:
            return text
    return None


def cgroup_cpu_quota(root: str = "/sys/fs/cgroup") -> float | None:
    """The CPUs this process's cgroup may use per period (quota / period), or None.

    cgroup v2 ``cpu.max`` (``"max 100000"`` or ``"200000 100000"``), else v1
    ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (-1: no quota). The cgroup's
    ancestors count too (a Slurm job's or a pod's quota may sit above the
    process's own cgroup): the smallest quota of any level.
    """
    paths = _cgroup_paths()
    quotas = []
    if "" in paths:
        for level in cgroup_levels(paths[""]):
            text = _under(root, level, "cpu.max")
            if not text:
                continue
            quota, _, period = text.partition(" ")
            if quota != "max":
                try:
                    quotas.append(int(quota) / int(period or 100000))
                except (ValueError, ZeroDivisionError):
                    continue
        if quotas:
            return min(quotas)
    for controller in ("cpu", "cpu,cpuacct"):
        if controller in paths or controller == "cpu":
            path = paths.get(controller, "/")
            for mount in (os.path.join(root, "cpu"), os.path.join(root, "cpu,cpuacct")):
                for level in cgroup_levels(path):
                    quota = _under(mount, level, "cpu.cfs_quota_us")
                    period = _under(mount, level, "cpu.cfs_period_us")
                    try:
                        q, p = int(quota), int(period)
                    except (TypeError, ValueError):
                        continue
                    if q > 0 and p > 0:
                        quotas.append(q / p)
                if quotas:
                    return min(quotas)
    return None


def available_cores() -> int:
    """The cores this process may use: its affinity, capped by its cgroup's CPU quota.

    A fractional quota (1.5 CPUs) rounds up, as loky and the JVM do: the
    scheduler lets the process burst, and one thread fewer would leave half a
    core idle.
    """
    try:
        cores = len(os.sched_getaffinity(0)) or 1
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    quota = cgroup_cpu_quota()
    if quota is not None:
        cores = max(1, min(cores, math.ceil(quota)))
    return cores


def parse_threads(value, where: str = THREADS_ENV) -> int:
    """A thread count: a positive integer, or ``0``/``auto`` for :func:`available_cores`."""
    text = str(value).strip().lower()
    if text in ("0", "auto", ""):
        return available_cores()
    try:
        n = int(text)
    except ValueError:
        raise SpecError(f"{where}: {value!r} is not a thread count "
                        "(a positive integer, or 0/auto for every core)") from None
    if n < 0:
        raise SpecError(f"{where}: {value!r} is not a thread count "
                        "(a positive integer, or 0/auto for every core)")
    return n or available_cores()


def threads() -> int:
    """The thread count in effect (see the module notes for where it comes from)."""
    n = _threads.get()
    if n is not None:
        return n
    env = os.environ.get(THREADS_ENV)
    if env:
        return parse_threads(env)
    return available_cores()


@contextlib.contextmanager
def use_threads(n: int | None):
    """Run the block inside with ``n`` threads (None: keep the count in effect)."""
    if n is None:
        yield threads()
        return
    if int(n) < 1:
        raise ValueError(f"thread count must be at least 1, got {n}")
    token = _threads.set(int(n))
    try:
        yield int(n)
    finally:
        _threads.reset(token)


def cuts(lo: int, hi: int, parts: int) -> list[int]:
    """Boundaries of ``parts`` near-equal ranges of [lo, hi) (fewer when the range is short)."""
    parts = max(1, min(int(parts), hi - lo))
    return [lo + (hi - lo) * i // parts for i in range(parts + 1)]


def run_blocks(task: Callable, blocks: Sequence | Iterable, n: int | None = None) -> list:
    """``[task(b) for b in blocks]`` over ``n`` threads (default :func:`threads`), in order.

    Each task runs in a copy of the caller's context (its thread count, its
    memory budget). The tasks must write disjoint outputs and release the
    GIL for the threads to help (volwarp's kernels do: numba ``nogil`` and the
    C extension). An exception in a task is raised here once the others end
    (the first in block order); a stop (an exception in the calling thread
    while it waits) starts no more tasks and is raised once the running ones
    end. Plain threads taking the next block in turn: ``concurrent.futures``
    imports :mod:`logging` (5 ms of a small command).
    """
    blocks = list(blocks)
    n = threads() if n is None else int(n)
    if n <= 1 or len(blocks) <= 1:
        return [task(b) for b in blocks]
    contexts = [contextvars.copy_context() for _ in blocks]
    results: list = [None] * len(blocks)
    errors: dict[int, BaseException] = {}
    taken = iter(range(len(blocks)))  # (next() on it is atomic: one thread a block)
    stop = threading.Event()

    def work() -> None:
        for i in taken:
            if stop.is_set():
                return
            try:
                results[i] = contexts[i].run(task, blocks[i])
            except BaseException as exc:  # (raised in the caller, in block order)
                errors[i] = exc

    # (not daemons, as the pool's were: an interpreter ending while a caller's thread is in
    # here waits for the blocks under way rather than stopping them inside a kernel)
    workers = [threading.Thread(target=work, name=f"volwarp_{k}")
               for k in range(min(n, len(blocks)))]
    try:  # (a stop while they start, or while they run: those started end first)
        for w in workers:
            w.start()
        for w in workers:
            w.join()
    finally:
        stop.set()
        for w in workers:
            if w.ident is not None:
                w.join()
    if errors:
        raise errors[min(errors)]
    return results



def run_ranges(task: Callable, length: int, n: int | None = None, parts: int | None = None
               ) -> None:
    """``task(a, b)`` over near-equal ranges covering [0, ``length``), on ``n`` threads.

    ``parts`` ranges (default one per thread; more balance tasks of uneven
    cost); the numba kernels' way of using the threads (see the module notes).
    """
    n = threads() if n is None else max(1, int(n))
    if length <= 0:
        return
    edges = cuts(0, int(length), n if parts is None else parts)
    run_blocks(lambda ab: task(*ab), list(zip(edges[:-1], edges[1:], strict=True)), n)


@contextlib.contextmanager
def library_threads(n: int | None = None):
    """Run the block inside with ``n`` threads (default :func:`threads`) and BLAS at one.

    For a library caller running volwarp's functions in a process of its own
    (the command line does not need it: its entry point sets
    ``OPENBLAS_NUM_THREADS=1`` before numpy loads). BLAS (through
    threadpoolctl) gets one thread: volwarp's kernels already spread over the
    ``n`` threads and make only small dense products, so BLAS threads inside
    them would oversubscribe the cores. Its limit is process-wide (set here and
    put back after), which is why this wraps a whole job, not a kernel. The
    numba kernels' ranges (:func:`run_blocks`) and VTK's SMP filters
    (``surface.isosurface``) take the count in effect when they run.
    """
    from threadpoolctl import threadpool_limits

    n = threads() if n is None else int(n)
    restore = threadpool_limits(limits=1, user_api="blas")
    try:
        with use_threads(n):
            yield n
    finally:
        restore.restore_original_limits()


#: work (voxels) from which the kernels split over threads: each thread gets this much at least
SPLIT_MIN_WORK = 1 << 18


def run_split(job_for, lo_z: int, hi_z: int, work: int) -> list:
    """Run ``job_for(z0, z1).run()`` (a compiled kernel's call) over slabs of [lo_z, hi_z).

    One slab per thread: as many slabs as :func:`threads` allows, each with at
    least ``SPLIT_MIN_WORK`` of ``work`` (one slab, in this thread, when
    ``work`` is 0 or small). The kernels release the GIL (numba ``nogil``, or
    the compiled ones of ``_warpkernels.c``); the slabs write disjoint output.
    (Python threads instead of numba's ``prange``, whose threading layer
    costs time to start in every process.) Returns the kernel's results, one
    per slab.
    """
    if work <= 0:
        return [job_for(lo_z, hi_z).run()]
    parts = min(threads(), max(1, work // max(SPLIT_MIN_WORK, 1)), hi_z - lo_z)
    if parts <= 1:
        return [job_for(lo_z, hi_z).run()]
    edges = cuts(lo_z, hi_z, parts)
    return run_blocks(lambda i: job_for(edges[i], edges[i + 1]).run(), range(len(edges) - 1))


class Beside:
    """The outcome of :func:`beside`'s ``fn(*args)``: :meth:`result` waits for it.

    (Not ``concurrent.futures``'s Future: that package imports :mod:`logging`,
    5 ms of a command that emits no record.)
    """

    def __init__(self):
        self._ended = threading.Event()
        self._value = self._error = None

    def _run(self, fn: Callable, args, catching: type[BaseException] = BaseException) -> None:
        try:
            self._value = fn(*args)
        except catching as exc:  # (raised where the caller asks for the result)
            self._error = exc
        finally:
            self._ended.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until ``fn`` has ended (returned or raised): whether it has."""
        return self._ended.wait(timeout)

    def result(self, timeout: float | None = None):
        """``fn``'s result, once it has ended; its error is raised here.

        ``TimeoutError`` where it has not ended within ``timeout`` seconds.
        """
        if not self._ended.wait(timeout):
            raise TimeoutError(f"not ended within {timeout} s")
        if self._error is not None:
            raise self._error
        return self._value


def beside(fn: Callable, *args) -> Beside:
    """Start ``fn(*args)`` in a thread of its own while the caller goes on: its :class:`Beside`.

    For work beside other work that waits on other things than the GIL (an
    input's label scan while the transforms' files inflate; a volume's reading
    while the spec is checked), in a copy of the caller's context (its run,
    budget and thread count). It should decide nothing by the memory left:
    the caller's allocations meanwhile are not yet in what it would read. With
    one thread (:func:`threads`) it runs here, now; its error, if any, is then
    raised by ``result()`` as from the thread (a stop is raised at once).
    """
    outcome = Beside()
    if threads() <= 1:
        outcome._run(fn, args, Exception)  # (a stop is no Exception: raised at once)
        return outcome
    threading.Thread(target=contextvars.copy_context().run, args=(outcome._run, fn, args),
                     daemon=True, name="volwarp-beside").start()
    return outcome
