"""What a batch says of a scan still arriving, read as a user reads it.

A scan still arriving is not read: its card in the HTML report gave it a time
("0.0 s", as if it had run in no time) and a stopped run's summary counted it
among the scans not done ("with 1 of 3 done" where only one scan was left).
"""

from __future__ import annotations

import signal
from pathlib import Path

from volwarp_cli.batch.manifest import Scan
from volwarp_cli.batch.report import summary_line
from volwarp_cli.batch.report_html import report_html
from volwarp_cli.batch.run import ARRIVING, ScanResult, StepResult


class M:
    path = Path("m.yaml")
    output_dir = Path("out")


def _scan(name: str) -> Scan:
    return Scan(id=name, path=Path(f"scans/{name}"), stem=name, relpath="")


def _card(page: str, name: str) -> str:
    start = page.index(f'data-scan="{name}"')
    return page[start:page.index("</div>\n</div>", start)]


def test_a_still_arriving_card_gives_no_time():
    """Not read, not run: its card says why (the reason), never a time of its own."""
    arriving = ScanResult(_scan("b"), ARRIVING, 0.0004, reason="newest file 3 s old, settle 60 s")
    ran = ScanResult(_scan("a"), "ok", 1.25, [StepResult("conv", "convert", "ok", seconds=1.2)])
    for r in (arriving, ran):
        r.thumbnails = {"input": None, "outputs": []}
    page = report_html(M, [arriving, ran])
    card = _card(page, "b")
    assert "newest file 3 s old, settle 60 s" in card
    assert '<div class="facts">' not in card and " s</div>" not in card.replace(
        "settle 60 s</div>", "")
    assert '<div class="facts">1.2 s</div>' in _card(page, "a")


def test_a_stopped_run_counts_the_scans_still_arriving_as_done_with():
    """Three scans: one ok, one still arriving (dealt with: left to the next run), one not
    started: one scan was left undone by the stop, not two."""
    results = [ScanResult(_scan("a"), "ok", 1.0),
               ScanResult(_scan("b"), ARRIVING, 0.0, reason="newest file 3 s old, settle 60 s"),
               ScanResult(_scan("c"), "not started")]
    line = summary_line(results, stop=signal.SIGTERM)
    assert line.startswith("volwarp batch: stopped by SIGTERM with 2 of 3 done: "), line
    assert line.endswith("1 not started, 1 still arriving"), line


def test_a_compressed_multiframe_dicom_is_read_without_a_stray_traceback(monkeypatch):
    """pydicom's frame generator was left suspended past the file's close: every read of a
    compressed multi-frame file (RLE, JPEG 2000, a BINARY SEG read in a folder) printed
    'Exception ignored in: <generator object iter_pixels> ... ValueError: seek of closed
    file' on stderr. The samples are pydicom's own decoding."""
    import gc
    import sys

    import numpy as np
    import pytest

    pydicom = pytest.importorskip("pydicom")
    from pydicom.data import get_testdata_file

    from volwarp_cli.io import read_volume

    stray = []
    monkeypatch.setattr(sys, "unraisablehook", stray.append)
    path = get_testdata_file("emri_small_RLE.dcm")
    vol = read_volume(path)
    gc.collect()
    assert not stray, [f"{u.exc_type.__name__}: {u.exc_value}" for u in stray]
    frames = pydicom.dcmread(path).pixel_array  # [frame, y, x]
    assert sorted(vol.data.reshape(-1).tolist()) == sorted(frames.reshape(-1).tolist())
    assert np.asarray(vol.data).shape == frames.shape
