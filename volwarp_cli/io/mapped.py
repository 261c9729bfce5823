"""Inputs read while the work runs: what another program does to them meanwhile.

An input read box by box as the work goes (by ``pread``: a lazy volume, a
field read by windows; or through a memory map) is not a copy: if it is
rewritten in place meanwhile (``dd conv=notrunc``, a program saving over it),
the work reads a mix of the two, and a run by blocks wrote such a mix with
exit 0. :func:`watch` records such a file's identity; :func:`check_unchanged`,
called before every output's rename, refuses to rename an output made from
an input that changed (size, modification time, inode) while it was read.
A mapped file (:func:`guard`) also gets a SIGBUS handler (in C,
``_mapguard``: it removes the temporary outputs, writes one line and exits
1): if it is truncated while mapped (``cp new.nrrd in.nrrd`` truncates
first), a read past the new end raises SIGBUS.
"""

from __future__ import annotations

import os

from ..errors import FormatError
from ..runscope import in_run, run_files
from ..signals import temporaries

_guard = None  # the _mapguard module, once a file is mapped


def _identity(st: os.stat_result) -> tuple[int, int, int]:
    # (not the change time: a chmod, a hard link made by a backup, an xattr move it with
    # the bytes unchanged; a rewrite that puts the modification time back goes unseen)
    return st.st_size, st.st_mtime_ns, st.st_ino


def watch(file, where: str | None = None) -> None:
    """Record the identity of ``file`` (open, or a path), an input read as the work goes.

    ``where``: its path (default: the open file's name). The first identity
    seen in a run stands. Only inside a command's run (:func:`.runscope.run_scope`):
    the API's process-wide files would hold a file's identity for the life of
    a script, and refuse its outputs once the script changed that file itself.
    Never volwarp's own temporaries (:func:`.atomic.is_own_temporary`).
    """
    if not in_run():
        return
    from .atomic import is_own_temporary

    opened = hasattr(file, "fileno")
    path = str(where if where is not None else file.name if opened else file)
    if is_own_temporary(path):  # (a scratch file the work writes and reads back)
        return
    st = os.fstat(file.fileno()) if opened else os.stat(file)
    run_files().mapped.setdefault(path, _identity(st))


def guard(fh, where: str) -> None:
    """Watch the open file ``fh`` (about to be mapped; ``where`` names it)."""
    global _guard
    watch(fh, where)
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
