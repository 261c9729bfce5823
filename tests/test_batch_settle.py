"""A DICOM series still arriving is not read as a whole series, silently.

A PACS (or rsync, or a scanner's export) stores a series slice by slice, and
no tag says how many slices a classic series has: a cron job's ``volwarp
batch`` that ran while the last slices were not there wrote a volume short
of them, reported "ok", exit 0. A folder scan whose newest file is younger
than the settle time (``inputs.settle``, ``--settle``; 60 s) is now left to
the next run and said; a single command warns.

A file's arrival is its ctime too (``rsync -a`` copies old mtimes), which no
test can set back: the batch's clock (:func:`volwarp_cli.batch.plan._now`)
is moved an hour ahead instead, so that every file the test wrote is an hour
old and a file given the moved clock's time (``os.utime``) was stored just now.
"""

from __future__ import annotations

import json
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
from volwarp_cli.io import read_volume, write_volume  # noqa: E402
from volwarp_cli.volume import Volume  # noqa: E402

HOUR = 3600.0
STACK = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6) * 3 - 40

MANIFEST = """version: 1
inputs: {list: [scans/a, scans/b]SETTLE}
output_dir: out
steps:
  - {name: conv, run: convert, output: "{stem}.nrrd"}
"""


@pytest.fixture
def clock(monkeypatch):
    """The batch's clock an hour ahead: every file the test wrote is an hour old."""
    monkeypatch.setattr(plan, "_now", lambda: time.time() + HOUR)
    return lambda: time.time() + HOUR


def _manifest(root: Path, settle: str | None = None) -> Path:
    m = root / "m.yaml"
    m.write_text(MANIFEST.replace("SETTLE", "" if settle is None else f", settle: {settle}"))
    return m


def _summary(stderr: str) -> str:
    """The summary line without its ``(N with warnings)``.

    The steps run on the real clock, where a series the test just wrote is
    0 s old: each read of one warns (tested below, and in ``test_settle_0``).
    """
    line = [line for line in stderr.splitlines() if line.startswith("volwarp batch:")][-1]
    return re.sub(r" \(\d+ with warnings\)", "", line)


def _sitk_series(folder: Path) -> np.ndarray:
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(reader.GetGDCMSeriesFileNames(str(folder)))
    return sitk.GetArrayFromImage(reader.Execute())


def test_a_series_still_arriving_is_left_to_the_next_run(tmp_path, run, clock):
    """Two of b's four slices stored, one of them just now: a ok, b still arriving (not read
    short, not recorded, exit 0); once the rest has come and settled, the next run reads b
    whole, as SimpleITK reads it."""
    write_series(tmp_path / "scans" / "a", STACK)
    paths = write_series(tmp_path / "scans" / "b", STACK)
    later = tmp_path / "later"
    later.mkdir()
    for p in paths[2:]:  # (not there yet)
        p.rename(later / p.name)
    os.utime(paths[0], (clock(), clock()))  # stored just now
    m = _manifest(tmp_path)
    res = run("batch", m, "--progress", "lines", "--report", tmp_path / "r.json",
              "--report", tmp_path / "r.html")
    assert res.code == 0, res.stderr
    assert "still arriving scans/b (newest file 0 s old, settle 60 s)" in res.stderr
    assert _summary(res.stderr) == ("volwarp batch: 2 scans, 1 ok, 0 skipped, 0 failed, "
                                    "1 still arriving")
    assert not (tmp_path / "out" / "scans" / "b.nrrd").exists()
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["exit_code"] == 0 and report["summary"]["still_arriving"] == 1
    scans = {s["scan"]: s for s in report["scans"]}
    assert scans["scans/a"]["status"] == "ok" and scans["scans/a"]["reason"] is None
    assert scans["scans/b"]["status"] == "still arriving"
    assert scans["scans/b"]["reason"] == "newest file 0 s old, settle 60 s"
    page = (tmp_path / "r.html").read_text()
    assert 'data-status="still arriving"' in page and "newest file 0 s old" in page

    for p in paths[2:]:  # the rest comes, and the folder settles
        (later / p.name).rename(p)
    for p in paths:
        os.utime(p, (clock() - HOUR, clock() - HOUR))
    res = run("batch", m, "--progress", "lines", "--report", tmp_path / "r.json")
    assert res.code == 0, res.stderr
    assert _summary(res.stderr) == "volwarp batch: 2 scans, 1 ok, 1 skipped, 0 failed"
    report = json.loads((tmp_path / "r.json").read_text())
    assert {s["scan"]: s["status"] for s in report["scans"]} == {"scans/a": "skipped",
                                                                "scans/b": "ok"}
    got = read_volume(tmp_path / "out" / "scans" / "b.nrrd").data
    np.testing.assert_array_equal(got, _sitk_series(tmp_path / "scans" / "b"))
    assert got.shape[0] == 4


def test_a_copy_with_old_dates_is_still_arriving(tmp_path, run):
    """``rsync -a`` and ``cp -p`` give the slices their source's old mtimes: the ctime says
    they came just now (the real clock here)."""
    write_series(tmp_path / "scans" / "a", STACK)
    paths = write_series(tmp_path / "scans" / "b", STACK)
    for p in paths:
        os.utime(p, (time.time() - 30 * 86400, time.time() - 30 * 86400))
    res = run("batch", _manifest(tmp_path), "--progress", "lines")
    assert res.code == 0, res.stderr
    assert _summary(res.stderr).endswith("0 ok, 0 skipped, 0 failed, 2 still arriving")


