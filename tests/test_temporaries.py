"""A file output's temporary (:func:`volwarp_cli.io.atomic._make_temporary`), made as
``tempfile.mkstemp`` makes one without importing tempfile (and shutil and random with
it: 4-5 ms of every command's start)."""

from __future__ import annotations

import json
import os
import re
import stat
import subprocess
import sys
import textwrap

import pytest

from volwarp_cli.io import atomic
from volwarp_cli.warmup import write_inputs


def test_a_temporary_is_private_new_and_not_inherited(tmp_path):
    prefix = atomic._temporary_prefix("out.nrrd")
    fd, path = atomic._make_temporary(prefix, ".part.nrrd", tmp_path)
    try:
        assert os.path.isabs(path) and os.path.dirname(path) == str(tmp_path)
        assert stat.S_IMODE(os.fstat(fd).st_mode) == 0o600
        assert not os.get_inheritable(fd)
        assert os.path.samestat(os.fstat(fd), os.stat(path))
    finally:
        os.close(fd)
    # named so that the next run removes it if this process is killed
    stale = re.compile(re.escape(prefix) + r"[A-Za-z0-9_]{8}\.part\.nrrd$")
    assert stale.match(os.path.basename(path))


def test_a_taken_name_is_never_opened_another_is_drawn(tmp_path, monkeypatch):
    """Neither an existing file nor a symbolic link (to a file elsewhere) is written through."""
    victim = tmp_path / "victim"
    victim.write_bytes(b"keep me")
    draws = iter([b"\x00" * 8, b"\x01" * 8, b"\x02" * 8])
    monkeypatch.setattr(atomic.os, "urandom", lambda n: next(draws))
    prefix = ".o.nrrd.vw-1@h."
    first, second = (tmp_path / f"{prefix}{c * 8}.part" for c in "ab")
    first.write_bytes(b"another run's")
    second.symlink_to(victim)
    fd, path = atomic._make_temporary(prefix, ".part", tmp_path)
    os.write(fd, b"new")
    os.close(fd)
    assert os.path.basename(path) == f"{prefix}{'c' * 8}.part"
    assert first.read_bytes() == b"another run's" and victim.read_bytes() == b"keep me"


def test_a_warp_imports_neither_tempfile_nor_shutil(tmp_path):
    p = write_inputs(tmp_path)
    code = textwrap.dedent(f"""
        import json, sys
        from volwarp_cli.cli.main import main
        code = main(["warp", {p["blob"]!r}, "--spec", {p["move"]!r}, "-o", "w.nrrd"])
        sys.stdout.write("\\n" + json.dumps([m for m in ("tempfile", "shutil")
                                            if m in sys.modules]))
        sys.exit(code)
        """)
    res = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout.splitlines()[-1]) == []
    assert (tmp_path / "w.nrrd").stat().st_size > 4096
    assert stat.S_IMODE((tmp_path / "w.nrrd").stat().st_mode) == 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _store(folder, content: str):
    folder.mkdir()
    (folder / "zarr.json").write_text(content)
    return folder


def test_a_store_replaced_has_its_new_one_swapped_in_one_step(tmp_path, monkeypatch):
    """``path`` holds a whole store at every moment: never renamed aside (Linux, ext4/tmpfs)."""
    if not sys.platform.startswith("linux"):
        return
    path = _store(tmp_path / "o.ome.zarr", "old")
    tmp = _store(tmp_path / ".o.ome.zarr.vw-1@h.abcdefgh.partdir", "new")
    real = os.rename

    def no_aside(src, dst, *a, **k):
        assert os.fspath(src) != os.fspath(path), "the store was renamed aside"
        return real(src, dst, *a, **k)

    monkeypatch.setattr(atomic.os, "rename", no_aside)
    atomic._rename_folder(str(tmp), path)
    assert (path / "zarr.json").read_text() == "new"
    assert sorted(os.listdir(tmp_path)) == ["o.ome.zarr"]  # (the old store removed)


