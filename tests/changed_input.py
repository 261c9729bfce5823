"""A command by blocks over an input another program changes after its first read.

Shared by the tests of inputs watched while they are read (DICOM series, TIFF stacks).
"""

from __future__ import annotations


def change_after_first_read(monkeypatch, cls, change) -> list:
    """``change()`` run once the first read through ``cls.__getitem__`` is done; the reads."""
    real = cls.__getitem__
    reads: list = []

    def read(self, key):
        reads.append(key)
        got = real(self, key)
        if len(reads) == 1:
            change()
        return got

    monkeypatch.setattr(cls, "__getitem__", read)
    return reads


def distance_by_blocks_refused(run, src, out, folder, reads: list, message: str,
                               listing: list[str]) -> None:
    """``distance`` of ``src`` by blocks into ``out`` (holding "old output"): refused.

    ``reads``: the reads the changing hook counted (more than one: read by
    blocks); exit 1 with one line holding ``message``; the old output kept, and
    ``folder`` holding ``listing`` only (no temporary left).
    """
    r = run("distance", src, "--iso", "1500", "--values", "intensity", "--surface", "voxel",
            "-o", out, "--chunked", "--block", "8", "--scheduler", "synchronous")
    assert len(reads) > 1, "the input was not read by blocks"
    assert r.code == 1, r
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], r.stderr
    assert out.read_bytes() == b"old output"
    assert sorted(p.name for p in folder.iterdir()) == listing
