"""A command's outputs are one set: renamed into place together, or not at all.

volwarp_cli.io.atomic.outputs_together holds every atomic write's rename
until its block ends; every command but batch runs in one (cli/main.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import write_volume
from volwarp_cli.io.atomic import atomic_output, outputs_together, scratch_folder
from volwarp_cli.volume import Volume


def _names(folder):
    return sorted(p.name for p in folder.iterdir())


def test_renames_wait_for_the_end_then_all_happen(tmp_path):
    a, b = tmp_path / "a.nrrd", tmp_path / "b.txt"
    with outputs_together():
        write_volume(Volume(np.zeros((2, 3, 4), np.uint8)), a)
        with atomic_output(b) as tmp:
            tmp.write_text("new")
        assert not a.exists() and not b.exists()  # held: only temporaries so far
        assert len(_names(tmp_path)) == 2
    assert _names(tmp_path) == ["a.nrrd", "b.txt"] and b.read_text() == "new"


def test_an_error_leaves_every_existing_output_as_it_was(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old a")
    with pytest.raises(RuntimeError, match="half-way"), outputs_together():
        with atomic_output(a) as tmp:
            tmp.write_text("new a")
        with atomic_output(b) as tmp:
            tmp.write_text("new b")
        raise RuntimeError("half-way")
    assert _names(tmp_path) == ["a.txt"] and a.read_text() == "old a"


def test_nested_blocks_commit_once_at_the_outermost(tmp_path):
    a = tmp_path / "a.txt"
    with outputs_together():
        with outputs_together():
            with atomic_output(a) as tmp:
                tmp.write_text("x")
        assert not a.exists()
    assert a.read_text() == "x"


def test_a_scratch_folder_s_files_are_there_at_once(tmp_path):
    """The work reads its scratch back: those files are not the command's outputs."""
    with outputs_together(), scratch_folder(tmp_path / "out.nrrd") as scratch:
        with atomic_output(scratch / "field.raw") as tmp:
            tmp.write_bytes(b"123")
        assert (scratch / "field.raw").read_bytes() == b"123"


def test_outside_a_block_each_output_is_renamed_at_once(tmp_path):
    a = tmp_path / "a.txt"
    with atomic_output(a) as tmp:
        tmp.write_text("x")
    assert a.read_text() == "x"


def test_a_failing_warp_with_an_export_keeps_both_old_files(run, data_dir, tmp_path,
                                                           monkeypatch):
    """The warped volume was complete, but its export failed: neither is replaced."""
    from volwarp_cli.warp import export_outputs

    out, field = tmp_path / "o.nrrd", tmp_path / "d.nrrd"
    out.write_bytes(b"an earlier result")
    field.write_bytes(b"an earlier field")
    args = [data_dir / "ball_30_uint8.nrrd", "--spec",
            Path(__file__).parents[1] / "specs" / "warp-ball.yaml", "-o", out, "--displacement-to", field]
    calls = []

    def failing(*a, **k):
        calls.append(1)
        raise OSError("disk on fire")

    monkeypatch.setattr(export_outputs, "write_exports", failing)
    res = run("warp", *args)
    assert calls and res.code == 1 and "disk on fire" in res.stderr
    assert out.read_bytes() == b"an earlier result"
    assert field.read_bytes() == b"an earlier field"
    assert _names(tmp_path) == ["d.nrrd", "o.nrrd"]


def test_a_rename_failing_at_the_end_leaves_no_temporary(tmp_path, monkeypatch):
    """No temporary is left, and the one renamed before it, a new file, is removed again
    (all new or all old: :mod:`tests.test_commit_rollback`); the error names the output."""
    import os

    from volwarp_cli.errors import VolwarpError

    real = os.replace
    calls = []

    def replace(src, dst):
        calls.append(dst)
        if len(calls) == 2:
            raise OSError(28, "No space left on device", str(src))
        return real(src, dst)

    said = (r"b\.txt: cannot put the new output in place \(No space left on device\); "
            "the other outputs are left as they were")
    with pytest.raises(VolwarpError, match=said), outputs_together():
        for name in ("a.txt", "b.txt", "c.txt"):
            with atomic_output(tmp_path / name) as tmp:
                tmp.write_text(name)
        monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "replace", real)
    assert _names(tmp_path) == []
