"""An output replacing a file has its samples asked out as they are written (io/writeback).

The requests change no byte of any output (the kernel writes the pages out
anyway); what is tested is that they are made where a rename would wait for
them (an output replacing a file, by spans covering its samples), never for
a new file or a scratch file, that the libc call is the right one, and that
a slow disk cannot make them pile up.
"""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import writeback

SPECS = Path(__file__).resolve().parent.parent / "specs"
linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="sync_file_range")


@pytest.fixture
def asked(monkeypatch):
    """Record every request as (file, offset, bytes), made at once (no thread)."""
    calls = []

    def record(fd, offset, nbytes):
        if nbytes < writeback.MIN_BYTES:
            return False
        calls.append((os.path.realpath(f"/proc/self/fd/{fd}"), offset, nbytes))
        return True

    monkeypatch.setattr(writeback, "start", record)
    monkeypatch.setattr(writeback, "MIN_BYTES", 0)
    return calls


@pytest.fixture
def slow_disk(tmp_path, monkeypatch):
    """A disk whose requests wait until released: ``(release event, a 1 MiB file)``."""
    release = threading.Event()

    def slow_call(fd, offset, nbytes, flags):
        release.wait(10)
        return 0

    monkeypatch.setattr(writeback, "_state", {"call": slow_call})
    path = tmp_path / "out.bin"
    path.write_bytes(b"\0" * (1 << 20))
    yield release, path
    release.set()


def _drained() -> None:
    """Wait (10 s at most) for the thread to have made every request."""
    for _ in range(1000):
        if writeback.pending() == 0:
            return
        threading.Event().wait(0.01)


def _covered(calls, name_part):
    """The byte ranges asked out of files whose name holds ``name_part``, merged."""
    spans = sorted((o, o + n) for f, o, n in calls if name_part in os.path.basename(f))
    merged = []
    for lo, hi in spans:
        if merged and lo <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    return [tuple(m) for m in merged]


@linux
def test_the_libc_call_is_sync_file_range_asking_a_write(tmp_path):
    # a wrong flag (or argument types) makes the kernel answer EINVAL, not 0
    call = writeback._sync_file_range()
    assert call is not None
    path = tmp_path / "f.bin"
    path.write_bytes(os.urandom(3 << 20))
    fd = os.open(path, os.O_RDONLY)
    try:
        import ctypes

        assert call(fd, ctypes.c_int64(4096), ctypes.c_int64(2 << 20),
                    writeback._SYNC_FILE_RANGE_WRITE) == 0
        assert call(fd, ctypes.c_int64(0), ctypes.c_int64(1), 1 << 7) == -1  # (no such flag)
        assert ctypes.get_errno() == 22  # EINVAL
    finally:
        os.close(fd)


@linux
def test_requests_reach_the_thread_and_their_descriptors_are_closed(tmp_path, monkeypatch):
    seen, done = [], threading.Event()

    def fake_call(fd, offset, nbytes, flags):
        seen.append((os.path.realpath(f"/proc/self/fd/{fd}"), offset.value, nbytes.value, flags))
        if len(seen) == 2:
            done.set()
        return 0

    monkeypatch.setattr(writeback, "_state", {"call": fake_call})
    path = tmp_path / "out.bin"
    path.write_bytes(b"\0" * (4 << 20))
    before = set(os.listdir("/proc/self/fd"))
    with open(path, "r+b") as fh:
        assert writeback.start(fh.fileno(), 0, 2 << 20)
        assert writeback.start(fh.fileno(), 2 << 20, 2 << 20)
        assert not writeback.start(fh.fileno(), 0, writeback.MIN_BYTES - 1)  # (too small)
    assert done.wait(10)
    _drained()
    assert writeback.pending() == 0
    assert seen == [(str(path), 0, 2 << 20, 2), (str(path), 2 << 20, 2 << 20, 2)]
    assert set(os.listdir("/proc/self/fd")) <= before  # the duplicates are closed


