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