def test_without_a_swap_the_store_is_replaced_through_a_name_aside(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    path = _store(tmp_path / "o.ome.zarr", "old")
    tmp = _store(tmp_path / ".o.ome.zarr.vw-1@h.abcdefgh.partdir", "new")
    atomic._rename_folder(str(tmp), path)
    assert (path / "zarr.json").read_text() == "new"
    assert sorted(os.listdir(tmp_path)) == ["o.ome.zarr"]


def test_a_store_set_aside_by_a_killed_process_is_put_back(tmp_path):
    """Killed between the two renames (no swap): no store at the path, the old one aside.

    The next write of that output puts it back before anything else (it took it
    for a stale temporary and removed it: the earlier output lost).
    """
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = atomic._host()
    path = tmp_path / "o.ome.zarr"
    _store(tmp_path / f".o.ome.zarr.vw-{dead.pid}@{host}.abcdefgh.old", "earlier")
    _store(tmp_path / f".o.ome.zarr.vw-{dead.pid}@{host}.ijklmnop.partdir", "unfinished")
    atomic._remove_stale_temporaries(path)
    assert sorted(os.listdir(tmp_path)) == ["o.ome.zarr"]
    assert (path / "zarr.json").read_text() == "earlier"
    # with the store in place, an old one set aside is a stale temporary
    _store(tmp_path / f".o.ome.zarr.vw-{dead.pid}@{host}.qrstuvwx.old", "older")
    atomic._remove_stale_temporaries(path)
    assert sorted(os.listdir(tmp_path)) == ["o.ome.zarr"]
    assert (path / "zarr.json").read_text() == "earlier"


def test_a_detached_pair_is_renamed_under_its_folders_lock(tmp_path, monkeypatch):
    """Two runs committing one `.nhdr` + `.raw` at once: their renames never interleave.

    While a run renames its pair, another cannot take the folder's lock (the
    other run's renames wait for it), so one whole pair wins.
    """
    import fcntl

    import numpy as np

    from volwarp_cli.io import read_volume, write_volume
    from volwarp_cli.volume import Volume

    out = tmp_path / "o.nhdr"
    held = []
    real = os.replace

    def probe(src, dst, *a, **k):
        fd = os.open(tmp_path, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            held.append(False)
        except BlockingIOError:
            held.append(True)
        finally:
            os.close(fd)
        return real(src, dst, *a, **k)

    monkeypatch.setattr(atomic.os, "replace", probe)
    vol = Volume(np.arange(24, dtype=np.float32).reshape(2, 3, 4))
    write_volume(vol, out)
    assert held == [True, True]  # (the data file, then the header)
    np.testing.assert_array_equal(read_volume(out).data, vol.data)


def test_a_store_put_in_place_by_another_run_meanwhile_is_replaced(tmp_path, monkeypatch):
    """Two runs writing one store: the second found no store, then the first's was there
    (its rename failed, "Directory not empty", exit 1): it is replaced as any old store."""
    path = tmp_path / "o.ome.zarr"
    tmp = _store(tmp_path / ".o.ome.zarr.vw-1@h.abcdefgh.partdir", "new")
    real = os.rename

    def first_run_wins_the_race(src, dst, *a, **k):
        if os.fspath(dst) == os.fspath(path) and not path.exists():
            _store(path, "the other run's")
        return real(src, dst, *a, **k)

    monkeypatch.setattr(atomic.os, "rename", first_run_wins_the_race)
    atomic._rename_folder(str(tmp), path)
    assert (path / "zarr.json").read_text() == "new"
    assert sorted(os.listdir(tmp_path)) == ["o.ome.zarr"]


def test_a_store_killed_while_removed_is_never_put_back(tmp_path):
    """The old store is renamed '.gone' before its removal: a kill during the removal leaves
    a half-removed folder that no later write takes for the earlier output."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    path = tmp_path / "o.ome.zarr"
    _store(tmp_path / f".o.ome.zarr.vw-{dead.pid}@{atomic._host()}.abcdefgh.gone", "half")
    atomic._remove_stale_temporaries(path)
    assert os.listdir(tmp_path) == []


def test_the_old_store_is_removed_under_a_name_never_put_back(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    path = _store(tmp_path / "o.ome.zarr", "old")
    tmp = _store(tmp_path / ".o.ome.zarr.vw-1@h.abcdefgh.partdir", "new")
    removed = []
    monkeypatch.setattr(atomic, "_remove_tree", lambda root: removed.append(os.path.basename(root)))
    atomic._rename_folder(str(tmp), path)
    (name,) = removed
    assert name.endswith(".gone") and (tmp_path / name / "zarr.json").read_text() == "old"


def test_a_store_that_cannot_be_put_back_is_kept(tmp_path, monkeypatch):
    """Putting a dead process's old store back fails (a full disk): it is kept where it is,
    the earlier output's only copy (it was removed as a stale temporary)."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    path = tmp_path / "o.ome.zarr"
    old = _store(tmp_path / f".o.ome.zarr.vw-{dead.pid}@{atomic._host()}.abcdefgh.old", "earlier")

    def full(src, dst, *a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic.os, "rename", full)
    atomic._remove_stale_temporaries(path)
    assert (old / "zarr.json").read_text() == "earlier" and not path.exists()


def test_a_store_neither_replaced_nor_put_back_is_named_and_put_back_later(tmp_path,
                                                                            monkeypatch):
    """No swap, and both renames fail after the old store was set aside (a file system
    gone read-only): the error says where the earlier output is kept (it was a raw
    "No space left on device" naming only the hidden name), and the next write of that
    output, once this process is gone, puts it back."""
    from volwarp_cli.errors import VolwarpError

    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    path = _store(tmp_path / "o.ome.zarr", "old")
    tmp = _store(tmp_path / ".o.ome.zarr.vw-1@h.abcdefgh.partdir", "new")
    real = os.rename

    def only_aside(src, dst, *a, **k):
        if os.fspath(dst) != os.fspath(path):
            return real(src, dst, *a, **k)
        raise OSError(30, "Read-only file system", os.fspath(src), None, os.fspath(dst))

    monkeypatch.setattr(atomic.os, "rename", only_aside)
    with pytest.raises(VolwarpError) as err:
        atomic._rename_folder(str(tmp), path)
    (aside,) = [n for n in os.listdir(tmp_path) if n.endswith(".old")]
    message = str(err.value)
    assert f"kept whole at {tmp_path / aside} (rename it back yourself" in message, message
    assert "Read-only file system" in message and str(path) in message
    assert (tmp_path / aside / "zarr.json").read_text() == "old" and not path.exists()
    monkeypatch.setattr(atomic.os, "rename", real)
    # this process's name on it: another process's write of the output would put it back
    # once this one is gone, and its claim on the store with it (atomic._claim)
    for name in list(atomic._claims):
        atomic._unclaim(name)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    later = aside.replace(f".vw-{os.getpid()}@", f".vw-{dead.pid}@")
    real(tmp_path / aside, tmp_path / later)
    atomic._remove_stale_temporaries(path)
    assert (path / "zarr.json").read_text() == "old"


def test_a_fork_whose_lock_was_not_taken_releases_nothing():
    """A stop may cut the fork hook's acquire short: the hook after it releases only what it
    took (it released a lock another thread held)."""
    from volwarp_cli.io import writeback

    writeback._held_for_fork[0] = False
    writeback._release_after_fork()  # (no RuntimeError: nothing was taken)
    writeback._hold_for_fork()
    assert writeback._lock.locked()
    writeback._release_after_fork()
    assert not writeback._lock.locked()