@linux
def test_a_slow_disk_holds_at_most_max_pending_requests(slow_disk):
    release, path = slow_disk
    before_set = set(os.listdir("/proc/self/fd"))
    before = len(before_set)
    with open(path, "rb") as fh:
        made = [writeback.start(fh.fileno(), 0, 1 << 20) for _ in range(3 * writeback.MAX_PENDING)]
        held = len(os.listdir("/proc/self/fd")) - before - 1  # (less fh's own)
    # one request may be taken by the thread already: the rest wait, MAX_PENDING at most
    assert sum(made) <= writeback.MAX_PENDING + 1
    assert not made[-1]  # dropped, not waited for
    assert held <= writeback.MAX_PENDING + 1
    release.set()
    _drained()
    assert writeback.pending() == 0
    # (as sets: another test's object collected meanwhile may close a descriptor of its own)
    assert set(os.listdir("/proc/self/fd")) <= before_set


def test_no_request_where_the_system_has_no_call(monkeypatch, tmp_path):
    monkeypatch.setattr(writeback, "_state", {"call": None})
    with open(tmp_path / "f", "wb") as fh:
        assert not writeback.start(fh.fileno(), 0, 8 << 20)
    assert writeback.pending() == 0


def _warp(run, src, out, *extra):
    """The ball warped to float32 (samples of 4 bytes: an offset or a size counted in
    samples, not bytes, leaves a gap)."""
    res = run("warp", src, "--spec", SPECS / "warp-ball.yaml", "-o", out, "--values",
              "intensity", "--dtype", "float32", *extra)
    assert res.code == 0, res.stderr
    assert writeback._replacing == set()  # (each temporary forgotten with its rename)


def test_a_warp_replacing_its_output_asks_out_all_its_samples(run, data_dir, tmp_path,
                                                               monkeypatch, asked):
    from volwarp_cli import execute

    monkeypatch.setattr(execute, "STREAMED_FROM", 0)  # (written as computed: this is small)
    src = data_dir / "ball_30_uint8.nrrd"
    out = tmp_path / "o.nrrd"
    _warp(run, src, out)
    assert asked == []  # a new file: its rename waits for nothing
    first = out.read_bytes()
    _warp(run, src, out)
    assert out.read_bytes() == first
    header = first.index(b"\n\n") + 2
    assert _covered(asked, ".o.nrrd.") == [(header, len(first))]


@pytest.mark.parametrize("block", ["8,64,64", "1,16,64"])
def test_blocks_replacing_an_output_ask_their_spans_out(run, data_dir, tmp_path, asked, block):
    """Blocks of whole planes, and single planes' row bands (from y > 0), ask each its span."""
    src = data_dir / "ball_30_uint8.nrrd"
    out, blocks = tmp_path / "o.nrrd", tmp_path / "b.nrrd"
    for path in (out, blocks):
        path.write_bytes(b"an earlier result")
    _warp(run, src, out)
    asked.clear()
    _warp(run, src, blocks, "--chunked", "--block", block)
    data = blocks.read_bytes()
    assert data == out.read_bytes()
    spans = sorted((o, n) for f, o, n in asked if ".b.nrrd." in os.path.basename(f))
    assert all(a + n == b for (a, n), (b, _) in zip(spans, spans[1:], strict=False))  # (no overlap, no gap)
    assert _covered(asked, ".b.nrrd.") == [(data.index(b"\n\n") + 2, len(data))]


