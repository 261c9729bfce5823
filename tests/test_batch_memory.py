"""A batch's ``--memory-limit`` holds its scans' step processes, shared by the scans at once.

It was parsed and applied to the batch process only: the steps (each its own
process) never saw it, so ``batch --memory-limit 1M`` ran a distance step that
needs 23 MiB and said ok, and ``VOLWARP_MEMORY_LIMIT`` reached every step
whole (four scans at once under 8G could hold 32G).
"""

from __future__ import annotations

import json

import numpy as np

from volwarp_cli import memory
from volwarp_cli.batch import cluster
from volwarp_cli.batch.run import child_memory
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
    r = run("batch", tmp_path / "m.yaml", "--memory-limit", "1M", "--report-json",
            tmp_path / "r.json")
    assert r.code == 1, r.stderr
    assert "memory limit" in r.stderr and "VOLWARP_MEMORY_LIMIT" in r.stderr
    assert not (tmp_path / "out" / "ball_d.nrrd").exists()
    steps = json.loads((tmp_path / "r.json").read_text())["scans"][0]["steps"]
    assert steps[0]["status"] == "failed"
    # the same batch with room: ok, and the output a plain run's
    r = run("batch", tmp_path / "m.yaml", "--memory-limit", "2G")
    assert r.code == 0, r.stderr
    assert run("distance", tmp_path / "ball.nrrd", "--iso", "50", "-o",
               tmp_path / "ref.nrrd").code == 0
    assert (tmp_path / "out" / "ball_d.nrrd").read_bytes() == (tmp_path / "ref.nrrd").read_bytes()


def test_each_scan_at_once_gets_its_share_of_an_explicit_limit(monkeypatch):
    monkeypatch.delenv(memory.MEMORY_ENV, raising=False)
    assert child_memory(4) is None  # (no explicit limit: each step weighs the machine's)
    held = memory.process_rss()
    with memory.use_memory_limit(8 << 30):
        share = child_memory(4)
    assert abs(share - ((8 << 30) - held) // 4) < 64 * M  # (this process's own, taken off)
    monkeypatch.setenv(memory.MEMORY_ENV, "2G")  # (the variable: the lower of the two holds)
    with memory.use_memory_limit(8 << 30):
        assert child_memory(2) < (1 << 30)
    assert child_memory(1) <= 2 << 30


def test_a_cluster_hosts_scans_at_once_share_it():
    hosts = {"10.0.0.1": 4, "10.0.0.2": 1}
    assert cluster.scans_at_once("10.0.0.1", hosts, 2) == 4  # (two workers of 2 threads)
    assert cluster.scans_at_once("10.0.0.3", hosts, 2) == 2  # (a worker that joined later)
    assert cluster.share_of_cores(8, "10.0.0.1", hosts, 2) == 2


def test_a_local_clusters_steps_are_held_to_it_too(run, tmp_path):
    _manifest(tmp_path, "  - {name: d, run: distance, output: '{stem}_d.nrrd', "
                        "options: ['--iso', '50']}\n")
    r = run("batch", tmp_path / "m.yaml", "--scheduler", "local", "--workers", "1",
            "--memory-limit", "1M")
    assert r.code == 1, r.stderr
    assert "memory limit" in r.stderr and "VOLWARP_MEMORY_LIMIT" in r.stderr
    assert not (tmp_path / "out" / "ball_d.nrrd").exists()
