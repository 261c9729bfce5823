"""A command's outputs are committed all or none, and a replaced output keeps its mode.

volwarp_cli.io.atomic._commit renames a set of finished temporaries onto their
outputs; where one rename fails (an output made immutable, another user's file
in a sticky folder) the outputs already replaced are put back from a second
name kept first, so that a detached header never describes another run's
samples. A rename cannot fail on demand without root: these tests make
``os.replace`` (or ``os.rename``) fail for one output, in process.
"""

from __future__ import annotations

import errno
import os
import signal
import stat
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.io import atomic, read_volume, write_volume
from volwarp_cli.io.atomic import atomic_folder, atomic_output, outputs_together
from volwarp_cli.volume import Volume


def _names(folder):
    return sorted(os.listdir(folder))


def _failing(monkeypatch, name: str, func: str = "replace"):
    """``os.<func>`` fails (EPERM, as for an immutable file) for a destination called ``name``."""
    real = getattr(os, func)

    def fail(src, dst, *a, **k):
        if os.path.basename(os.fspath(dst)) == name:
            raise OSError(errno.EPERM, "Operation not permitted", os.fspath(src))
        return real(src, dst, *a, **k)

    monkeypatch.setattr(atomic.os, func, fail)


def _write_set(folder, contents: dict):
    """Write each ``name: text`` as one set (one command's outputs)."""
    with outputs_together():
        for name, text in contents.items():
            with atomic_output(folder / name) as tmp:
                tmp.write_text(text)


def test_a_failed_rename_puts_back_every_output_already_replaced(tmp_path, monkeypatch):
    """a and b replaced, c new, then d's rename fails: a and b old again, c gone."""
    (tmp_path / "a.txt").write_text("old a")
    (tmp_path / "b.txt").write_text("old b")
    (tmp_path / "d.txt").write_text("old d")
    _failing(monkeypatch, "d.txt")
    with pytest.raises(VolwarpError) as err:
        _write_set(tmp_path, {"a.txt": "new a", "b.txt": "new b", "c.txt": "new c",
                              "d.txt": "new d"})
    assert str(err.value) == (f"{tmp_path / 'd.txt'}: cannot put the new output in place "
                              "(Operation not permitted); the other outputs are left as they were")
    assert _names(tmp_path) == ["a.txt", "b.txt", "d.txt"]  # (no temporary, no second name)
    assert [(tmp_path / n).read_text() for n in ("a.txt", "b.txt", "d.txt")] == \
        ["old a", "old b", "old d"]


def test_a_committed_set_leaves_no_second_name(tmp_path):
    for name in "abc":
        (tmp_path / f"{name}.txt").write_text("old")
    _write_set(tmp_path, {f"{n}.txt": f"new {n}" for n in "abcd"})
    assert _names(tmp_path) == ["a.txt", "b.txt", "c.txt", "d.txt"]
    assert [(tmp_path / f"{n}.txt").read_text() for n in "abcd"] == \
        ["new a", "new b", "new c", "new d"]


def test_a_detached_header_that_cannot_be_replaced_keeps_its_own_samples(run, tmp_path,
                                                                         monkeypatch):
    """The reported case: `out.nhdr` immutable, its `out.raw` was replaced all the same
    and the old header described the new samples (a truncated file, or wrong values)."""
    out = tmp_path / "out.nhdr"
    write_volume(Volume(np.arange(60, dtype=np.uint8).reshape(3, 4, 5)), out)
    before = {n: (tmp_path / n).read_bytes() for n in _names(tmp_path)}
    flat = tmp_path / "flat.nrrd"
    write_volume(Volume(np.full((2, 2, 2), 7, np.int16)), flat)
    _failing(monkeypatch, "out.nhdr")
    res = run("convert", flat, "-o", out)
    assert res.code == 1
    # the output, not its hidden temporary, named
    assert f"{out}: cannot put the new output in place (Operation not permitted)" in res.stderr
    assert ".part" not in res.stderr
    assert _names(tmp_path) == ["flat.nrrd", "out.nhdr", "out.raw"]
    assert {n: (tmp_path / n).read_bytes() for n in before} == before
    np.testing.assert_array_equal(read_volume(out).data,
                                  np.arange(60, dtype=np.uint8).reshape(3, 4, 5))


