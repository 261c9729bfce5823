"""Atomic output files.

Every file volwarp writes goes to a temporary file in the output's folder and is
renamed into place only once it is complete, so a failure, Ctrl-C or SIGTERM
never leaves a partial output and never touches an existing one. Temporary
files still open when the process is told to stop are removed by the signal
handler installed by :func:`install_signal_handlers` (the CLI calls it).

A command's outputs belong together (a morph's frames and meshes, a warp and
its exports): inside :func:`outputs_together` (every command but ``batch``
runs in one) the renames are held until the command ends, then made
together, so that a failure half-way leaves the previous run's files as
they were, never a mix of new and old.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import stat
import sys
import threading
from pathlib import Path

from ..errors import BadUsage, VolwarpError
from ..runscope import run_files
from ..signals import Interrupted, blocked, check_stop, install, temporaries
from . import writeback
from .mapped import check_unchanged, sync_temporaries

__all__ = ["Interrupted", "atomic_folder", "atomic_output", "atomic_outputs",
           "check_output_path", "install_signal_handlers", "is_folder_output", "is_zarr_store",
           "outputs_together", "write_bytes_atomic"]

#: extensions of outputs that are folders (OME-Zarr stores)
FOLDER_EXTENSIONS = (".zarr",)

#: the registry the signal handler empties (see :mod:`volwarp_cli.signals`)
_live_temporaries = temporaries

#: the renames :func:`outputs_together` holds back: ``(rename, temporaries)``, or None
_held: list | None = None
_held_lock = threading.Lock()


@contextlib.contextmanager
def outputs_together():
    """Every output written inside renamed into place together, when the block ends.

    Inside, each atomic write completes its temporary and holds its rename
    (the temporary stays registered: a stop removes it). On a clean exit the
    renames run in the order the outputs were written, with SIGINT and SIGTERM
    held back, after the last checks (a stop asked meanwhile, an input that
    changed); on any error or stop every held temporary is removed and every
    existing output is left as it was. Nested, the outermost one commits. The
    paths renamed into place are the run's ``committed``
    (:mod:`volwarp_cli.runscope`).
    """
    global _held
    if _held is not None:
        yield
        return
    _held = held = []
    committed = run_files().committed
    try:
        yield
        with blocked():
            check_stop()
            check_unchanged()
            while held:
                rename, tmps, path = held[0]
                rename()
                committed.append(str(path))
                held.pop(0)  # (only once renamed: a failed one's temporary is removed below)
                for tmp in tmps:
                    _live_temporaries.discard(tmp)
    except BaseException:
        for _, tmps, _ in held:
            for tmp in tmps:
                _remove_temporary(tmp)
        raise
    finally:
        for _, tmps, _ in held:
            for tmp in tmps:
                _live_temporaries.discard(tmp)
        _held = None
        sync_temporaries()


#: the live :func:`scratch_folder` s: what is written in them is read back at once, not held
_scratch_folders: set[str] = set()


def is_own_temporary(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a temporary of this process or lies in one (a scratch folder).

    Such a file is volwarp's own, rewritten as the work goes: not an input
    another program could change (:func:`.mapped.watch`).
    """
    real = os.path.realpath(path)
    folders = _scratch_folders | {os.path.realpath(t) for t in list(_live_temporaries)}
    return any(real == f or real.startswith(f + os.sep) for f in folders)


def _hold(rename, tmps, path: Path) -> bool:
    """Hold ``rename`` of ``tmps`` until :func:`outputs_together` ends (False outside one).

    Never a file of a scratch folder (the work reads it back; it is not an output).
    """
    with _held_lock:
        if _held is None or os.path.realpath(path.parent) in _scratch_folders:
            return False
        _held.append((rename, list(tmps), path))
        return True


def _remove_temporary(tmp: str) -> None:
    if os.path.isdir(tmp) and not os.path.islink(tmp):
        _remove_tree(tmp)
    else:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def install_signal_handlers() -> None:
    """Record and raise SIGINT/SIGTERM (:mod:`volwarp_cli.signals`) so outputs are cleaned up."""
    install()


def is_folder_output(path: str | os.PathLike) -> bool:
    """True when ``path`` names an output that is a folder (``.zarr``, ``.ome.zarr``)."""
    return Path(path).name.lower().endswith(FOLDER_EXTENSIONS)


