"""Deflate streams (io/deflate.py): ISA-L's and zlib's fallback both make standard streams.

And both read back in bounded pieces, members, padding and empty members as gzip allows.
"""

from __future__ import annotations

import gzip
import io
import tracemalloc
import zlib

import numpy as np
import pytest

from volwarp_cli.errors import FormatError
from volwarp_cli.io import deflate
from volwarp_cli.io.common import read_gzip_exact
from volwarp_cli.io.nifti import _gunzip_range, gunzip_range_into

PAYLOAD = (np.random.default_rng(2).random(200_000) * 300).astype(np.int16).tobytes()


@pytest.fixture(params=["isal", "zlib"])
def impl(request, monkeypatch):
    if request.param == "zlib":  # as on a platform without python-isal
        monkeypatch.setattr(deflate, "_igzip", None)
        monkeypatch.setattr(deflate, "_zlib_impl", zlib)
        monkeypatch.setattr(deflate, "ERRORS", (zlib.error,))
    return request.param


def test_streams_are_standard_and_deterministic(impl):
    gz = deflate.gzip_bytes(PAYLOAD, level=1)
    assert gzip.decompress(gz) == PAYLOAD  # the standard library reads it
    assert gz[4:8] == b"\0\0\0\0"  # mtime 0
    assert deflate.gzip_bytes(PAYLOAD, level=1) == gz
    z = deflate.zlib_bytes(PAYLOAD, 1)
    assert zlib.decompress(z) == PAYLOAD
    dec = deflate.decompressobj()
    assert dec.decompress(gz) == PAYLOAD and dec.eof
    with pytest.raises(deflate.ERRORS):
        deflate.decompressobj().decompress(b"\x1f\x8b\x08\x00garbage" + gz[12:])

# -- inflating by bounded pieces -------------------------------------------------------
# A stream of zeros inflates about 1029:1: a 64 KB piece handed to the inflater without
# an output limit came back as 64 MB at once (a mostly-empty mask read with 178-297 MiB
# above its own size). The inflater returns at most INFLATE_OUTPUT a call, so the memory
# above the samples stays a few MB, and an over-long stream is refused early.
ZEROS = 64 << 20


@pytest.fixture(scope="module")
def zeros_gz():
    return gzip.compress(bytes(ZEROS), compresslevel=6, mtime=0)


def _peak_above(fn, base: int) -> int:
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        result = fn()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    del result
    return peak - base


def test_zeros_inflate_in_bounded_pieces(impl, zeros_gz, tmp_path):
    assert len(zeros_gz) < deflate.INFLATE_INPUT  # (one input piece holds the whole stream)
    above = _peak_above(lambda: read_gzip_exact(io.BytesIO(zeros_gz), ZEROS, "z"), ZEROS)
    assert above < 8 << 20  # (unbounded: 64 MB)
    (tmp_path / "z.gz").write_bytes(zeros_gz)
    above = _peak_above(lambda: _gunzip_range(tmp_path / "z.gz", 0, ZEROS, ZEROS, "z", "s"),
                        ZEROS)
    assert above < 8 << 20  # (unbounded: 64 MB)


def test_an_over_long_stream_is_refused_early(impl, zeros_gz):
    def read():
        with pytest.raises(FormatError, match="holds more than 1048576 bytes"):
            read_gzip_exact(io.BytesIO(zeros_gz), 1 << 20, "z")

    assert _peak_above(read, 1 << 20) < 8 << 20


def test_members_padding_and_an_empty_last_member(impl):
    data = np.arange(300_000, dtype=np.int32).tobytes()
    a, b = data[:500_000], data[500_000:]
    bgzip_eof = gzip.compress(b"", mtime=0)  # (an empty member ends bgzip's files)
    for stream in (gzip.compress(a) + gzip.compress(b) + bgzip_eof,
                   gzip.compress(a) + bytes(300) + gzip.compress(b) + bytes(70_000),
                   gzip.compress(data) + bgzip_eof + bytes(5)):
        assert bytes(read_gzip_exact(io.BytesIO(stream), len(data), "m")) == data


def test_garbage_after_the_stream_is_corrupt_data(impl):
    data = bytes(range(256)) * 100
    with pytest.raises(FormatError, match="corrupt compressed data"):
        read_gzip_exact(io.BytesIO(gzip.compress(data) + b"garbage!"), len(data), "g")


# -- placing inflated pieces beside the inflation ----------------------------------------
# A large range's pieces are placed on a thread of their own (deflate.sink_beside), in
# batches; the tests make the batches small so that a small stream takes that path.

def _sink_threads() -> list:
    import threading

    return [t for t in threading.enumerate() if t.name == "volwarp-inflate-sink"]


@pytest.fixture
def small_batches(monkeypatch):
    monkeypatch.setattr(deflate, "BESIDE_BATCH", 4096)


def _recorder():
    import threading

    got = []

    def sink(at, piece):
        got.append((at, bytes(piece), threading.get_ident()))

    return got, sink


