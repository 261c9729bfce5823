"""Inputs read while the work runs: what another program does to them meanwhile.

An input read box by box as the work goes (by ``pread``: a lazy volume, a
field read by windows; or through a memory map) is not a copy: if it is
rewritten in place meanwhile (``dd conv=notrunc``, a program saving over it),
the work reads a mix of the two, and a run by blocks wrote such a mix with
exit 0. :func:`watch` records such a file's identity; :func:`check_unchanged`,
called before every output's rename, refuses to rename an output made from
an input that changed while it was read: its size, modification time or
inode, or its change time with nothing in its metadata to account for it.
A rewrite in place that puts the modification time back (``cp -p`` of a
file the same size, ``touch -r`` after a slow rewrite) still moves the
change time, which no program can set back; a chmod, a chown, a hard link
made or removed (a backup's), an xattr or ACL set also move it, with the
bytes unchanged, and are told apart by the mode, owner, link count and
xattrs they change (:func:`_explained`).
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
    return st.st_size, st.st_mtime_ns, st.st_ino


def _xattrs(file) -> tuple:
    """``file``'s extended attributes (names and values; ACLs among them), () where none can be read."""
    try:
        names = sorted(os.listxattr(file))
        return tuple((n, os.getxattr(file, n)) for n in names)
    except OSError:  # (a file system without them, or the file gone: the stat tells)
        return ()


def _explained(st: os.stat_result, file) -> tuple:
    """What moves a file's change time without its bytes: mode, owner, links, xattrs."""
    return st.st_mode, st.st_uid, st.st_gid, st.st_nlink, _xattrs(file)




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
    if path in run_files().mapped:  # (the first identity seen in a run stands)
        return
    handle = file.fileno() if opened else file
    st = os.stat(handle)
    run_files().mapped[path] = (_identity(st), st.st_ctime_ns, _explained(st, handle))


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
    for where, (ident, ctime, explained) in list(run_files().mapped.items()):
        try:
            st = os.stat(where)
        except OSError:
            st = None
        if st is None or _identity(st) != ident:
            raise FormatError(f"{where}: the file changed while it was being read (replaced "
                              "or rewritten by another program?); the output is not written")
        if st.st_ctime_ns != ctime and _explained(st, where) == explained:
            raise FormatError(f"{where}: the file changed while it was being read (its change "
                              "time moved, its size and modification time kept: rewritten in "
                              "place with its time put back?); the output is not written "
                              "(if only its times were set, run again)")
