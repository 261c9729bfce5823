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
from volwarp_cli.io.nifti import _gunzip_range

PAYLOAD = (np.random.default_rng(2).random(200_000) * 300).astype(np.int16).tobytes()


@pytest.fixture(params=["isal", "zlib"])
def impl(request, monkeypatch):
    if request.param == "zlib":  # as on a platform without python-isal
        monkeypatch.setattr(deflate, "_igzip", None)
        monkeypatch.setattr(deflate, "_zlib_impl", zlib)
        monkeypatch.setattr(deflate, "ERRORS", (zlib.error,))
    return request.param


def test_streams_are_standard_and_deterministic(impl):
    gz = deflate.gzip_bytes(PAYLOAD, 1)
    assert gzip.decompress(gz) == PAYLOAD  # the standard library reads it
    assert gz[4:8] == b"\0\0\0\0"  # mtime 0
    assert deflate.gzip_bytes(PAYLOAD, 1) == gz
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
