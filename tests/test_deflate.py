"""Deflate streams (io/deflate.py): ISA-L's and zlib's fallback both make standard streams."""

from __future__ import annotations

import gzip
import zlib

import numpy as np
import pytest

from volwarp_cli.io import deflate

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
