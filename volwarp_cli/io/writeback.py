"""An output's finished samples sent towards the disk while the work goes on (Linux).

Every output is written to a temporary file and renamed over its path
(:mod:`.atomic`). Where that path holds an earlier file, ext4 (its default
``auto_da_alloc``, so that a crash leaves the old file or the new one, never an
empty one) writes the new file's data out during the rename, and the rename
waits for it: 40-47 ms of a 256^3 float32 warp's 0.5 s, its earlier output
replaced (5 ms of it CPU: the rest is the disk's queue). Asked for as each part
of the file is finished, from a thread of its own (a compute thread asking would
wait on that queue itself), the same writing overlaps the work, and the rename
finds little left to write (about 15 ms, the earlier file's freeing).

Asked for only where the output replaces a file (:func:`replacing`, said by
:func:`~.atomic.atomic_outputs` of each temporary it makes): a new file's rename
waits for nothing, and its writing out beside the work cost 1-2% there. This
changes neither what is written nor when an output appears: the kernel writes
those pages out a few seconds later anyway (but a temporary removed on an error
or a stop, whose pages a request may have sent out first). Only contiguous spans
of at least :data:`MIN_BYTES` are asked for (an output written by whole planes,
as the in-memory runs write theirs), and of a span only its whole pages, so that
a page shared with a neighbouring span is not sent out before that span is
written into it (it goes with the rename's own writing out). A request that
cannot be made (a system without ``sync_file_range``, no thread to be had,
:data:`MAX_PENDING` requests already waiting) is dropped: it was only ever a
head start. On a file system without writeback (tmpfs) a request does nothing.
"""

from __future__ import annotations

import os
import sys
import threading

#: spans smaller than this are left to the rename's writing out (a request costs a
#: system call and a descriptor; a small output's rename has little to wait for); an
#: in-memory warp of 160^3 float32 places 400 KiB at a time, its parts' edges 200 KiB
MIN_BYTES = 128 << 10

#: requests waiting for the thread or being made at most (each holds a duplicated
#: descriptor)
MAX_PENDING = 16

_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096

_SYNC_FILE_RANGE_WRITE = 2  # <fcntl.h>: start writing the dirty pages, do not wait

#: bytes a whole-file write (:func:`write`) writes between its requests
SPAN = 16 << 20

_lock = threading.Lock()
_state: dict = {}  # "call": sync_file_range (or None: unavailable), "queue", "pending"
_replacing: set[str] = set()  # temporaries to be renamed over an existing file


def replacing(tmp, replaces: bool) -> None:
    """Note whether the temporary ``tmp`` replaces an existing file (False: forgotten)."""
    if replaces:
        _replacing.add(os.fspath(tmp))
    else:
        _replacing.discard(os.fspath(tmp))


def replaces(path) -> bool:
    """Whether ``path`` is a temporary that replaces an existing file."""
    return os.fspath(path) in _replacing


def write(fh, view: memoryview) -> None:
    """``fh.write(view)``; where ``fh``'s file replaces one, :data:`SPAN` at a time, each asked out."""
    name = getattr(fh, "name", None)
    if len(view) < MIN_BYTES or not isinstance(name, str) or not replaces(name):
        fh.write(view)
        return
    for at in range(0, len(view), SPAN):
        offset = fh.tell()
        fh.write(view[at:at + SPAN])
        fh.flush()
        start(fh.fileno(), offset, min(SPAN, len(view) - at))


def start(fd: int, offset: int, nbytes: int) -> bool:
    """Ask for the whole pages of the ``nbytes`` bytes at ``offset`` of ``fd`` to be written out.

    True if asked. Returns at once; the request is made by a thread of this
    module's, on a duplicate of ``fd`` (the caller may close its own
    descriptor at once).
    """
    if nbytes < MIN_BYTES:
        return False
    first = -(-int(offset) // _PAGE) * _PAGE
    end = (int(offset) + int(nbytes)) // _PAGE * _PAGE
    from ..signals import blocked

    with _lock, blocked():  # (a stop between the dup and the put would leak the duplicate)
        if "call" not in _state:
            _state["call"] = _sync_file_range()
        if _state["call"] is None or _state.get("pending", 0) >= MAX_PENDING:
            return False
        if "queue" not in _state and not _start_thread():
            return False
        try:
            fd = os.dup(fd)
        except OSError:  # (out of descriptors: no head start)
            return False
        _state["pending"] = _state.get("pending", 0) + 1
        _state["queue"].append((fd, first, end - first))
        _state["ready"].notify()
    return True


def _start_thread() -> bool:
    """The thread that makes the requests, started (False, and none asked again, if it cannot)."""
    import collections

    _state["queue"], _state["ready"] = collections.deque(), threading.Condition(_lock)
    try:
        threading.Thread(target=_serve, args=(_state, _state["call"]),
                         name="volwarp-writeback", daemon=True).start()
    except RuntimeError:  # (no thread to be had: a limit on tasks)
        _state["call"] = None
        del _state["queue"], _state["ready"]
        return False
    return True


def pending() -> int:
    """Requests waiting for the thread, or being made (for the tests)."""
    with _lock:
        return _state.get("pending", 0)


def _serve(state: dict, call) -> None:
    """Make the requests queued in ``state`` (the module's), one at a time.

    A request stays first in the queue, with its descriptor, until it is made
    and the descriptor closed: a child forked meanwhile (under the lock, see
    :func:`_forget_in_child`) finds every descriptor it inherits listed.
    """
    import ctypes

    ready, requests = state["ready"], state["queue"]
    while True:
        with ready:
            while not requests:
                ready.wait()
            fd, offset, nbytes = requests[0]
        try:
            call(fd, ctypes.c_int64(offset), ctypes.c_int64(nbytes), _SYNC_FILE_RANGE_WRITE)
        except Exception:  # pragma: no cover - ctypes raises only on a wrong signature
            pass
        finally:
            with ready:
                requests.popleft()
                os.close(fd)
                state["pending"] -= 1


def _sync_file_range():
    """The C library's ``sync_file_range``, or None where there is none (not Linux)."""
    from ..memory import libc

    call = getattr(libc(), "sync_file_range", None) if sys.platform.startswith("linux") else None
    if call is None:
        return None
    import ctypes

    call.argtypes = [ctypes.c_int, ctypes.c_int64, ctypes.c_int64, ctypes.c_uint]
    call.restype = ctypes.c_int
    return call


def _forget_in_child() -> None:
    """A forked child has no thread: the requests it inherited closed, its own thread later.

    The fork happens with the lock held (:func:`_hold_for_fork`), so the queue
    lists every duplicate, the one being made included.
    """
    global _lock
    _lock = threading.Lock()
    requests = _state.pop("queue", None) or ()
    _state.pop("ready", None)
    _state.pop("pending", None)
    for fd, _, _ in requests:
        try:
            os.close(fd)
        except OSError:  # pragma: no cover - the duplicate is the queue's own
            pass


_held_for_fork = [False]  # (a stop may cut the acquire short: released only if taken)


def _hold_for_fork() -> None:
    _held_for_fork[0] = False
    _lock.acquire()
    _held_for_fork[0] = True


def _release_after_fork() -> None:
    if _held_for_fork[0]:
        _held_for_fork[0] = False
        _lock.release()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_hold_for_fork, after_in_parent=_release_after_fork,
                        after_in_child=_forget_in_child)