@pytest.mark.parametrize("block", ["8,8,8", "4,16,64"])
def test_blocks_whose_rows_lie_apart_are_not_asked_out(run, data_dir, tmp_path, asked, block):
    """A block of several planes' partial rows is no span of the file: not asked for.

    (A block one plane thick, the grid's last, is one: its rows are contiguous.) So
    every span asked lies in one plane, or is whole planes.
    """
    from volwarp_cli.io import read_volume

    out = tmp_path / "c.nrrd"
    out.write_bytes(b"an earlier result")
    _warp(run, data_dir / "ball_30_uint8.nrrd", out, "--chunked", "--block", block)
    data = out.read_bytes()
    header = data.index(b"\n\n") + 2
    nz, ny, nx = read_volume(out).data.shape
    plane = ny * nx * 4
    assert nz % int(block.split(",")[0])  # (a last block of fewer planes: some asked, below)
    for _, offset, nbytes in asked:
        first, last = (offset - header) // plane, (offset + nbytes - 1 - header) // plane
        assert first == last or ((offset - header) % plane == 0 and nbytes % plane == 0)
    if block == "4,16,64":
        assert asked  # (the last block's single plane)


def test_a_whole_write_replacing_a_file_asks_it_out_span_by_span(tmp_path, monkeypatch, asked):
    from volwarp_cli.io import read_volume, write_volume
    from volwarp_cli.volume import Volume

    monkeypatch.setattr(writeback, "SPAN", 1 << 16)
    vol = Volume(np.arange(40 * 40 * 40, dtype=np.float32).reshape(40, 40, 40))
    out = tmp_path / "v.nrrd"
    write_volume(vol, out)
    assert asked == []
    write_volume(vol, out)
    data = out.read_bytes()
    header = data.index(b"\n\n") + 2
    assert _covered(asked, ".v.nrrd.") == [(header, len(data))]
    assert {n for _, _, n in asked} <= {1 << 16, (len(data) - header) % (1 << 16)}
    np.testing.assert_array_equal(read_volume(out).data, vol.data)


def test_scratch_files_are_never_asked_out(run, data_dir, tmp_path, asked):
    # the distance's passes by blocks write a scratch file; an OME-Zarr by blocks
    # stages its samples in one: both are removed, never renamed over anything
    from volwarp_cli.io import write_volume

    store = tmp_path / "w.ome.zarr"
    for _ in range(2):  # (the second replaces the first)
        _warp(run, data_dir / "ball_30_uint8.nrrd", store, "--chunked", "--block", "8,64,64")
    assert asked == []
    from volwarp_cli.volume import Volume

    z, y, x = np.mgrid[:40, :40, :40]
    ball = Volume((((z - 20) ** 2 + (y - 19) ** 2 + (x - 21) ** 2) < 120).astype(np.uint8))
    src = tmp_path / "ball.nrrd"
    write_volume(ball, src)
    dist, store = tmp_path / "d.nrrd", tmp_path / "d.ome.zarr"
    for argv in (["distance", src, "--iso", "0.5", "-o", dist, "--chunked", "--block", "8,40,40"],
                 ["distance", src, "--iso", "0.5", "-o", store, "--chunked", "--block", "8,40,40"]):
        assert run(*argv).code == 0
        assert run(*argv).code == 0  # (the second replaces the first)
    names = {os.path.basename(f) for f, _, _ in asked}
    assert names and all(n.startswith(".d.nrrd.") for n in names), names


