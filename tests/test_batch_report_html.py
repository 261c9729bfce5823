"""`volwarp batch --report report.html`: one self-contained page, a card per scan.

Checked with an HTML parser always (structure, statuses, escaped error text,
every picture an inline PNG), and in a real headless browser (Debian's
Chromium) where one is installed: the page renders, not blank, every picture
decodes.
"""

from __future__ import annotations

import base64
import html
import json
import os
import struct
import subprocess
import sys
import zlib
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.batch.manifest import Scan
from volwarp_cli.batch.report_html import report_html
from volwarp_cli.batch.run import ScanResult, StepResult
from volwarp_cli.batch.thumbs import png_bytes
from volwarp_cli.io import write_volume

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import CONVERT_MANIFEST, scan_volume  # noqa: E402

CHROMIUM = next((p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser")
                 if os.path.exists(p)), None)
BAD = "site-a/b&d<1>"  # a scan whose name needs escaping, and which is broken


class Page(HTMLParser):
    """The cards, their text, and every picture and link of a report page."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.cards: list[dict] = []
        self.imgs: list[str] = []
        self.external: list[str] = []
        self._error = 0
        self.scripts = 0

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        cls = (a.get("class") or "").split()
        if tag == "div" and "scan" in cls:
            self.cards.append({"scan": a["data-scan"], "status": a["data-status"], "error": "",
                               "imgs": 0})
        if tag == "div" and "error" in cls:
            self._error = 1
        if tag == "img":
            self.imgs.append(a["src"])
            self.cards[-1]["imgs"] += 1
        if tag == "script":
            self.scripts += 1
            if "src" in a:
                self.external.append(a["src"])
        for key in ("href", "src"):
            if key in a and tag != "img" and not a[key].startswith(("#", "data:")):
                self.external.append(a[key])

    def handle_endtag(self, tag):
        if tag == "div" and self._error:
            self._error = 0

    def handle_data(self, data):
        if self._error:
            self.cards[-1]["error"] += data


def decode_png(uri: str) -> tuple[int, int]:
    """The (width, height) of a data: URI's PNG, its pixels decompressed to check them."""
    assert uri.startswith("data:image/png;base64,")
    raw = base64.b64decode(uri.split(",", 1)[1], validate=True)
    assert raw[:8] == b"\x89PNG\r\n\x1a\n"
    w, h, depth, colour = struct.unpack(">IIBB", raw[16:26])
    pos, idat = 8, b""
    while pos < len(raw):
        (n,), kind = struct.unpack(">I", raw[pos:pos + 4]), raw[pos + 4:pos + 8]
        if kind == b"IDAT":
            idat += raw[pos + 8:pos + 8 + n]
        pos += 12 + n
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[colour]
    assert depth == 8 and len(zlib.decompress(idat)) == h * (1 + w * channels)
    return w, h


@pytest.fixture(scope="module")
def night(tmp_path_factory):
    """A batch of four scans, one broken, with a mesh render: its page and JSON report."""
    root = tmp_path_factory.mktemp("night")
    for i, rel in enumerate(["site-a/p01.nrrd", "site-b/p02.nrrd", "p03.nrrd"]):
        (root / "scans" / rel).parent.mkdir(parents=True, exist_ok=True)
        write_volume(scan_volume(i), root / "scans" / rel)
    bad = root / "scans" / f"{BAD}.nrrd"
    write_volume(scan_volume(0), bad)
    bad.write_bytes(bad.read_bytes()[:-300])
    (root / "manifest.yaml").write_text(CONVERT_MANIFEST.replace("scans/**/*.n*",
                                                                 "scans/**/*.nrrd")
                                        + '  - {name: m, run: mesh, input: conv, output: '
                                          '"{stem}.ply", options: ["--iso", "50", "--render", '
                                          '"{stem}.png", "--render-size", "160x120"]}\n')
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "batch",
                          str(root / "manifest.yaml"), "-j", "2", "--report",
                          str(root / "night.html"), "--report", str(root / "night.json")],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 1, res.stderr
    return root, json.loads((root / "night.json").read_text())


