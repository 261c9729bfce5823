"""`volwarp batch --scheduler`: each scan one task on a Dask cluster, workers that die.

A worker killed in the middle of a scan: its scan runs again elsewhere,
nothing is lost, no partial file is left, the summary and the report say
what happened, and every output is byte for byte the local pool's.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from volwarp_cli.batch.lock import BOOK_DIR
from volwarp_cli.io import write_volume

pytest.importorskip("distributed")

sys.path.insert(0, str(Path(__file__).parent))
from test_batch import scan_volume  # noqa: E402

MANIFEST = """version: 1
inputs: {glob: "scans/**/*.nrrd"}
output_dir: out
steps:
  - {name: conv, run: convert, output: "{stem}.nrrd"}
  - {name: sdf, run: distance, input: conv, output: "{stem}_sdf.nrrd", options: ["--iso", "50"]}
"""
SCANS = [f"site-{'ab'[i % 2]}/p{i:02d}" for i in range(6)]


def make_tree(root: Path) -> Path:
    for i, scan in enumerate(SCANS):
        path = root / "scans" / f"{scan}.nrrd"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_volume(scan_volume(i % 3), path)
    (root / "manifest.yaml").write_text(MANIFEST)
    return root / "manifest.yaml"


def outputs(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root / "out")): p.read_bytes()
            for p in sorted((root / "out").rglob("*")) if p.is_file() and BOOK_DIR not in p.parts}


def leftovers(root: Path) -> list[Path]:
    """Temporaries (hidden files, ``.part``) anywhere under the output folder."""
    return [p for p in (root / "out").rglob("*")
            if BOOK_DIR not in p.parts and (p.name.startswith(".") or p.suffix == ".part")]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The local pool's outputs of the manifest."""
    root = tmp_path_factory.mktemp("pool")
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "batch",
                          str(make_tree(root)), "-j", "2"], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    return outputs(root)


def _has_child(pid: int) -> bool:
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return False
    for tid in tasks:
        try:
            if Path(f"/proc/{pid}/task/{tid}/children").read_text().split():
                return True
        except OSError:
            pass
    return False


def run_and_kill(cmd: list[str], cwd: Path) -> tuple[int, list[dict], str, str]:
    """Run the batch; SIGKILL the worker of the first scan to start, while a step of it runs.

    ``(exit code, the JSON lines, other stderr, the killed scan)``.
    """
    events, other, killed = [], [], None
    with subprocess.Popen(cmd, cwd=cwd, stderr=subprocess.PIPE, text=True) as proc:
        try:
            for line in proc.stderr:
                if not line.startswith("{"):
                    other.append(line)
                    continue
                event = json.loads(line)
                events.append(event)
                if killed is None and event["event"] == "start":
                    pid = event["pid"]
                    deadline = time.monotonic() + 30
                    while not _has_child(pid) and time.monotonic() < deadline:
                        time.sleep(0.005)
                    assert _has_child(pid), "the scan's step never started"
                    os.kill(pid, signal.SIGKILL)  # the worker process, in the middle of a step
                    killed = event["id"]
            code = proc.wait(timeout=300)
        finally:
            if proc.poll() is None:
                proc.kill()
    return code, events, "".join(other), killed


def test_killed_worker_reruns_its_scan(tmp_path, reference):
    manifest = make_tree(tmp_path)
    code, events, stderr, killed = run_and_kill(
        [sys.executable, "-m", "volwarp_cli", "batch", str(manifest), "--scheduler", "local",
         "--workers", "2", "--retries", "1", "--progress", "jsonl",
         "--report-json", str(tmp_path / "r.json")], tmp_path)
    assert code == 0, stderr
    assert stderr.strip().splitlines()[-1] == "volwarp batch: 6 scans, 6 ok, 0 skipped, 0 failed"
    # nothing lost, nothing partial, the same bytes as the local pool
    assert outputs(tmp_path) == reference
    assert not leftovers(tmp_path)
    starts = [e["id"] for e in events if e["event"] == "start"]
    assert starts.count(killed) == 2 and sorted(set(starts)) == sorted(SCANS)
    done = [e for e in events if e["event"] == "done"]
    assert sorted(e["id"] for e in done) == sorted(SCANS)
    assert all(e["seconds"] > 0 and e["peak_rss"] > 1 << 20 for e in done)
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["scheduler"] == "local" and report["jobs"] == 2
    by_scan = {s["scan"]: s for s in report["scans"]}
    assert {k: s["attempts"] for k, s in by_scan.items()} == {
        k: 2 if k == killed else 1 for k in SCANS}
    for s in by_scan.values():
        assert s["status"] == "ok" and s["worker"].startswith("tcp://")
        assert all(st["peak_rss"] > 1 << 20 for st in s["steps"])
    # a rerun on the cluster finds everything up to date (the record was kept)
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "batch", str(manifest),
                          "--scheduler", "local", "--workers", "2"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert res.stderr.strip().splitlines()[-1] == \
        "volwarp batch: 6 scans, 0 ok, 6 skipped, 0 failed", res.stderr


