"""Progress bars and step logging for long work, on stderr.

The core calls :func:`progress` and :func:`timed`; both do nothing visible
unless the command line switched them on (a bar only when stderr is a
terminal and ``--quiet`` was not given; step timings with ``--verbose``).
"""

from __future__ import annotations

import contextlib
import contextvars
import sys
import threading
import time

DEBUG, INFO, WARNING, ERROR = 10, 20, 30, 40  # (logging's levels)


class _VolwarpLog:
    """The ``volwarp`` logger (:mod:`logging`'s), imported when a record may be emitted.

    Importing :mod:`logging` (and the traceback, string and weakref modules it
    imports) took 5 ms of every command's start, and a run at the default
    verbosity mostly emits nothing. So until something imports logging (a
    warning to emit, a reader that uses it, a library caller's own set-up), a
    call below the level the command line asked for (:func:`configure`) ends
    here. Everything else is the real logger's: the records, its level,
    handlers and filters (any other attribute is read from it and set on it).
    Every module of volwarp logs through this one (a module logging on the
    real ``volwarp`` logger before the first record here would find it not
    set up: no prefix, no ``-q``).
    """

    def __init__(self):
        object.__setattr__(self, "_asked", None)  # configure()'s, while logging is not loaded
        object.__setattr__(self, "_lock", threading.Lock())

    def _logger(self):
        import logging

        logger = logging.getLogger("volwarp")
        if self._asked is not None:  # (configured before logging was imported)
            with self._lock:  # (two threads' first records: one set-up, one handler)
                if self._asked is not None:
                    _set_up(logger, self._asked)
                    object.__setattr__(self, "_asked", None)
        return logger

    def isEnabledFor(self, level: int) -> bool:  # noqa: N802 - logging's name
        if self._asked is not None and "logging" not in sys.modules:
            return level >= self._asked
        return self._logger().isEnabledFor(level)

    def _emit(self, level: int, msg, args, kwargs) -> None:
        if self.isEnabledFor(level):
            kwargs.setdefault("stacklevel", 3)  # (the record names its caller, not this)
            self._logger().log(level, msg, *args, **kwargs)

    def debug(self, msg, *args, **kwargs) -> None:
        self._emit(DEBUG, msg, args, kwargs)

    def info(self, msg, *args, **kwargs) -> None:
        self._emit(INFO, msg, args, kwargs)

    def warning(self, msg, *args, **kwargs) -> None:
        self._emit(WARNING, msg, args, kwargs)

    def error(self, msg, *args, **kwargs) -> None:
        self._emit(ERROR, msg, args, kwargs)

    def __getattr__(self, name: str):  # level, handlers, filters, setLevel, addFilter, ...
        return getattr(self._logger(), name)

    def __setattr__(self, name: str, value) -> None:  # propagate, level, disabled, ...
        setattr(self._logger(), name, value)


log = _VolwarpLog()

#: Whether bars are drawn, per context: the command line's (set by :func:`configure`),
#: not a process-wide setting a library caller or a Dask worker's threads would share.
_bars: contextvars.ContextVar[bool] = contextvars.ContextVar("volwarp_progress_bars",
                                                              default=False)


def configure(verbosity: int) -> None:
    """``verbosity``: -1 quiet, 0 default, 1 verbose (steps), 2 debug.

    Bars are switched on for the calling context (the command line's thread
    and the tasks :func:`volwarp_cli.parallel.run_blocks` runs for it); the
    level is the ``volwarp`` logger's, which a caller may set as it likes
    (set when logging is imported, if it is not yet: :class:`_VolwarpLog`).
    """
    _bars.set(verbosity >= 0 and sys.stderr.isatty())
    level = {-1: ERROR, 0: WARNING, 1: INFO}.get(verbosity, DEBUG)
    if "logging" in sys.modules:
        object.__setattr__(log, "_asked", None)
        _set_up(sys.modules["logging"].getLogger("volwarp"), level)
    else:
        object.__setattr__(log, "_asked", level)


def _set_up(logger, level: int) -> None:
    """The command line's ``volwarp`` logger: ``level``, one line a record on stderr."""
    import logging

    class _StderrHandler(logging.StreamHandler):
        """Writes to whatever ``sys.stderr`` is when a record is emitted.

        A plain StreamHandler keeps the stream it was made with; when the CLI runs
        several times in one process (tests, a Python caller redirecting stderr)
        messages would go to a stale, possibly closed stream.
        """

        def __init__(self):
            super().__init__(sys.stderr)

        @property
        def stream(self):
            return sys.stderr

        @stream.setter
        def stream(self, value):  # StreamHandler.__init__ assigns it; the property ignores it
            pass

    class _Formatter(logging.Formatter):
        """``volwarp: MESSAGE``, a warning's ``volwarp: warning: MESSAGE`` whoever wrote it.

        Two thirds of the warnings said it themselves and the rest did not
        (``volwarp: steps[1]: the handles cannot all be reached``): a script
        sorting stderr lines by that word missed them.
        """

        def format(self, record) -> str:
            text = super().format(record)
            if record.levelno == logging.WARNING and not text.startswith("volwarp: warning"):
                text = "volwarp: warning: " + text[len("volwarp: "):]
            return text

    logger.setLevel(level)
    # (its own handler looked for, not any: a caller's handler on the logger, added before
    # the first command, left the command lines of that process without their stderr)
    if not any(getattr(h, "volwarp_stderr", False) for h in logger.handlers):
        handler = _StderrHandler()
        handler.volwarp_stderr = True
        handler.setFormatter(_Formatter("volwarp: %(message)s"))
        logger.addHandler(handler)
    logger.propagate = False


class Progress:
    """A counter from 0 to ``total`` drawn as a one-line bar."""

    def __init__(self, total: int, label: str):
        self.total = max(int(total), 1)
        self.label = label
        self.done = 0
        self.enabled = _bars.get()
        self._start = time.perf_counter()
        self._last_draw = 0.0

    def advance(self, n: int = 1) -> None:
        """Count ``n`` more steps done (at most ``total``); the bar redrawn every 0.1 s at most."""
        self.done = min(self.done + n, self.total)
        if self.enabled:
            now = time.perf_counter()
            if now - self._last_draw > 0.1 or self.done == self.total:
                self._last_draw = now
                self._draw()

    def _draw(self) -> None:
        width = 30
        filled = int(width * self.done / self.total)
        bar = "#" * filled + "-" * (width - filled)
        sys.stderr.write(f"\r{self.label} [{bar}] {self.done}/{self.total}")
        sys.stderr.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()
        log.info("%s: %d steps in %.2f s", self.label, self.done,
                 time.perf_counter() - self._start)
        return False


def progress(total: int, label: str) -> Progress:
    """A :class:`Progress` bar of ``total`` steps labelled ``label`` (drawn if bars are on)."""
    return Progress(total, label)


@contextlib.contextmanager
def timed(label: str):
    """Log how long the block took (shown with --verbose)."""
    start = time.perf_counter()
    try:
        yield
    finally:
        log.info("%s: %.3f s", label, time.perf_counter() - start)
