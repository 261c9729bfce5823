"""A TIFF stack rewritten while a command reads it by box: refused, never a mix.

A stack read lazily goes through tifffile's zarr view, which decodes its
pages from the open file as the work asks for them: the file rewritten in
place meanwhile (a program saving over it) gave the later boxes the new
pages, a volume mixing two stacks written with exit 0. The file is now
watched as mapped inputs are (:func:`volwarp_cli.io.mapped.watch`): the
output is not renamed into place.
"""

from __future__ import annotations

import shutil

import numpy as np
import tifffile
from changed_input import change_after_first_read, distance_by_blocks_refused

from volwarp_cli.io import lazy

SHAPE = (24, 12, 10)


def _stack(path, seed: int) -> None:
    data = np.random.default_rng(seed).integers(0, 3000, size=SHAPE).astype(np.uint16)
    # (pages tifffile's zarr view decodes, not a mapped layout; its voxel size given, so
    # that the error is the only line)
    tifffile.imwrite(path, data, metadata={"spacing": [1.0, 1.0, 1.0]})


def test_a_stack_rewritten_while_read_by_blocks_writes_nothing(run, tmp_path, monkeypatch):
    """Before: exit 0 and a field of the first stack's first slabs and the second's others."""
    src, other = tmp_path / "s.tif", tmp_path / "other.tif"
    _stack(src, 0)
    _stack(other, 1)
    out = tmp_path / "d.nrrd"
    out.write_bytes(b"old output")
    # (copied in place: the view's open file sees the new pages)
    reads = change_after_first_read(monkeypatch, lazy._ZarrView,
                                    lambda: shutil.copyfile(other, src))
    distance_by_blocks_refused(run, src, out, tmp_path, reads,
                               "s.tif: the file changed while it was being read",
                               ["d.nrrd", "other.tif", "s.tif"])


def test_a_stack_left_alone_is_read_by_blocks_as_in_memory(run, tmp_path):
    """The watch refuses nothing that did not change: by blocks equals in memory."""
    src = tmp_path / "s.tif"
    _stack(src, 0)
    args = ("distance", src, "--iso", "1500", "--values", "intensity", "--surface", "voxel")
    assert run(*args, "-o", tmp_path / "a.nrrd").code == 0
    r = run(*args, "-o", tmp_path / "b.nrrd", "--chunked", "--block", "8",
            "--scheduler", "synchronous")
    assert r.code == 0, r
    assert (tmp_path / "a.nrrd").read_bytes() == (tmp_path / "b.nrrd").read_bytes()
