"""The memory budget: how much volwarp's work may allocate, and refusing what will not fit.

The limit in effect (:func:`memory_limit`) is the lowest of:

- :func:`use_memory_limit`'s budget (the CLI's ``--memory-limit``);
- ``VOLWARP_MEMORY_LIMIT`` (a size, :func:`parse_size`);
- the memory this process can still get (:func:`available_memory`): the
  kernel's ``MemAvailable`` and its cgroup's limit minus the cgroup's usage
  (:func:`cgroup_memory_limit`; inside a container or a cluster job limited to
  4 GiB, what is left of the 4 GiB, not the host's free memory).

Everything is read again at each call (free memory changes while a command
runs); a call costs a few small file reads, 0.1-0.2 ms.

The budget lives in a context variable, not in a module global: a Dask
worker's threads or a caller's each have their own, and
:func:`volwarp_cli.parallel.run_blocks` hands the caller's to its tasks. A
thread started otherwise does not see it (run it in
``contextvars.copy_context()`` to pass it on).

A step about to allocate (:func:`ensure_fits_in_memory`, before the
allocation) is compared with what is left: an explicit limit is the whole
process's, so what the process holds already (the interpreter and its
libraries, about 100-200 MiB, and the volumes read) is taken off it.
:func:`block_bytes` sizes the blocks of block-wise work from what is left.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import re
import threading
from collections.abc import Mapping

from .errors import BadUsage, OutOfMemoryError

#: Environment variable lowering the memory limit (a size: ``8G``, ``512M``, bytes).
MEMORY_ENV = "VOLWARP_MEMORY_LIMIT"
#: what :data:`MEMORY_ENV` is, for messages, where a parent set it (a batch: a scan's share
#: of its own limit)
MEMORY_FROM_ENV = "VOLWARP_MEMORY_LIMIT_FROM"

#: A cgroup v1 limit at or above this means none (v1 writes 2^63 - 1 rounded down to
#: the page size, 9223372036854771712 with 4 KiB pages).
_V1_UNLIMITED = 1 << 62

_UNITS = {"": 0, "k": 1, "m": 2, "g": 3, "t": 4}
_SIZE = re.compile(r"""\s*(?P<num>[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:e[+-]?\d+)?)\s*
                       (?P<unit>[kmgt]?)(?P<i>i?)(?P<b>b?)\s*""", re.IGNORECASE | re.VERBOSE)
_FORMS = ("a byte count (123456) or a number with k, M, G or T, optionally followed by "
          "B or iB (8G, 512M, 1.5GiB, 300MB); units are powers of 1024")

#: (bytes, where it came from) of the innermost :func:`use_memory_limit`, or None
_budget: contextvars.ContextVar[tuple[int, str] | None] = contextvars.ContextVar(
    "volwarp_memory_limit", default=None)


# -- sizes ----------------------------------------------------------------------------

def parse_size(text) -> int:
    """Bytes in a memory size.

    For example ``"8G"``, ``"512M"``, ``"1.5GiB"``, ``"2g"``, ``"300MB"``, ``"123456"``.

    A number (decimals and exponents allowed) with an optional unit k, M, G or T,
    case-insensitive, optionally followed by ``B`` or ``iB``. **Every unit is a
    power of 1024**, as Docker's ``--memory`` reads ``g`` and Dask its ``GiB``:
    ``GB`` and ``GiB`` alike mean 2^30 bytes (a memory limit written "8GB" is
    meant as 8 GiB; Dask reads ``GB`` as 10^9, volwarp does not). No unit, or
    ``B``, is bytes. The result is rounded down to a whole byte.

    Raises ``ValueError`` (one line, naming the accepted forms) for anything
    else and for a size that is not positive.
    """
    s = str(text)
    m = _SIZE.fullmatch(s)
    if not m:
        raise ValueError(f"{s.strip()!r} is not a memory size: give {_FORMS}")
    if m["i"] and not m["unit"]:
        raise ValueError(f"{s.strip()!r} is not a memory size: give {_FORMS}")
    value = float(m["num"]) * 1024 ** _UNITS[m["unit"].lower()]
    if value == float("inf"):
        raise ValueError(f"{s.strip()!r} is too large a memory size")
    if not value >= 1:
        raise ValueError(f"{s.strip()!r} is not a positive memory size: give {_FORMS}")
    return int(value)


def human_bytes(n: int) -> str:
    """``n`` bytes for a message: ``512 B``, ``15.2 MiB``, ``1.5 GiB`` (units of 1024)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            if unit == "B":
                return f"{n} B"
            return f"{n:.1f} {unit}" if abs(n) < 1e6 else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n} B"  # pragma: no cover - the loop returns


