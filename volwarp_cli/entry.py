"""The ``volwarp`` command's entry point: the stop handling comes before any import.

Importing numpy, click and the command modules takes about 0.1 s; a SIGINT in
that time used to print a KeyboardInterrupt traceback and exit -2. The
handlers of :mod:`volwarp_cli.signals` (standard library only) are installed
first, so a stop at any moment exits 130 / 143 with one line.

Before numba is imported, :func:`configure_numba_cache` chooses where the
compiled kernels are cached, so that the kernels ``python -m volwarp_cli.warmup``
compiled at install (``make install`` runs it) are the ones every command loads,
whoever runs it:

1. ``NUMBA_CACHE_DIR`` set by the user: that folder (numba's own rule).
2. The package folder writable (an editable or a user's own install; a
   container run by the user who built it): numba's default, each kernel's
   ``__pycache__`` beside its source, where the warm-up wrote them.
3. Otherwise (a read-only install: a system site-packages, a read-only
   image or mount, another user): ``NUMBA_CACHE_DIR`` is set to a per-user
   folder, ``$XDG_CACHE_HOME/volwarp/numba`` (``~/.cache/volwarp/numba``), or
   ``$TMPDIR/volwarp-numba-<uid>`` where the home folder cannot be written, and
   the kernels compiled at install are copied into it once per install (numba
   finds a kernel's cache files by its source folder's path: the copy puts
   them where it looks, and a cache file is checked against its source file's
   contents when loaded, so a stale or foreign one is recompiled, never used).

Standard library only, a few ``stat`` calls (and one small file read on a read-only
install): it costs a command nothing measurable.
"""

from __future__ import annotations

import os
import sys

#: the file the warm-up leaves in the package's ``__pycache__``: which warm-up the
#: install's compiled kernels are from (a per-user cache copies them once per value)
WARMUP_MARK = "volwarp-numba-warmup.txt"
_SEEDED = ".volwarp-seeded-{}"  # in the per-user cache: the warm-up mark it was copied from


def package_dir() -> str:
    """The folder of the ``volwarp_cli`` package (the kernels' sources)."""
    return os.path.dirname(os.path.abspath(__file__))


def _writable(folder: str) -> bool:
    """Whether numba can write its cache files beside the package's sources."""
    pycache = os.path.join(folder, "__pycache__")
    if os.path.isdir(pycache):
        return os.access(pycache, os.W_OK | os.X_OK)
    return os.access(folder, os.W_OK | os.X_OK)


def user_cache_dir() -> str:
    """The per-user folder of compiled kernels for a read-only install (module notes)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "volwarp", "numba")


def _usable(folder: str) -> bool:
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return False
    return os.access(folder, os.W_OK | os.X_OK)


def numba_cache_dir() -> str | None:
    """Where this process's compiled kernels are cached.

    None: numba's own choice (``NUMBA_CACHE_DIR`` as the user set it, or the
    ``__pycache__`` folders beside the sources); else the folder to set as
    ``NUMBA_CACHE_DIR`` (a read-only install: see the module notes).
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    pkg = package_dir()
    if _writable(pkg):
        return None
    for folder in (user_cache_dir(),
                   os.path.join(os.environ.get("TMPDIR") or "/tmp",
                                f"volwarp-numba-{os.getuid() if hasattr(os, 'getuid') else 0}")):
        if _usable(folder):
            return folder
    return None  # nowhere to write: numba compiles in memory, each run (it still works)


def _numba_subpath(source_dir: str) -> str:
    """The folder, inside ``NUMBA_CACHE_DIR``, where numba keeps the kernels of ``source_dir``.

    ``_CacheLocator.get_suitable_cache_subpath``: the folder's name and the SHA-1
    of its absolute path.
    """
    import hashlib

    source_dir = os.path.abspath(source_dir)
    digest = hashlib.sha1(source_dir.encode()).hexdigest()
    return "_".join([os.path.basename(source_dir), digest])