def test_without_hard_links_the_earlier_file_is_renamed_aside_and_back(tmp_path, monkeypatch):
    """A file system without hard links (or a file another user owns, under
    protected_hardlinks): the earlier output renamed to its second name instead."""
    def no_links(*a, **k):
        raise OSError(errno.EPERM, "Operation not permitted")

    real = os.replace
    monkeypatch.setattr(atomic.os, "link", no_links)
    (tmp_path / "a.txt").write_text("old a")
    (tmp_path / "b.txt").write_text("old b")
    _failing(monkeypatch, "b.txt")
    with pytest.raises(VolwarpError, match="b.txt: cannot put"):
        _write_set(tmp_path, {"a.txt": "new a", "b.txt": "new b"})
    assert _names(tmp_path) == ["a.txt", "b.txt"]
    assert (tmp_path / "a.txt").read_text() == "old a"
    monkeypatch.setattr(atomic.os, "replace", real)
    _write_set(tmp_path, {"a.txt": "new a", "b.txt": "new b"})
    assert _names(tmp_path) == ["a.txt", "b.txt"]
    assert (tmp_path / "a.txt").read_text() == "new a"


def test_a_file_set_aside_by_a_killed_process_is_put_back(tmp_path):
    """Killed between the earlier file's rename aside and the new one's: the next write of
    that output puts it back first (else it removed it as a stale temporary)."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "o.txt"
    (tmp_path / f".o.txt.vw-{dead.pid}@{atomic._host()}.abcdefgh.old").write_text("earlier")
    atomic._remove_stale_temporaries(out)
    assert _names(tmp_path) == ["o.txt"] and out.read_text() == "earlier"


def _store(folder, content: str):
    folder.mkdir()
    (folder / "zarr.json").write_text(content)
    return folder


@pytest.mark.parametrize("swap", [True, False], ids=["exchange", "aside"])
def test_a_store_replaced_before_a_failed_rename_is_put_back(tmp_path, monkeypatch, swap):
    """A store's old one is removed only once every output is in; put back where one fails."""
    if not swap:
        monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    store = _store(tmp_path / "o.ome.zarr", "old store")
    (tmp_path / "o.txt").write_text("old")
    _failing(monkeypatch, "o.txt")
    with pytest.raises(VolwarpError, match="o.txt: cannot put"), outputs_together():
        with atomic_folder(store) as tmp:
            (tmp / "zarr.json").write_text("new store")
        with atomic_output(tmp_path / "o.txt") as tmp:
            tmp.write_text("new")
    assert _names(tmp_path) == ["o.ome.zarr", "o.txt"]
    assert _names(store) == ["zarr.json"] and (store / "zarr.json").read_text() == "old store"
    assert (tmp_path / "o.txt").read_text() == "old"


def test_a_new_store_before_a_failed_rename_is_removed(tmp_path, monkeypatch):
    (tmp_path / "o.txt").write_text("old")
    _failing(monkeypatch, "o.txt")
    with pytest.raises(VolwarpError), outputs_together():
        with atomic_folder(tmp_path / "o.ome.zarr") as tmp:
            (tmp / "zarr.json").write_text("new store")
        with atomic_output(tmp_path / "o.txt") as tmp:
            tmp.write_text("new")
    assert _names(tmp_path) == ["o.txt"]


def test_a_stop_during_the_commit_waits_for_it_and_leaves_no_second_name(tmp_path):
    """SIGTERM landing between two renames: the commit ends (all new), its second names
    removed, then the stop is raised."""
    code = textwrap.dedent(f"""
        import os, signal, sys
        from pathlib import Path
        from volwarp_cli import signals
        from volwarp_cli.io import atomic
        signals.install()
        folder = Path({str(tmp_path)!r})
        real = os.replace
        def replace(src, dst):
            os.kill(os.getpid(), signal.SIGTERM)
            return real(src, dst)
        try:
            with atomic.outputs_together():
                for name in ("a.txt", "b.txt"):
                    with atomic.atomic_output(folder / name) as tmp:
                        tmp.write_text("new")
                atomic.os.replace = replace
        except signals.Interrupted as exc:
            sys.exit(128 + exc.signum)
        """)
    for name in ("a.txt", "b.txt"):
        (tmp_path / name).write_text("old")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 128 + signal.SIGTERM, res.stderr
    assert _names(tmp_path) == ["a.txt", "b.txt"]
    assert [(tmp_path / n).read_text() for n in ("a.txt", "b.txt")] == ["new", "new"]