# -- what the machine and the cgroup leave --------------------------------------------

def _int(text: str | None) -> int | None:
    try:
        return int(text) if text is not None else None
    except ValueError:
        return None


def _stat(text: str | None, *keys: str) -> int:
    """The first of ``keys`` found in a ``memory.stat`` text (0 if none)."""
    values = {}
    for line in (text or "").splitlines():
        key, _, value = line.partition(" ")
        values[key] = value
    for key in keys:
        n = _int(values.get(key))
        if n is not None:
            return n
    return 0


def cgroup_memory_limit(root: str = "/sys/fs/cgroup",
                        cgroups: Mapping[str, str] | None = None) -> tuple[int, int] | None:
    """``(limit, usage)`` in bytes of this process's cgroup memory limit, or None if none.

    cgroup v2: the unified hierarchy's path (``0::/path`` in /proc/self/cgroup)
    gives ``<root>/<path>/memory.max`` (``max``: no limit) and
    ``memory.current``. cgroup v1: the ``memory`` controller's path gives
    ``<root>/memory/<path>/memory.limit_in_bytes`` (2^63 rounded to the page:
    no limit) and ``memory.usage_in_bytes``. Inside a container the cgroup's
    path is often not mounted under its name (the container's cgroup is the
    mount's root): each file is looked for at ``<mount>/<path>/`` and then at
    ``<mount>/`` (:func:`volwarp_cli.parallel._under`, as the CPU quota is).

    The cgroup's ancestors are read too (a Slurm job's limit sits on the
    job's cgroup, above the task's): the result is the level that leaves the
    least, ``limit - usage``. ``usage`` is the working set, as the kubelet and
    ``docker stats`` count it: the charged memory less its inactive page cache
    (``inactive_file`` in ``memory.stat``, v1 ``total_inactive_file``), which
    the kernel reclaims before it would kill the process (reading a 2 GiB
    volume charges 2 GiB of cache; ``MemAvailable`` counts it as available too).

    ``root`` is where the hierarchies are mounted; ``cgroups`` maps controller
    to cgroup path (``""`` for v2) as :func:`volwarp_cli.parallel._cgroup_paths`
    reads them from /proc/self/cgroup (the default); both are parameters for the
    tests' fake trees.
    """
    from .parallel import _cgroup_paths, _under
    from .parallel import cgroup_levels as _levels

    paths = _cgroup_paths() if cgroups is None else dict(cgroups)
    # v2 first; a hybrid system's v2 tree (at <root>/unified) has no memory files
    layouts = []
    if "" in paths:
        layouts.append((root, paths[""], "memory.max", "memory.current",
                        ("inactive_file",)))
    if "memory" in paths:
        layouts.append((os.path.join(root, "memory"), paths["memory"],
                        "memory.limit_in_bytes", "memory.usage_in_bytes",
                        ("total_inactive_file", "inactive_file")))
    for mount, path, max_name, usage_name, inactive in layouts:
        found = False
        best = None
        for level in _levels(path):
            text = _under(mount, level, max_name)
            if text is None:
                continue
            found = True
            limit = _int(text)  # "max" (v2): None
            usage = _int(_under(mount, level, usage_name))
            if limit is None or limit >= _V1_UNLIMITED or usage is None:
                continue
            usage = max(0, usage - _stat(_under(mount, level, "memory.stat"), *inactive))
            if best is None or limit - usage < best[0] - best[1]:
                best = (limit, usage)
        if found:
            return best
    return None


def meminfo_available(path: str = "/proc/meminfo") -> int | None:
    """The kernel's estimate of memory available without swapping (``MemAvailable``)."""
    try:
        with open(path) as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _machine() -> tuple[int, str]:
    """What the machine and the cgroup leave, and a phrase saying which is the bound."""
    avail = meminfo_available()
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):  # pragma: no cover - not Linux
            avail = 1 << 62
    where = "available on this machine"
    cg = cgroup_memory_limit()
    if cg is not None:
        limit, usage = cg
        left = max(0, limit - usage)
        if left < avail:
            avail = left
            where = (f"left by this process's cgroup (its limit {human_bytes(limit)}, "
                     f"{human_bytes(usage)} in use)")
    return avail, where


