"""`volwarp batch MANIFEST.yaml`: every scan of a manifest through its chain of steps.

volwarp batch MANIFEST.yaml [--jobs N] [--scheduler pool|local|tcp://...|file:PATH|env]
[--workers N] [--threads-per-worker N] [--shard I/N] [--force] [--fail-fast]
[--retries N] [--settle SECONDS] [--progress bar|lines|jsonl|none] [--report REPORT.html|.json]
[--report-json REPORT.json] [--wait] [-q]
"""

from __future__ import annotations

import os
import re

import click

from .options import INPUT_PATH, Command, common_options, examples

#: ``--scheduler`` words of the batch (the engine's others name clusters)
POOL = "pool"
ENV = "env"


def _shard(ctx, param, value):
    if value is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", value)
    if not m or not int(m.group(2)) > int(m.group(1)) >= 0:
        raise click.BadParameter(f"expected I/N with 0 <= I < N (e.g. 0/4), got {value!r}",
                                 ctx=ctx, param=param)
    return int(m.group(1)), int(m.group(2))


def _scheduler(ctx, param, value):
    """``pool`` (None), or the engine's :class:`SchedulerChoice` of a cluster."""
    if value is None or value.strip().lower() == POOL:
        return None
    from ..engine import SCHEDULER_ENV, parse_scheduler
    from ..errors import VolwarpError

    text = value.strip()
    if text.lower() == ENV:
        text = os.environ.get(SCHEDULER_ENV, "").strip()
        if not text:
            raise click.BadParameter(f"'env' names the cluster in ${SCHEDULER_ENV}, "
                                     "which is not set", ctx=ctx, param=param)
    try:
        choice = parse_scheduler(text)
    except VolwarpError as exc:
        raise click.BadParameter(str(exc).replace("(known: ", "(known here: pool, env, "),
                                 ctx=ctx, param=param) from None
    if not choice.distributed:
        raise click.BadParameter(
            f"{choice.kind!r} is a scheduler of block graphs; a batch runs its scans on "
            "'pool' (the default: threads of this process, --jobs), 'local' (a LocalCluster, "
            "--workers), tcp://HOST:PORT, file:PATH or env", ctx=ctx, param=param)
    return choice


def _reports(ctx, param, value):
    for path in value:
        if not path.lower().endswith((".html", ".htm", ".json")):
            raise click.BadParameter(f"{path!r}: a report is .html (the page with previews) "
                                     "or .json (the run report)", ctx=ctx, param=param)
    return value


@click.command(name="batch", cls=Command, epilog=examples(
    "volwarp batch scans.yaml --jobs 4 --report night.html --report night.json",
    "volwarp batch scans.yaml --scheduler local --workers 4 --retries 2 --progress jsonl",
))
@click.argument("manifest", type=INPUT_PATH)
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=None, metavar="N",
              help="Scans processed at once by the local pool (default: the CPUs this "
                   "process may use).")
@click.option("--scheduler", callback=_scheduler, default=None, metavar="SCHED",
              help="Where scans run, one task each: 'pool' (default: this machine, --jobs "
                   "at once), 'local' (a Dask LocalCluster of --workers processes), "
                   "tcp://HOST:PORT or file:PATH (an existing Dask cluster), 'env' (the "
                   "cluster in $DASK_SCHEDULER_ADDRESS, read only when asked so).")
@click.option("--workers", type=click.IntRange(min=1), default=None, metavar="N",
              help="--scheduler local: worker processes (default: the CPUs this process "
                   "may use, divided by --threads-per-worker).")
@click.option("--threads-per-worker", type=click.IntRange(min=1), default=None, metavar="N",
              help="--scheduler local: scans each worker runs at once (default 1).")
@click.option("--shard", callback=_shard, default=None, metavar="I/N",
              help="Process only shard I (0-based) of N: every N-th of the sorted scans "
                   "(SLURM/PBS arrays: --shard $SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT).")
@click.option("--force", is_flag=True, help="Redo every step, even where it is up to date.")
@click.option("--fail-fast", is_flag=True,
              help="Start no new scan after one failed (running ones finish).")
@click.option("--retries", type=click.IntRange(min=0), default=0, show_default=True,
              metavar="N", help="Run a step again up to N times when its process died of a "
                                "signal, and a scan whose cluster worker died (--scheduler "
                                "local; never for a scan that failed).")
@click.option("--settle", type=click.FloatRange(min=0, max=86400), default=None,
              metavar="SECONDS",
              help="Read a scan that is a folder (a DICOM series, an OME-Zarr store) only once "
                   "its newest file is this old; a younger one is still arriving, left to the "
                   "next run (default: the manifest's inputs.settle, else 60; 0: at once).")