def test_page_has_a_card_per_scan_with_status_error_and_previews(night):
    root, report = night
    text = (root / "night.html").read_text(encoding="utf-8")
    page = Page()
    page.feed(text)
    assert not page.external  # self-contained: nothing fetched from anywhere
    assert sorted(c["scan"] for c in page.cards) == sorted(s["scan"] for s in report["scans"])
    assert page.cards[0]["scan"] == BAD  # failed scans first
    statuses = {c["scan"]: c["status"] for c in page.cards}
    assert statuses == {s["scan"]: s["status"] for s in report["scans"]}
    assert statuses[BAD] == "failed" and list(statuses.values()).count("ok") == 3
    bad = next(c for c in page.cards if c["scan"] == BAD)
    full = next(s["error"] for s in report["scans"] if s["scan"] == BAD)
    assert bad["error"].strip() and bad["error"].strip() in full
    assert BAD not in text and html.escape(BAD) in text  # escaped, never raw markup
    # ok cards: the input, the converted volume, its distance field and the mesh's render
    for c in page.cards:
        assert c["imgs"] == (4 if c["status"] == "ok" else 0), c
    assert page.imgs and all(max(decode_png(uri)) <= 128 for uri in page.imgs)
    assert "no preview" in text  # the broken scan's input has none


def test_text_is_escaped():
    scan = Scan(id="x/<script>", path=Path("x/<script>.nrrd"), stem="<script>", relpath="x")
    r = ScanResult(scan, "failed", 1.0, [StepResult("s", "convert", "failed",
                                                    error="volwarp: error: <b>&'\"oops")])
    r.thumbnails = {"input": png_bytes(np.zeros((4, 6), np.uint8)), "outputs": [("<o>", None)]}

    class M:
        path = Path("m<&>.yaml")
        output_dir = Path("out")

    text = report_html(M, [r])
    assert "<script>alert" not in text and "<b>" not in text and "<o>" not in text
    assert "&lt;b&gt;&amp;&#x27;&quot;oops" in text
    page = Page()
    page.feed(text)
    assert page.cards[0]["error"] == "<b>&'\"oops"
    assert [decode_png(u) for u in page.imgs] == [(6, 4)]



def test_a_scan_named_in_no_utf8_is_written_escaped(tmp_path):
    """A scan named ``caf\\xe9.nrrd`` (bytes that are not UTF-8): the page's write was an
    error after the batch's outputs were in place (exit 1); its name is escaped now."""
    from volwarp_cli.batch.report_html import write_html

    name = os.fsdecode(b"caf\xe9")
    scan = Scan(id=name, path=Path(name + ".nrrd"), stem=name, relpath="")
    r = ScanResult(scan, "ok", 1.0, [StepResult("s", "convert", "ok")])
    r.thumbnails = {"input": None, "outputs": []}

    class M:
        path = Path("m.yaml")
        output_dir = Path("out")

    write_html(tmp_path / "r.html", report_html(M, [r]))
    text = (tmp_path / "r.html").read_bytes().decode("utf-8")  # (valid UTF-8 throughout)
    page = Page()
    page.feed(text)
    assert [c["scan"] for c in page.cards] == ["caf\\udce9"]

def _chromium(*args, tmp_path):
    return subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                           "--disable-quic", "--no-first-run", "--disable-background-networking",
                           "--disable-component-update", "--disable-sync",
                           f"--user-data-dir={tmp_path / 'profile'}", *args],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed (apt-get install chromium)")
def test_page_renders_in_a_headless_browser(night, tmp_path):
    from volwarp_cli.io.images import read_image

    root, report = night
    url = (root / "night.html").as_uri()
    shot = tmp_path / "shot.png"
    res = _chromium(f"--screenshot={shot}", "--window-size=1200,900", url, tmp_path=tmp_path)
    assert shot.is_file(), res.stderr
    img = read_image(shot)
    assert img.shape[:2] == (900, 1200)
    assert float(img[..., :3].std()) > 0.05  # not a blank page
    dom = _chromium("--dump-dom", "--virtual-time-budget=5000", url, tmp_path=tmp_path).stdout
    head = dom[dom.index("<body"):dom.index(">", dom.index("<body"))]
    total = int(head.split('data-images="')[1].split('"')[0])
    loaded = int(head.split('data-images-loaded="')[1].split('"')[0])
    assert total == loaded == 12  # three ok scans, four previews each, every one decoded