def test_a_file_dated_ahead_does_not_hold_its_series_back(tmp_path, run, clock):
    """A slice dated a day ahead of this clock (copied with its dates from a scanner whose
    clock is ahead) would keep its series "still arriving" for a day: its ctime counts."""
    write_series(tmp_path / "scans" / "a", STACK)
    paths = write_series(tmp_path / "scans" / "b", STACK)
    os.utime(paths[1], (clock() + 86400, clock() + 86400))
    res = run("batch", _manifest(tmp_path), "--progress", "lines")
    assert res.code == 0, res.stderr
    assert _summary(res.stderr) == "volwarp batch: 2 scans, 2 ok, 0 skipped, 0 failed"


@pytest.mark.parametrize("how", ["manifest", "option"])
def test_settle_0_reads_at_once(tmp_path, run, clock, how):
    write_series(tmp_path / "scans" / "a", STACK)
    paths = write_series(tmp_path / "scans" / "b", STACK)
    os.utime(paths[0], (clock(), clock()))
    m = _manifest(tmp_path, "0" if how == "manifest" else "600")
    res = run("batch", m, "--progress", "lines", *(["--settle", "0"] if how == "option" else []))
    assert res.code == 0, res.stderr
    assert _summary(res.stderr) == "volwarp batch: 2 scans, 2 ok, 0 skipped, 0 failed"
    assert "  warning: conv: the newest file of " in res.stderr  # (read at once, and said)
    np.testing.assert_array_equal(read_volume(tmp_path / "out" / "scans" / "b.nrrd").data,
                                  _sitk_series(tmp_path / "scans" / "b"))


def test_the_option_wins_over_the_manifest(tmp_path, run, clock):
    """``--settle 7200``: files an hour old are still arriving."""
    write_series(tmp_path / "scans" / "a", STACK)
    write_series(tmp_path / "scans" / "b", STACK)
    res = run("batch", _manifest(tmp_path, "0"), "--progress", "lines", "--settle", "7200")
    assert res.code == 0, res.stderr
    assert "still arriving scans/a (newest file 3600 s old, settle 7200 s)" in res.stderr


@pytest.mark.parametrize("value, why", [
    ("-1", "less than the minimum of 0"), ("soon", "is not of type 'number'"),
    ("1e9", "greater than the maximum of 86400"), ("true", "is not of type 'number'"),
    ("[60]", "is not of type 'number'")])
def test_a_bad_settle_is_a_spec_error_at_its_key(tmp_path, run, value, why):
    write_series(tmp_path / "scans" / "a", STACK)
    write_series(tmp_path / "scans" / "b", STACK)
    res = run("batch", _manifest(tmp_path, value))
    assert res.code == 2
    assert "m.yaml:2: inputs.settle: " in res.stderr and why in res.stderr, res.stderr
    assert not (tmp_path / "out").exists()


def test_a_bad_settle_option_is_a_usage_error(tmp_path, run):
    write_series(tmp_path / "scans" / "a", STACK)
    res = run("batch", _manifest(tmp_path), "--settle", "-5")
    assert res.code == 2 and "'--settle': -5.0 is not in the range 0<=x<=86400" in res.stderr


def test_an_ome_zarr_store_still_arriving_is_left_too(tmp_path, run):
    """A store copied chunk by chunk reads its missing chunks as the fill value: the same
    rule holds for every folder scan (the real clock: written just now)."""
    write_volume(Volume(np.ones((4, 5, 6), np.float32)), tmp_path / "z.ome.zarr")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {list: [z.ome.zarr]}\noutput_dir: out\nsteps:\n"
        "  - {name: conv, run: convert, output: \"{stem}.nrrd\"}\n")
    res = run("batch", tmp_path / "m.yaml", "--progress", "lines")
    assert res.code == 0, res.stderr
    assert "still arriving z.ome (newest file 0 s old, settle 60 s)" in res.stderr


def test_a_command_reading_a_young_series_warns_once(tmp_path, run, monkeypatch):
    """``convert FOLDER`` just after the slices came: one warning, and the volume written."""
    from volwarp_cli.io.dicom import _scan

    monkeypatch.setattr(_scan, "YOUNG_SECONDS", 5.0)  # (the suite's conftest turns it off)
    folder = tmp_path / "s"
    for p in write_series(folder, STACK):  # (copied with its old dates: ctime is now)
        os.utime(p, (time.time() - 86400, time.time() - 86400))
    for command in (["convert", folder, "-o", tmp_path / "o.nrrd"], ["info", folder]):
        res = run(*command)
        assert res.code == 0, res.stderr
        said = f"volwarp: warning: the newest file of {folder} is 0 s old: a series still " \
               "being copied would be read short"
        assert res.stderr.count("the newest file of") == 1 and said in res.stderr, res.stderr
    np.testing.assert_array_equal(read_volume(tmp_path / "o.nrrd").data, _sitk_series(folder))