@click.option("--progress", "progress_mode", default=None,
              type=click.Choice(["bar", "lines", "jsonl", "none"]),
              help="Progress on stderr: a bar (the default on a terminal), a line per scan "
                   "(the default elsewhere), JSON lines (start, done, failed: seconds, peak "
                   "memory, error) or none.")
@click.option("--report", "reports", multiple=True, callback=_reports,
              type=click.Path(dir_okay=False), metavar="REPORT.html|.json",
              help="Write a run report: .html a self-contained page with previews of each "
                   "scan and its outputs, .json the run report (may be given twice).")
@click.option("--report-json", type=click.Path(dir_okay=False), default=None,
              metavar="REPORT.json", help="Write the run report (per scan, per step) here.")
@click.option("--wait", is_flag=True,
              help="When another batch is processing the output folder, wait for it to end "
                   "(default: stop at once with exit 75).")
@common_options
def command(manifest, jobs, scheduler, workers, threads_per_worker, shard, force, fail_fast,
            retries, settle, progress_mode, reports, report_json, wait):
    """Run every scan of MANIFEST through its chain of volwarp steps.

    Each scan is one task, of a local pool by default or of a Dask cluster
    (--scheduler); each step is a volwarp command run in its own process.
    Every step's options and spec are checked first. Up-to-date steps are
    skipped: what their outputs were made from (the sha256 of the scan and
    every file the step reads, its options, volwarp's version) is what was
    recorded, and the outputs are unchanged; dates decide nothing. One batch
    at a time holds an output folder (--wait to wait for it). A failed scan
    does not stop the others. A scan that is a folder whose newest file is
    younger than the settle time (--settle) is still arriving: said, and left
    to the next run. Progress and a summary line go to stderr.
    Exit 0 when every scan is ok, skipped or still arriving, 1 when any failed, 2 for a
    malformed manifest or step option, 75 when another batch holds the
    output folder, 130/143 when stopped.
    """
    from ..batch.lock import Busy, check_writable, hold
    from ..batch.manifest import find_scans, load_manifest
    from ..batch.manifest import shard as take_shard
    from ..batch.plan import check_outputs
    from ..batch.report import ScanProgress
    from ..batch.run import Where, run_batch
    from ..io import check_output_path

    ctx = click.get_current_context()
    if scheduler is None and (workers or threads_per_worker):
        raise click.UsageError("--workers and --threads-per-worker are for --scheduler local "
                               "(the local pool's count is --jobs)", ctx=ctx)
    if scheduler is not None and jobs is not None:
        raise click.UsageError("--jobs is the local pool's; on a cluster its worker threads "
                               "run the scans (--workers, --threads-per-worker)", ctx=ctx)
    if scheduler is not None and scheduler.kind != "local" and (workers or threads_per_worker):
        raise click.UsageError("--workers and --threads-per-worker start a --scheduler local "
                               "cluster; an existing cluster has its own", ctx=ctx)
    quiet = ctx.meta.get("volwarp.verbosity", 0) < 0
    m = load_manifest(manifest)
    if settle is not None:
        m.settle = settle
    json_reports = [p for p in reports if p.lower().endswith(".json")]
    html_reports = [p for p in reports if not p.lower().endswith(".json")]
    if report_json is not None:
        json_reports.append(report_json)
    given = [("--report", p) for p in reports]
    given += [("--report-json", report_json)] if report_json is not None else []
    scans = find_scans(m)
    # all of them, whatever the shard: an error is the manifest's
    check_outputs(m, scans, reports=given)
    for option, path in given:
        check_output_path(path, option=option)
    total = len(scans)
    shard_info = None
    if shard is not None:
        scans = take_shard(scans, *shard)
        shard_info = (shard[0], shard[1], total)

    check_writable(m.output_dir)  # once, up front: not once per scan
    try:
        with hold(m.output_dir, shard=shard, wait=wait, manifest=m.path,
                  on_wait=None if quiet else _say_waiting):
            report = run_batch(m, scans, Where(scheduler, jobs, workers, threads_per_worker),
                               ScanProgress.chosen(progress_mode, quiet, len(scans)),
                               shard=shard_info, force=force, fail_fast=fail_fast,
                               retries=retries, thumbnails=bool(html_reports))
            report.write(m, json_reports, html_reports)
            click.echo(report.summary_line(), err=True)
    except Busy as exc:
        click.echo(f"volwarp: error: {exc}", err=True)
        raise click.exceptions.Exit(exc.exit_code) from None
    if report.return_code:
        raise click.exceptions.Exit(report.return_code)


def _say_waiting(holder: str) -> None:
    click.echo(f"volwarp: waiting: {holder}", err=True)
