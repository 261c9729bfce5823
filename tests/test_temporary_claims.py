"""A live run's temporaries are never taken for a dead one's (volwarp_cli.io.atomic._claim).

The next write of an output removes the temporaries of dead processes (their
names carry a process id and host name). A process id says nothing across PID
namespaces: two containers on one host name (``docker run --network host``)
sharing a data folder each saw the other's live temporaries as a dead
process's, and removed them (the other run's work then failed at its rename),
or put a store it had set aside mid-commit back at the path. Each temporary
now holds an exclusive ``flock`` while it is live, which any process sees. The
other run is played here by a child process holding the lock of a temporary
named with a process id that no longer exists (as the other namespace's ids
look from this one).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from volwarp_cli.io import atomic

HOLD = ("import fcntl, os, sys\n"
        "fd = os.open(sys.argv[1], os.O_RDONLY)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "print('held', flush=True)\n"
        "sys.stdin.read()\n")


@pytest.fixture
def dead_pid():
    """A process id that no longer exists (another namespace's live run looks so)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


class Holder:
    """Another run holding the lock of ``path``, until :meth:`end`."""

    def __init__(self, path):
        self.proc = subprocess.Popen([sys.executable, "-c", HOLD, str(path)],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout.readline().strip() == "held"

    def end(self):
        self.proc.stdin.close()
        self.proc.wait()
        self.proc.stdout.close()


def _temporary_of(path, pid: int, suffix: str) -> str:
    return os.path.join(path.parent, f".{path.name}.vw-{pid}@{atomic._host()}.abcdefgh{suffix}")


def test_a_live_temporary_of_another_namespace_survives_a_write(tmp_path, dead_pid):
    """Before: the next write of the output removed it while its run was writing it."""
    out = tmp_path / "o.nrrd"
    theirs = _temporary_of(out, dead_pid, ".part.nrrd")
    with open(theirs, "wb") as fh:
        fh.write(b"their run's samples")
    holder = Holder(theirs)
    try:
        atomic.write_bytes_atomic(out, b"ours")
        assert out.read_bytes() == b"ours"
        assert Path(theirs).read_bytes() == b"their run's samples"
    finally:
        holder.end()
    atomic.write_bytes_atomic(out, b"ours again")  # (their run is gone: its temporary too)
    assert not os.path.exists(theirs)
    assert sorted(os.listdir(tmp_path)) == ["o.nrrd"]


def test_a_store_set_aside_by_a_live_run_is_not_put_back(tmp_path, dead_pid):
    """A run between its store's two renames (the old one aside, the new one not yet in):
    before, another run's write of the output put the old store back at the path."""
    out = tmp_path / "o.ome.zarr"
    aside = _temporary_of(out, dead_pid, ".old")
    os.mkdir(aside)
    with open(os.path.join(aside, "zarr.json"), "w") as fh:
        fh.write("old")
    holder = Holder(aside)
    try:
        atomic._remove_stale_temporaries(out)
        assert not out.exists() and os.path.isdir(aside)
    finally:
        holder.end()
    atomic._remove_stale_temporaries(out)  # (now a killed run's: put back)
    assert (out / "zarr.json").read_text() == "old" and not os.path.exists(aside)


def test_a_temporary_is_claimed_while_it_is_written_and_let_go_after(tmp_path):
    out = tmp_path / "o.bin"
    with atomic.atomic_output(out) as tmp:
        tmp.write_bytes(b"x")
        assert atomic._in_use(str(tmp))  # (a lock held: seen from any open of it)
    assert out.read_bytes() == b"x"
    assert not atomic._in_use(str(out)) and not atomic._claims
    with atomic.scratch_folder(out) as scratch:
        assert atomic._in_use(str(scratch))
    assert not atomic._claims


def test_a_store_and_a_file_of_a_set_are_claimed_until_their_commit(tmp_path):
    store, out = tmp_path / "s.ome.zarr", tmp_path / "o.bin"
    with atomic.outputs_together():
        with atomic.atomic_folder(store) as folder:
            (folder / "zarr.json").write_text("new")
        with atomic.atomic_output(out) as tmp:
            tmp.write_bytes(b"x")
        held = list(atomic._claims)
        assert str(folder) in held and str(tmp) in held  # (held, renamed at the set's end)
        assert all(atomic._in_use(name) for name in held)
    assert (store / "zarr.json").read_text() == "new" and out.read_bytes() == b"x"
    assert not atomic._claims


def test_claims_are_capped_the_outputs_beyond_kept_by_process_id(tmp_path, monkeypatch):
    """A morph's hundreds of frames, renamed together at its end: a descriptor each would
    near the usual 1024 open files; beyond the cap a temporary is not claimed."""
    monkeypatch.setattr(atomic, "CLAIMS_MAX", 3)
    outs = [tmp_path / f"f{k}.bin" for k in range(8)]
    with atomic.outputs_together():
        for k, out in enumerate(outs):
            with atomic.atomic_output(out) as tmp:
                tmp.write_bytes(bytes([k]))
        assert sum(map(len, atomic._claims.values())) == 3
    assert [o.read_bytes() for o in outs] == [bytes([k]) for k in range(8)]
    assert not atomic._claims


def test_an_earlier_output_kept_for_a_rollback_is_claimed(tmp_path):
    """A set's earlier outputs keep a second name until every new one is in (the rollback
    needs it): another run must not remove it meanwhile."""
    out = tmp_path / "o.bin"
    out.write_bytes(b"earlier")
    kept = atomic._keep(out)
    assert kept is not None and kept[1]
    assert atomic._in_use(kept[0])
    atomic._discard(kept)
    assert not os.path.exists(kept[0]) and not atomic._claims
    assert not atomic._in_use(str(out))