def test_worker_dying_too_often_fails_that_scan_alone(tmp_path, reference):
    """An existing cluster (tcp://) allowing no worker death: the scan is failed, the rest ok."""
    import dask
    from distributed import Client, LocalCluster

    manifest = make_tree(tmp_path)
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                         dashboard_address=None, silence_logs=50) as cluster, \
            Client(cluster):
        code, events, stderr, killed = run_and_kill(
            [sys.executable, "-m", "volwarp_cli", "batch", str(manifest), "--scheduler",
             cluster.scheduler_address, "--progress", "jsonl", "--retries", "3",
             "--report-json", str(tmp_path / "r.json")], tmp_path)
    assert code == 1, stderr
    assert stderr.strip().splitlines()[-1] == (
        f"volwarp batch: 6 scans, 5 ok, 0 skipped, 1 failed: {killed} (worker died)")
    failed = [e for e in events if e["event"] == "failed"]
    assert [(e["id"], e["error"]) for e in failed] == [(killed, "worker died")]
    got = outputs(tmp_path)

    def scan_of(path):
        return path.split(".")[0].removesuffix("_sdf")

    assert {k: v for k, v in got.items() if scan_of(k) != killed} == {
        k: v for k, v in reference.items() if scan_of(k) != killed}
    # the killed scan: a step that finished before the kill (the kill lands in whichever
    # step runs) left its whole output, the reference's bytes; nothing else of it is there
    assert all(reference.get(k) == v for k, v in got.items() if scan_of(k) == killed)
    assert not leftovers(tmp_path)
    report = json.loads((tmp_path / "r.json").read_text())
    bad = next(s for s in report["scans"] if s["scan"] == killed)
    assert bad["status"] == "failed" and bad["error"] == "worker died" and bad["attempts"] == 1
    assert report["exit_code"] == 1 and report["scheduler"].startswith("tcp://")


def test_scheduler_usage_errors(tmp_path):
    manifest = make_tree(tmp_path)
    for args, message in [
        (["--scheduler", "threads"], "a batch runs its scans on"),
        (["--scheduler", "nowhere"], "unknown scheduler"),
        (["--workers", "2"], "are for --scheduler local"),
        (["--scheduler", "local", "-j", "2"], "--jobs is the local pool's"),
        (["--scheduler", "tcp://127.0.0.1:1", "--workers", "2"], "an existing cluster"),
        (["--report", "r.txt"], "a report is .html"),
    ]:
        res = subprocess.run([sys.executable, "-m", "volwarp_cli", "batch", str(manifest),
                              *args], capture_output=True, text=True, timeout=60,
                             env=dict(os.environ, DASK_SCHEDULER_ADDRESS=""))
        assert res.returncode == 2 and message in res.stderr, (args, res.stderr)
    env = {k: v for k, v in os.environ.items() if k != "DASK_SCHEDULER_ADDRESS"}
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "batch", str(manifest),
                          "--scheduler", "env"], capture_output=True, text=True, timeout=60,
                         env=env)
    assert res.returncode == 2 and "DASK_SCHEDULER_ADDRESS" in res.stderr, res.stderr
    assert not (tmp_path / "out").exists()


def test_pool_ignores_the_dask_variable_and_imports_no_dask(tmp_path):
    """The local pool is the default, whatever $DASK_SCHEDULER_ADDRESS says, and needs no dask."""
    manifest = make_tree(tmp_path)
    code = ("import sys\n"
            "from volwarp_cli.cli.main import main\n"
            f"code = main(['batch', {str(manifest)!r}, '-q', '-j', '2'])\n"
            "mods = sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed'))\n"
            "print(code, mods)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, env=dict(os.environ,
                                               DASK_SCHEDULER_ADDRESS="tcp://127.0.0.1:1"))
    assert res.stdout.strip() == "0 []", res.stdout + res.stderr
    assert res.stderr.strip() == "volwarp batch: 6 scans, 6 ok, 0 skipped, 0 failed"


def test_workers_on_one_host_share_its_cores():
    """`dask worker --nworkers 4 --nthreads 2` on a 16-core host: 8 scans at once there,
    2 threads for each scan's steps (not 8: each worker alone would think it had 16)."""
    from volwarp_cli.batch.cluster import host_threads, share_of_cores

    info = {"workers": {
        f"tcp://10.0.0.1:{4000 + i}": {"host": "10.0.0.1", "nthreads": 2} for i in range(4)}
        | {"tcp://10.0.0.2:4000": {"host": "10.0.0.2", "nthreads": 3}}}
    hosts = host_threads(info)
    assert hosts == {"10.0.0.1": 8, "10.0.0.2": 3}
    assert share_of_cores(16, "10.0.0.1", hosts, 2) == 2
    assert share_of_cores(16, "10.0.0.2", hosts, 3) == 5
    assert share_of_cores(16, "10.0.0.9", hosts, 2) == 8  # joined later: its own threads
    assert share_of_cores(2, "10.0.0.1", hosts, 2) == 1  # never below one