def test_a_sink_beside_gets_every_piece_in_order_on_its_own_thread(small_batches):
    import threading

    from volwarp_cli.parallel import use_threads

    pieces = [PAYLOAD[i:i + 1000] for i in range(0, 60_000, 1000)]
    got, sink = _recorder()
    with use_threads(2), deflate.sink_beside(sink, 60_000) as place:
        at = 0
        for p in pieces:
            place(at, memoryview(p))
            at += len(p)
    assert [g[0] for g in got] == list(range(0, 60_000, 1000))
    assert b"".join(g[1] for g in got) == PAYLOAD[:60_000]
    assert {g[2] for g in got} != {threading.get_ident()}
    assert not _sink_threads()
    # one thread, or a range under four batches: the sink itself, here
    for threads, total in ((1, 60_000), (2, 4 * 4096 - 1)):
        got, sink = _recorder()
        with use_threads(threads), deflate.sink_beside(sink, total) as place:
            assert place is sink
            place(0, memoryview(PAYLOAD[:10]))
        assert got[0][2] == threading.get_ident()


def test_a_gzip_range_read_beside_is_the_same_bytes(small_batches, tmp_path):
    from volwarp_cli.parallel import use_threads

    path = tmp_path / "a.gz"
    path.write_bytes(gzip.compress(PAYLOAD, mtime=0))
    reads = {}
    for threads in (1, 2):
        with use_threads(threads):
            got, sink = _recorder()
            gunzip_range_into(path, 1000, 300_000, 400_000, "a", "samples", sink, beside=True)
            reads[threads] = got
    assert b"".join(g[1] for g in reads[1]) == PAYLOAD[1000:301_000]
    assert [g[:2] for g in reads[1]] == [g[:2] for g in reads[2]]
    assert len({g[2] for g in reads[1]}) == 1 and {g[2] for g in reads[1]} != {
        g[2] for g in reads[2]}  # (one thread: here; two: placed beside)


def test_the_sinks_error_is_raised_in_the_caller(small_batches):
    from volwarp_cli.parallel import use_threads

    calls = []

    def sink(at, piece):
        calls.append(at)
        if len(calls) == 3:
            raise OSError(28, "No space left on device")

    with pytest.raises(OSError, match="No space"), use_threads(2):
        with deflate.sink_beside(sink, 1 << 20) as place:
            for at in range(0, 1 << 20, 1000):
                place(at, memoryview(PAYLOAD[:1000]))
    assert len(calls) == 3  # (nothing placed after the error)
    assert not _sink_threads()


def test_a_corrupt_stream_stops_the_sink_and_is_the_error(small_batches, tmp_path):
    from volwarp_cli.parallel import use_threads

    gz = bytearray(gzip.compress(PAYLOAD, mtime=0))
    gz[len(gz) // 2:len(gz) // 2 + 64] = bytes(64)
    path = tmp_path / "bad.gz"
    path.write_bytes(bytes(gz))
    got, sink = _recorder()
    with pytest.raises(FormatError, match="corrupt|truncated"), use_threads(2):
        gunzip_range_into(path, 0, len(PAYLOAD), len(PAYLOAD), "bad.gz", "samples", sink,
                          beside=True)
    assert not _sink_threads()


def test_the_callers_error_stops_the_placing(small_batches):
    import threading

    from volwarp_cli.parallel import use_threads

    release = threading.Event()
    placed = []

    def sink(at, piece):
        release.wait(10)  # (the first batch waits until the caller has failed)
        placed.append(at)

    piece = memoryview(PAYLOAD[:4096])  # a batch a piece
    threading.Timer(0.3, release.set).start()
    with pytest.raises(KeyboardInterrupt), use_threads(2):
        with deflate.sink_beside(sink, 1 << 20) as place:
            for k in range(3):  # one placing, two waiting: the queue is full
                place(k * 4096, piece)
            raise KeyboardInterrupt  # (a stop, say)
    assert placed == [0]  # the waiting batches were dropped, not placed
    assert not _sink_threads()


@pytest.mark.parametrize("size", [deflate.BLOCKS_FROM - 1, deflate.BLOCKS_FROM + 12_345])
def test_gzip_bytes_are_the_same_whatever_the_thread_count(size):
    """Data from BLOCKS_FROM on deflates by blocks on several threads: the same bytes on one
    thread as on four, a standard stream, mtime 0; parts deflate as their concatenation."""
    from volwarp_cli.parallel import use_threads

    rng = np.random.default_rng(5)
    data = np.repeat(rng.integers(0, 40, size // 8 + 1, dtype=np.uint8), 8)[:size].tobytes()
    outs = set()
    for threads in (1, 2, 4):
        with use_threads(threads):
            outs.add(deflate.gzip_bytes(data, level=1))
            outs.add(deflate.gzip_bytes(data[:1000], memoryview(data)[1000:], level=1))
    assert len(outs) == 1
    gz = outs.pop()
    assert gzip.decompress(gz) == data and gz[4:8] == b"\0\0\0\0"
    one = zlib.decompressobj(31)  # (one member, nothing after it: zlib's own reader)
    assert one.decompress(gz) == data and one.eof and one.unused_data == b""
