"""Stopping on SIGINT, SIGTERM and the other signals that end a run: recorded, raised, checked again.

A cron job or Make that kills a run must be able to rely on exit 130 / 143
and on its old outputs; a job left in the foreground of an ssh session that
closes gets SIGHUP (129), and it left its temporary output behind (a hidden
256 MB file). So did every signal whose default is to end the process: a
batch system's warning before its time limit (Slurm's ``--signal=USR1@60``:
SIGUSR1, 138), SIGUSR2, a timer's SIGALRM (142), a CPU limit's SIGXCPU (152).
All of them are stops, SIGINT and SIGTERM always, the others unless the
process started with them ignored (``nohup`` ignores SIGHUP: such a job goes
on; a launcher that ignores SIGUSR1 keeps it ignored).

Raising from the handler alone is not enough: a library's ``except
Exception`` (nibabel's optional imports, a reader's catch-all turning any
failure into "file damaged") or a callback from C
(llvmlite's, through ctypes) can swallow the exception, and the run would go
on to rename its output into place and exit 0. So the handler

1. records the first signal (:func:`stop_requested`),
2. removes every temporary output still open (:data:`temporaries`),
3. raises :class:`Interrupted`, a ``BaseException`` (as ``KeyboardInterrupt``
   is) so that ``except Exception`` does not catch it,

and the safe points check the record again: :func:`check_stop` before every
rename of an output (``atomic_output``), and the command line's exit, which
turns any run during which a stop was asked into 128 + N, whatever the
command's own result.

This module imports nothing but the standard library, so the command line
installs it before numpy, click or any volwarp module is imported.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading

#: paths of temporary outputs not yet renamed into place (removed on a stop)
temporaries: set[str] = set()
_stop: list[int] = []  # the first stop's signal number, once one is asked
#: the signals that stop a run (all but SIGINT and SIGTERM only where not ignored: :func:`stops`)
STOPS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1,
         signal.SIGUSR2, signal.SIGALRM, signal.SIGXCPU)
#: what blocked() and settle() hold back (SIGALRM: also the deferred stop's re-check)
_HELD = frozenset(STOPS)


def stops() -> tuple:
    """The stop signals this process takes: SIGINT, SIGTERM, and the others not ignored."""
    return tuple(s for s in STOPS if s in (signal.SIGINT, signal.SIGTERM)
                 or signal.getsignal(s) is not signal.SIG_IGN)


class Interrupted(BaseException):
    """Raised inside the work when a stop (SIGINT, SIGTERM, ...) arrives, or at a safe point."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(f"interrupted by {signal.Signals(signum).name}")


#: how many :func:`blocked` sections the main thread is in, and whether a stop waits for
#: the outermost to end
_held_back = [0]
_waiting = [False]


def _on_signal(signum, frame):  # pragma: no cover - exercised in subprocess tests
    if not _stop:
        _stop.append(signum)
    if _held_back[0]:  # inside blocked(): the stop is raised as the section ends
        _waiting[0] = True
        return
    _remove_temporaries()
    _raise_when_safe(frame)


def _remove_temporaries() -> None:
    # Before raising: if the raise is swallowed somewhere, the promise "no stray
    # temporary file" still holds, and the rename will find none.
    for tmp in list(temporaries):
        with contextlib.suppress(OSError):
            if os.path.isdir(tmp) and not os.path.islink(tmp):  # an OME-Zarr store's
                import shutil

                shutil.rmtree(tmp, ignore_errors=True)
            else:
                os.unlink(tmp)
    temporaries.clear()


#: how soon a stop deferred by an import is looked at again (seconds)
_RECHECK = 0.02


def _raise_when_safe(frame) -> None:
    """Raise :class:`Interrupted` now, or, inside an import or a JIT compile, once it is over.

    An exception raised while an extension module initialises (VTK's
    ``vtkCommonCore``) crashed the process with SIGSEGV in about one run in
    ten stopped there, and one raised while numba compiles or loads a kernel
    from its cache (its Python code calling LLVM through llvmlite) crashed
    it in most runs stopped there (``mesh --decimate``); a timer looks again
    every few milliseconds instead.
    """
    if _held_back[0]:  # (the deferred stop's timer, inside blocked())
        _waiting[0] = True
        return
    if _importing(frame) or _compiling(frame):
        signal.signal(signal.SIGALRM, lambda s, f: _raise_when_safe(f))
        signal.setitimer(signal.ITIMER_REAL, _RECHECK)
        return
    cancel_deferred()
    _remove_temporaries()  # (again: some may have been made while the raise waited)
    raise Interrupted(_stop[0])