@linux
def test_a_file_array_asks_its_planes_whole_pages_out(tmp_path, monkeypatch):
    """The real path: FileArray's write -> start -> the thread, the span's whole pages only."""
    from volwarp_cli.io.filearray import FileArray

    seen, done = [], threading.Event()

    def fake_call(fd, offset, nbytes, flags):
        seen.append((offset.value, nbytes.value))
        done.set()
        return 0

    monkeypatch.setattr(writeback, "_state", {"call": fake_call})
    path = tmp_path / "f.raw"
    header = 1000  # (not a page: the span's first and last pages are partly others')
    path.write_bytes(b"\0" * (header + 8 * 128 * 128 * 4))
    data = np.arange(8 * 128 * 128, dtype=np.float32).reshape(8, 128, 128)
    fa = FileArray(path, "<f4", header, (8, 128, 128), writable=True, write_back=True)
    fa[2:6, :, :] = data[2:6]
    fa.close()
    assert done.wait(10)
    page = writeback._PAGE
    lo, hi = header + 2 * 128 * 128 * 4, header + 6 * 128 * 128 * 4
    first, end = -(-lo // page) * page, hi // page * page
    assert seen == [(first, end - first)]
    np.testing.assert_array_equal(np.fromfile(path, "<f4", offset=header).reshape(8, 128, 128)
                                  [2:6], data[2:6])


def test_no_thread_to_be_had_drops_the_request_and_the_write_goes_on(tmp_path, monkeypatch):
    """A limit on tasks: the thread cannot start; the write succeeds, nothing is held."""
    from volwarp_cli.io.filearray import FileArray

    def refuse(self):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(writeback, "_state", {"call": lambda *a: 0})
    monkeypatch.setattr(threading.Thread, "start", refuse)
    path = tmp_path / "f.raw"
    path.write_bytes(b"\0" * (4 * 256 * 256 * 4))
    # (as sets: another test's object collected meanwhile may close a descriptor of its own)
    before = set(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else set()
    fa = FileArray(path, "<f4", 0, (4, 256, 256), writable=True, write_back=True)
    fa[:, :, :] = np.ones((4, 256, 256), np.float32)
    fa[0:2, :, :] = np.zeros((2, 256, 256), np.float32)  # (a second request: dropped too)
    fa.close()
    assert writeback._state["call"] is None and writeback.pending() == 0
    if before:
        assert set(os.listdir("/proc/self/fd")) <= before  # (nothing left open)
    assert np.fromfile(path, "<f4").sum() == 2 * 256 * 256


@linux
def test_a_forked_child_closes_the_requests_it_inherits(slow_disk):
    """The child has no thread: the duplicated descriptors queued at the fork are closed."""
    release, path = slow_disk
    with open(path, "rb") as fh:
        for _ in range(5):
            writeback.start(fh.fileno(), 0, 1 << 20)
    assert writeback.pending() >= 4
    pid = os.fork()
    if pid == 0:  # the child: count the descriptors still open on the file
        held = sum(os.path.realpath(f"/proc/self/fd/{n}") == str(path)
                   for n in os.listdir("/proc/self/fd"))
        os._exit(0 if held == 0 and writeback.pending() == 0 else 1)
    _, status = os.waitpid(pid, 0)
    release.set()
    assert os.waitstatus_to_exitcode(status) == 0


@linux
def test_a_stop_landing_on_a_request_leaks_no_descriptor(tmp_path):
    """A stop (SIGTERM) arriving just after the descriptor is duplicated: the request is
    queued whole and the stop raised after it, so the thread closes the duplicate (raised
    between the two, the duplicate was nobody's and stayed open). Its own process: the
    stops' handlers are installed, as in a command."""
    import subprocess
    import textwrap

    script = textwrap.dedent("""
        import os, signal, sys, time
        from volwarp_cli import signals
        from volwarp_cli.io import writeback

        signals.install()
        real_dup, made = os.dup, []

        def dup_then_stop(fd):
            made.append(real_dup(fd))
            os.kill(os.getpid(), signal.SIGTERM)  # (the stop lands here)
            return made[-1]

        fh = open(sys.argv[1], "wb")
        fh.write(bytes(1 << 20))
        fh.flush()
        os.dup = dup_then_stop
        try:
            writeback.start(fh.fileno(), 0, 1 << 20)
            print("not stopped")
        except signals.Interrupted:
            os.dup = real_dup
            for _ in range(500):
                if writeback.pending() == 0:
                    break
                time.sleep(0.01)
            try:
                os.fstat(made[0])
                print("leaked")
            except OSError:
                print("closed")
    """)
    r = subprocess.run([sys.executable, "-c", script, str(tmp_path / "out.raw")],
                       capture_output=True, text=True, timeout=60)
    assert r.stdout.split() == ["closed"], (r.stdout, r.stderr)