def is_zarr_store(path: str | os.PathLike) -> bool:
    """True when ``path`` is a folder holding a Zarr group or array (v2 or v3)."""
    path = Path(path)
    return path.is_dir() and any((path / name).is_file() for name in
                                 ("zarr.json", ".zgroup", ".zarray", ".zattrs"))


def check_output_path(path: str | os.PathLike, option: str | None = None) -> Path:
    """Fail early (before any work) when ``path`` cannot be written.

    An output that would replace one of the run's inputs (the files its
    command line and specs named, :mod:`.inputs`, and every file its readers
    opened) is a usage error (:class:`~volwarp_cli.errors.BadUsage`): the
    commands check each output before any work, and every write checks again.
    ``option`` names the output's option in that message; given, the file is
    claimed for it, and a file another option claimed is a usage error too.
    A folder output (``.zarr``) may replace an existing Zarr store, never a
    folder that is not one (nor a file of that name: that is someone else's).
    A detached header whose data file's name its header could not hold
    (``' x.nhdr'``: :func:`~.common.data_file_name_problem`) is a usage error.
    """
    from .common import refuse_unnamable_data_file
    from .inputs import claim_output, opened_as_input, refuse_output_over_input

    if isinstance(path, str) and path.endswith(("/", os.sep)) and \
            not is_folder_output(Path(path)):  # (Path drops the slash: out.png/ wrote out.png)
        raise BadUsage(f"{option + ' ' if option else ''}{path}: ends in a slash, which names a "
                       "folder: give the output file's name")
    path = Path(path)
    refuse_unnamable_data_file(path, option)  # (.nhdr, .mhd: the name their header gives)
    refuse_output_over_input(path, option=option)
    if option is not None:  # (the commands' checks before any work name their option)
        claim_output(path, option)
    if opened_as_input(path):  # a file a reader opened (a header's data file, a template)
        raise BadUsage(f"{option + ' ' if option else ''}{path} would overwrite a file this "
                       "command read as an input; volwarp never replaces an input: choose "
                       "another output name")
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise VolwarpError(f"{path}: output folder {str(folder)!r} does not exist")
    if not os.access(folder, os.W_OK):
        raise VolwarpError(f"{path}: output folder {str(folder)!r} is not writable")
    longest = _name_max(folder)
    if len(os.fsencode(path.name)) > longest:  # (else the work ran, and its rename failed)
        raise BadUsage(f"{option + ' ' if option else ''}{path}: the name is "
                       f"{len(os.fsencode(path.name))} bytes, more than the {longest} a file "
                       "name may have there: choose a shorter name")
    if is_folder_output(path):
        if path.is_dir() and not is_zarr_store(path):
            raise VolwarpError(f"{path}: is a folder that is not a Zarr store; volwarp "
                               "replaces only an earlier store (remove it or choose another name)")
        if path.exists() and not path.is_dir():
            raise VolwarpError(f"{path}: is a file; an OME-Zarr output is a folder (remove it "
                               "or choose another name)")
        return path
    if path.is_dir():
        raise VolwarpError(f"{path}: is a folder, not a file")
    kind = special_kind(path)
    if kind is not None:  # (the rename of a finished output would put a file in its place)
        raise VolwarpError(f"{path}: is {kind}, not a regular file; volwarp writes an output "
                           "as a new file renamed onto its name, which would replace it: "
                           "choose another output name")
    return path


