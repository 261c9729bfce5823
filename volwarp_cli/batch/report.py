"""What a batch says: a progress line per scan, one summary line, the JSON run report.

Progress (stderr, unless ``--quiet``; :class:`ScanProgress`): on a terminal a
bar, with a line for each failed scan and each still arriving; elsewhere (a
log, a pipe) a line as each scan ends::

    ok site-a/p01 3.2 s
      warning: warped: every voxel of the warp of ... is the background (0): ...
    skipped site-a/p02
    failed site-b/p17 0.4 s: truncated gzip stream
    still arriving site-b/p18 (newest file 3 s old, settle 60 s)

and with ``--progress jsonl`` one JSON object a line (the block lines' format,
:class:`volwarp_cli.engine.JsonlProgress`): ``{"event": "start", "kind":
"scan", "id": "site-a/p01", "t": ...}`` as a scan starts (on a cluster: as its
task starts on the worker, with ``worker`` and ``pid``), ``done`` (with
``status`` ok or skipped) or ``failed`` (with ``error``) or ``stopped`` as it
ends, with its ``seconds`` and ``peak_rss`` (bytes, its steps' largest); a
scan still arriving (its folder's newest file younger than the settle time)
is ``done`` with that ``status`` and its ``reason``: not read, not failed.

The summary (stderr, always), e.g.::

    volwarp batch: 412 scans, 409 ok (1 with warnings), 2 skipped, 1 failed, 1 still arriving: site-b/p17 (truncated gzip stream)

The report (``--report-json``, or ``--report`` with a ``.json`` name): per scan and per step its status, seconds,
attempts, exit code, error line, command and outputs, with the provenance
key/values every volwarp output carries (``volwarp_input``: the manifest's
name, ``volwarp_spec_sha256``: its sha256). Written atomically.
"""

from __future__ import annotations

import json
import signal
from dataclasses import dataclass
from pathlib import Path

from .run import ARRIVING, ScanResult

#: at most this many failed scans are named in the summary line
NAMED_FAILURES = 5
_PREFIX = "volwarp: error: "


def short_error(error: str | None, result: ScanResult) -> str:
    """The error line without ``volwarp: error:`` and without the scan's own path."""
    if not error:
        return "failed"
    return _without_path(error[len(_PREFIX):] if error.startswith(_PREFIX) else error, result)


def short_warnings(result: ScanResult, *, ran: bool = False) -> list[str]:
    """The scan's warning lines, each ``STEP: TEXT`` without the scan's own path.

    ``ran``: only those of the steps that ran now; a skipped step's are the
    run's that made its outputs (kept in the reports), said and counted by that run.
    """
    return [f"{s.name}: {_without_path(text, result)}" for s in result.steps
            if not (ran and s.status == "skipped") for text in s.warnings]


def _without_path(text: str, result: ScanResult) -> str:
    """``text`` without a leading ``PATH: `` naming the scan, an output or a command's file."""
    paths = [str(result.scan.path.absolute()), str(result.scan.path)]
    for step in result.steps:
        paths += step.outputs
        paths += [c for c in step.command if c.startswith("/")]
    for p in sorted(set(paths), key=len, reverse=True):
        if text.startswith(p + ": "):
            return text[len(p) + 2:]
    return text


def progress_line(result: ScanResult) -> str:
    """The progress line of a scan that ended: status, scan, seconds and, if failed, why.

    Then a line for each warning of its steps that ran (``  warning: STEP: TEXT``);
    a skipped step's are those of the run that made its outputs, not said again.
    """
    if result.status in ("skipped", "not started"):
        return f"{result.status} {result.scan.id}"
    if result.status == ARRIVING:
        return f"{result.status} {result.scan.id} ({result.reason})"
    line = f"{result.status} {result.scan.id} {result.seconds:.1f} s"
    if result.status == "failed":
        line += f": {short_error(result.error, result)}"
    return "\n".join([line, *(f"  warning: {w}" for w in short_warnings(result, ran=True))])


def warned(results: list[ScanResult]) -> int:
    """How many ok scans warned in a step that ran (the summary's ``N ok (M with warnings)``).

    A failed scan's warnings are said on its line, not counted among the ok ones.
    """
    return sum(1 for r in results if r.status == "ok" and short_warnings(r, ran=True))