def seed_cache(cache_dir: str, pkg: str | None = None) -> int:
    """Copy the install's compiled kernels into ``cache_dir``, once per warm-up.

    The files numba wrote beside the sources at install (``*.nbi`` indexes,
    ``*.nbc`` code) go where numba looks for them under ``NUMBA_CACHE_DIR``.
    Returns the number of files copied (0: already done, or no warm-up ran).
    """
    pkg = pkg or package_dir()
    try:
        with open(os.path.join(pkg, "__pycache__", WARMUP_MARK), encoding="utf-8") as f:
            mark = f.read()
    except OSError:
        return 0  # no warm-up at install: the commands compile into cache_dir as they go
    # (one mark per install folder; its name without hashlib, whose import costs 2 ms)
    seeded = os.path.join(cache_dir, _SEEDED.format(pkg.strip(os.sep).replace(os.sep, "%")[-200:]))
    try:
        with open(seeded, encoding="utf-8") as f:
            if f.read() == mark:
                return 0
    except OSError:
        pass
    import shutil

    copied = 0
    for folder, dirs, files in os.walk(pkg):
        dirs[:] = [d for d in dirs if not d.startswith(".")]
        if os.path.basename(folder) != "__pycache__":
            continue
        kernels = [f for f in files if f.endswith((".nbi", ".nbc"))]
        if not kernels:
            continue
        target = os.path.join(cache_dir, _numba_subpath(os.path.dirname(folder)))
        os.makedirs(target, exist_ok=True)
        for name in kernels:
            # (to a temporary name, then renamed: another process may be loading it)
            tmp = os.path.join(target, f".{name}.{os.getpid()}.tmp")
            shutil.copyfile(os.path.join(folder, name), tmp)
            os.replace(tmp, os.path.join(target, name))
            copied += 1
    tmp = f"{seeded}.{os.getpid()}.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(mark)
    os.replace(tmp, seeded)
    return copied


def configure_numba_cache() -> str | None:
    """Set ``NUMBA_CACHE_DIR`` for a read-only install (module notes), before numba loads.

    Returns the folder set, or None where numba's own choice stands. Any
    trouble copying the install's kernels only costs their compilation.
    """
    folder = numba_cache_dir()
    if folder is None:
        return None
    os.environ["NUMBA_CACHE_DIR"] = folder
    try:
        seed_cache(folder)
    except OSError:
        pass
    return folder


def occupy_standard_fds() -> None:
    """Put ``/dev/null`` on standard descriptors 0-2 the process was started without.

    A job started as ``volwarp ... 2>&-`` (or by a launcher that closes them)
    has no descriptor 2: Python's ``sys.stderr`` is None, and the first file
    the command opens, an output's temporary, would get number 2, so that
    anything written to the standard error (a library's message from C)
    would land in the output. Descriptors 0 and 2 get ``/dev/null`` opened
    for reading and writing, which discards what is said as ``2>/dev/null``
    would; descriptor 1 gets it opened for reading only, so that what a
    command writes there as its product (``info``, ``--help``) fails as on a
    closed descriptor (exit 1) instead of vanishing.
    """
    for fd, mode, flags in ((0, "r", os.O_RDONLY), (1, "w", os.O_RDONLY), (2, "w", os.O_RDWR)):
        try:
            os.fstat(fd)
            continue
        except OSError:
            pass
        os.open(os.devnull, flags)  # (the lowest free number: fd, the lower ones open by now)
        stream = open(fd, mode, closefd=False, errors="backslashreplace")  # noqa: SIM115
        setattr(sys, ("stdin", "stdout", "stderr")[fd], stream)


def main() -> int:
    """Run the ``volwarp`` command line; its exit code."""
    occupy_standard_fds()
    # A command-line run, before numpy is imported: BLAS's own threads stay at one.
    # volwarp's kernels take the cores with their own threads (--threads) and make no
    # large dense products; OpenBLAS's threads, woken by the small products of the
    # spline bases, would only spin beside them (about 5% of a warp's CPU) or, inside a
    # cluster worker, oversubscribe it. A user's own setting wins. (Set here, for the
    # command's process only: importing volwarp as a library changes no environment.)
    for name in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")
    from . import signals

    signals.install()
    from . import library_memory

    library_memory.install()  # (an explicit limit counts what the libraries will take)
    try:  # (a stop from here on is a stop: one line, no traceback)
        # (inherited by what the command starts: batch steps, Dask workers)
        configure_numba_cache()
        from . import dataclass_code

        dataclass_code.install()  # (before any module of a dataclass loads: 14-18 ms a warp)
        from . import numba_blas

        numba_blas.install()  # (scipy.linalg not imported by numba's BLAS probe: 0.2 s)
        from .cli.main import main as run

        # (a stop deferred by the imports above lands up to 20 ms later: maybe before
        # the command line's own handling starts, so the call is inside this try too)
        return run()
    except signals.Interrupted as exc:  # stopped while the command line was set up
        sys.stderr.write(f"volwarp: error: {exc}\n")
        sys.stderr.flush()
        os._exit(128 + exc.signum)
