"""Inputs read while the work runs: what another program does to them meanwhile.

An input read box by box as the work goes (by ``pread``: a lazy volume, a
field read by windows; or through a memory map) is not a copy: if it is
rewritten in place meanwhile (``dd conv=notrunc``, a program saving over it),
the work reads a mix of the two, and a run by blocks wrote such a mix with
exit 0. :func:`watch` records such a file's identity; :func:`check_unchanged`,
called before every output's rename, refuses to rename an output made from
an input that changed while it was read: its size, modification time or
inode changed, or its content did while those stayed. A rewrite in place
that puts the modification time back (``cp -p`` of a file the same size,
``touch -r`` after a slow rewrite, ``rsync -c --inplace``) keeps all three
but moves the change time, which no program can set back. The change time
alone would refuse too much: a chmod or chown (even to the values the file
already has), a hard link made or removed, an xattr set, ``touch -a``, an
overlay file system's copy-up all move it with the bytes unchanged. So
where it moved, the content decides: :func:`_fingerprint` hashes
:data:`SAMPLES` pieces of the file spread over it (first and last among
them), taken when the file was first watched and again at the check. A
rewrite that changes no sampled piece (less than 1/:data:`SAMPLES` of the
file, between pieces) still goes unseen, and so does one within the same
tick of a coarse change-time clock (Linux before 6.13: a few ms) as the
first read.
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


#: the pieces of a watched file its fingerprint hashes, and their size
SAMPLES, SAMPLE_BYTES = 64, 4096


def _fingerprint(fd: int, size: int) -> bytes:
    """A hash of :data:`SAMPLES` pieces of the open file's ``size`` bytes (all of a small file).

    Spread evenly from its first byte to its last, so that any change of a
    stretch longer than ``size / SAMPLES`` changes it: 256 KiB read, about a
    millisecond from the page cache.
    """
    try:
        from _blake2 import blake2b  # (hashlib loads OpenSSL first: 4 ms of a small command)
    except ImportError:  # pragma: no cover - a Python built without it
        from hashlib import blake2b

    digest = blake2b(digest_size=16)
    if size <= SAMPLES * SAMPLE_BYTES:
        starts = range(0, size, SAMPLE_BYTES)
    else:
        last = size - SAMPLE_BYTES
        starts = (k * last // (SAMPLES - 1) for k in range(SAMPLES))
    for start in starts:
        digest.update(os.pread(fd, SAMPLE_BYTES, start))
    return digest.digest()


def _taken(file) -> tuple | None:
    """``(identity, ctime_ns, fingerprint)`` of ``file`` (a path or a descriptor), None if unreadable.

    The stat is taken again after the fingerprint, until both stats agree (a
    change between them could pair the old identity with the new bytes).
    """
    fd = file if isinstance(file, int) else os.open(file, os.O_RDONLY)
    try:
        for _ in range(3):
            st = os.fstat(fd)
            sampled = _fingerprint(fd, st.st_size)
            again = os.fstat(fd)
            if (_identity(again), again.st_ctime_ns) == (_identity(st), st.st_ctime_ns):
                return _identity(st), st.st_ctime_ns, sampled
        return _identity(again), again.st_ctime_ns, None  # (changing all the while)
    except OSError:
        return None
    finally:
        if not isinstance(file, int):
            os.close(fd)


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
    taken = _taken(file.fileno() if opened else file)
    if taken is None:  # (unreadable now: its reader says why)
        st = os.stat(file.fileno() if opened else file)
        taken = _identity(st), st.st_ctime_ns, None
    run_files().mapped[path] = taken


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
    for where, (ident, ctime, sampled) in list(run_files().mapped.items()):
        how = _change(where, ident, ctime, sampled)
        if how == "replaced":
            raise FormatError(f"{where}: the file changed while it was being read (replaced "
                              "or rewritten by another program?); the output is not written")
        if how == "rewritten":
            raise FormatError(f"{where}: the file changed while it was being read (rewritten "
                              "in place, its size and modification time kept: cp -p, "
                              "touch -r?); the output is not written")


def _change(where: str, ident: tuple, ctime: int, sampled: bytes | None) -> str | None:
    """How the file at ``where`` changed since it was watched: None where, as far as can be told, it did not."""
    try:
        st = os.stat(where)
    except OSError:
        return "replaced"
    if _identity(st) != ident:
        return "replaced"
    if st.st_ctime_ns == ctime:
        return None
    now = _taken(where)  # (the change time moved: its metadata only, or its bytes?)
    if now is None or sampled is None or now[2] is None:
        return None  # (unreadable, then or now: a chmod 000; as before this check)
    if now[0] != ident:
        return "replaced"
    return None if now[2] == sampled else "rewritten"
