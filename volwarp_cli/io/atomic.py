"""Atomic output files.

Every file volwarp writes goes to a temporary file in the output's folder and is
renamed into place only once it is complete, so a failure, Ctrl-C or SIGTERM
never leaves a partial output and never touches an existing one. Temporary
files still open when the process is told to stop are removed by the signal
handler installed by :func:`install_signal_handlers` (the CLI calls it).
"""

from __future__ import annotations

import contextlib
import os
import re
import socket
import tempfile
from pathlib import Path

from ..errors import VolwarpError
from ..signals import Interrupted, blocked, check_stop, install, temporaries
from .mapped import check_unchanged, sync_temporaries

__all__ = ["Interrupted", "atomic_output", "atomic_outputs", "check_output_path",
           "install_signal_handlers", "write_bytes_atomic"]

#: the registry the signal handler empties (see :mod:`volwarp_cli.signals`)
_live_temporaries = temporaries


def install_signal_handlers() -> None:
    """Record and raise SIGINT/SIGTERM (:mod:`volwarp_cli.signals`) so outputs are cleaned up."""
    install()


def check_output_path(path: str | os.PathLike) -> Path:
    """Fail early (before any work) when ``path`` cannot be written."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise VolwarpError(f"{path}: output folder {str(folder)!r} does not exist")
    if not os.access(folder, os.W_OK):
        raise VolwarpError(f"{path}: output folder {str(folder)!r} is not writable")
    if path.is_dir():
        raise VolwarpError(f"{path}: is a folder, not a file")
    return path


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    ``suffix`` defaults to the output's own extension(s), so libraries that
    choose behaviour by file name (``.nii.gz``, ``.tif``) see the right one.
    """
    with atomic_outputs(path, suffixes=None if suffix is None else [suffix]) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_outputs(*paths: str | os.PathLike, suffixes: list[str] | None = None):
    """Temporaries for several files that belong together, renamed onto them together.

    A detached header and its data file (``.nhdr`` + ``.raw``, ``.mhd`` +
    ``.raw``) must be both new or both old: the renames run with SIGINT and
    SIGTERM held back, in the order given (the data file first, so that a
    header never names data it does not describe), after the last checks.
    """
    paths = [check_output_path(p) for p in paths]
    if suffixes is None:
        suffixes = ["".join(p.suffixes[-2:]) if p.name.endswith(".gz") else p.suffix
                    for p in paths]
    tmps: list[str] = []
    try:
        for path, suffix in zip(paths, suffixes, strict=True):
            _remove_stale_temporaries(path)
            with blocked():  # made and registered at once: a stop cannot leak it
                fd, tmp = tempfile.mkstemp(prefix=_temporary_prefix(path.name),
                                           suffix=f".part{suffix}", dir=path.parent)
                _live_temporaries.add(tmp)
                tmps.append(tmp)
            os.close(fd)
        sync_temporaries()
        yield [Path(t) for t in tmps]
        for tmp in tmps:  # mkstemp makes files 0600: give the outputs the usual mode
            os.chmod(tmp, 0o666 & ~_UMASK)
        with blocked():
            check_stop()  # a stop asked while writing (and swallowed somewhere): no rename
            check_unchanged()  # an input mapped for these outputs changed: no rename
            for tmp, path in zip(tmps, paths, strict=True):
                os.replace(tmp, path)
    except BaseException as exc:
        for tmp in tmps:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(exc, OSError) and (exc.filename is None or exc.filename in tmps):
            # writing an output failed (a full disk, a quota): say which output
            named = paths[tmps.index(exc.filename)] if exc.filename in tmps else paths[-1]
            raise VolwarpError(f"{named}: cannot write ({exc.strerror or exc})") from exc
        raise
    finally:
        for tmp in tmps:
            _live_temporaries.discard(tmp)
        sync_temporaries()


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: read once, at import (os.umask can only be read by setting it: racy under threads)
_UMASK = _read_umask()


def _host() -> str:
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname()) or "host"


def _temporary_prefix(name: str) -> str:
    """``.NAME.vw-PID@HOST.``: a temporary says whose it is (mkstemp adds 8 random characters)."""
    return f".{name}.vw-{os.getpid()}@{_host()}."


def _remove_stale_temporaries(path: Path) -> None:
    """Remove the temporaries of ``path`` left by dead volwarp processes of this host.

    A process killed with SIGKILL (or a machine that lost power) cannot clean
    up; the next write of the same output does. Only files named by
    :func:`_temporary_prefix` for this output, this host and a process that no
    longer exists are removed: never another host's (a shared folder), a
    live process's, or anything else.
    """
    pattern = re.compile(re.escape(f".{path.name}.vw-") + r"(\d+)@" + re.escape(_host())
                         + r"\.[A-Za-z0-9_]{8}\.part")
    try:
        names = os.listdir(path.parent if str(path.parent) else ".")
    except OSError:
        return
    for name in names:
        m = pattern.match(name)
        if m is None or _alive(int(m.group(1))):
            continue
        with contextlib.suppress(OSError):
            os.unlink(path.parent / name)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's process (EPERM): alive
        return True
    return True


def write_bytes_atomic(path: str | os.PathLike, payload: bytes) -> None:
    """Write ``payload`` to ``path`` atomically."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(payload)
