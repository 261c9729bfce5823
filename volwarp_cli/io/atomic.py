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
from ..signals import Interrupted, check_stop, install, temporaries
from .mapped import check_unchanged, sync_temporaries

__all__ = ["Interrupted", "atomic_output", "check_output_path", "install_signal_handlers",
           "write_bytes_atomic"]

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
    path = check_output_path(path)
    if suffix is None:
        suffix = "".join(path.suffixes[-2:]) if path.name.endswith(".gz") else path.suffix
    _remove_stale_temporaries(path)
    fd, tmp = tempfile.mkstemp(prefix=_temporary_prefix(path.name), suffix=f".part{suffix}",
                               dir=path.parent)
    os.close(fd)
    _live_temporaries.add(tmp)
    sync_temporaries()
    try:
        yield Path(tmp)
        # Files are created 0600 by mkstemp; give the output the usual mode.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        check_stop()  # a stop asked while writing (and swallowed somewhere): no rename
        check_unchanged()  # an input mapped for this output changed meanwhile: no rename
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename in (None, tmp):
            # writing the output failed (a full disk, a quota): say which output
            raise VolwarpError(f"{path}: cannot write ({exc.strerror or exc})") from exc
        raise
    finally:
        _live_temporaries.discard(tmp)
        sync_temporaries()


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