def special_kind(path: str | os.PathLike, *, follow: bool = False) -> str | None:
    """What ``path`` is when it exists and is neither a file, a folder nor a link.

    ``follow``: what a link leads to (an input is read through it; an output's
    rename replaces the link itself).
    """
    try:
        mode = (os.stat if follow else os.lstat)(path).st_mode
    except OSError:
        return None
    for test, kind in ((stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return None


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike):
    """Yield a temporary folder next to ``path``; rename it onto ``path`` on success.

    For outputs that are folders (OME-Zarr stores). The temporary is
    registered with the signal handler's temporaries and removed on any
    error or stop; an existing store at ``path`` is untouched until the new
    one is complete. Then, with SIGINT and SIGTERM held back, the new store
    takes its place (:func:`_rename_folder`: the two names swapped in one step
    where the file system can, else the old one renamed aside first), and only
    then is the old one removed. (A folder cannot be renamed over another in
    one step, as a file can.)
    """
    path = check_output_path(path)
    _remove_stale_temporaries(path)
    with blocked():  # made and registered at once: a stop cannot leak it
        tmp = _tempfile().mkdtemp(prefix=_temporary_prefix(path.name), suffix=".partdir",
                                  dir=path.parent)
        _live_temporaries.add(tmp)
    held = False
    try:
        sync_temporaries()
        yield Path(tmp)
        _chmod_tree(tmp)
        with blocked():
            check_stop()  # a stop asked while writing (and swallowed somewhere): no rename
            check_unchanged()  # an input mapped for this output changed: no rename
            held = _hold(lambda: _rename_folder(tmp, path), [tmp], path)
            if not held:
                _rename_folder(tmp, path)
                _live_temporaries.discard(tmp)
    except BaseException as exc:
        _remove_tree(tmp)
        if isinstance(exc, OSError) and (exc.filename is None
                                         or str(exc.filename).startswith(tmp)):
            raise write_error(path, exc) from exc
        raise
    finally:
        if not held:
            _live_temporaries.discard(tmp)
        sync_temporaries()


#: the environment variable naming the file where a batch's step notes each output it
#: renamed into place (:func:`note_committed`)
COMMITTED_LOG = "VOLWARP_COMMITTED_LOG"


def file_identity(st: os.stat_result) -> list[int]:
    """What tells a file written apart from another put in its place.

    Device, inode, size and modification time; a folder's device and inode
    (its size and time move with its entries).
    """
    if stat.S_ISDIR(st.st_mode):
        return [st.st_dev, st.st_ino]
    return [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns]


def note_committed(tmp, path) -> None:
    """Note, for a batch that asked (:data:`COMMITTED_LOG`), the output ``tmp`` is renamed to.

    Called just before the rename: ``tmp``'s identity is the output's after
    it (a rename keeps the inode and the times). The batch records an output
    only while the file at its path is still this one: another writer's file
    put there meanwhile (a second batch, a cron job) was recorded as the
    step's, and the next run skipped it.
    """
    log = os.environ.get(COMMITTED_LOG)
    if not log:
        return
    import json

    try:  # (never the command's failure: unnoted, the batch records the output as before)
        line = json.dumps({"path": os.path.abspath(path),
                           "identity": file_identity(os.stat(tmp))}) + "\n"
        fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        try:
            os.write(fd, line.encode("utf-8", "surrogateescape"))
        finally:
            os.close(fd)
    except OSError:
        pass


def committed_in(log: str | None) -> dict:
    """What :func:`note_committed` noted in ``log``: each output's identity by absolute path."""
    import json

    out = {}
    if log is None:
        return out
    try:
        with open(log, encoding="utf-8", errors="surrogateescape") as fh:
            for line in fh:
                try:
                    item = json.loads(line)
                    out[item["path"]] = item["identity"]
                except (ValueError, KeyError, TypeError):  # (a line cut short by a kill)
                    continue
    except OSError:
        return {}
    return out


@contextlib.contextmanager
def _folder_held(folder: Path | None):
    """An exclusive ``flock`` on ``folder`` for a few renames (None: nothing held).

    Two runs writing the same detached header and data file at once renamed
    their pairs in turns, and one run's header could end up over the other's
    samples (a review saw 19 of 150 such races end mixed, both exit 0): the
    renames of a pair are made under the folder's lock, so one whole pair
    wins. Only volwarp's renames take it; a file system that cannot lock
    (some network mounts) renames as before.
    """
    if folder is None:
        yield
        return
    import fcntl

    try:
        fd = os.open(folder if str(folder) else ".", os.O_RDONLY)
    except OSError:
        yield
        return
    try:
        with contextlib.suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # (the lock goes with it)


def _rename_folder(tmp: str, path: Path) -> None:
    """Put the folder ``tmp`` at ``path``; an old one there removed after.

    A folder cannot be renamed over another. Where the system can swap two
    names in one step (Linux's ``renameat2`` with ``RENAME_EXCHANGE``: ext4,
    xfs, btrfs, tmpfs), the old store and the new swap, so that ``path``
    always holds a whole store, then the old one (now at ``tmp``) is removed.
    Elsewhere the old store is renamed aside first, to ``.NAME.vw-...old``: a
    process killed between the two renames leaves no store at ``path``, and
    the next write of it puts the old one back (:func:`_remove_stale_temporaries`).
    """
    note_committed(tmp, path)
    if not path.is_dir():
        try:
            os.rename(tmp, path)
            return
        except OSError as exc:  # (another run's store put there since: replaced as any)
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST) or not path.is_dir():
                raise
    if _exchange(tmp, path):
        _remove_tree(tmp)
        return
    aside = _tempfile().mkdtemp(prefix=_temporary_prefix(path.name), suffix=".old",
                                dir=path.parent)
    os.rmdir(aside)  # (only the unique name was wanted)
    os.rename(path, aside)
    try:
        os.rename(tmp, path)
    except BaseException as exc:
        try:
            os.rename(aside, path)  # put the old store back
        except OSError as back:  # (both failed: say where the earlier output is)
            raise VolwarpError(
                f"{path}: the new store could not take its place ({_why(exc)}) and the "
                f"earlier one could not be put back ({_why(back)}): it is kept whole at "
                f"{aside} (rename it back yourself; the next write of {path.name} puts it "
                "back only while nothing is at that path, and removes it where another "
                "store is)") from exc
        raise
    # (renamed again before its removal: a kill during it leaves a '.gone' folder, never
    # put back, where a half-removed '.old' would have been)
    gone = aside[:-len(".old")] + ".gone"
    try:
        os.rename(aside, gone)
    except OSError:
        gone = aside
    _remove_tree(gone)


