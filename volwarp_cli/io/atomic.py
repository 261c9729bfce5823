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
import signal
import tempfile
from pathlib import Path

from ..errors import VolwarpError

_live_temporaries: set[str] = set()


class Interrupted(VolwarpError):
    """Raised inside the work when SIGINT or SIGTERM arrives."""

    def __init__(self, signum: int):
        self.signum = signum
        super().__init__(f"interrupted by {signal.Signals(signum).name}")


def _on_signal(signum, frame):  # pragma: no cover - exercised in a subprocess test
    # Remove temporaries first: if the raise below is swallowed somewhere,
    # the promise "no stray temporary file" still holds.
    for tmp in list(_live_temporaries):
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    _live_temporaries.clear()
    raise Interrupted(signum)


def install_signal_handlers() -> None:
    """Turn SIGINT/SIGTERM into :class:`Interrupted` so outputs are cleaned up."""
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)


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
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".part{suffix}", dir=path.parent)
    os.close(fd)
    _live_temporaries.add(tmp)
    try:
        yield Path(tmp)
        # Files are created 0600 by mkstemp; give the output the usual mode.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
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


def write_bytes_atomic(path: str | os.PathLike, payload: bytes) -> None:
    """Write ``payload`` to ``path`` atomically."""
    with atomic_output(path) as tmp:
        tmp.write_bytes(payload)
