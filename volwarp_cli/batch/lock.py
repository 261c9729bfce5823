"""One batch at a time per output folder: its bookkeeping folder, checked writable, and locked.

Two ``volwarp batch`` runs on one output folder (a cron job still going when
the next starts, a user's run beside it) would both do all the work and
write the same outputs. A run holds ``OUT/.volwarp-batch/lock`` with
``flock`` for its whole length: exclusively, or shared by the shards of a
SLURM array (``--shard I/N``), each of which also holds its own
``shard-I-of-N.lock`` exclusively (the shards share the folder, never a
scan). The holder writes its pid and host into the file it holds
exclusively, so a second run can say whom it waits for. The lock ends with
the process (the kernel drops it, even after SIGKILL); the files stay
(removing a lock file another run has open would let a third run in).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
import tempfile
from pathlib import Path

from ..errors import VolwarpError

#: the batch's own files, in the output folder
BOOK_DIR = ".volwarp-batch"
LOCK_NAME = "lock"
ARRAY_LOCK_NAME = "array.lock"


class Busy(VolwarpError):
    """The output folder is held by another batch (exit 75, EX_TEMPFAIL)."""

    exit_code = 75


def book_dir(output_dir: Path) -> Path:
    """The folder of the batch's bookkeeping (state, locks) in ``output_dir``."""
    return Path(output_dir) / BOOK_DIR


def check_writable(output_dir: Path) -> None:
    """Make the output folder and fail once, before any work, when it cannot be written."""
    folder = Path(output_dir)
    try:
        book_dir(folder).mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=".volwarp-batch-probe-", dir=folder)
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        raise VolwarpError(f"{folder}: cannot write in the output folder "
                           f"({exc.strerror or exc}); nothing was run") from None


def _owner(path: Path) -> str:
    """``pid N on HOST`` from a lock file its holder wrote, or a vaguer phrase."""
    try:
        info = json.loads(path.read_text())
        text = f"pid {int(info['pid'])} on {info['host']}"
        return text + (f", shard {info['shard']}" if info.get("shard") else "")
    except (OSError, ValueError, KeyError, TypeError):
        return "its pid unknown"


def _try(fd: int, mode: int) -> bool:
    try:
        fcntl.flock(fd, mode | fcntl.LOCK_NB)
    except OSError as exc:
        if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False
        raise
    return True


def _holder(folder: Path, fd: int) -> str:
    """Who holds the main lock: an exclusive holder wrote it; else the shards' files say."""
    if not _try(fd, fcntl.LOCK_SH):
        return _owner(folder / LOCK_NAME)
    fcntl.flock(fd, fcntl.LOCK_UN)
    with _gate(folder):  # (a probe outside it could make a starting shard think its file held)
        for shard in _held_shards(folder):
            return _owner(shard)
    return "its pid unknown"


def _held_shards(folder: Path, mine: Path | None = None):
    """The shard files a run holds (probed under :func:`_gate`), ``mine`` left out."""
    for shard in sorted(folder.glob("shard-*.lock")):
        if shard == mine:
            continue
        probe = os.open(shard, os.O_RDONLY)
        try:
            held = not _try(probe, fcntl.LOCK_EX)
        finally:
            os.close(probe)  # (a probe that took it lets it go here)
        if held:
            yield shard


@contextlib.contextmanager
def _gate(folder: Path):
    """``array.lock``, held exclusively for a moment.

    The shards' files are taken, signed and probed under it only, so a probe
    never meets a taking, nor a file not yet signed.
    """
    gate = _open(folder / ARRAY_LOCK_NAME)
    try:
        fcntl.flock(gate, fcntl.LOCK_EX)
        yield
    finally:
        os.close(gate)


def _acquire(fd: int, mode: int, wait: bool, who, on_wait) -> None:
    if _try(fd, mode):
        return
    if not wait:
        raise Busy(f"{who()}; give --wait to wait")
    if on_wait is not None:
        on_wait(who())
    fcntl.flock(fd, mode)


def _open(path: Path) -> int:
    return os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)


def _sign(fd: int, shard: str | None, array: str | None = None) -> None:
    os.ftruncate(fd, 0)
    os.pwrite(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                              "shard": shard, "array": array}).encode() + b"\n", 0)


def _other_array(folder: Path, count: int, array: str, mine: Path):
    """``(file, holder)`` of a shard of another array holding ``folder``, or None.

    Under :func:`_gate`, holding ``mine`` (this shard's file, left out): every
    file held was taken and signed under it. Another array: another N (in
    the file's name), or another manifest (in what its holder signed).
    """
    for shard in _held_shards(folder, mine):
        try:
            theirs = json.loads(shard.read_text()).get("array")
        except (OSError, ValueError, AttributeError):
            theirs = None
        if shard.stem.rsplit("-of-", 1)[-1] != str(count) or theirs != array:
            return shard, _owner(shard)
    return None


def _take_shard(folder: Path, fd: int, path: Path, label: str, array: str, count: int,
                wait: bool, busy: str, on_wait) -> None:
    """Take this shard's file and sign it, the other shards held being of its array only.

    Another holder of the file (the same shard run twice) or of another
    array: :class:`Busy`, or with ``wait`` waited for (``on_wait`` once).
    """
    said = False
    while True:
        with _gate(folder):
            if _try(fd, fcntl.LOCK_EX):
                other = _other_array(folder, count, array, path)
                if other is None:
                    _sign(fd, label, array)
                    return
                fcntl.flock(fd, fcntl.LOCK_UN)  # (let go under the gate)
                held, who = other[0], f"another --shard array: {other[1]}"
            else:
                held, who = path, _owner(path)
        if not wait:
            raise Busy(f"{busy} ({who}); give --wait to wait")
        if on_wait is not None and not said:
            on_wait(f"{busy} ({who})")
            said = True
        probe = os.open(held, os.O_RDONLY)  # (until its holder ends)
        try:
            fcntl.flock(probe, fcntl.LOCK_EX)
        finally:
            os.close(probe)


@contextlib.contextmanager
def hold(output_dir: Path, *, shard: tuple[int, int] | None = None, wait: bool = False,
         on_wait=None, manifest: Path | None = None):
    """Hold the output folder for this run (raises :class:`Busy` when another run has it).

    ``wait``: wait for it instead, calling ``on_wait(holder)`` once first.
    A shard shares the folder with the shards of its own array only: the
    same ``N`` and the same ``manifest`` (another array's running shard is
    another batch: :class:`Busy`, or waited for with ``wait``).
    """
    folder = book_dir(output_dir)
    folder.mkdir(parents=True, exist_ok=True)
    busy = f"{output_dir} is being processed by another batch"
    fds = []
    try:
        main = _open(folder / LOCK_NAME)
        fds.append(main)
        label = f"{shard[0]}/{shard[1]}" if shard else None
        _acquire(main, fcntl.LOCK_SH if shard else fcntl.LOCK_EX, wait,
                 lambda: f"{busy} ({_holder(folder, main)})", on_wait)
        if shard:
            path = folder / f"shard-{shard[0]}-of-{shard[1]}.lock"
            mine = _open(path)
            fds.append(mine)
            array = f"{shard[1]} {os.path.realpath(manifest) if manifest else ''}"
            _take_shard(folder, mine, path, label, array, shard[1], wait, busy, on_wait)
        else:
            _sign(main, label)
        yield
    finally:
        for fd in reversed(fds):
            os.close(fd)
