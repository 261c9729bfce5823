"""Inputs read through a memory map: what another program does to them meanwhile.

A mapped input (``volwarp warp``'s NRRD) is not a copy: if the file is
truncated while it is mapped (``cp new.nrrd in.nrrd`` truncates first), a
read past the new end raises SIGBUS, and if it is rewritten in place the warp
reads a mix of the two. :func:`guard` installs a SIGBUS handler (in C,
``_mapguard``: it removes the temporary outputs, writes one line and exits 1)
and records the file's identity; :func:`check_unchanged`, called before
every output's rename, refuses to rename an output made from an input that
changed (size, modification time or inode) while it was read.
"""

from __future__ import annotations

import os

from ..errors import FormatError
from ..runscope import run_files
from ..signals import temporaries

_guard = None  # the _mapguard module, once a file is mapped


def _identity(st: os.stat_result) -> tuple[int, int, int]:
    return st.st_size, st.st_mtime_ns, st.st_ino


def guard(fh, where: str) -> None:
    """Watch the open file ``fh`` (about to be mapped; ``where`` names it)."""
    global _guard
    run_files().mapped[where] = _identity(os.fstat(fh.fileno()))
    if _guard is None:
        from . import _mapguard

        _mapguard.install((f"volwarp: error: {where}: the file was truncated while it was "
                           "being read (replaced by another program?)\n")
                          .encode("utf-8", "surrogateescape"))  # (a name's own bytes)
        _guard = _mapguard
    sync_temporaries()


def sync_temporaries() -> None:
    """Tell the SIGBUS handler which temporary outputs exist now (no-op when none is mapped)."""
    if _guard is not None:
        _guard.set_temporaries(sorted(temporaries))


def check_unchanged() -> None:
    """Raise if a mapped input of this run changed since it was mapped (before a rename)."""
    for where, ident in list(run_files().mapped.items()):
        try:
            now = _identity(os.stat(where))
        except OSError:
            now = None
        if now != ident:
            raise FormatError(f"{where}: the file changed while it was being read (replaced "
                              "or rewritten by another program?); the output is not written")
