"""The HTML run report (``--report report.html``): a night's work at a glance.

One self-contained page: its CSS and a few lines of script inline, every
picture a ``data:image/png;base64`` URI, no link to anything outside it, so
it can be mailed, archived or opened from a share. A card per scan, failed
scans first: its name, status, seconds, peak memory, attempts, the error line
(every text escaped), and the previews side by side: the input scan's, then
each output's (a volume's middle slice, a mesh step's render; see
:mod:`.thumbs`). Written atomically.
"""

from __future__ import annotations

import base64
import html
import signal
from pathlib import Path

from .report import counts, short_error, short_warnings, summary_line
from .run import ARRIVING, ScanResult

_ORDER = {"failed": 0, "stopped": 1, "not started": 2, "still arriving": 3, "ok": 4,
          "skipped": 5}

_CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:1.5em;color:#222;background:#fafafa}
h1{font-size:1.3em;margin:0 0 .3em}
.summary{font-family:monospace;margin:.3em 0 1em;padding:.5em;background:#fff;
 border:1px solid #ddd;white-space:pre-wrap}
.counts span{display:inline-block;margin-right:1em}
.filter{margin:.5em 0 1em}
.scans{display:flex;flex-wrap:wrap;gap:12px}
.scan{background:#fff;border:1px solid #ccc;border-left:6px solid #999;border-radius:4px;
 padding:8px;width:min(100%,560px);box-sizing:border-box}
.scan.status-ok{border-left-color:#2a7d2a}
.scan.status-skipped{border-left-color:#7a8fa6}
.scan.status-failed{border-left-color:#c0392b;background:#fff5f4}
.scan.status-stopped,.scan.status-not-started,.scan.status-still-arriving{
 border-left-color:#d68910}
.scan h2{font-size:1em;margin:0 0 4px;word-break:break-all}
.status{font-weight:bold;text-transform:uppercase;font-size:.8em;padding:1px 6px;
 border-radius:3px;background:#eee}
.status-failed .status{background:#c0392b;color:#fff}
.status-ok .status{background:#2a7d2a;color:#fff}
.facts{color:#555;font-size:.9em;margin:2px 0 6px}
.error{font-family:monospace;color:#a00;white-space:pre-wrap;word-break:break-word;
 margin:4px 0}
.warning,.reason{font-family:monospace;color:#8a5a00;white-space:pre-wrap;word-break:break-word;
 margin:4px 0}
.thumbs{display:flex;gap:6px;flex-wrap:wrap;align-items:flex-start}
figure{margin:0;text-align:center;font-size:.75em;color:#555}
figure img{display:block;background:#000;image-rendering:pixelated;max-width:128px}
.none{width:128px;height:64px;line-height:64px;background:#eee;color:#888}
.steps{font-size:.8em;color:#555;margin-top:4px}
body.failed-only .scan:not(.status-failed){display:none}
"""

# counts the pictures that decoded (a check for a browser, and for the reader: "N of M")
_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) { if (imgs[i].complete && imgs[i].naturalWidth > 0) ok++; }
  document.body.setAttribute('data-images', imgs.length);
  document.body.setAttribute('data-images-loaded', ok);
  var box = document.getElementById('failed-only');
  if (box) box.addEventListener('change', function () {
    document.body.classList.toggle('failed-only', box.checked); });
});
"""


def _e(text) -> str:
    return html.escape("" if text is None else str(text), quote=True)


def _size(n: int | None) -> str:
    if n is None:
        return "-"
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return "-"


def _figure(label: str, png: bytes | None) -> str:
    if png is None:
        return f'<figure><div class="none">no preview</div><figcaption>{_e(label)}' \
               '</figcaption></figure>'
    uri = "data:image/png;base64," + base64.b64encode(png).decode("ascii")
    return (f'<figure><img src="{uri}" alt="{_e(label)}"><figcaption>{_e(label)}'
            '</figcaption></figure>')


def _card(r: ScanResult) -> str:
    status = r.status
    cls = "status-" + status.replace(" ", "-")
    # (a scan not run, still arriving or not started, has no time of its own: "0.0 s" read
    # as a run that took none)
    facts = [] if status in (ARRIVING, "not started") else [f"{r.seconds:.1f} s"]
    if r.peak_rss is not None:
        facts.append(f"peak {_size(r.peak_rss)}")
    if r.attempts > 1:
        facts.append(f"{r.attempts} attempts (worker died)")
    if r.worker:
        facts.append(f"on {r.worker}")
    parts = [f'<div class="scan {cls}" id="scan-{_e(r.scan.id)}" data-scan="{_e(r.scan.id)}" '
             f'data-status="{_e(status)}">',
             f'<h2>{_e(r.scan.id)} <span class="status">{_e(status)}</span></h2>',
             *([f'<div class="facts">{_e(" · ".join(facts))}</div>'] if facts else [])]
    if status == "failed":
        parts.append(f'<div class="error">{_e(short_error(r.error, r))}</div>')
    if r.reason:  # (a scan still arriving: not read this run)
        parts.append(f'<div class="reason">{_e(r.reason)}</div>')
    for line in short_warnings(r):  # (a skipped scan's: the run's that made its outputs)
        parts.append(f'<div class="warning">warning: {_e(line)}</div>')
    thumbs = r.thumbnails or {}
    figures = [_figure("input: " + r.scan.path.name, thumbs.get("input"))]
    figures += [_figure(name, png) for name, png in thumbs.get("outputs", [])]
    parts.append('<div class="thumbs">' + "".join(figures) + "</div>")
    steps = ", ".join(f"{s.name} {s.status}" + (f" {s.seconds:.1f} s" if s.seconds else "")
                      for s in r.steps)
    if steps:
        parts.append(f'<div class="steps">{_e(steps)}</div>')
    parts.append("</div>")
    return "\n".join(parts)


def report_html(manifest, results: list[ScanResult], *, stop: int | None = None,
                shard: tuple[int, int, int] | None = None, scheduler: str = "pool") -> str:
    """The page, as text."""
    from .. import __version__

    c = counts(results)
    order = sorted(results, key=lambda r: (_ORDER.get(r.status, 9), r.scan.id))
    title = f"volwarp batch: {Path(manifest.path).name}"
    count_html = "".join(f'<span class="count-{k}">{_e(k.replace("_", " "))}: {v}</span>'
                         for k, v in c.items() if k == "scans" or v)
    stopped = f" (stopped by {signal.Signals(stop).name})" if stop is not None else ""
    return "\n".join([
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(title)}</title>",
        f"<style>{_CSS}</style>",
        f"<script>{_SCRIPT}</script>",
        "</head><body>",
        f"<h1>{_e(title)}{_e(stopped)}</h1>",
        f'<div class="meta">{_e(str(manifest.path))} → {_e(str(manifest.output_dir))}; '
        f"scheduler {_e(scheduler)}; volwarp {_e(__version__)}</div>",
        f'<div class="summary">{_e(summary_line(results, stop=stop, shard=shard))}</div>',
        f'<div class="counts">{count_html}</div>',
        '<div class="filter"><label><input type="checkbox" id="failed-only"> '
        "failed scans only</label></div>",
        '<div class="scans">',
        *(_card(r) for r in order),
        "</div>",
        "</body></html>",
        "",
    ])


def write_html(path: str | Path, text: str) -> None:
    """Write the page to ``path``, atomically."""
    from ..io.atomic import write_bytes_atomic

    write_bytes_atomic(path, text.encode("utf-8", "backslashreplace"))
