"""`volwarp batch MANIFEST.yaml`: every scan of a manifest through its chain of steps.

volwarp batch MANIFEST.yaml [--jobs N] [--shard I/N] [--force] [--fail-fast]
[--retries N] [--report-json REPORT.json] [-q]
"""

from __future__ import annotations

import re

import click

from .options import INPUT_PATH, common_options, examples


def _shard(ctx, param, value):
    if value is None:
        return None
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", value)
    if not m or not int(m.group(2)) > int(m.group(1)) >= 0:
        raise click.BadParameter(f"expected I/N with 0 <= I < N (e.g. 0/4), got {value!r}",
                                 ctx=ctx, param=param)
    return int(m.group(1)), int(m.group(2))


@click.command(name="batch", epilog=examples(
    "volwarp batch scans.yaml --jobs 4 --report-json report.json",
    "volwarp batch scans.yaml --shard 0/8 --retries 1",
))
@click.argument("manifest", type=INPUT_PATH)
@click.option("-j", "--jobs", type=click.IntRange(min=1), default=None, metavar="N",
              help="Scans processed at once (default: the CPUs this process may use).")
@click.option("--shard", callback=_shard, default=None, metavar="I/N",
              help="Process only shard I (0-based) of N: every N-th of the sorted scans "
                   "(SLURM/PBS arrays: --shard $SLURM_ARRAY_TASK_ID/$SLURM_ARRAY_TASK_COUNT).")
@click.option("--force", is_flag=True, help="Redo every step, even where it is up to date.")
@click.option("--fail-fast", is_flag=True,
              help="Start no new scan after one failed (running ones finish).")
@click.option("--retries", type=click.IntRange(min=0), default=0, show_default=True,
              metavar="N", help="Run a step again up to N times when its process died of a "
                                "signal (never for a scan that failed).")
@click.option("--report-json", type=click.Path(dir_okay=False), default=None,
              metavar="REPORT.json", help="Write the run report (per scan, per step) here.")
@common_options
def command(manifest, jobs, shard, force, fail_fast, retries, report_json):
    """Run every scan of MANIFEST through its chain of volwarp steps.

    Each scan is one task of a local pool; each step is a volwarp command run
    in its own process. Up-to-date scans are skipped (their outputs exist,
    are newer than their inputs and specs, and their provenance matches);
    a failed scan does not stop the others. One line per scan and a summary
    line go to stderr. Exit 0 when every scan is ok or skipped, 1 when any
    failed, 2 for a malformed manifest, 130/143 when stopped.
    """
    from ..batch.manifest import find_scans, load_manifest
    from ..batch.manifest import shard as take_shard
    from ..batch.plan import check_outputs
    from ..batch.report import progress_line, report_dict, summary_line, write_report
    from ..batch.run import Batch, default_jobs
    from ..io import check_output_path

    quiet = click.get_current_context().meta.get("volwarp.verbosity", 0) < 0
    m = load_manifest(manifest)
    if report_json is not None:
        check_output_path(report_json)
    scans = find_scans(m)
    check_outputs(m, scans)  # all of them, whatever the shard: an error is the manifest's
    total = len(scans)
    shard_info = None
    if shard is not None:
        scans = take_shard(scans, *shard)
        shard_info = (shard[0], shard[1], total)
    jobs = jobs or default_jobs()

    def on_scan(result):
        if not quiet:
            click.echo(progress_line(result), err=True)

    results, stop = Batch(m, scans, jobs=jobs, force=force, fail_fast=fail_fast,
                          retries=retries, on_scan=on_scan).run()
    if stop is not None:
        code = 128 + stop
    else:
        code = 1 if any(r.status == "failed" for r in results) else 0
    if report_json is not None:
        write_report(report_json, report_dict(m, results, jobs=jobs, stop=stop,
                                              shard=shard_info, exit_code=code))
    click.echo(summary_line(results, stop=stop, shard=shard_info), err=True)
    if code:
        raise click.exceptions.Exit(code)