def _other_group() -> int | None:
    """A group this process may give its files other than its own (None: none)."""
    mine = os.getegid()
    if os.geteuid() == 0:
        return 1 if mine != 1 else 2
    return next((g for g in os.getgroups() if g != mine), None)


@pytest.mark.parametrize("mode", [0o640, 0o444, 0o600], ids=oct)
def test_a_replaced_output_keeps_its_permissions_and_group(tmp_path, mode):
    """A group-only output (patient data) became world-readable at the next run; a
    read-only one writable."""
    out = tmp_path / "o.nrrd"
    vol = Volume(np.ones((2, 3, 4), np.uint8))
    write_volume(vol, out)
    group = _other_group()
    if group is not None:
        os.chown(out, -1, group)
    os.chmod(out, mode)
    write_volume(vol.with_data(np.zeros((2, 3, 4), np.uint8)), out)
    st = os.stat(out)
    assert stat.S_IMODE(st.st_mode) == mode
    if group is not None:
        assert st.st_gid == group
    assert read_volume(out).data.max() == 0  # (replaced)


def test_a_new_output_follows_the_umask(tmp_path):
    old = os.umask(0o027)
    try:
        write_volume(Volume(np.ones((2, 3, 4), np.uint8)), tmp_path / "n.nrrd")
    finally:
        os.umask(old)
    assert stat.S_IMODE(os.stat(tmp_path / "n.nrrd").st_mode) == 0o640


def test_a_replaced_store_keeps_its_permissions_and_group(tmp_path):
    path = tmp_path / "o.ome.zarr"
    vol = Volume(np.ones((2, 3, 4), np.uint8))
    write_volume(vol, path)
    group = _other_group()
    os.chmod(path, 0o750)
    if group is not None:
        os.chown(path, -1, group)
    write_volume(vol, path)
    st = os.stat(path)
    assert stat.S_IMODE(st.st_mode) == 0o750
    for folder, dirs, files in os.walk(path):
        for name in dirs:
            assert stat.S_IMODE(os.stat(os.path.join(folder, name)).st_mode) == 0o750
        for name in files:
            assert stat.S_IMODE(os.stat(os.path.join(folder, name)).st_mode) == 0o640
    if group is not None:
        assert st.st_gid == group


@pytest.mark.parametrize("signum", [signal.SIGUSR1, signal.SIGUSR2, signal.SIGALRM,
                                    signal.SIGXCPU], ids=lambda s: s.name)
def test_the_batch_system_s_signals_are_stops(tmp_path, signum):
    """Slurm's ``--signal=USR1@60``, a timer's SIGALRM, a CPU limit's SIGXCPU killed the
    run as they came, leaving its temporary output behind (exit 138, 142, 152)."""
    code = textwrap.dedent(f"""
        import os, sys, time
        from volwarp_cli import signals
        signals.install()
        tmp = {str(tmp_path / ".o.nrrd.vw-1@h.abcdefgh.part.nrrd")!r}
        open(tmp, "w").close()
        signals.temporaries.add(tmp)
        try:
            os.kill(os.getpid(), {int(signum)})
            time.sleep(30)
        except signals.Interrupted as exc:
            sys.exit(128 + exc.signum)
        """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, preexec_fn=lambda: signal.signal(signum, signal.SIG_DFL))
    assert res.returncode == 128 + signum, res.stderr
    assert _names(tmp_path) == []


def _chattr(flag: str, path) -> bool:
    """``chattr flag path``; False where it cannot be done (not root, no such tool or file system)."""
    try:
        return subprocess.run(["chattr", flag, str(path)], capture_output=True).returncode == 0
    except OSError:
        return False


@pytest.mark.parametrize(("flag", "what"), [("+i", "immutable (chattr +i)"),
                                            ("+a", "append-only (chattr +a)")])