def counts(results: list[ScanResult]) -> dict[str, int]:
    """The number of scans, and of scans per status (``not started`` as ``not_started``)."""
    out = {"scans": len(results)}
    for status in ("ok", "skipped", "failed", "stopped", "not started", ARRIVING):
        out[status.replace(" ", "_")] = sum(r.status == status for r in results)
    return out


def summary_line(results: list[ScanResult], *, stop: int | None = None,
                 shard: tuple[int, int, int] | None = None) -> str:
    """One line: how many scans, how many ok / skipped / failed, which failed and why."""
    c = counts(results)
    head = f"{c['scans']} scan{'' if c['scans'] == 1 else 's'}"
    if shard is not None:
        head += f" (shard {shard[0]}/{shard[1]} of {shard[2]})"
    ok = f"{c['ok']} ok"
    n = warned(results)
    if n:  # (each said on its scan's progress line, and in the reports)
        ok += f" ({n} with warnings)"
    parts = [head, ok, f"{c['skipped']} skipped", f"{c['failed']} failed"]
    if c["stopped"]:
        parts.append(f"{c['stopped']} stopped")
    if c["not_started"]:
        parts.append(f"{c['not_started']} not started")
    if c["still_arriving"]:  # (not read, not failed: the next run takes them)
        parts.append(f"{c['still_arriving']} {ARRIVING}")
    line = "volwarp batch: "
    if stop is not None:
        # (a scan still arriving was left to the next run: dealt with, not cut short)
        done = c["ok"] + c["skipped"] + c["failed"] + c["still_arriving"]
        line += f"stopped by {signal.Signals(stop).name} with {done} of {c['scans']} done: "
    line += ", ".join(parts)
    failed = [r for r in results if r.status == "failed"]
    if failed:
        named = ", ".join(f"{r.scan.id} ({short_error(r.error, r)})"
                          for r in failed[:NAMED_FAILURES])
        more = len(failed) - NAMED_FAILURES
        line += f": {named}" + (f" and {more} more" if more > 0 else "")
    return " ".join(line.split())


def report_dict(manifest, results: list[ScanResult], *, jobs: int, stop: int | None,
                shard: tuple[int, int, int] | None, exit_code: int,
                scheduler: str = "pool") -> dict:
    """The JSON run report: the provenance key/values, the run's figures, each scan's steps.

    ``jobs``: scans at once (the pool's threads, the cluster's worker threads);
    ``scheduler``: ``pool`` or the cluster as ``--scheduler`` named it. Per
    scan its ``attempts`` (runs of its task: more than one when a worker
    died), its ``worker`` (on a cluster) and ``peak_rss`` (bytes, the largest
    of its steps'), ``reason`` (why a scan still arriving was not read); per
    step the step process's ``peak_rss``.
    """
    from ..provenance import provenance

    meta = provenance("batch", manifest.path)
    meta["volwarp_spec_sha256"] = manifest.sha256
    return {
        **meta,
        "manifest": str(manifest.path),
        "output_dir": str(manifest.output_dir),
        "scheduler": scheduler,
        "jobs": jobs,
        "shard": None if shard is None else f"{shard[0]}/{shard[1]}",
        "stopped_by": None if stop is None else signal.Signals(stop).name,
        "exit_code": exit_code,
        "summary": counts(results),
        "scans": [{
            "scan": r.scan.id,
            "input": str(r.scan.path),
            "status": r.status,
            "seconds": round(r.seconds, 3),
            "error": r.error,
            "reason": r.reason,
            "attempts": r.attempts,
            "worker": r.worker,
            "peak_rss": r.peak_rss,
            "steps": [{
                "name": s.name, "run": s.run, "status": s.status,
                "seconds": round(s.seconds, 3), "error": s.error, "attempts": s.attempts,
                "exit_code": s.exit_code, "reason": s.reason, "peak_rss": s.peak_rss,
                "command": s.command, "outputs": s.outputs, "warnings": s.warnings,
            } for s in r.steps],
        } for r in results],
    }