def _why(exc: BaseException) -> str:
    """An error's reason in a few words (an OSError's strerror)."""
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__


_RENAME_EXCHANGE = 2  # <linux/fs.h>
_AT_FDCWD = -100


def _exchange(a, b) -> bool:
    """Swap the names ``a`` and ``b`` in one step; False where the system cannot (nothing done)."""
    from ..memory import libc

    # (a C library without it: not Linux, glibc before 2.28)
    call = getattr(libc(), "renameat2", None) if sys.platform.startswith("linux") else None
    if call is None:
        return False
    import ctypes

    call.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                     ctypes.c_uint]
    # (any failure: the names aside, as without the call; a real one fails there again)
    return call(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0


def _chmod_tree(root: str) -> None:
    """Give the output the usual modes (mkdtemp makes folders 0700)."""
    mask = current_umask()
    os.chmod(root, 0o777 & ~mask)
    for folder, dirs, files in os.walk(root):
        for d in dirs:
            os.chmod(os.path.join(folder, d), 0o777 & ~mask)
        for f in files:
            os.chmod(os.path.join(folder, f), 0o666 & ~mask)


def _remove_tree(root) -> None:
    """Remove a temporary folder (again, if a writer thread still added files meanwhile).

    A link is removed, not followed: an output store named by a link is replaced
    by the new store, as an output file named by one is by the new file, and the
    link, swapped aside, was left behind (rmtree refuses links; its error ignored).
    """
    import shutil

    if os.path.islink(root):
        with contextlib.suppress(OSError):
            os.unlink(root)
        return
    for _ in range(5):
        shutil.rmtree(root, ignore_errors=True)
        if not os.path.lexists(root):
            return


def write_error(path, exc: OSError) -> VolwarpError:
    """The one-line error of an output that could not be written (a full disk, a quota)."""
    return VolwarpError(f"{path}: cannot write ({exc.strerror or exc})")


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    ``suffix`` defaults to the output's own extension(s), so libraries that
    choose behaviour by file name (``.nii.gz``, ``.tif``) see the right one.
    """
    with atomic_outputs(path, suffixes=None if suffix is None else [suffix]) as (tmp,):
        yield tmp


@contextlib.contextmanager
def atomic_outputs(*paths: str | os.PathLike, suffixes: list[str] | None = None,
                   replaced=()):
    """Temporaries for several files that belong together, renamed onto them together.

    A detached header and its data file (``.nhdr`` + ``.raw``, ``.mhd`` +
    ``.raw``) must be both new or both old: the renames run with SIGINT and
    SIGTERM held back, in the order given (the data file first, so that a
    header never names data it does not describe), after the last checks.
    ``replaced``: files of the earlier output these replace that no new file
    takes the place of (its data file under another name), removed with the
    renames.
    """
    paths = [check_output_path(p) for p in paths]
    if suffixes is None:
        suffixes = ["".join(p.suffixes[-2:]) if p.name.endswith(".gz") else p.suffix
                    for p in paths]
    tmps: list[str] = []
    held = False
    try:
        for path, suffix in zip(paths, suffixes, strict=True):
            _remove_stale_temporaries(path)
            with blocked():  # made and registered at once: a stop cannot leak it
                fd, tmp = _make_temporary(_temporary_prefix(path.name), f".part{suffix}",
                                          path.parent)
                _live_temporaries.add(tmp)
                tmps.append(tmp)
                os.close(fd)  # (here: a stop deferred by blocked() is raised as it ends)
            writeback.replacing(tmp, os.path.lexists(path))
        sync_temporaries()
        yield [Path(t) for t in tmps]
        mask = current_umask()
        for tmp in tmps:  # the temporaries are 0600: give the outputs the usual mode
            os.chmod(tmp, 0o666 & ~mask)
        with blocked():
            check_stop()  # a stop asked while writing (and swallowed somewhere): no rename
            check_unchanged()  # an input mapped for these outputs changed: no rename
            pairs = list(zip(tmps, paths, strict=True))

            def rename():
                with _folder_held(paths[-1].parent if len(pairs) > 1 else None):
                    for tmp, path in pairs:
                        note_committed(tmp, path)
                        os.replace(tmp, path)
                    for old in replaced:
                        with contextlib.suppress(OSError):
                            os.unlink(old)

            held = _hold(rename, tmps, paths[-1])
            if not held:
                rename()
    except BaseException as exc:
        for tmp in tmps:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(exc, OSError) and (exc.filename is None or exc.filename in tmps):
            # writing an output failed (a full disk, a quota): say which output
            named = paths[tmps.index(exc.filename)] if exc.filename in tmps else paths[-1]
            raise write_error(named, exc) from exc
        raise
    finally:
        for tmp in tmps:
            writeback.replacing(tmp, False)
        if not held:
            for tmp in tmps:
                _live_temporaries.discard(tmp)
        sync_temporaries()


def current_umask() -> int:
    """The process's umask, read without changing it where the system tells it.

    Linux (4.7 on) shows it in /proc/self/status; elsewhere ``os.umask`` can
    only be read by setting it, which is racy under threads (another thread
    creating a file in between gets the wrong mode), so that is the fallback.
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _host() -> str:
    # (os.uname's node name: socket's gethostname costs its module's import, 2.5 ms a command)
    return re.sub(r"[^A-Za-z0-9_-]", "_", os.uname().nodename) or "host"


@contextlib.contextmanager
def scratch_folder(near: str | os.PathLike):
    """A temporary folder next to the output ``near``, removed on exit, on error or on a stop.

    For intermediate results too large for memory (a distance's passes by
    blocks); named and cleaned like the output's own temporaries.
    """
    tmp = make_scratch_folder(near)
    try:
        yield tmp
    finally:
        remove_scratch_folder(tmp)


def make_scratch_folder(near: str | os.PathLike) -> Path:
    """:func:`scratch_folder`'s folder, for a caller that removes it itself (:func:`remove_scratch_folder`).

    A stop (SIGINT, SIGTERM) removes it meanwhile; one left by a killed
    process goes with the next run that writes ``near``.
    """
    path = Path(near)
    _remove_stale_temporaries(path)
    with blocked():
        tmp = _tempfile().mkdtemp(prefix=_temporary_prefix(path.name), suffix=".scratch",
                                  dir=path.parent if str(path.parent) else ".")
        _live_temporaries.add(tmp)
        _scratch_folders.add(os.path.realpath(tmp))
    return Path(tmp)


def remove_scratch_folder(tmp: str | os.PathLike) -> None:
    """Remove a :func:`make_scratch_folder` folder and all it holds."""
    import shutil

    tmp = str(tmp)
    with blocked():
        shutil.rmtree(tmp, ignore_errors=True)
        _live_temporaries.discard(tmp)
        _scratch_folders.discard(os.path.realpath(tmp))


def _tempfile():
    """The tempfile module, imported by the outputs that are folders only.

    (It imports shutil and random: 4-5 ms of every command's start, where a
    file output's temporary is :func:`_make_temporary`'s.)
    """
    import tempfile

    return tempfile


#: the characters of a temporary's random part (32 of tempfile's: a byte's low 5 bits)
_NAME_CHARS = "abcdefghijklmnopqrstuvwxyz012345"


def _make_temporary(prefix: str, suffix: str, folder) -> tuple[int, str]:
    """``(fd, path)`` of a new file ``PREFIX`` + 8 random characters + ``SUFFIX`` in ``folder``.

    As ``tempfile.mkstemp``: created exclusively, mode 0600, not through a
    symbolic link, its descriptor not inherited; the path absolute.
    """
    flags = (os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
             | getattr(os, "O_CLOEXEC", 0))
    folder = os.path.abspath(folder)
    for _ in range(getattr(os, "TMP_MAX", 10000)):  # (tempfile's number of tries)
        name = "".join(_NAME_CHARS[b & 31] for b in os.urandom(8))
        path = os.path.join(folder, f"{prefix}{name}{suffix}")
        try:
            return os.open(path, flags, 0o600), path
        except FileExistsError:
            continue
    raise FileExistsError(errno.EEXIST, "no unused name for a temporary", folder)


def _temporary_prefix(name: str) -> str:
    """``.NAME.vw-PID@HOST.``: a temporary says whose it is (8 random characters follow)."""
    return f".{_temporary_stem(name)}.vw-{os.getpid()}@{_host()}."


def _name_max(folder) -> int:
    """The longest file name, in bytes, the file system of ``folder`` takes (255 where unsaid)."""
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def _temporary_stem(name: str) -> str:
    """The output's name as its temporaries carry it: whole, or cut and hashed where long.

    A temporary adds about 40 bytes to the name (its owner, a random part, the
    extension again): an output name of 220 to 255 bytes, legal itself, had
    temporaries too long to make, a failure after the work, naming the temporary.
    """
    raw = os.fsencode(name)
    # (a pid's room is its most digits, so that every process cuts a name the same way)
    room = 255 - len(os.fsencode(f"..vw-{'9' * 7}@{_host()}.")) - 8 - 24
    if len(raw) <= room:
        return name
    from _blake2 import blake2b

    digest = blake2b(raw, digest_size=8).hexdigest()
    return os.fsdecode(raw[:max(room - 17, 1)]) + "~" + digest


def _remove_stale_temporaries(path: Path) -> None:
    """Remove the temporaries of ``path`` left by dead volwarp processes of this host.

    A process killed with SIGKILL (or a machine that lost power) cannot clean
    up; the next write of the same output does. Only files named by
    :func:`_temporary_prefix` for this output, this host and a process that no
    longer exists are removed: never another host's (a shared folder), a
    live process's, or anything else.
    """
    owner = re.escape(f".{_temporary_stem(path.name)}.vw-") + r"(\d+)@" + re.escape(_host())
    pattern = re.compile(owner + r"\.[A-Za-z0-9_]{8}\.part")
    folders = re.compile(owner + r"\.[A-Za-z0-9_]{8}\.(partdir|old|gone|scratch)$")
    try:
        names = os.listdir(path.parent if str(path.parent) else ".")
    except OSError:
        return
    for name in sorted(names, key=lambda n: not n.endswith(".old")):  # (an old store first)
        m = pattern.match(name) or folders.match(name)
        if m is None or _alive(int(m.group(1))):
            continue
        stale = path.parent / name
        if name.endswith(".old") and not os.path.lexists(path) and stale.is_dir():
            # a store set aside by a process killed before the new one took its place
            # (_rename_folder): the earlier output, put back (and kept where that fails:
            # its only copy)
            try:
                os.rename(stale, path)
                continue
            except OSError:
                if not os.path.lexists(path):
                    continue
        if stale.is_dir() and not stale.is_symlink():
            _remove_tree(stale)  # a folder output's temporary (or an old store set aside)
            continue
        with contextlib.suppress(OSError):
            os.unlink(stale)


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
