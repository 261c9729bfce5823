"""A batch's ``--memory-limit`` holds its scans' step processes, shared by the scans at once.

It was parsed and applied to the batch process only: the steps (each its own
process) never saw it, so ``batch --memory-limit 1M`` ran a distance step that
needs 23 MiB and said ok, and ``VOLWARP_MEMORY_LIMIT`` reached every step
whole (four scans at once under 8G could hold 32G).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from volwarp_cli import memory
from volwarp_cli.batch import cluster
from volwarp_cli.batch.run import child_memory
from volwarp_cli.errors import OutOfMemoryError
from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

M = 1 << 20


def _manifest(tmp_path, step: str) -> None:
    z, y, x = np.ogrid[:96, :96, :96]
    ball = ((x - 48) ** 2 + (y - 48) ** 2 + (z - 48) ** 2 <= 30 ** 2).astype(np.uint8) * 100
    write_volume(Volume(ball), tmp_path / "ball.nrrd")
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {list: [ball.nrrd]}\noutput_dir: out\nsteps:\n" + step)


def test_a_step_that_cannot_fit_the_batchs_limit_fails_and_writes_nothing(run, tmp_path):
    _manifest(tmp_path, "  - {name: d, run: distance, output: '{stem}_d.nrrd', "
                        "options: ['--iso', '50']}\n")
    # (the batch runs in this process here: its share is what the limit leaves over it)
    tight = memory.process_rss() + 30 * M
    r = run("batch", tmp_path / "m.yaml", "--memory-limit", tight, "--report-json",
            tmp_path / "r.json")
    assert r.code == 1, r.stderr
    assert "memory limit" in r.stderr and "share of the batch's memory limit" in r.stderr
    assert not (tmp_path / "out" / "ball_d.nrrd").exists()
    steps = json.loads((tmp_path / "r.json").read_text())["scans"][0]["steps"]
    assert steps[0]["status"] == "failed"
    # the same batch with room: ok, and the output a plain run's
    r = run("batch", tmp_path / "m.yaml", "--memory-limit", memory.process_rss() + (2 << 30))
    assert r.code == 0, r.stderr
    assert run("distance", tmp_path / "ball.nrrd", "--iso", "50", "-o",
               tmp_path / "ref.nrrd").code == 0
    assert (tmp_path / "out" / "ball_d.nrrd").read_bytes() == (tmp_path / "ref.nrrd").read_bytes()


def test_each_scan_at_once_gets_its_share_of_an_explicit_limit(monkeypatch):
    monkeypatch.delenv(memory.MEMORY_ENV, raising=False)
    assert child_memory(4) == (None, "")  # (no explicit limit: each step weighs the machine's)
    held = memory.process_rss()
    with memory.use_memory_limit(8 << 30):
        share, what = child_memory(4)
    assert abs(share - ((8 << 30) - held) // 4) < 64 * M  # (this process's own, taken off)
    assert what == "memory limit 8.0 GiB, 4 scans at once"
    monkeypatch.setenv(memory.MEMORY_ENV, "2G")  # (the variable: the lower of the two holds)
    with memory.use_memory_limit(8 << 30):
        assert child_memory(2)[0] < (1 << 30)
    assert child_memory(1)[0] <= 2 << 30
    with memory.use_memory_limit(held // 2), pytest.raises(OutOfMemoryError,
                                                           match="leaves nothing"):
        child_memory(1)  # (what this batch process holds already: no step could run)


def test_one_scan_gets_the_whole_limit_whatever_the_jobs(run, tmp_path):
    """The share is of the scans that run at once, not of --jobs: a one-scan batch with
    -j 8 (the default on an 8-core machine) gave its step an eighth and failed."""
    _manifest(tmp_path, "  - {name: d, run: distance, output: '{stem}_d.nrrd', "
                        "options: ['--iso', '50', '--no-chunked']}\n")
    # (the step needs about 60 MiB with its interpreter: an eighth of 150M, 19M, cannot hold
    # it; the whole can)
    r = run("batch", tmp_path / "m.yaml", "--memory-limit", memory.process_rss() + 150 * M,
            "-j", "8")
    assert r.code == 0, r.stderr


def test_a_limit_the_batch_itself_holds_is_refused_before_any_scan(run, tmp_path):
    _manifest(tmp_path, "  - {name: d, run: distance, output: '{stem}_d.nrrd', "
                        "options: ['--iso', '50']}\n")
    r = run("batch", tmp_path / "m.yaml", "--memory-limit", "1M")
    assert r.code == 1
    assert "leaves nothing for the scans' steps" in r.stderr and r.stderr.count("\n") == 1
    assert not (tmp_path / "out" / "ball_d.nrrd").exists()


def test_a_hosts_own_limit_is_never_raised_and_the_message_names_the_batchs(monkeypatch):
    from volwarp_cli.batch.run import ScanRunner

    runner = ScanRunner.__new__(ScanRunner)
    runner.child_memory, runner.memory_from = 100 * M, "memory limit 400.0 MiB, 4 scans at once"
    monkeypatch.setenv(memory.MEMORY_ENV, "60M")  # (a cluster worker's own: its host's)
    env = runner._env(2)
    assert env[memory.MEMORY_ENV] == "60M" and memory.MEMORY_FROM_ENV not in env
    monkeypatch.setenv(memory.MEMORY_ENV, "1G")
    env = runner._env(2)
    assert env[memory.MEMORY_ENV] == str(100 * M) and env["VOLWARP_THREADS"] == "2"
    assert "share of the batch's memory limit 400.0 MiB" in env[memory.MEMORY_FROM_ENV]


def test_a_cluster_hosts_scans_at_once_share_it():
    hosts = {"10.0.0.1": 4, "10.0.0.2": 1}
    assert cluster.scans_at_once("10.0.0.1", hosts, 2) == 4  # (two workers of 2 threads)
    assert cluster.scans_at_once("10.0.0.3", hosts, 2) == 2  # (a worker that joined later)
    assert cluster.share_of_cores(8, "10.0.0.1", hosts, 2) == 2


def test_a_local_clusters_own_workers_count_against_the_limit(run, tmp_path):
    """A local cluster's worker and nanny processes (about 120 MiB a worker) run on this
    machine beside the batch and its steps, but the steps shared all the batch process
    left: with 150 MiB over the batch, a distance step ran (exit 0) while the worker
    held most of it. Now the workers are taken off first, and what they leave is too
    little for any step: refused before any scan, naming the workers."""
    _manifest(tmp_path, "  - {name: d, run: distance, output: '{stem}_d.nrrd', "
                        "options: ['--iso', '50']}\n")
    r = run("batch", tmp_path / "m.yaml", "--scheduler", "local", "--workers", "1",
            "--memory-limit", memory.process_rss() + 150 * M)
    assert r.code == 1, r.stderr
    assert "the memory limit leaves nothing for the scans' steps: the local cluster's " \
           "workers hold" in r.stderr, r.stderr
    assert not (tmp_path / "out" / "ball_d.nrrd").exists()
    # with room for the workers, the steps get the rest, shared (the pool's test above)
    r = run("batch", tmp_path / "m.yaml", "--scheduler", "local", "--workers", "1",
            "--memory-limit", memory.process_rss() + (2 << 30))
    assert r.code == 0, r.stderr
    assert (tmp_path / "out" / "ball_d.nrrd").exists()
