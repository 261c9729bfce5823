"""Shared test fixtures: running the CLI in-process and small volumes."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

DATA = Path(__file__).parent / "data"


class Result:
    def __init__(self, code: int, stdout: str, stderr: str):
        self.code = code
        self.stdout = stdout
        self.stderr = stderr

    def __repr__(self):
        return f"Result(code={self.code}, stderr={self.stderr!r})"


@pytest.fixture
def run():
    """``run("info", path, "--json")`` -> Result(code, stdout, stderr), in process."""
    from volwarp_cli.cli.main import cli

    def _run(*args) -> Result:
        runner = CliRunner()
        res = runner.invoke(cli, [str(a) for a in args], catch_exceptions=False)
        return Result(res.exit_code, res.stdout, res.stderr)

    return _run


@pytest.fixture(autouse=True)
def _series_written_just_now(monkeypatch):
    """No warning that a DICOM folder's newest file is seconds old (a copy under way?).

    Every test reads the series it wrote a moment before, and many check that
    a command says one line; the warning is tested in ``test_batch_settle.py``.
    """
    try:
        from volwarp_cli.io.dicom import _scan
    except ImportError:  # (without pydicom: no DICOM folder is read)
        return
    monkeypatch.setattr(_scan, "YOUNG_SECONDS", 0.0)


@pytest.fixture(params=["subtract", "rebuild"])
def local_updates(request):
    """How scenes update locally (pass it as ``Scene(..., update=local_updates)``): each of
    the two local updates, even where another way would be cheaper (all give the same
    sums), so that tests exercise them on small lattices."""
    return request.param


@pytest.fixture
def small_splits(monkeypatch):
    """The warp's thread splits taken on test sizes (production keeps small blocks whole)."""
    from volwarp_cli import parallel
    from volwarp_cli.bspline import work

    monkeypatch.setattr(parallel, "SPLIT_MIN_WORK", 1)
    monkeypatch.setattr(work, "PARALLEL_MIN_VOXELS", 1)
    monkeypatch.setattr(work, "SPLIT_MAX_SHARE", 1.01)


@pytest.fixture
def data_dir() -> Path:
    return DATA


def ball(n: int = 30, radius: float | None = None, dtype=np.uint8) -> np.ndarray:
    """A binary ball in an n^3 array (the value 1 inside, [z, y, x])."""
    radius = radius if radius is not None else n / 3
    c = (n - 1) / 2
    z, y, x = np.mgrid[:n, :n, :n]
    return (((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2) <= radius ** 2).astype(dtype)


def open_files(under: Path) -> list[str]:
    """The files under ``under`` this process holds open (its descriptors in /proc/self/fd).

    For tests that a reader closes what it opened, on its error paths too: a
    batch of thousands of scans would otherwise run out of descriptors.
    """
    root = os.path.realpath(under) + os.sep
    held = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:  # (the listing's own descriptor, closed meanwhile)
            continue
        if target.startswith(root):
            held.append(target)
    return sorted(held)
