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
