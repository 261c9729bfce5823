"""Atomic output files.

Every file volwarp writes goes to a temporary file in the output's folder and is
renamed into place only once it is complete, so a failure, Ctrl-C or SIGTERM
never leaves a partial output and never touches an existing one. Temporary
files still open when the process is told to stop are removed by the signal
handler installed by :func:`install_signal_handlers` (the CLI calls it).

A command's outputs belong together (a morph's frames and meshes, a warp and
its exports): inside :func:`outputs_together` (every command but ``batch``
runs in one) the renames are held until the command ends, then made
together (:func:`_commit`: all of them, or, where one fails, none, the
outputs already replaced put back), so that a failure half-way leaves the
previous run's files as they were, never a mix of new and old.

An output that replaces a file keeps that file's permissions and, where the
process may give it, its group (:func:`_give_mode`); a new one has the umask's.
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
    renames run in the order the outputs were written, as one :func:`_commit`
    (all made, or none: a rename that fails puts back the outputs already
    replaced), with the stops held back, after the last checks (a stop asked
    meanwhile, an input that changed); on any error or stop every held
    temporary is removed and every existing output is left as it was, and an
    error is that of an input that changed meanwhile where one did. Nested,
    the outermost one commits. The paths renamed into place are the run's
    ``committed`` (:mod:`volwarp_cli.runscope`).
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
            if held:
                _commit([move for moves, _, _ in held for move in moves],
                        [old for _, replaced, _ in held for old in replaced])
            committed.extend(str(path) for _, _, path in held)
            for moves, _, _ in held:
                for tmp, _, _ in moves:
                    _forget(tmp)
            held.clear()
    except BaseException as exc:
        for moves, _, _ in held:  # (those renamed into place and put back again are gone)
            for tmp, _, _ in moves:
                _remove_temporary(tmp)
        if isinstance(exc, Exception):  # (not a stop)
            # a failure of a run whose input changed meanwhile: the change is why (another
            # store's chunk that does not decode, a mix taken for a label map)
            check_unchanged()
        raise
    finally:
        for moves, _, _ in held:
            for tmp, _, _ in moves:
                _forget(tmp)
        _held = None
        sync_temporaries()


#: the live :func:`scratch_folder` s: what is written in them is read back at once, not held
_scratch_folders: set[str] = set()

#: the descriptors holding this process's claims (:func:`_claim`), by the name claimed
_claims: dict[str, list[int]] = {}
#: claims held at once at most (each an open descriptor)
CLAIMS_MAX = 256
_claims_lock = threading.Lock()
_OPEN_FOR_LOCK = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)


def _claim(name: str, fd: int | None = None, *,
           of: str | os.PathLike | None = None) -> int | None:
    """Hold an exclusive ``flock`` on a temporary of this process for as long as it is live.

    A temporary's name says whose it is (its process id and host name), and
    the next write of the same output removes those of processes that no
    longer exist (:func:`_remove_stale_temporaries`). A process id says
    nothing across PID namespaces: two containers on one host name (``docker
    run --network host``, a shared data folder) each took the other's live
    temporaries for a dead process's and removed them, the work's output
    with them, or put a store set aside back at its path mid-commit. The lock
    is held by the open file, whatever process looks at it: a temporary
    whose lock is held is live (:func:`_in_use`). ``fd``: the temporary's own
    descriptor, kept open (else it is opened); ``of``: the file or folder to
    open and lock, where ``name`` is the name it is about to take (an earlier
    output set aside). Returns the descriptor holding the lock, or None where
    none is held: a file system that cannot lock, a symbolic link, or more
    than :data:`CLAIMS_MAX` claims at once (a morph's hundreds of frames,
    renamed together at its end: a descriptor each would near the usual limit
    of 1024 open files); those keep the liveness by process id alone, as
    before.
    """
    import fcntl

    with _claims_lock:
        room = sum(map(len, _claims.values())) < CLAIMS_MAX
    try:
        if not room:
            raise OSError(errno.EMFILE, "claims held")
        if fd is None:
            fd = os.open(of if of is not None else name, _OPEN_FOR_LOCK)
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        if fd is not None:
            os.close(fd)
        return None
    with _claims_lock:
        _claims.setdefault(str(name), []).append(fd)
    return fd


def _unclaim(name: str, fd: int | None = None) -> None:
    """Let go of the :func:`_claim` s of ``name`` (``fd``: that one only); their locks go with them."""
    with _claims_lock:
        held = _claims.get(str(name), [])
        mine = [d for d in held if fd is None or d == fd]
        rest = [d for d in held if d not in mine]
        if rest:
            _claims[str(name)] = rest
        else:
            _claims.pop(str(name), None)
    for d in mine:
        with contextlib.suppress(OSError):
            os.close(d)


def _forget(tmp: str) -> None:
    """``tmp`` is no temporary of this process any more: unregistered, its claim let go."""
    _live_temporaries.discard(tmp)
    _unclaim(tmp)


def _in_use(name: str) -> bool:
    """Whether some process holds the :func:`_claim` of the temporary ``name`` (any PID namespace).

    False where it cannot be opened or locked (then its process id decides).
    """
    import fcntl

    try:
        fd = os.open(name, _OPEN_FOR_LOCK)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    finally:
        os.close(fd)
    return False


def is_own_temporary(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a temporary of this process or lies in one (a scratch folder).

    Such a file is volwarp's own, rewritten as the work goes: not an input
    another program could change (:func:`.mapped.watch`).
    """
    real = os.path.realpath(path)
    folders = _scratch_folders | {os.path.realpath(t) for t in list(_live_temporaries)}
    return any(real == f or real.startswith(f + os.sep) for f in folders)


