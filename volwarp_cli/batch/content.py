"""What a file holds, by its sha256, hashed once per change (the batch's "up to date" is by content).

A scan replaced by ``rsync -a`` or ``cp -p`` may carry an older modification
time than the outputs made from it; only its bytes tell. Hashing a 2 GB scan
on every run costs seconds, so each digest is kept with the file's
``(device, inode, size, mtime_ns, ctime_ns)``: while all five are the same,
the bytes are taken to be the same. A replaced file changes its ctime (which
no program can set back) and, when renamed into place, its inode, whatever
mtime it was given; a file changed within :data:`RACY_SECONDS` of being
hashed is hashed again next time (a timestamp's granularity could hide a
second change, as git's "racily clean" index entries).

FAT and exFAT store no change time: exfat-fuse reports the modification
time as ctime, which ``cp -p`` and ``touch -r`` set back, and a file
rewritten in place keeps its inode; the kernel's drivers keep a ctime in
memory only (a creation time once read from the disk again). A scan
replaced that way on a USB disk, same size, could keep all five and its old
digest: the batch would skip it. On those filesystems (:data:`NO_CHANGE_TIME`,
found by the device's mount) a digest is never taken from the cache: every
run hashes the files again. FUSE mounts (``fuse.*``) too: a FUSE daemon
reports the ctime it chooses, and sshfs and rclone report the modification
time (SFTP carries no change time), which ``rsync -a --inplace`` on the
server sets back.

An input is all its files (:func:`content_digest`): a detached header with its
data files, a folder (a DICOM series, a Zarr store) with every file in it,
by name and content.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import stat
import threading
import time
from pathlib import Path

#: a file whose ctime is this close to its hashing is not trusted to the cache
RACY_SECONDS = 2.0
#: bytes read at once while hashing
_CHUNK = 1 << 20


#: filesystems whose ctime is not a change time (fuseblk: exfat-fuse's, and ntfs-3g's;
#: fuse: every ``fuse.SUBTYPE``, sshfs's and rclone's the modification time)
NO_CHANGE_TIME = frozenset({"vfat", "msdos", "fat", "exfat", "fuseblk", "fuse"})


def filesystem_type(dev: int, mountinfo: str = "/proc/self/mountinfo") -> str | None:
    """The type of the filesystem mounted as device ``dev`` (``st_dev``), or None if unknown.

    From the mount table's ``major:minor`` field (a Linux mount table; none elsewhere).
    """
    want = f"{os.major(dev)}:{os.minor(dev)}"
    try:
        with open(mountinfo, encoding="utf-8", errors="replace") as fh:
            for line in fh:
                fields = line.split()
                if len(fields) > 2 and fields[2] == want and " - " in line:
                    return line.split(" - ", 1)[1].split()[0]
    except OSError:
        pass
    return None


_change_time_kept: dict[int, bool] = {}


def keeps_change_time(dev: int) -> bool:
    """Whether files on device ``dev`` have a ctime that changes with their bytes (module notes)."""
    kept = _change_time_kept.get(dev)
    if kept is None:
        kind = (filesystem_type(dev) or "").split(".", 1)[0]  # (fuse.sshfs: fuse)
        kept = _change_time_kept[dev] = kind not in NO_CHANGE_TIME
    return kept


def stat_key(st: os.stat_result) -> list[int]:
    """The identity of a file's current bytes, as far as its metadata tells."""
    return [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]


def file_sha256(path: str | os.PathLike) -> str:
    """The sha256 of a file's bytes (hex)."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


class FileHashes:
    """sha256 of files, cached by :func:`stat_key` (shared by the scans of one batch).

    ``entries``: absolute path -> ``[*stat_key, sha256]``; ``fresh``: the
    entries computed since this object was made (what a cluster task sends
    back for the batch process to keep). A file hashed too soon after its
    last change is remembered for this process only (``_racy``): a step's
    output is hashed once when it is recorded, not again when the next step
    reads it, and hashed again by the next run.
    """

    def __init__(self, entries: dict[str, list] | None = None):
        self.entries: dict[str, list] = dict(entries or {})
        self.fresh: dict[str, list] = {}
        self._racy: dict[str, list] = {}
        self.lock = threading.Lock()
        self.hashed_bytes = 0  # (what the cache did not spare: for the measurements)

    def sha256(self, path: str | os.PathLike) -> str:
        """The sha256 of ``path``'s bytes; raises OSError when it cannot be read."""
        name = os.path.abspath(path)
        st = os.stat(name)
        key = stat_key(st)
        trusted = keeps_change_time(st.st_dev)
        with self.lock:  # (a saved entry out of date, a racy one of this run may be current)
            known = [k for k in (self.entries.get(name), self._racy.get(name))
                     if trusted and k is not None and k[:-1] == key]
        if known:
            return known[0][-1]
        digest = file_sha256(name)
        if stat_key(os.stat(name)) != key:  # changed while hashed: trust it nowhere
            return digest
        with self.lock:
            self.hashed_bytes += st.st_size
            if time.time() - st.st_ctime_ns / 1e9 > RACY_SECONDS:
                self.entries[name] = self.fresh[name] = [*key, digest]
                self._racy.pop(name, None)
            else:
                self._racy[name] = [*key, digest]
        return digest

    def subset(self, roots: list[str]) -> dict[str, list]:
        """The entries of the files at or under ``roots`` (absolute paths)."""
        want = set(roots)
        prefixes = tuple(r.rstrip("/") + "/" for r in roots)
        with self.lock:
            return {k: v for k, v in self.entries.items()
                    if k in want or k.startswith(prefixes)}


