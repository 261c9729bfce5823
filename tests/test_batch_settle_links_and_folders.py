"""Review of the batch's settle time and the nested-output checks (review44a)."""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
sitk = pytest.importorskip("SimpleITK")

from test_io_dicom import write_series  # noqa: E402

from volwarp_cli.batch import plan  # noqa: E402

HOUR = 3600.0
STACK = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6) * 3 - 40


@pytest.fixture
def clock(monkeypatch):
    """The batch's clock an hour ahead: every file the test wrote is an hour old."""
    monkeypatch.setattr(plan, "_now", lambda: time.time() + HOUR)
    return lambda: time.time() + HOUR


def _summary(stderr: str) -> str:
    line = [line for line in stderr.splitlines() if line.startswith("volwarp batch:")][-1]
    return re.sub(r" \(\d+ with warnings\)", "", line)


def _manifest(root: Path, scans: str) -> Path:
    m = root / "m.yaml"
    m.write_text(f"version: 1\ninputs: {{list: [{scans}]}}\noutput_dir: out\nsteps:\n"
                 "  - {name: conv, run: convert, output: \"{stem}.nrrd\"}\n")
    return m


def test_a_series_of_links_being_made_is_still_arriving(tmp_path, run, clock):
    """A series folder of links to slices stored an hour ago, two of its four links made
    just now (the rest to come): the links' own times say the folder is arriving; the
    targets' old times read it short (2 of 4 slices, "ok", exit 0)."""
    paths = write_series(tmp_path / "store", STACK)
    series = tmp_path / "scans" / "b"
    series.mkdir(parents=True)
    for p in paths[:2]:
        link = series / p.name
        link.symlink_to(p)
        os.utime(link, (clock(), clock()), follow_symlinks=False)  # made just now
    res = run("batch", _manifest(tmp_path, "scans/b"), "--progress", "lines")
    assert res.code == 0, res.stderr
    assert "still arriving scans/b (newest file 0 s old, settle 60 s)" in res.stderr, res.stderr
    assert _summary(res.stderr).endswith("0 ok, 0 skipped, 0 failed, 1 still arriving")
    assert not (tmp_path / "out" / "scans" / "b.nrrd").exists()


@pytest.mark.parametrize("how", ["a slice folder moved in", "an empty folder"])
def test_a_folder_changed_just_now_is_still_arriving(tmp_path, run, clock, how):
    """The folder's own times count: a folder of slices ``mv``-ed into the series keeps its
    slices' old times (a rename changes the folder's, not its files'), and on exFAT or sshfs
    (no ctime: ``rsync -a`` dates each slice back) only the folder's mtime says a slice came;
    a series folder just made has no slice yet. Read at once: 2 of 4 slices, "ok", exit 0
    (and the empty folder a failure, exit 1)."""
    series = tmp_path / "scans" / "b"
    series.mkdir(parents=True)
    if how != "an empty folder":
        paths = write_series(tmp_path / "staging", STACK)
        (series / "part1").mkdir()
        for p in paths[:2]:
            p.rename(series / "part1" / p.name)
    os.utime(series, (clock(), clock()))  # (its entries changed just now)
    res = run("batch", _manifest(tmp_path, "scans/b"), "--progress", "lines")
    assert res.code == 0, res.stderr
    assert "still arriving scans/b (newest file 0 s old, settle 60 s)" in res.stderr, res.stderr
    assert not (tmp_path / "out" / "scans" / "b.nrrd").exists()


def test_a_scan_that_is_a_link_made_just_now_is_read(tmp_path, run, clock):
    """A script linking each series into ``scans/`` before the batch runs: the link's own
    time is no slice arriving (the scan would be held back at every run)."""
    write_series(tmp_path / "pacs" / "b", STACK)
    (tmp_path / "scans").mkdir()
    link = tmp_path / "scans" / "b"
    link.symlink_to(tmp_path / "pacs" / "b")
    os.utime(link, (clock(), clock()), follow_symlinks=False)  # made just now
    res = run("batch", _manifest(tmp_path, "scans/b"), "--progress", "lines")
    assert res.code == 0, res.stderr
    assert _summary(res.stderr) == "volwarp batch: 1 scan, 1 ok, 0 skipped, 0 failed"
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(tmp_path / "pacs" / "b")))
    from volwarp_cli.io import read_volume

    np.testing.assert_array_equal(read_volume(tmp_path / "out" / "scans" / "b.nrrd").data,
                                  sitk.GetArrayFromImage(reader.Execute()))