def _hold(moves: list, replaced, path: Path) -> bool:
    """Hold ``moves`` (:func:`_commit`'s) until :func:`outputs_together` ends (False outside one).

    Never a file of a scratch folder (the work reads it back; it is not an output).
    """
    with _held_lock:
        if _held is None or os.path.realpath(path.parent) in _scratch_folders:
            return False
        _held.append((list(moves), list(replaced), path))
        return True


def _remove_temporary(tmp: str) -> None:
    if os.path.isdir(tmp) and not os.path.islink(tmp):
        _remove_tree(tmp)
    else:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def install_signal_handlers() -> None:
    """Record and raise the stops (:mod:`volwarp_cli.signals`) so outputs are cleaned up."""
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
        _check_replaceable(path)
        return path
    if path.is_dir():
        raise VolwarpError(f"{path}: is a folder, not a file")
    kind = special_kind(path)
    if kind is not None:  # (the rename of a finished output would put a file in its place)
        raise VolwarpError(f"{path}: is {kind}, not a regular file; volwarp writes an output "
                           "as a new file renamed onto its name, which would replace it: "
                           "choose another output name")
    _check_replaceable(path)
    return path


#: <linux/fs.h>'s FS_IOC_GETFLAGS, ``_IOR('f', 1, long)`` as the machines below encode it
_FS_IOC_GETFLAGS = (2 << 30) | ((8 if sys.maxsize > 2 ** 32 else 4) << 16) | (ord("f") << 8) | 1
_GENERIC_IOCTL = ("x86_64", "i386", "i686", "aarch64", "armv7l", "armv6l", "riscv64", "s390x")
_FS_IMMUTABLE_FL, _FS_APPEND_FL = 0x10, 0x20


def _check_replaceable(path: Path) -> None:
    """Fail before any work where the earlier output at ``path`` cannot be renamed over.

    An immutable or append-only file or store (``chattr +i``, ``+a``), or
    another user's in a sticky folder that is not this user's either: the
    rename at the end failed, after all the work (and :func:`_commit` put back
    the outputs renamed before it). What does not show here (a file system's
    own refusal) still fails at the end, all outputs left as they were.
    """
    try:
        st = os.lstat(path)
    except OSError:
        return
    if not (stat.S_ISREG(st.st_mode) or stat.S_ISDIR(st.st_mode)):
        return
    euid = os.geteuid()
    if euid != 0 and st.st_uid != euid:  # (root may, as any holder of CAP_FOWNER)
        with contextlib.suppress(OSError):
            folder = os.stat(path.parent if str(path.parent) else ".")
            if folder.st_mode & stat.S_ISVTX and folder.st_uid != euid:
                raise VolwarpError(f"{path}: cannot be replaced: it belongs to another user "
                                   "and its folder is sticky (as /tmp: only its owner may "
                                   "replace it there); choose another output name")
    flags = _inode_flags(path)
    for flag, what in ((_FS_IMMUTABLE_FL, "immutable (chattr +i)"),
                       (_FS_APPEND_FL, "append-only (chattr +a)")):
        if flags & flag:
            raise VolwarpError(f"{path}: cannot be replaced: it is {what}; choose another "
                               "output name")


