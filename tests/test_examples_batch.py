"""examples/batch: the cron-style reprocessing of a scan folder.

One pipeline run per module (it takes a few seconds): the tests then check
what users of a nightly job rely on: a summary line and exit status, no work
and no changed file on a second run, a corrupt scan failing alone, the lock,
and provenance in every output.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from volwarp_cli.io import read_volume

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SCANS = ["patient01", "patient02", "site-b/patient03"]

pytestmark = pytest.mark.examples


def batch(folder: Path, *args: str, env_extra=None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}",
               **(env_extra or {}))
    return subprocess.run(["bash", str(folder / "volwarp-batch.sh"), "-C", str(folder),
                           f"VOLWARP={BIN / 'volwarp'}", f"PYTHON={sys.executable}", *args],
                          capture_output=True, text=True, timeout=400, env=env)


def snapshot(folder: Path) -> dict[str, tuple[int, bytes]]:
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns, hashlib.sha256(p.read_bytes())
                                         .digest())
            for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    if shutil.which("make") is None or shutil.which("flock") is None:
        pytest.fail("make and flock are needed (the README's install provides them)")
    work = tmp_path_factory.mktemp("batch") / "batch"
    shutil.copytree(ROOT / "examples" / "batch", work,
                    ignore=shutil.ignore_patterns("scans", "processed", "logs", ".batch.lock"))
    res = batch(work)
    return work, res


def test_first_run_processes_every_scan(first_run):
    work, res = first_run
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip() == "volwarp-batch: 3 scans, 3 ok, 0 failed"
    for name in SCANS:
        for ext in ("nrrd", "ply", "png"):
            assert (work / "processed" / f"{name}.{ext}").is_file(), (name, ext)
    log = (work / "logs" / "batch.log").read_text()
    assert "volwarp warp" in log and "3 scans, 3 ok" in log


def test_outputs_carry_provenance(first_run):
    work, _ = first_run
    spec_sha = hashlib.sha256((work / "batch-warp.yaml").read_bytes()).hexdigest()
    from volwarp_cli import __version__

    for name in SCANS:
        meta = read_volume(work / "processed" / f"{name}.nrrd").meta
        assert meta["volwarp_version"] == __version__
        assert meta["volwarp_spec_sha256"] == spec_sha
        assert meta["volwarp_input"] == Path(name).name + ".nrrd"
        assert meta["volwarp_command"] == "warp"
        head = (work / "processed" / f"{name}.ply").read_bytes()[:1000]
        assert f"volwarp_input={Path(name).name}.nrrd".encode() in head


def test_second_run_does_nothing(first_run):
    work, _ = first_run
    before = snapshot(work / "processed")
    res = batch(work)
    assert res.returncode == 0
    assert "volwarp warp" not in res.stderr and "volwarp mesh" not in res.stderr
    assert snapshot(work / "processed") == before


def test_rebuild_from_scratch_gives_identical_bytes(first_run, tmp_path):
    work, _ = first_run
    again = tmp_path / "batch"
    shutil.copytree(work, again, ignore=shutil.ignore_patterns("processed", "logs"))
    assert batch(again).returncode == 0
    for name in SCANS:
        for ext in ("nrrd", "ply", "png"):
            a = (work / "processed" / f"{name}.{ext}").read_bytes()
            b = (again / "processed" / f"{name}.{ext}").read_bytes()
            assert a == b, f"{name}.{ext} differs between two runs"


def test_lock_prevents_overlapping_runs(first_run):
    work, _ = first_run
    before = snapshot(work / "processed")
    with open(work / ".batch.lock", "w") as fh:
        holder = subprocess.Popen(["flock", "-x", str(work / ".batch.lock"), "sleep", "30"])
        try:
            # wait until the holder has the lock
            for _ in range(100):
                probe = subprocess.run(["flock", "-n", str(work / ".batch.lock"), "true"])
                if probe.returncode != 0:
                    break
                subprocess.run(["sleep", "0.05"])
            res = batch(work)
        finally:
            holder.kill()
            holder.wait()
    del fh
    assert res.returncode == 75
    assert "another run holds" in res.stderr
    assert snapshot(work / "processed") == before


def test_corrupt_scan_fails_alone(first_run, tmp_path):
    work, _ = first_run
    bad = tmp_path / "batch"
    shutil.copytree(work, bad)
    victim = bad / "scans" / "patient02.nrrd"
    victim.write_bytes(victim.read_bytes()[:-500])  # truncated
    others = {n: (bad / "processed" / f"{n}.nrrd").read_bytes() for n in SCANS
              if n != "patient02"}
    old_output = (bad / "processed" / "patient02.nrrd").read_bytes()
    # a new scan next to the bad one must still be processed
    shutil.copy(bad / "scans" / "patient01.nrrd", bad / "scans" / "patient04.nrrd")
    res = batch(bad)
    assert res.returncode == 1
    assert res.stdout.strip() == "volwarp-batch: 4 scans, 3 ok, 1 failed: patient02"
    assert "truncated" in res.stderr
    for n, data in others.items():
        assert (bad / "processed" / f"{n}.nrrd").read_bytes() == data
    assert (bad / "processed" / "patient04.ply").is_file()
    # the failed scan's earlier output is left as it was, and no temporary file remains
    assert (bad / "processed" / "patient02.nrrd").read_bytes() == old_output
    leftovers = [p.name for p in (bad / "processed").rglob("*") if ".tmp" in p.name
                 or p.name.startswith(".")]
    assert leftovers == []


def test_slurm_script_and_readme_use_real_options():
    """Every option the SLURM script, the cron line and the README give `volwarp batch` exists."""
    import re

    folder = Path(__file__).parent.parent / "examples" / "batch"
    text = (folder / "volwarp-batch.slurm").read_text() + (folder / "README.md").read_text()
    lines = [line for line in text.replace("\\\n", " ").splitlines() if " batch " in line
             and ("volwarp" in line or "VOLWARP" in line)]
    used = {opt for line in lines for opt in re.findall(r"(?<![\w-])(--[a-z][a-z-]+|-[jq])\b",
                                                        line.split(" batch ", 1)[1])}
    assert {"--shard", "--retries", "--report", "--scheduler", "--progress"} <= used
    help_text = subprocess.run([sys.executable, "-m", "volwarp_cli", "batch", "--help"],
                               capture_output=True, text=True, timeout=60).stdout
    for opt in used:
        assert re.search(rf"(?<![\w-]){re.escape(opt)}\b", help_text), opt


def test_a_detached_headers_new_data_file_is_a_changed_scan(tmp_path):
    """The Makefile's rule depended on a `.nhdr` alone: a new `p1.raw` under it (newer
    date) left the old output, `make` said nothing to do and `make status` said ok."""
    import numpy as np

    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    work = tmp_path / "batch"
    shutil.copytree(ROOT / "examples" / "batch", work,
                    ignore=shutil.ignore_patterns("scans", "processed", "logs", ".batch.lock"))
    (work / "mine").mkdir()
    z, y, x = np.mgrid[:64, :64, :64].astype(np.float32)  # (the spec's handles: mm about 0)
    ball = 100.0 * (np.sqrt((x - 32) ** 2 + (y - 32) ** 2 + (z - 32) ** 2) < 24)
    write_volume(Volume(ball.astype(np.float32), origin=(-32.0, -32.0, -32.0)),
                 work / "mine" / "p1.nhdr")
    make = ["make", "-C", str(work), "IN=mine", "OUT=out", f"VOLWARP={BIN / 'volwarp'}",
            f"PYTHON={sys.executable}", "ISO=50"]
    res = subprocess.run(make, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    before = read_volume(work / "out" / "p1.nrrd").data
    assert subprocess.run([*make, "-q", "pipeline"], capture_output=True).returncode == 0
    for p in work.rglob("*"):  # (the first run's files 10 s older: no clock skew)
        t = p.stat().st_mtime_ns - 10_000_000_000
        os.utime(p, ns=(t, t))
    raw = work / "mine" / "p1.raw"
    raw.write_bytes(np.roll(ball, 5, axis=2).astype(np.float32).tobytes())
    assert subprocess.run([*make, "-q", "pipeline"], capture_output=True).returncode == 1
    assert subprocess.run(make, capture_output=True, timeout=300).returncode == 0
    assert not np.array_equal(read_volume(work / "out" / "p1.nrrd").data, before)
    assert subprocess.run([*make, "-q", "pipeline"], capture_output=True).returncode == 0
