"""Errors raised by the volwarp core.

The core never imports click: the command line maps these to exit codes
(``SpecError`` and ``BadUsage`` -> 2, every other ``VolwarpError`` -> 1)
and prints them as one line, ``volwarp: error: ...``.
"""

from __future__ import annotations


class VolwarpError(Exception):
    """A failure the user can act on: bad data, I/O, an impossible computation."""


class FormatError(VolwarpError):
    """A volume, image or capture file that is unreadable, truncated or malformed."""


class SpecError(VolwarpError):
    """A YAML spec that is malformed or asks for something impossible.

    ``key`` is the path of the offending key in the form ``steps[2].move[0].index``
    and ``line`` its 1-based line number in ``file``, when known.
    """

    def __init__(self, message: str, *, file: str | None = None, key: str | None = None,
                 line: int | None = None):
        self.message = message
        self.file = file
        self.key = key
        self.line = line
        super().__init__(str(self))

    def __str__(self) -> str:
        where = ""
        if self.file:
            where = f"{self.file}:{self.line}: " if self.line else f"{self.file}: "
        elif self.line:
            where = f"line {self.line}: "
        key = f"{self.key}: " if self.key else ""
        return f"{where}{key}{self.message}"


class BadUsage(VolwarpError):
    """A usage mistake the core finds (exit 2, as click's own usage errors).

    The command line was well formed but asks for something that must not
    run: an output that is one of the command's inputs, an option that
    contradicts the input it was given. Nothing has been written.
    """


class ChoiceNeeded(BadUsage):
    """An input that holds several things where one is needed, and only the user can say which.

    For example a DICOM folder with several series: a usage error, since an option chooses.
    """


class OutOfMemoryError(VolwarpError):
    """A volume whose size exceeds the memory this machine has available."""