def _inode_flags(path: Path) -> int:
    """The Linux inode flags of ``path`` (``lsattr``'s), 0 where they cannot be read."""
    if not sys.platform.startswith("linux") or os.uname().machine not in _GENERIC_IOCTL:
        return 0
    import fcntl

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError:
        return 0
    try:
        got = fcntl.ioctl(fd, _FS_IOC_GETFLAGS, bytes(8))
    except OSError:  # (a file system without them: ENOTTY)
        return 0
    finally:
        os.close(fd)
    return int.from_bytes(got[:4], sys.byteorder)


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
    one is complete. Then, with the stops held back, the new store takes its
    place (:func:`_rename_folder`: the two names swapped in one step where the
    file system can, else the old one renamed aside first), and only then (once
    every output of the set is in, :func:`_commit`) is the old one removed. (A
    folder cannot be renamed over another in one step, as a file can.)
    """
    path = check_output_path(path)
    _remove_stale_temporaries(path)
    with blocked():  # made and registered at once: a stop cannot leak it
        tmp = _tempfile().mkdtemp(prefix=_temporary_prefix(path.name), suffix=".partdir",
                                  dir=path.parent)
        _live_temporaries.add(tmp)
        _claim(tmp)
    held = False
    try:
        sync_temporaries()
        yield Path(tmp)
        _chmod_tree(tmp, path)
        with blocked():
            check_stop()  # a stop asked while writing (and swallowed somewhere): no rename
            check_unchanged()  # an input mapped for this output changed: no rename
            held = _hold([(tmp, path, True)], (), path)
            if not held:
                _commit([(tmp, path, True)])
                _forget(tmp)
    except BaseException as exc:
        _remove_tree(tmp)
        if isinstance(exc, OSError) and (exc.filename is None
                                         or str(exc.filename).startswith(tmp)):
            raise write_error(path, exc) from exc
        raise
    finally:
        if not held:
            _forget(tmp)
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
        _lock_a_while(fd, fcntl)
        yield
    finally:
        os.close(fd)  # (the lock goes with it)


#: how long a commit waits for a folder's lock before it renames without it
LOCK_WAIT = 5.0


def _lock_a_while(fd: int, fcntl) -> None:
    """``flock(fd, LOCK_EX)``, tried for :data:`LOCK_WAIT` seconds at most, then given up.

    A wait without end hung a run for good, its stops held back: a lock its own
    process held through another descriptor (``flock OUT volwarp ... -o
    OUT/...``: flock(1)'s, inherited) or the same folder reached by two paths
    (a bind mount). The lock only orders two runs' renames of the same outputs;
    without it they rename as they did before it was taken.
    """
    import time

    deadline = time.monotonic() + LOCK_WAIT
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return
        except BlockingIOError:
            if time.monotonic() >= deadline:
                return
            time.sleep(0.02)
        except OSError:  # (a file system that cannot lock)
            return


def _commit(moves: list, replaced=()) -> None:
    """Rename each finished temporary onto its output: all of them, or none.

    ``moves``: ``(temporary, output, is_folder)``, renamed in that order;
    ``replaced``: files of the earlier outputs no new one takes the place of,
    removed once all are in. Renames run in order and one can fail half-way
    (an output made immutable, another user's file in a sticky folder): so
    each existing output but the last keeps a second name first (a hard link,
    :func:`_keep`; a store swapped aside keeps its own), and where a rename
    fails every output already replaced is put back from it, every new one
    removed, before the error, which names the output and why. Only once all
    are in are the earlier outputs removed. A single output needs none of it
    (its rename is all or nothing by itself). Called with the stops held back
    (:func:`~volwarp_cli.signals.blocked`): a stop waits for the whole commit,
    rollback and clean-up included, and nothing is left behind.
    """
    done: list = []  # (output, is_folder, its earlier file or store's name now, or None)
    failed = None  # (output, OSError) of the rename that failed
    try:
        with _folders_held(moves):
            for i, (tmp, path, folder) in enumerate(moves):
                path = Path(path)
                note_committed(tmp, path)
                try:
                    if folder:
                        done.append((path, True, _rename_folder_in(tmp, path)))
                        continue
                    kept = _keep(path) if i < len(moves) - 1 else None
                    try:
                        _replace_file(tmp, path, kept)
                    except BaseException:
                        _discard(kept)
                        raise
                    done.append((path, False, kept and kept[0]))
                except OSError as exc:
                    failed = path, exc
                    raise
    except BaseException as exc:
        lost = _roll_back(done)
        if failed is not None:
            said = ("; " + "; ".join(lost) if lost else
                    "; the other outputs are left as they were" if len(moves) > 1 else "")
            raise VolwarpError(f"{failed[0]}: cannot put the new output in place "
                               f"({_why(failed[1])}){said}") from exc
        if lost:
            raise VolwarpError(f"{exc}; " + "; ".join(lost)) from exc
        raise
    for _, folder, earlier in done:
        if folder and earlier is not None:
            _remove_old_store(earlier)
        elif earlier is not None:
            with contextlib.suppress(OSError):
                os.unlink(earlier)
        if earlier is not None:
            _unclaim(earlier)
    for old in replaced:
        with contextlib.suppress(OSError):
            os.unlink(old)


def _rename_folder(tmp: str, path: Path) -> None:
    """Put the folder ``tmp`` at ``path`` (:func:`_commit` of one store)."""
    _commit([(tmp, path, True)])


@contextlib.contextmanager
def _folders_held(moves: list):
    """:func:`_folder_held` of every folder of a set of outputs (one output: none).

    Each folder once (a second ``flock`` of it by this process would wait for
    the first), in one order (two runs locking two folders never wait for each other).
    """
    if len(moves) < 2:
        yield
        return
    folders: dict = {}  # (device, inode) -> a path of it: a folder reached by two paths, once
    for _, path, _ in moves:
        folder = Path(path).parent if str(Path(path).parent) else Path(".")
        try:
            st = os.stat(folder)
        except OSError:
            continue
        folders.setdefault((st.st_dev, st.st_ino), folder)
    with contextlib.ExitStack() as stack:
        for key in sorted(folders):
            stack.enter_context(_folder_held(folders[key]))
        yield


def _keep(path: Path) -> tuple[str, bool] | None:
    """A second name for the existing file ``path``, to put it back from: ``(name, linked)``.

    A hard link where the file system makes one (cheap: no data copied); else
    (none there, a file another user owns under ``protected_hardlinks``) only a
    free name, which :func:`_replace_file` renames the earlier file to first.
    Named as the stale temporaries are: a link ``.kept`` (a copy: one a killed
    process left is only removed by the next write), a name to rename to
    ``.old`` (then the only copy: put back by the next write where the output
    is missing; a ``.kept`` put back would bring back an output its user
    deleted since). None where there is no earlier file.
    """
    if not os.path.lexists(path):
        return None
    while True:
        name = _spare_name(path, ".kept")
        try:
            os.link(path, name, follow_symlinks=False)  # (a link output: the link kept)
            _claim(name)
            return name, True
        except FileExistsError:
            continue
        except OSError:
            aside = _spare_name(path, ".old")
            _claim(aside, of=path)  # (the earlier file, before it is renamed to it)
            return aside, False


def _replace_file(tmp: str, path: Path, kept: tuple[str, bool] | None) -> None:
    """Rename ``tmp`` onto ``path``.

    Where the :func:`_keep` name is not a link, the earlier file is renamed to
    it first (and back, where the new one's rename fails).
    """
    if kept is None or kept[1]:
        os.replace(tmp, path)
        return
    os.rename(path, kept[0])
    try:
        os.rename(tmp, path)
    except BaseException as exc:
        try:
            os.rename(kept[0], path)
        except OSError as back:
            raise VolwarpError(f"{path}: cannot put the new output in place ({_why(exc)}), "
                               f"and the earlier one could not be put back ({_why(back)}): "
                               f"it is kept at {kept[0]}") from exc
        raise


def _discard(kept: tuple[str, bool] | None) -> None:
    """Remove a :func:`_keep` link no rename used (a name only: nothing to remove)."""
    if kept is not None and kept[1]:
        with contextlib.suppress(OSError):
            os.unlink(kept[0])
    if kept is not None:
        _unclaim(kept[0])


def _roll_back(done: list) -> list[str]:
    """Put back the earlier outputs of a failed :func:`_commit`, the last one first.

    Returns what could not be put back, each naming where its earlier output is kept.
    """
    lost = []
    for path, folder, earlier in reversed(done):
        try:
            if folder:
                _put_store_back(path, earlier)
            elif earlier is not None:
                os.replace(earlier, path)
            else:
                os.unlink(path)  # (a new output: there was none before)
            if earlier is not None:
                _unclaim(earlier)
        except OSError as exc:
            lost.append(f"{path}: the earlier output could not be put back ({_why(exc)})"
                        + (f": it is kept at {earlier}" if earlier is not None else ""))
    return lost


def _rename_folder_in(tmp: str, path: Path) -> str | None:
    """Put the folder ``tmp`` at ``path``; returns where the earlier store is now (or None).

    A folder cannot be renamed over another. Where the system can swap two
    names in one step (Linux's ``renameat2`` with ``RENAME_EXCHANGE``: ext4,
    xfs, btrfs, tmpfs), the old store and the new swap, so that ``path``
    always holds a whole store: the old one is then at ``tmp``. Elsewhere the
    old store is renamed aside first, to ``.NAME.vw-...old``: a process killed
    between the two renames leaves no store at ``path``, and the next write of
    it puts the old one back (:func:`_remove_stale_temporaries`). The earlier
    store is removed by :func:`_commit` once every output is in.
    """
    if not path.is_dir():
        try:
            os.rename(tmp, path)
            return None
        except OSError as exc:  # (another run's store put there since: replaced as any)
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST) or not path.is_dir():
                raise
    earlier = _claim(tmp, of=path)  # (the earlier store, at ``tmp`` once the two are swapped)
    if _exchange(tmp, path):
        return tmp
    if earlier is not None:
        _unclaim(tmp, earlier)
    aside = _spare_name(path, ".old")
    _claim(aside, of=path)  # (the earlier store, before it is renamed to it)
    os.rename(path, aside)
    try:
        os.rename(tmp, path)
    except BaseException as exc:
        try:
            os.rename(aside, path)  # put the old store back
            _unclaim(aside)
        except OSError as back:  # (both failed: say where the earlier output is)
            raise VolwarpError(
                f"{path}: the new store could not take its place ({_why(exc)}) and the "
                f"earlier one could not be put back ({_why(back)}): it is kept whole at "
                f"{aside} (rename it back yourself; the next write of {path.name} puts it "
                "back only while nothing is at that path, and removes it where another "
                "store is)") from exc
        raise
    return aside


def _put_store_back(path: Path, earlier: str | None) -> None:
    """Undo :func:`_rename_folder_in`: the earlier store (or none) at ``path``, the new one removed."""
    if earlier is not None and _exchange(earlier, path):
        _remove_tree(earlier)  # (the new store, now)
        return
    new = _spare_name(path, ".gone")
    os.rename(path, new)
    if earlier is not None:
        try:
            os.rename(earlier, path)
        except OSError:
            with contextlib.suppress(OSError):
                os.rename(new, path)  # (the new one back: a store at the path, not none)
            raise
    _remove_tree(new)


def _remove_old_store(old: str) -> None:
    """Remove an earlier store set aside by :func:`_rename_folder_in`.

    One renamed aside (``.old``) is renamed again before its removal: a kill
    during it leaves a ``.gone`` folder, never put back, where a half-removed
    ``.old`` would have been.
    """
    gone = old
    if old.endswith(".old"):
        gone = old[:-len(".old")] + ".gone"
        try:
            os.rename(old, gone)
        except OSError:
            gone = old
    _remove_tree(gone)


def _spare_name(path: Path, suffix: str) -> str:
    """A free name ``.NAME.vw-PID@HOST.XXXXXXXX`` + ``suffix`` beside ``path`` (nothing made)."""
    prefix = os.path.join(os.path.abspath(path.parent if str(path.parent) else "."),
                          _temporary_prefix(path.name))
    while True:
        name = prefix + "".join(_NAME_CHARS[b & 31] for b in os.urandom(8)) + suffix
        if not os.path.lexists(name):
            return name


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


def _chmod_tree(root: str, path: Path) -> None:
    """Give the store ``root`` its modes (mkdtemp makes folders 0700): the earlier store's.

    Where it replaces a store (:func:`_give_mode`), its folders get the earlier
    top folder's permissions and its files the same without the execute bits,
    and all the earlier one's group where the process may give it; a new store
    has the umask's (folders ``0777 & ~umask``, files ``0666 & ~umask``).
    """
    earlier = _earlier_mode(path, stat.S_ISDIR, 0o2777)
    # (the owner keeps rwx on folders: a read-only store's copy could not be removed, and
    # every later run left one more whole store behind)
    folders = 0o777 & ~current_umask() if earlier is None else earlier[0] | 0o700
    group = None
    if earlier is not None and os.stat(root).st_gid != earlier[1]:
        group = earlier[1]
    _set_mode(root, folders, group)
    for folder, dirs, files in os.walk(root):
        for d in dirs:
            _set_mode(os.path.join(folder, d), folders, group)
        for f in files:
            _set_mode(os.path.join(folder, f), folders & 0o666 if earlier is None
                      else earlier[0] & 0o666, group)


def _earlier_mode(path, kind, bits: int = 0o777) -> tuple[int, int] | None:
    """The permission ``bits`` and group of the earlier output at ``path``, a link followed.

    None where there is none, or it is not a ``kind`` (``stat.S_ISREG``, ``stat.S_ISDIR``).
    """
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mode & bits, st.st_gid) if kind(st.st_mode) else None


def _set_mode(name: str, mode: int, group: int | None) -> None:
    if group is not None:  # (first: a chown may clear bits a chmod set)
        with contextlib.suppress(OSError):  # (a group the process is not in: the default)
            os.chown(name, -1, group)
    os.chmod(name, mode)


def _give_mode(tmp: str, path: Path, mask: int) -> None:
    """Give the finished temporary ``tmp`` of ``path`` its mode (temporaries are 0600).

    An output that replaces a file keeps that file's permission bits and, where
    the process may set it, its group: a group-only output of patient data
    (0640, a group of its readers) stays so through the next run, a read-only
    one stays read-only. A new output gets ``0666 & ~umask``.
    """
    earlier = _earlier_mode(path, stat.S_ISREG)
    if earlier is None:
        os.chmod(tmp, 0o666 & ~mask)
        return
    mode, group = earlier
    _set_mode(tmp, mode, group if os.stat(tmp).st_gid != group else None)


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
    ``.raw``) must be both new or both old: the renames run with the stops
    held back, in the order given (the data file first, so that a header never
    names data it does not describe), after the last checks, as one
    :func:`_commit` (a failed one puts back what it replaced).
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
                _claim(tmp, fd)  # (its descriptor kept open, holding the lock)
            writeback.replacing(tmp, os.path.lexists(path))
        sync_temporaries()
        yield [Path(t) for t in tmps]
        mask = current_umask()
        for tmp, path in zip(tmps, paths, strict=True):
            _give_mode(tmp, path, mask)
        with blocked():
            check_stop()  # a stop asked while writing (and swallowed somewhere): no rename
            check_unchanged()  # an input mapped for these outputs changed: no rename
            moves = [(tmp, path, False) for tmp, path in zip(tmps, paths, strict=True)]
            held = _hold(moves, replaced, paths[-1])
            if not held:
                _commit(moves, replaced)
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
                _forget(tmp)
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
        _claim(tmp)
        _scratch_folders.add(os.path.realpath(tmp))
    return Path(tmp)


def remove_scratch_folder(tmp: str | os.PathLike) -> None:
    """Remove a :func:`make_scratch_folder` folder and all it holds."""
    import shutil

    tmp = str(tmp)
    with blocked():
        shutil.rmtree(tmp, ignore_errors=True)
        _forget(tmp)
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
    folders = re.compile(owner + r"\.[A-Za-z0-9_]{8}\.(partdir|old|kept|gone|scratch)$")
    try:
        names = os.listdir(path.parent if str(path.parent) else ".")
    except OSError:
        return
    for name in sorted(names, key=lambda n: not n.endswith(".old")):  # (an old store first)
        m = pattern.match(name) or folders.match(name)
        if m is None or _alive(int(m.group(1))):
            continue
        stale = path.parent / name
        if _in_use(str(stale)):  # (a live run's, in another PID namespace: _claim)
            continue
        if name.endswith(".old") and not os.path.lexists(path):
            # a store or file set aside by a process killed before the new one took its
            # place (_commit): the earlier output, put back (and kept where that fails:
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
