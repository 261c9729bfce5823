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

A folder read file by file as the work goes (an OME-Zarr store: its chunks
are opened by path) is watched the same way (:func:`watch_folder`), by
:func:`folder_identity`: another store swapped in by renames (as volwarp
writes one) gave the rest of the read the new store's chunks, a mix written
with exit 0. Its identity is the folder's inode and, under the folder that
is read (the store's level 0), every entry's name, inode, size and
modification time: a stat a file, a few microseconds a chunk file beside the
fraction of a millisecond each one's read takes. A chunk rewritten in place
with its size and modification time kept goes unseen.

A file scanned first and read later by what the scan found (a DICOM
series: its headers scanned, then its images' pixels read by offset, slab by
slab as the work goes) is stamped as its header is read (:func:`stamp`) and
checked on the descriptor each later read opens (:func:`unchanged`): the
pixels read are always the scanned file's, so nothing is left to check
before a rename.
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


def _blake2b():
    try:
        from _blake2 import blake2b  # (hashlib loads OpenSSL first: 4 ms of a small command)
    except ImportError:  # pragma: no cover - a Python built without it
        from hashlib import blake2b
    return blake2b(digest_size=16)


def _fingerprint(fd: int, size: int) -> bytes:
    """A hash of :data:`SAMPLES` pieces of the open file's ``size`` bytes (all of a small file).

    Spread evenly from its first byte to its last, so that any change of a
    stretch longer than ``size / SAMPLES`` changes it: 256 KiB read, about a
    millisecond from the page cache.
    """
    digest = _blake2b()
    if size <= SAMPLES * SAMPLE_BYTES:
        starts = range(0, size, SAMPLE_BYTES)
    else:
        last = size - SAMPLE_BYTES
        starts = (k * last // (SAMPLES - 1) for k in range(SAMPLES))
    for start in starts:
        digest.update(os.pread(fd, SAMPLE_BYTES, start))
    return digest.digest()


def _taken(file, digest=_fingerprint) -> tuple | None:
    """``(identity, ctime_ns, fingerprint)`` of ``file`` (a path or a descriptor), None if unreadable.

    ``digest(fd, size)``: the fingerprint (default :func:`_fingerprint`). The
    stat is taken again after the fingerprint, until both stats agree (a
    change between them could pair the old identity with the new bytes).
    """
    fd = file if isinstance(file, int) else os.open(file, os.O_RDONLY)
    try:
        for _ in range(3):
            st = os.fstat(fd)
            sampled = digest(fd, st.st_size)
            again = os.fstat(fd)
            if (_identity(again), again.st_ctime_ns) == (_identity(st), st.st_ctime_ns):
                return _identity(st), st.st_ctime_ns, sampled
        return _identity(again), again.st_ctime_ns, None  # (changing all the while)
    except OSError:
        return None
    finally:
        if not isinstance(file, int):
            os.close(fd)


def _head(head: int):
    """A fingerprint of a file's first ``head`` bytes (a DICOM image's header).

    Any other image has other identifiers there (its SOP Instance UID); a
    rewrite of the same image's samples alone, its size and modification
    time kept, goes unseen.
    """
    def digest(fd: int, size: int) -> bytes:
        hashed = _blake2b()
        hashed.update(os.pread(fd, min(head, size), 0))
        return hashed.digest()
    return digest


def stamp(fd: int, head: int) -> tuple:
    """What tells the open file ``fd`` from another put in its place or rewritten meanwhile.

    For a file that is scanned first and whose samples are read later, by
    offsets the scan found (a DICOM series' images: every one opened again
    as its slices are needed): its size, modification time and inode, its
    change time, and a hash of its first ``head`` bytes (the header scanned).
    :func:`unchanged` tells, on the file opened again,
    whether it is still that file.
    """
    taken = _taken(fd, _head(head))
    if taken is None:  # (a file read a moment ago: its descriptor cannot fail a stat)
        raise OSError(f"cannot stat the descriptor {fd}")
    return head, taken


def unchanged(fd: int, stamped: tuple) -> bool:
    """Whether the open file ``fd`` is still the one :func:`stamp` gave ``stamped`` of.

    Its size, modification time and inode are; where its change time moved
    (a chmod, a hard link, or bytes rewritten and the modification time put
    back), its header's hash too.
    """
    head, (ident, ctime, sampled) = stamped
    st = os.fstat(fd)
    if _identity(st) != ident:
        return False
    if st.st_ctime_ns == ctime:
        return True
    now = _taken(fd, _head(head))
    return now is not None and now[0] == ident and sampled is not None and now[2] == sampled


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
    """Raise if an input of this run read as the work goes changed since it was opened (before a rename)."""
    for where, (root, inner, taken) in list(run_files().folders.items()):
        if folder_identity(root, inner) != taken:
            raise folder_changed(where, "; the output is not written")
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


def folder_identity(root, inner, root_key: tuple | None = None) -> bytes | None:
    """A digest of the folder ``root`` (device, inode) and of what lies under ``inner`` in it.

    Every entry under ``inner``: its name, inode, size and modification time
    (a folder's changes as entries come and go). ``root_key``: the
    ``(device, inode)`` of ``root`` as first seen, for one taken before its
    contents are read (a store swapped between the two then differs from
    every later identity). None where it cannot be read.
    """
    digest = _blake2b()
    try:
        if root_key is None:
            st = os.stat(root)
            root_key = st.st_dev, st.st_ino
        digest.update(repr(tuple(root_key)).encode())
        folders = [(os.fspath(inner), ".")]  # (each with its name under ``inner``)
        while folders:
            folder, name = folders.pop()
            st = os.stat(folder)
            digest.update(f"{name}\0{st.st_ino}\0{st.st_mtime_ns}\n".encode(
                "utf-8", "surrogateescape"))
            with os.scandir(folder) as entries:
                for entry in sorted(entries, key=lambda e: e.name):
                    if entry.is_dir(follow_symlinks=False):
                        folders.append((entry.path, f"{name}/{entry.name}"))
                        continue
                    st = entry.stat()
                    digest.update(f"{entry.name}\0{st.st_ino}\0{st.st_size}\0"
                                  f"{st.st_mtime_ns}\n".encode("utf-8", "surrogateescape"))
    except OSError:
        return None
    return digest.digest()


def watch_folder(root, inner, taken: bytes | None, where: str) -> None:
    """Record ``taken`` (:func:`folder_identity` at the opening) of a folder read as the work goes.

    ``where`` names it. As :func:`watch`: the first identity seen in a run
    stands, only inside a run, never volwarp's own temporaries.
    """
    if not in_run():
        return
    from .atomic import is_own_temporary

    if is_own_temporary(root) or where in run_files().folders:
        return
    run_files().folders[where] = (os.path.abspath(root), os.path.abspath(inner), taken)


def folder_changed(where: str, then: str = "") -> FormatError:
    """The error of a folder input (a store) that changed while it was read; ``then``: what follows."""
    return FormatError(f"{where}: the store changed while it was being read (replaced or "
                       f"rewritten by another program?){then}")