def _env_limit() -> int | None:
    text = os.environ.get(MEMORY_ENV, "")
    if not text.strip():
        return None
    try:
        return parse_size(text)
    except ValueError as exc:
        raise BadUsage(f"{MEMORY_ENV}={text!r}: {exc}") from None  # (exit 2, as VOLWARP_THREADS)


def explicit_limit() -> int | None:
    """The explicit limit in effect (``--memory-limit``, ``VOLWARP_MEMORY_LIMIT``: the lower), or None.

    The whole process's, before what it holds is taken off (:func:`_limit`).
    """
    found = [v for v in (_env_limit(), (_budget.get() or (None,))[0]) if v is not None]
    return min(found) if found else None


def process_rss() -> int:
    """The resident memory of this process now (bytes; 0 where /proc is not there)."""
    from .parallel import _read

    text = _read("/proc/self/statm")
    try:
        return int(text.split()[1]) * os.sysconf("SC_PAGE_SIZE") if text else 0
    except (IndexError, ValueError, OSError):  # pragma: no cover - not Linux
        return 0


def release_freed() -> None:
    """Give the memory freed so far back to the system (glibc's ``malloc_trim``), where it can.

    Arrays freed by the block tasks' threads stay in their malloc arenas, and
    count in the process's resident memory (:func:`process_rss`), until
    trimmed: a step after them (an output's commit) that weighs what is left
    under an explicit limit would otherwise find less than there is. Nothing
    where the C library has no ``malloc_trim`` (not glibc).
    """
    trim = getattr(libc(), "malloc_trim", None)
    if trim is not None:
        trim(0)


def libc():
    """The C library through ctypes (loaded once), or None where it cannot be loaded.

    Its functions are looked up by name (``getattr(libc(), name, None)``: None where
    this C library has none).
    """
    global _loaded
    if _loaded is None:
        import ctypes

        try:  # glibc's name, loaded as is: find_library runs ldconfig, a fork of the process
            _loaded = ctypes.CDLL("libc.so.6", use_errno=True)  # (2 ms a command)
        except OSError:
            import ctypes.util

            try:
                _loaded = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so", use_errno=True)
            except OSError:
                _loaded = False
    return _loaded or None


_loaded = None

#: glibc's mallopt parameter numbers of the trim and mmap thresholds, and of the arenas' count
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8


#: the mmap threshold :func:`large_allocations_mapped` fixes (glibc's own starting value)
MMAP_THRESHOLD = 128 << 10
#: the thresholds it leaves: the highest glibc's own rule raises the mmap threshold to
#: (DEFAULT_MMAP_THRESHOLD_MAX on 64-bit), and the trim threshold that rule pairs with it
AFTER_MMAP_THRESHOLD, AFTER_TRIM_THRESHOLD = 32 << 20, 64 << 20


def bound_arenas() -> None:
    """At most one glibc malloc arena a core from here on (glibc's default: eight a core).

    zarr decodes a store's chunks on a pool of threads, each with an arena of its
    own, which keeps the chunks it freed: read by box, a 256^3 store's blocks
    left 25-30 MiB more resident than the work (a ``distance`` by blocks peaked
    at 125 MiB under ``--memory-limit 112M``, a warp at 156 under 150M, or was
    refused for blocks). Sharing fewer arenas, the threads reuse what others
    freed: 97-101 MiB for that ``distance``, and the warp took 2.7-3.3 s
    instead of 4.7-5.9 (its page faults). Called where a store is opened for
    reading, before its threads start (arenas made before keep going). A
    ``MALLOC_ARENA_MAX`` of the environment wins; nothing where the C library
    is not glibc.
    """
    if os.environ.get("MALLOC_ARENA_MAX"):
        return
    mallopt = getattr(libc(), "mallopt", None)
    if mallopt is not None:
        from .parallel import available_cores

        mallopt(_M_ARENA_MAX, max(2, available_cores()))


