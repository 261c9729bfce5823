"""One `volwarp batch` at a time per output folder (the shards of one array side by side).

Two runs on one folder both did all the work before: now the second stops at
once (exit 75, one line naming the first's pid and host) or, with ``--wait``,
waits and then finds everything up to date.
"""

from __future__ import annotations

import fcntl
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

from volwarp_cli.batch.lock import BOOK_DIR, LOCK_NAME, hold
from volwarp_cli.io import write_volume

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import scan_volume, summary, volwarp  # noqa: E402

MANIFEST = """version: 1
inputs: {glob: "scans/*.nrrd"}
output_dir: out
steps:
  - {name: conv, run: convert, output: "{stem}.nrrd", options: ["--dtype", "float32"]}
"""


def make_tree(root: Path, scans: int) -> Path:
    (root / "scans").mkdir()
    for i in range(scans):
        write_volume(scan_volume(i % 3), root / "scans" / f"p{i:02d}.nrrd")
    (root / "manifest.yaml").write_text(MANIFEST)
    return root / "manifest.yaml"


def start(manifest: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "volwarp_cli", "batch", str(manifest),
                             "-j", "1", *args], stderr=subprocess.PIPE, text=True)


def held(path: Path) -> bool:
    """True when another process holds ``path`` locked."""
    if not path.exists():
        return False
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
    return False


def wait_until_held(proc: subprocess.Popen, path: Path) -> None:
    deadline = time.monotonic() + 60
    while not held(path):
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "the first run never took the lock"
        time.sleep(0.01)


def finish(proc: subprocess.Popen) -> tuple[int, str]:
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err


def test_second_run_stops_with_75_naming_the_first(tmp_path):
    manifest = make_tree(tmp_path, 5)
    first = start(manifest)
    try:
        wait_until_held(first, tmp_path / "out" / BOOK_DIR / LOCK_NAME)
        second = volwarp("batch", manifest)
    finally:
        code, err = finish(first)
    assert second.returncode == 75, second.stderr
    assert second.stderr.strip() == (
        f"volwarp: error: {tmp_path / 'out'} is being processed by another batch "
        f"(pid {first.pid} on {socket.gethostname()}); give --wait to wait")
    assert code == 0, err
    assert summary(subprocess.CompletedProcess([], code, "", err)) == (
        "volwarp batch: 5 scans, 5 ok, 0 skipped, 0 failed")


def test_wait_waits_then_finds_everything_up_to_date(tmp_path):
    manifest = make_tree(tmp_path, 4)
    first = start(manifest)
    try:
        wait_until_held(first, tmp_path / "out" / BOOK_DIR / LOCK_NAME)
        second = volwarp("batch", manifest, "--wait")
    finally:
        code, err = finish(first)
    assert code == 0 and "4 ok" in err, err
    assert second.returncode == 0, second.stderr
    assert re.search(rf"^volwarp: waiting: \S+ is being processed by another batch "
                     rf"\(pid {first.pid} on ", second.stderr, re.M), second.stderr
    assert summary(second) == "volwarp batch: 4 scans, 0 ok, 4 skipped, 0 failed"


def test_shards_share_the_folder_and_its_record(tmp_path):
    """The tasks of a SLURM array run side by side; a whole run waits for them.

    This process holds shard 0's locks as a running shard 0 would (a real shard
    0 could end before the other runs start on a busy machine), then runs it.
    """
    manifest = make_tree(tmp_path, 6)
    with hold(tmp_path / "out", shard=(0, 2), manifest=manifest):
        whole = volwarp("batch", manifest)
        again = volwarp("batch", manifest, "--shard", "0/2")
        shard1 = volwarp("batch", manifest, "--shard", "1/2")
    shard0 = volwarp("batch", manifest, "--shard", "0/2")
    assert whole.returncode == 75 and re.search(
        rf"\(pid {os.getpid()} on \S+, shard 0/2\); give --wait", whole.stderr), whole.stderr
    assert again.returncode == 75 and re.search(
        rf"\(pid {os.getpid()} on \S+, shard 0/2\)", again.stderr), again.stderr
    assert shard1.returncode == 0 and "3 ok" in summary(shard1), shard1.stderr
    assert shard0.returncode == 0 and "3 ok" in summary(shard0), shard0.stderr
    res = volwarp("batch", manifest)  # both shards' records were kept
    assert summary(res) == "volwarp batch: 6 scans, 0 ok, 6 skipped, 0 failed", res.stderr


def test_only_the_shards_of_one_array_share_the_folder(tmp_path):
    """--shard 0/2 running: --shard 0/3 (another array: it would split the scans otherwise)
    or the same N of another manifest is another batch (75, or waited for with --wait); the
    array's other shards come in, also where a file holds a stale signature of another
    array (the folder's previous batch)."""
    import json
    import threading

    import pytest

    from volwarp_cli.batch.lock import Busy

    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    book = tmp_path / BOOK_DIR
    book.mkdir()
    (book / "shard-1-of-2.lock").write_text(json.dumps(
        {"pid": 1, "host": "x", "shard": "1/2", "array": f"2 {tmp_path / 'old.yaml'}"}))
    with hold(tmp_path, shard=(0, 2), manifest=a):
        with pytest.raises(Busy, match="another --shard array"):
            with hold(tmp_path, shard=(0, 3), manifest=a):
                pass
        with pytest.raises(Busy, match="another --shard array"):
            with hold(tmp_path, shard=(1, 2), manifest=b):
                pass
        with hold(tmp_path, shard=(1, 2), manifest=a):  # (its file's stale signature: no matter)
            pass
        entered = []

        def other_array():
            with hold(tmp_path, shard=(0, 3), manifest=a, wait=True):
                entered.append(time.monotonic())

        waiter = threading.Thread(target=other_array)
        waiter.start()
        time.sleep(0.5)
        assert not entered  # (it waits for this array's shards to end)
        released = time.monotonic()
    waiter.join(10)
    assert entered and entered[0] >= released


def test_a_shard_starting_during_another_s_probe_of_its_file_comes_in(tmp_path):
    """SLURM starts every shard at once, and each start probes the others' files by taking
    them for a moment: a shard whose own take met such a probe was refused (85 of 4,332
    starts). Probes and takes are now under array.lock: the start waits for the probe."""
    import threading

    book = tmp_path / BOOK_DIR
    book.mkdir()
    gate = os.open(book / "array.lock", os.O_RDWR | os.O_CREAT)
    probe = os.open(book / "shard-1-of-4.lock", os.O_RDWR | os.O_CREAT)
    outcome = []

    def start():
        try:
            with hold(tmp_path, shard=(1, 4), manifest=tmp_path / "m.yaml"):
                outcome.append("in")
        except Exception as exc:  # noqa: BLE001 - the outcome asserted below
            outcome.append(exc)

    try:
        fcntl.flock(gate, fcntl.LOCK_EX)  # a probe under way: the gate and shard 1's file
        fcntl.flock(probe, fcntl.LOCK_EX)
        t = threading.Thread(target=start)
        t.start()
        time.sleep(0.3)
        assert not outcome  # (waiting for the gate, not refused)
        fcntl.flock(probe, fcntl.LOCK_UN)
        fcntl.flock(gate, fcntl.LOCK_UN)
        t.join(10)
    finally:
        os.close(probe)
        os.close(gate)
    assert outcome == ["in"], outcome