def test_an_output_that_cannot_be_renamed_over_is_refused_before_any_work(run, tmp_path, flag,
                                                                          what):
    out, flat = tmp_path / "out.nhdr", tmp_path / "flat.nrrd"
    write_volume(Volume(np.arange(60, dtype=np.uint8).reshape(3, 4, 5)), out)
    write_volume(Volume(np.full((2, 2, 2), 7, np.int16)), flat)
    before = {n: (tmp_path / n).read_bytes() for n in _names(tmp_path)}
    if not _chattr(flag, out):
        pytest.skip("chattr needs root and a file system with inode flags")
    try:
        res = run("convert", flat, "-o", out)
    finally:
        _chattr(flag.replace("+", "-"), out)
    assert res.code == 1 and f"{out}: cannot be replaced: it is {what}" in res.stderr, res
    assert {n: (tmp_path / n).read_bytes() for n in _names(tmp_path)} == before


def test_another_user_s_file_in_a_sticky_folder_is_refused_before_any_work(tmp_path,
                                                                          monkeypatch):
    """As in /tmp: only the file's owner (or the folder's) may rename over it."""
    folder = tmp_path / "shared"
    folder.mkdir()
    out = folder / "o.nrrd"
    out.write_bytes(b"another user's")
    try:
        os.chown(out, 4242, -1)
    except PermissionError:
        pytest.skip("giving a file to another user needs root")
    os.chmod(folder, 0o1777)
    monkeypatch.setattr(atomic.os, "geteuid", lambda: 4343)
    with pytest.raises(VolwarpError, match="o.nrrd: cannot be replaced: it belongs to another "
                                           "user and its folder is sticky"):
        atomic.check_output_path(out)
    os.chmod(folder, 0o777)  # (not sticky: the rename may replace it)
    assert atomic.check_output_path(out) == out


def test_a_hard_link_kept_by_a_killed_process_is_never_put_back(tmp_path):
    """A ``.kept`` link is a copy (the output was replaced after it was made): put back, it
    brought back an output its user had deleted since, even on a failed run."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out = tmp_path / "o.txt"
    (tmp_path / f".o.txt.vw-{dead.pid}@{atomic._host()}.abcdefgh.kept").write_text("earlier")
    atomic._remove_stale_temporaries(out)
    assert _names(tmp_path) == []


def test_a_read_only_store_replaced_stays_removable_by_its_owner(tmp_path):
    """Its folders' modes copied whole, a read-only store's replacement was read-only too:
    its temporary could not be removed, and each later run left one more behind."""
    path = tmp_path / "o.ome.zarr"
    vol = Volume(np.ones((2, 3, 4), np.uint8))
    write_volume(vol, path)
    for folder, dirs, files in os.walk(path, topdown=False):
        for name in files:
            os.chmod(os.path.join(folder, name), 0o444)
        for name in dirs:
            os.chmod(os.path.join(folder, name), 0o555)
    os.chmod(path, 0o2555)
    write_volume(vol, path)
    assert stat.S_IMODE(os.stat(path).st_mode) & 0o700 == 0o700
    for folder, dirs, files in os.walk(path):
        for name in dirs:
            assert stat.S_IMODE(os.stat(os.path.join(folder, name)).st_mode) & 0o700 == 0o700
        for name in files:
            assert stat.S_IMODE(os.stat(os.path.join(folder, name)).st_mode) == 0o444


def test_a_commit_does_not_wait_for_a_lock_its_own_process_holds(tmp_path):
    """``flock OUT volwarp ... -o OUT/x.nhdr``: the command inherits flock(1)'s locked
    descriptor of OUT; its own lock of OUT waited for it for good (stops held back)."""
    import fcntl

    src = tmp_path / "in.nrrd"
    write_volume(Volume(np.arange(24, dtype=np.uint8).reshape(2, 3, 4)), src)
    out = tmp_path / "out"
    out.mkdir()
    fd = os.open(out, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        res = subprocess.run([sys.executable, "-m", "volwarp_cli", "convert", str(src), "-o",
                              str(out / "x.nhdr")], pass_fds=(fd,), capture_output=True,
                             text=True, timeout=60)
    finally:
        os.close(fd)
    assert res.returncode == 0, res.stderr
    assert np.array_equal(read_volume(out / "x.nhdr").data,
                          np.arange(24, dtype=np.uint8).reshape(2, 3, 4))