def _content_files(path: Path) -> tuple[list[Path], Path]:
    """The files ``path`` stands for, and the folder their names are taken from.

    A file with the data files its header names (:func:`..io.inputs.input_files`),
    a folder with every file in it.
    """
    from ..io.inputs import folder_files, input_files

    if path.is_dir():
        return folder_files(path), path
    return input_files(path), path.parent


def content_digest(path: str | os.PathLike, hashes: FileHashes) -> str:
    """The sha256 of everything ``path`` stands for: its files' names and bytes.

    Raises OSError when one is missing.
    """
    files, base = _content_files(Path(path))
    parts = [(os.path.relpath(f, base), hashes.sha256(f)) for f in files]
    return hashlib.sha256(json.dumps(parts).encode()).hexdigest()


def changed_at(st: os.stat_result, now: float) -> float:
    """When a file last changed or arrived (seconds since the epoch), as its times tell.

    The later of its mtime and ctime: ``rsync -a`` and ``cp -p`` give a file
    its source's old mtime, and its ctime (set by every write and rename, and
    by no program back) says when it came. An mtime ahead of ``now`` is not
    taken (a file dated by a clock ahead of this one, copied with its dates,
    would else not settle before that date): the ctime is.
    """
    if st.st_mtime > now:
        return st.st_ctime
    return max(st.st_mtime, st.st_ctime)


def last_change(files, now: float) -> float | None:
    """The latest :func:`changed_at` of ``files`` (None: no file).

    A file gone since it was listed was being moved: it changed ``now``. A
    link counts by its own times and its target's (a series of links made
    one by one to slices stored long ago was read short, its slices' old
    times taken: exit 0); one whose target is missing by its own.
    """
    newest = None
    for f in files:
        try:
            found = [os.lstat(f)]
        except OSError:
            return now
        if stat.S_ISLNK(found[0].st_mode):
            with contextlib.suppress(OSError):
                found.append(os.stat(f))
        for st in found:
            t = changed_at(st, now)
            newest = t if newest is None or t > newest else newest
    return newest


def age_words(age: float) -> str:
    """``3 s old``, or ``dated 40 s ahead of this machine's clock`` (a file from a clock ahead)."""
    if age > -1:
        return f"{max(age, 0):.0f} s old"
    return f"dated {-age:.0f} s ahead of this machine's clock"


def input_last_change(path: str | os.PathLike, now: float) -> float | None:
    """:func:`last_change` of every file ``path`` stands for (those :func:`content_digest` reads).

    A folder's own, and each folder its files lie in, count too: a folder of
    slices moved in keeps its slices' times (a rename changes the folder's
    entries, not its files), on exFAT or sshfs (no ctime) ``rsync -a`` dates
    each slice back and only the folder's mtime says one came, and a folder
    just made has no file yet. A link that is ``path`` itself counts by its
    target's times only (a script making a link to each series before the
    batch runs would else hold every scan back at every run).
    """
    path = Path(path)
    files, _ = _content_files(path)
    if path.is_dir():
        folders = dict.fromkeys(f.parent for f in files if f.parent != path)
        files = [*files, Path(os.path.realpath(path)), *folders]
    return last_change(files, now)


def content_stamp(path: str | os.PathLike) -> list:
    """The name and :func:`stat_key` of each file :func:`content_digest` reads (None: missing).

    Taken before a step's inputs are hashed and again once it has run: a file
    replaced meanwhile (and perhaps put back) may not be what the step read.
    """
    files, base = _content_files(Path(path))
    out = []
    for f in files:
        try:
            key = stat_key(os.stat(f))
        except OSError:
            key = None
        out.append([os.path.relpath(f, base), key])
    return out