@contextlib.contextmanager
def large_allocations_mapped():
    """While inside, glibc maps every allocation above 128 KiB on its own and unmaps it when freed.

    glibc raises its mmap threshold (up to 32 MiB) each time a mapped block is
    freed, and then serves those sizes from its arenas; zarr encodes and
    decodes on a pool of threads, each with its own arena, which
    ``malloc_trim`` cannot shrink past the chunks still in use: a store's
    writes by blocks left 60-70 MiB of freed frames resident (measured,
    256^3 float32), counted by every later check against an explicit limit
    (the commit's pyramid) and in the process's peak. A fixed threshold
    (``mallopt(M_MMAP_THRESHOLD)``, as ``MALLOC_MMAP_THRESHOLD_`` sets it)
    gives them back at once. Entered where OME-Zarr stores are written.

    The threshold is the process's: kept after the write, every later
    allocation of 128 KiB to 32 MiB was a fresh mapping (a script's 200 KB
    numpy temporaries ran 1.4x slower after one ``api.write`` of a store).
    glibc cannot go back to its own rule once a threshold is set, so on
    leaving (the last of nested or concurrent writes) the thresholds are
    set where that rule takes them after large frees: mmap 32 MiB, trim
    64 MiB; or, where the environment sets them (``MALLOC_MMAP_THRESHOLD_``,
    ``MALLOC_TRIM_THRESHOLD_``: a user's, Dask's nanny's), back to those,
    and a lower mmap threshold of the environment's holds inside too.
    Nothing where the C library is not glibc.
    """
    mallopt = getattr(libc(), "mallopt", None)
    if mallopt is None:
        yield
        return
    global _mapping_writes
    given_mmap = _malloc_env("MALLOC_MMAP_THRESHOLD_")
    given_trim = _malloc_env("MALLOC_TRIM_THRESHOLD_")
    with _mapping_lock:
        _mapping_writes += 1
        if _mapping_writes == 1:
            mallopt(_M_MMAP_THRESHOLD, min(MMAP_THRESHOLD, given_mmap or MMAP_THRESHOLD))
    try:
        yield
    finally:
        with _mapping_lock:
            _mapping_writes -= 1
            if _mapping_writes == 0:
                mallopt(_M_TRIM_THRESHOLD, AFTER_TRIM_THRESHOLD if given_trim is None
                        else given_trim)
                mallopt(_M_MMAP_THRESHOLD, AFTER_MMAP_THRESHOLD if given_mmap is None
                        else given_mmap)


def _malloc_env(name: str) -> int | None:
    """A glibc tunable the environment sets (``MALLOC_MMAP_THRESHOLD_=65536``), or None."""
    text = os.environ.get(name, "").strip()
    try:
        value = int(text) if text else None
    except ValueError:
        return None  # (glibc ignores what it cannot read too)
    return value if value is not None and 0 <= value < 2 ** 31 else None


_mapping_writes = 0
_mapping_lock = threading.Lock()


def _limit() -> tuple[int, str]:
    """The limit in effect and where it comes from (``--memory-limit``, the variable, ...).

    An explicit limit (``--memory-limit``, ``VOLWARP_MEMORY_LIMIT``) is the whole
    process's: what this process holds already (the interpreter, its libraries,
    the volumes read) is taken off it. The machine's and the cgroup's figures
    already count it.
    """
    avail, where = _machine()
    explicit = []
    env = _env_limit()
    if env is not None:
        explicit.append((env, os.environ.get(MEMORY_FROM_ENV) or MEMORY_ENV))
    budget = _budget.get()
    if budget is not None:
        explicit.append(budget)
    if explicit:
        held = process_rss()
        for limit, source in explicit:
            left = max(0, limit - held)
            if left <= avail:
                avail = left
                where = (f"the memory limit ({source}: {human_bytes(limit)}, of which this "
                         f"process holds {human_bytes(held)})")
    return avail, where


def available_memory() -> int:
    """Bytes this process may still allocate.

    The lower of ``MemAvailable`` and its cgroup's limit less usage, capped by
    ``VOLWARP_MEMORY_LIMIT`` and by the budget in effect (:func:`use_memory_limit`).

    A bad ``VOLWARP_MEMORY_LIMIT`` is a :class:`~volwarp_cli.errors.VolwarpError`
    naming the variable.
    """
    return _limit()[0]


# -- the budget -----------------------------------------------------------------------

@contextlib.contextmanager
def use_memory_limit(nbytes: int | None, *, source: str = "--memory-limit"):
    """Run the block inside with at most ``nbytes`` of memory (None: keep the limit).

    Nested budgets only lower the limit (the tighter one holds). ``source``
    names the budget in :func:`ensure_fits_in_memory`'s message. Yields the
    budget in effect inside (bytes; None if there is none), without reading
    the machine's memory (:func:`memory_limit` does).
    """
    outer = _budget.get()
    if nbytes is None:
        yield outer[0] if outer is not None else None
        return
    nbytes = int(nbytes)
    if nbytes < 1:
        raise ValueError(f"memory limit must be positive, got {nbytes}")
    inner = (nbytes, source) if outer is None or nbytes < outer[0] else outer
    token = _budget.set(inner)
    try:
        yield inner[0]
    finally:
        _budget.reset(token)