@dataclass(frozen=True)
class Report:
    """What a batch run did, and the exit code that says it (as black's ``Report``).

    ``results``: each scan's, in scan order; ``stop``: the signal number that
    stopped the run, or None; ``jobs``: scans at once; ``scheduler``: ``pool``
    or the cluster as ``--scheduler`` named it; ``shard``: ``(I, N, scans in
    all)`` of a ``--shard I/N`` run.
    """

    results: list[ScanResult]
    stop: int | None = None
    jobs: int = 1
    scheduler: str = "pool"
    shard: tuple[int, int, int] | None = None

    @property
    def return_code(self) -> int:
        """The batch's exit code: 128 + the signal when stopped, 1 when a scan failed, else 0.

        A scan still arriving is no failure: a cron job's next run reads it, and
        the summary and reports say it meanwhile.
        """
        if self.stop is not None:
            return 128 + self.stop
        return 1 if any(r.status == "failed" for r in self.results) else 0

    def summary_line(self) -> str:
        """:func:`summary_line` of this run."""
        return summary_line(self.results, stop=self.stop, shard=self.shard)

    def write(self, manifest, json_paths=(), html_paths=()) -> None:
        """The JSON run report (:func:`report_dict`) and the HTML page, each to its paths."""
        if json_paths:
            report = report_dict(manifest, self.results, jobs=self.jobs, stop=self.stop,
                                 shard=self.shard, exit_code=self.return_code,
                                 scheduler=self.scheduler)
            for path in json_paths:
                write_report(path, report)
        if html_paths:
            from .report_html import report_html, write_html

            page = report_html(manifest, self.results, stop=self.stop, shard=self.shard,
                               scheduler=self.scheduler)
            for path in html_paths:
                write_html(path, page)


def write_report(path: str | Path, report: dict) -> None:
    """Write ``report`` to ``path`` as indented JSON, atomically."""
    from ..io.atomic import write_bytes_atomic

    text = json.dumps(report, indent=2, sort_keys=False) + "\n"
    write_bytes_atomic(path, text.encode("utf-8"))


class ScanProgress:
    """What is said as scans start and end: ``mode`` is ``bar``, ``lines``, ``jsonl`` or ``none``.

    Its methods may be called from any thread (the pool's, the client's).
    """

    def __init__(self, mode: str, total: int, stream=None):
        import sys
        import threading

        self.mode = mode
        self.stream = stream if stream is not None else sys.stderr
        self._lock = threading.Lock()
        self._bar = None
        self._jsonl = None
        if mode == "jsonl":
            from ..engine import JsonlProgress

            self._jsonl = JsonlProgress(self.stream)
        elif mode == "bar":
            from ..progress import Progress

            self._bar = Progress(total, "volwarp batch")
            self._bar.enabled = True

    @classmethod
    def chosen(cls, given: str | None, quiet: bool, total: int) -> ScanProgress:
        """``--progress`` if given, else none when quiet, a bar on a terminal, lines elsewhere."""
        import sys

        if given is None:
            given = "none" if quiet else "bar" if sys.stderr.isatty() else "lines"
        return cls(given, total)

    def start(self, scan, worker: str | None = None, pid: int | None = None) -> None:
        """A scan started (on ``worker``, process ``pid``: a cluster's)."""
        if self._jsonl is not None:
            self._jsonl.emit("start", "scan", scan.id, worker=worker, pid=pid)

    def end(self, result: ScanResult) -> None:
        """A scan ended."""
        with self._lock:
            if self._jsonl is not None:
                event = {"ok": "done", "skipped": "done", ARRIVING: "done",
                         "failed": "failed"}.get(
                    result.status, "stopped" if result.status == "stopped" else None)
                if event is not None:
                    self._jsonl.emit(event, "scan", result.scan.id, status=result.status,
                                     seconds=round(result.seconds, 4),
                                     peak_rss=result.peak_rss, worker=result.worker,
                                     error=(short_error(result.error, result)
                                            if result.status == "failed" else None),
                                     warnings=short_warnings(result) or None,
                                     reason=result.reason)
            elif self.mode == "lines":
                self.stream.write(progress_line(result) + "\n")
                self.stream.flush()
            elif self._bar is not None:
                if result.status in ("failed", ARRIVING) or short_warnings(result, ran=True):
                    self.stream.write("\r\x1b[2K" + progress_line(result) + "\n")
                self._bar.advance()

    def close(self) -> None:
        """End the bar's line."""
        if self._bar is not None:
            self._bar.__exit__(None, None, None)
            self._bar = None