@contextlib.contextmanager
def blocked():
    """Hold the stops (and the deferred stop's SIGALRM) back for a few steps.

    Steps that must not be cut in two: a temporary made and registered, several
    files renamed together. A stop asked meanwhile is handled as soon as the block ends.

    The signal mask alone does not hold a stop back: it is the calling
    thread's, so another thread (numba's, a pool's) still takes the signal,
    and a signal that arrived just before the mask leaves Python's handler
    pending, to run at the next bytecode, inside the block. Both raised in the
    middle of ``mkstemp``: its file made, not yet registered, and left behind
    (about one stop in ten landing on a mesh's deferred raise). So the handlers
    see the block too, and only note the stop; it is raised here, at its end.
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # Python runs its handlers in the main thread only
        return
    # (counted before the mask is set and after it is restored: a handler running between
    # the two calls, at a bytecode, only notes the stop, and the mask is always restored)
    _held_back[0] += 1
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD)
        try:
            yield
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
    finally:
        _held_back[0] -= 1
    if not _held_back[0] and _waiting[0]:
        _waiting[0] = False
        _remove_temporaries()
        _raise_when_safe(sys._getframe(1))


#: code whose Python frames hold native state (LLVM's) that an exception would leave torn
_JIT_PACKAGES = ("numba", "llvmlite")


def _compiling(frame) -> bool:
    # frames inside the imported packages' own folders only (a path that merely contains
    # "numba" would defer every stop for good)
    roots = []
    for name in _JIT_PACKAGES:
        where = getattr(sys.modules.get(name), "__file__", None)
        if where:
            roots.append(os.path.dirname(where) + os.sep)
    if not roots:
        return False
    while frame is not None:
        if frame.f_code.co_filename.startswith(tuple(roots)):
            return True
        frame = frame.f_back
    return False


def _importing(frame) -> bool:
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib._bootstrap"):
            return True
        frame = frame.f_back
    return False


def _unraisable(hook):
    """An unraisable-exception hook that stays quiet about a stop.

    An exception raised in a ctypes callback (numba's compiler calls back into
    Python) cannot propagate: Python prints it as "Exception ignored in ..." with
    a traceback. A stop is recorded anyway, so it needs no such report.
    """
    def quiet(info):
        if isinstance(info.exc_value, Interrupted):
            return
        hook(info)
    return quiet


def install() -> None:
    """Handle the stops as described above (main thread only; an ignored SIGHUP stays so)."""
    for signum in stops():
        signal.signal(signum, _on_signal)
    if not getattr(sys.unraisablehook, "_volwarp", False):
        hook = _unraisable(sys.unraisablehook)
        hook._volwarp = True
        sys.unraisablehook = hook


def cancel_deferred() -> None:
    """Cancel the re-check timer of a stop deferred by an import (if one is armed).

    Once the stop has been raised, or the work is over and the stop is being
    reported, a late re-check would only raise again somewhere else.
    """
    if threading.current_thread() is threading.main_thread() and _stop:
        signal.setitimer(signal.ITIMER_REAL, 0)


def settle() -> None:
    """Let no stop raise any more: hold the stops and SIGALRM back, cancel a deferred stop.

    For the end of a command-line run, once its exit code is decided: a stop
    deferred by an import (the re-check timer) or a second Ctrl-C must not raise
    out of the exit itself, which would skip the fast exit and print a traceback
    (the interpreter's tear-down with numba's and VTK's threads alive can then
    crash). A stop that lands while this runs raises :class:`Interrupted` once,
    before the mask is in place: call it again.
    """
    signal.pthread_sigmask(signal.SIG_BLOCK, _HELD)
    signal.setitimer(signal.ITIMER_REAL, 0)


def stop_requested() -> int | None:
    """The signal number of the stop asked so far, or None."""
    return _stop[0] if _stop else None


def check_stop() -> None:
    """Raise :class:`Interrupted` if a stop was asked (a safe point: before a rename)."""
    if _stop:
        raise Interrupted(_stop[0])


def reset() -> None:
    """Forget a recorded stop (for in-process callers such as tests)."""
    _stop.clear()
    _waiting[0] = False