def limit_and_source() -> tuple[int, str]:
    """:func:`memory_limit` and where it comes from, as the refusals word it."""
    return _limit()


def memory_limit() -> int:
    """The memory budget in effect.

    The lower of :func:`use_memory_limit`'s (if any) and :func:`available_memory`
    (which is already capped by it).
    """
    return _limit()[0]


def ensure_fits_in_memory(nbytes: int, what: str) -> None:
    """Refuse, before allocating, ``nbytes`` for ``what`` if more than :func:`memory_limit`.

    Raises :class:`~volwarp_cli.errors.OutOfMemoryError`, whose one-line message
    gives both sizes and whether the limit is ``--memory-limit`` /
    ``VOLWARP_MEMORY_LIMIT`` or what the machine or the cgroup leaves.
    """
    limit, where = _limit()
    if nbytes > limit:
        if where.startswith("the memory limit"):
            raise OutOfMemoryError(f"{what} needs {human_bytes(nbytes)} but only "
                                   f"{human_bytes(limit)} is left under {where}")
        raise OutOfMemoryError(f"{what} needs {human_bytes(nbytes)} but only "
                               f"{human_bytes(limit)} of memory is {where}")


#: an input whose samples exceed this share of the memory budget is read by box (from its
#: file, or from a scratch copy where the file is compressed), not held whole: what is
#: left must hold the work's own arrays
READ_BY_BOX_SHARE = 0.25


def read_by_box(nbytes: int) -> bool:
    """Whether an input of ``nbytes`` samples is read by box rather than held whole."""
    return nbytes > READ_BY_BOX_SHARE * memory_limit()


#: More than what a command's libraries and compiled kernels take when they load (VTK's
#: filters, numba and its kernels: 60-250 MiB): see :func:`ensure_fits_once_loaded`.
LOAD_MARGIN = 512 << 20


def ensure_fits_once_loaded(nbytes: int, what: str, load) -> None:
    """:func:`ensure_fits_in_memory` for work whose libraries may not be loaded yet.

    An explicit limit is the whole process's, so what the work will load
    (libraries, compiled kernels) must count. Where the budget leaves
    :data:`LOAD_MARGIN` beyond ``nbytes`` that is so whatever they take, and
    nothing more is done; otherwise ``load()`` loads them first (it runs the
    work's kernels on something small; None: nothing to load), and the check
    counts what the process then holds.
    """
    limit, _ = _limit()
    if nbytes + LOAD_MARGIN <= limit:
        return
    ensure_fits_in_memory(nbytes, what)  # (what cannot fit even now: refused before loading)
    if load is not None:
        load()
        ensure_fits_in_memory(nbytes, what)


#: :func:`block_bytes`'s bounds.
BLOCK_FLOOR = 8 << 20
BLOCK_CEILING = 256 << 20


def block_bytes(threads: int | None = None, fraction: float = 0.5) -> int:
    """The bytes one block task may hold when ``threads`` tasks run at once.

    ``memory_limit() * fraction / threads``, kept within [8 MiB, 256 MiB]
    (:data:`BLOCK_FLOOR`, :data:`BLOCK_CEILING`). ``fraction`` is the share of
    the budget the blocks' working memory may take together (the rest: the
    whole-volume inputs and outputs, which the caller checks with
    :func:`ensure_fits_in_memory`). ``threads`` defaults to
    :func:`volwarp_cli.parallel.threads`.

    The floor wins over the budget: a block below 8 MiB (128^3 bytes) costs
    more in per-block overhead than it saves, and the whole work's own check
    refuses what does not fit. The ceiling bounds one task's temporaries and
    latency: past a few hundred MiB a block is no faster per byte, and smaller
    blocks balance the threads' load and let progress show.
    """
    if threads is None:
        from .parallel import threads as current_threads

        threads = current_threads()
    threads = int(threads)
    if threads < 1:
        raise ValueError(f"thread count must be at least 1, got {threads}")
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    per = int(memory_limit() * fraction) // threads
    return max(BLOCK_FLOOR, min(BLOCK_CEILING, per))
