"""`volwarp batch MANIFEST`: chains of steps over many scans, Make's habits, shards, reports.

Small synthetic scans (16^3), run through the real command line in a subprocess,
as shell scripts, Make and cron run it.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli import __version__
from volwarp_cli.batch.lock import BOOK_DIR
from volwarp_cli.batch.manifest import find_scans, load_manifest, shard, stem_of
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.runscope import run_scope
from volwarp_cli.volume import Volume

# relative path under scans/ -> scan id
SCANS = {"site-a/p01.nii.gz": "site-a/p01", "site-a/p02.nrrd": "site-a/p02",
         "site-b/p03.nii.gz": "site-b/p03"}

WARP_SPEC = """version: 1
units: voxel
capture: {lattice: 5, oversample: 1}
steps:
  - move:
      - {index: [2, 2, 2], by: [1.0, 0.5, 0.0]}
"""

WARP_MANIFEST = """version: 1
inputs: {glob: "scans/**/*.n*"}
output_dir: out
steps:
  - {name: warped, run: warp, spec: warp.yaml, output: "{stem}_warped.nrrd"}
  - {name: sdf, run: distance, input: warped, output: "{stem}_sdf.nrrd", options: ["--iso", 50]}
"""

CONVERT_MANIFEST = """version: 1
inputs: {glob: "scans/**/*.n*"}
output_dir: out
steps:
  - {name: conv, run: convert, output: "{stem}.nrrd"}
  - {name: sdf, run: distance, input: conv, output: "{stem}_sdf.nrrd", options: ["--iso", "50"]}
"""


def scan_volume(seed: int) -> Volume:
    n = 16
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32)
    r = np.sqrt((x - 7.5) ** 2 + (y - 7.5) ** 2 + ((z - 7.5) * 1.2) ** 2)
    data = np.clip(100 - 12 * (r - 3 - seed * 0.5), 0, 100).astype(np.int16)
    return Volume(data, spacing=(1.0, 1.0, 1.5), origin=(-8, -8, -12),
                  space="left-posterior-superior")


def make_tree(root: Path, manifest: str) -> Path:
    for seed, rel in enumerate(SCANS):
        path = root / "scans" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        write_volume(scan_volume(seed), path)
    (root / "warp.yaml").write_text(WARP_SPEC)
    (root / "manifest.yaml").write_text(manifest)
    return root / "manifest.yaml"


def volwarp(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "volwarp_cli", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def summary(res) -> str:
    lines = [line for line in res.stderr.splitlines() if line.startswith("volwarp batch:")]
    assert len(lines) == 1, res.stderr
    return lines[0]


def bookkeeping(path: Path) -> bool:
    """The batch's own files (its state and locks, in OUT/.volwarp-batch/)."""
    return BOOK_DIR in path.parts


def snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (p.stat().st_mtime_ns,
                                         hashlib.sha256(p.read_bytes()).hexdigest())
            for p in sorted(folder.rglob("*")) if p.is_file() and not bookkeeping(p)}


@pytest.fixture(scope="module")
def warped(tmp_path_factory):
    """One first run of the warp -> distance manifest on three scans."""
    root = tmp_path_factory.mktemp("batch")
    manifest = make_tree(root, WARP_MANIFEST)
    res = volwarp("batch", manifest, "-j", 2, "--report-json", root / "report.json")
    return root, res


def test_chain_outputs_mirror_folders_and_equal_hand_runs(warped, tmp_path):
    root, res = warped
    assert res.returncode == 0, res.stderr
    assert summary(res) == "volwarp batch: 3 scans, 3 ok, 0 skipped, 0 failed"
    for rel, scan_id in SCANS.items():
        assert re.search(rf"^ok {scan_id} \d+\.\d s$", res.stderr, re.M), res.stderr
        folder, stem = os.path.split(scan_id)
        assert stem == stem_of(Path(rel).name)  # p01.nii.gz -> p01, not p01.nii
        out = root / "out" / folder
        # the same commands by hand give the same bytes
        hand = tmp_path / folder
        hand.mkdir(parents=True, exist_ok=True)
        w = hand / f"{stem}_warped.nrrd"
        s = hand / f"{stem}_sdf.nrrd"
        assert volwarp("warp", root / "scans" / rel, "--spec", root / "warp.yaml",
                       "-o", w).returncode == 0
        assert volwarp("distance", w, "--iso", 50, "-o", s).returncode == 0
        assert (out / w.name).read_bytes() == w.read_bytes()
        assert (out / s.name).read_bytes() == s.read_bytes()
        meta = read_volume(out / w.name).meta
        assert meta["volwarp_input"] == Path(rel).name
        assert read_volume(out / s.name).meta["volwarp_input"] == w.name
    assert sorted(str(p.relative_to(root / "out")) for p in (root / "out").rglob("*")
                  if p.is_file() and not bookkeeping(p)) == sorted(
        f"{sid}{suffix}" for sid in SCANS.values() for suffix in ("_sdf.nrrd", "_warped.nrrd"))


def test_report_json(warped):
    root, res = warped
    report = json.loads((root / "report.json").read_text())
    assert report["volwarp_version"] == __version__
    assert report["volwarp_command"] == "batch"
    assert report["volwarp_input"] == "manifest.yaml"
    assert report["volwarp_spec_sha256"] == hashlib.sha256(
        (root / "manifest.yaml").read_bytes()).hexdigest()
    assert report["exit_code"] == 0 and report["jobs"] == 2 and report["shard"] is None
    assert report["summary"] == {"scans": 3, "ok": 3, "skipped": 0, "failed": 0, "stopped": 0,
                                 "not_started": 0, "still_arriving": 0}
    assert [s["scan"] for s in report["scans"]] == sorted(SCANS.values())
    for scan in report["scans"]:
        assert scan["status"] == "ok" and scan["error"] is None and scan["seconds"] > 0
        assert [(s["name"], s["run"], s["status"], s["attempts"], s["exit_code"])
                for s in scan["steps"]] == [("warped", "warp", "ok", 1, 0),
                                            ("sdf", "distance", "ok", 1, 0)]
        for step in scan["steps"]:
            assert step["seconds"] > 0 and step["error"] is None
            assert step["command"][:2] == ["volwarp", step["run"]]
            assert all(Path(p).is_file() for p in step["outputs"])


def test_rerun_skips_and_changes_no_byte(warped, tmp_path):
    root = tmp_path / "tree"
    shutil.copytree(warped[0], root)  # (copytree keeps modification times)
    before = snapshot(root / "out")
    res = volwarp("batch", root / "manifest.yaml")
    assert res.returncode == 0, res.stderr
    assert summary(res) == "volwarp batch: 3 scans, 0 ok, 3 skipped, 0 failed"
    assert sorted(re.findall(r"^skipped (\S+)$", res.stderr, re.M)) == sorted(SCANS.values())
    assert snapshot(root / "out") == before


@pytest.mark.parametrize("option", ["--report", "--report-json"])
def test_a_report_over_the_batch_s_own_state_is_refused(warped, tmp_path, option):
    """--report OUT/.volwarp-batch/state.json replaced the state with the report (exit 0), and
    the next run redid every scan."""
    root = tmp_path / "tree"
    shutil.copytree(warped[0], root)
    state = root / "out" / ".volwarp-batch" / "state.json"
    before = state.read_bytes()
    res = volwarp("batch", root / "manifest.yaml", option, state)
    assert res.returncode == 2 and "inside the batch's own records" in res.stderr, res.stderr
    assert state.read_bytes() == before
    res = volwarp("batch", root / "manifest.yaml")
    assert summary(res) == "volwarp batch: 3 scans, 0 ok, 3 skipped, 0 failed"


def test_changed_spec_or_force_redoes(warped, tmp_path):
    root = tmp_path / "tree"
    shutil.copytree(warped[0], root)
    # a changed spec: every scan's warp, and the distance that reads it, run again
    spec = root / "warp.yaml"
    spec.write_text(WARP_SPEC.replace("[1.0, 0.5, 0.0]", "[1.5, 0.5, 0.0]"))
    res = volwarp("batch", root / "manifest.yaml", "--report-json", root / "r.json")
    assert res.returncode == 0, res.stderr
    assert summary(res) == "volwarp batch: 3 scans, 3 ok, 0 skipped, 0 failed"
    sha = hashlib.sha256(spec.read_bytes()).hexdigest()
    for scan_id in SCANS.values():
        assert read_volume(root / "out" / f"{scan_id}_warped.nrrd").meta[
            "volwarp_spec_sha256"] == sha
    steps = [s for scan in json.loads((root / "r.json").read_text())["scans"]
             for s in scan["steps"]]
    assert {s["status"] for s in steps} == {"ok"}
    # a touched spec (same bytes, newer): up to date (the content decides, not the date)
    assert volwarp("batch", root / "manifest.yaml").returncode == 0
    future = time.time() + 5
    os.utime(spec, (future, future))
    res = volwarp("batch", root / "manifest.yaml")
    assert summary(res) == "volwarp batch: 3 scans, 0 ok, 3 skipped, 0 failed", res.stderr
    # --force redoes what is up to date, with the same bytes
    before = {k: v[1] for k, v in snapshot(root / "out").items()}
    res = volwarp("batch", root / "manifest.yaml", "--force")
    assert summary(res) == "volwarp batch: 3 scans, 3 ok, 0 skipped, 0 failed", res.stderr
    assert {k: v[1] for k, v in snapshot(root / "out").items()} == before


def test_output_with_other_provenance_is_redone(warped, tmp_path):
    root = tmp_path / "tree"
    shutil.copytree(warped[0], root)
    # a newer output made from another spec: its times say "up to date", its provenance not
    victim = root / "out" / "site-b" / "p03_warped.nrrd"
    with run_scope():  # (read here, written in another scope: no output over an input)
        vol = read_volume(victim)
    write_volume(vol.with_data(vol.data, meta={**vol.meta, "volwarp_spec_sha256": "0" * 64}),
                 victim)
    res = volwarp("batch", root / "manifest.yaml")
    assert summary(res) == "volwarp batch: 3 scans, 1 ok, 2 skipped, 0 failed", res.stderr
    assert re.search(r"^ok site-b/p03 ", res.stderr, re.M)
    assert victim.read_bytes() == (warped[0] / "out" / "site-b" / "p03_warped.nrrd").read_bytes()


def truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:-400])


def test_bad_scan_fails_alone(tmp_path):
    manifest = make_tree(tmp_path, CONVERT_MANIFEST)
    truncate(tmp_path / "scans" / "site-a" / "p01.nii.gz")
    res = volwarp("batch", manifest, "-j", 2, "--report-json", tmp_path / "r.json")
    assert res.returncode == 1, res.stderr
    line = summary(res)
    assert line.startswith("volwarp batch: 3 scans, 2 ok, 0 skipped, 1 failed: site-a/p01 (")
    assert "cannot read NIfTI data" in line and "/" not in line.split("(", 1)[1][:20]
    assert re.search(r"^failed site-a/p01 \d+\.\d s: cannot read NIfTI data", res.stderr, re.M)
    for scan_id in ("site-a/p02", "site-b/p03"):
        assert (tmp_path / "out" / f"{scan_id}_sdf.nrrd").is_file()
    assert not (tmp_path / "out" / "site-a" / "p01.nrrd").exists()
    assert not [p for p in (tmp_path / "out").rglob(".*")
                if not bookkeeping(p)]  # no temporary left
    report = json.loads((tmp_path / "r.json").read_text())
    bad = next(s for s in report["scans"] if s["scan"] == "site-a/p01")
    assert bad["status"] == "failed" and bad["error"].startswith("volwarp: error: ")
    assert [(s["status"], s["exit_code"], s["attempts"]) for s in bad["steps"]] == [
        ("failed", 1, 1), ("not run", None, 0)]
    assert report["exit_code"] == 1
    # --fail-fast: one worker, the bad scan first: no other scan starts
    shutil.rmtree(tmp_path / "out")
    res = volwarp("batch", manifest, "-j", 1, "--fail-fast", "--retries", 3)
    assert res.returncode == 1, res.stderr
    assert summary(res).startswith(
        "volwarp batch: 3 scans, 0 ok, 0 skipped, 1 failed, 2 not started: site-a/p01 (")
    assert not any(p.is_file() and not bookkeeping(p) for p in (tmp_path / "out").rglob("*"))


def test_shards_cover_every_scan_once(tmp_path):
    manifest = make_tree(tmp_path, CONVERT_MANIFEST)
    for rel in ("site-c/p04.nrrd", "p05.nrrd", "site-a/deeper/p06.nii.gz"):
        (tmp_path / "scans" / rel).parent.mkdir(parents=True, exist_ok=True)
        write_volume(scan_volume(1), tmp_path / "scans" / rel)
    everything = [s.id for s in find_scans(load_manifest(manifest))]
    assert everything == sorted(everything) and len(everything) == 6
    assert "site-a/deeper/p06" in everything and "p05" in everything
    for n in range(1, 8):
        parts = [[s.id for s in shard(find_scans(load_manifest(manifest)), i, n)]
                 for i in range(n)]
        flat = [x for p in parts for x in p]
        assert sorted(flat) == everything and len(flat) == len(set(flat))
        assert max(map(len, parts)) - min(map(len, parts)) <= 1
    # through the command line: two shards, each doing its own scans
    done = []
    for i in range(2):
        res = volwarp("batch", manifest, "--shard", f"{i}/2", "--report-json",
                      tmp_path / f"r{i}.json")
        assert res.returncode == 0, res.stderr
        assert summary(res).startswith(f"volwarp batch: 3 scans (shard {i}/2 of 6), 3 ok")
        done += [s["scan"] for s in json.loads((tmp_path / f"r{i}.json").read_text())["scans"]]
    assert sorted(done) == everything
    for bad in ("2/2", "-1/2", "1", "a/b"):
        res = volwarp("batch", manifest, "--shard", bad)
        assert res.returncode == 2 and "--shard" in res.stderr, (bad, res.stderr)


MALFORMED = {
    "unknown input step": (
        CONVERT_MANIFEST.replace("input: conv", "input: converted"),
        r"manifest\.yaml:6: steps\[1\]\.input: unknown step 'converted'"),
    "later input step": (
        CONVERT_MANIFEST.replace("input: conv", "input: sdf"),
        r"manifest\.yaml:6: steps\[1\]\.input: step 'sdf' comes later|"
        r"manifest\.yaml:6: steps\[1\]\.input: unknown step 'sdf'"),
    "unknown subcommand": (
        CONVERT_MANIFEST.replace("run: distance", "run: sharpen"),
        r"manifest\.yaml:6: steps\[1\]\.run: 'sharpen' is not one of"),
    "missing output": (
        CONVERT_MANIFEST.replace(', output: "{stem}_sdf.nrrd"', ""),
        r"manifest\.yaml:6: steps\[1\]: 'output' is required"),
    "unknown placeholder": (
        CONVERT_MANIFEST.replace("{stem}_sdf", "{name}_sdf"),
        r"manifest\.yaml:6: steps\[1\]\.output: bad pattern"),
    "reserved option": (
        CONVERT_MANIFEST.replace('"--iso", "50"', '"-o", "x.nrrd"'),
        r"manifest\.yaml:6: steps\[1\]\.options\[0\]: -o is set by the step's output key"),
    "warp without spec": (
        CONVERT_MANIFEST.replace("run: convert", "run: warp"),
        r"manifest\.yaml:5: steps\[0\]: a warp step needs 'spec'"),
    "mesh read by a step": (
        CONVERT_MANIFEST.replace('run: convert, output: "{stem}.nrrd"',
                                 'run: mesh, output: "{stem}.ply"'),
        r"manifest\.yaml:6: steps\[1\]\.input: step 'conv' writes a mesh"),
    "unknown key": (
        CONVERT_MANIFEST.replace("output_dir: out", "output_dir: out\njobs: 4"),
        r"manifest\.yaml:4: jobs: unknown key 'jobs'"),
    # found by a review: each of these ran, and lost or mixed up data
    "an output that is a scan": (
        "version: 1\ninputs: {list: [scans/site-a/p02.nrrd], root: scans}\noutput_dir: scans\n"
        "steps:\n  - {name: conv, run: convert, output: \"{stem}.nrrd\", "
        "options: [\"--dtype\", \"uint8\"]}\n",
        r"manifest\.yaml:5: steps\[0\]\.output: scan site-a/p02: -o .*p02\.nrrd would "
        r"overwrite the input .*p02\.nrrd; volwarp never replaces an input"),
    "two steps, one output": (
        CONVERT_MANIFEST.replace('output: "{stem}_sdf.nrrd"', 'output: "{stem}.nrrd"'),
        r"manifest\.yaml:6: steps\[1\]\.output: .* also written by step 'conv'"),
    "an output option in the = form": (
        CONVERT_MANIFEST.replace('options: ["--iso", "50"]}',
                                 'options: ["--iso", "50"]}\n  - {name: m, run: mesh, input: conv, '
                                 'output: "{stem}.ply", options: ["--iso=50", "--render={stem}.png"]}'),
        r"manifest\.yaml:7: steps\[2\]\.options\[1\]: write --render and its output name as "
        "two items"),
}


@pytest.mark.parametrize("case", MALFORMED)
def test_malformed_manifest_is_a_spec_error_before_any_work(tmp_path, case):
    text, message = MALFORMED[case]
    manifest = make_tree(tmp_path, text)
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    assert re.search(message, res.stderr), res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_two_scans_sharing_outputs_are_refused(tmp_path):
    manifest = make_tree(tmp_path, CONVERT_MANIFEST)
    write_volume(scan_volume(0), tmp_path / "scans" / "site-a" / "p02.nii.gz")
    res = volwarp("batch", manifest)
    assert res.returncode == 2
    assert "would share outputs (both are scan 'site-a/p02')" in res.stderr


@pytest.mark.parametrize("how", ["list", "csv"])
def test_a_scan_reached_by_dotdot_is_outside_the_root_too(tmp_path, how):
    """'../x' under output_dir is outside it: a listed scan spelled so put its outputs beside
    the output folder and replaced a file there (exit 0, before); an absolute path to the
    same file was refused. Both are now."""
    make_tree(tmp_path, CONVERT_MANIFEST)
    steps = CONVERT_MANIFEST.split("steps:", 1)[1]
    keep = tmp_path / "proj" / "scans" / "site-a" / "p02_sdf.nrrd"  # out/../scans/site-a/
    keep.parent.mkdir(parents=True)
    keep.write_bytes(b"my notes")
    if how == "list":
        inputs = "{list: [../scans/site-a/p02.nrrd]}"
    else:
        (tmp_path / "proj" / "t.csv").write_text("path\n../scans/site-a/p02.nrrd\n")
        inputs = "{csv: t.csv}"
    manifest = tmp_path / "proj" / "m.yaml"
    manifest.write_text(f"version: 1\ninputs: {inputs}\noutput_dir: out\nsteps:{steps}")
    res = volwarp("batch", manifest)
    assert res.returncode == 2, res.stderr
    assert "is not under the inputs' root" in res.stderr
    assert keep.read_bytes() == b"my notes"
    assert not (tmp_path / "proj" / "out").exists()


def test_list_and_csv_inputs(tmp_path):
    make_tree(tmp_path, CONVERT_MANIFEST)
    steps = CONVERT_MANIFEST.split("steps:", 1)[1]
    (tmp_path / "list.yaml").write_text(
        "version: 1\ninputs: {list: [scans/site-b/p03.nii.gz, scans/site-a/p02.nrrd]}\n"
        "output_dir: out_list\nsteps:" + steps.replace('"{stem}.nrrd"', '"{relpath}/c_{stem}.nrrd"'))
    res = volwarp("batch", tmp_path / "list.yaml")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "out_list" / "scans" / "site-b" / "c_p03.nrrd").is_file()
    assert (tmp_path / "out_list" / "scans" / "site-a" / "p02_sdf.nrrd").is_file()
    (tmp_path / "scans" / "table.csv").write_text("id,file\n1,site-a/p02.nrrd\n2,\n")
    (tmp_path / "csv.yaml").write_text(
        "version: 1\ninputs: {csv: scans/table.csv, column: scan}\noutput_dir: out_csv\nsteps:"
        + steps)
    res = volwarp("batch", tmp_path / "csv.yaml")
    assert res.returncode == 2 and "csv.yaml:2: inputs.column: table.csv has no column 'scan'" \
        in res.stderr, res.stderr
    (tmp_path / "csv.yaml").write_text((tmp_path / "csv.yaml").read_text().replace("scan}",
                                                                                 "file}"))
    res = volwarp("batch", tmp_path / "csv.yaml")
    assert res.returncode == 2 and "table.csv:3: file: empty cell" in res.stderr, res.stderr
    (tmp_path / "scans" / "table.csv").write_text("id,file\n1,site-a/p02.nrrd\n")
    res = volwarp("batch", tmp_path / "csv.yaml")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "out_csv" / "site-a" / "p02_sdf.nrrd").is_file()


def test_retries_only_for_a_dead_worker(tmp_path, monkeypatch):
    from volwarp_cli.batch.run import Batch, ScanRunner

    manifest = load_manifest(make_tree(tmp_path, CONVERT_MANIFEST))
    scans = find_scans(manifest)[:1]
    calls = []

    def fake(codes):
        def call(self, argv):
            calls.append(argv[0])
            code = codes.pop(0)
            if code == 0:
                for out in (Path(argv[argv.index("-o") + 1]),):
                    write_volume(scan_volume(0), out)
            return (code, "volwarp: error: x: went wrong\n" if code > 0 else "", 1 << 20, {})
        return call

    monkeypatch.setattr(ScanRunner, "_call", fake([-signal.SIGKILL, -signal.SIGSEGV, 0, 0]))
    (result,), stop = Batch(manifest, scans, jobs=1, retries=2).run()
    assert stop is None and result.status == "ok"
    assert [s.attempts for s in result.steps] == [3, 1] and calls == ["convert"] * 3 + [
        "distance"]
    calls.clear()
    monkeypatch.setattr(ScanRunner, "_call", fake([-signal.SIGKILL, -signal.SIGKILL]))
    (result,), _ = Batch(manifest, scans, jobs=1, retries=1, force=True).run()
    assert result.status == "failed" and result.steps[0].error == "killed by SIGKILL"
    assert result.steps[0].attempts == 2
    monkeypatch.setattr(ScanRunner, "_call", fake([1]))
    (result,), _ = Batch(manifest, scans, jobs=1, retries=5, force=True).run()
    assert result.status == "failed" and result.steps[0].attempts == 1
    assert result.error == "volwarp: error: x: went wrong"


def test_sigterm_stops_the_batch(tmp_path):
    manifest = make_tree(tmp_path, WARP_MANIFEST)
    with subprocess.Popen([sys.executable, "-m", "volwarp_cli", "batch", str(manifest),
                           "-j", "1", "--report-json", str(tmp_path / "r.json")],
                          stderr=subprocess.PIPE, text=True) as proc:  # (closes the pipe)
        try:
            first = proc.stderr.readline()  # the first scan done; the second is running
            assert first.startswith("ok site-a/p01"), first
            time.sleep(0.3)
            proc.send_signal(signal.SIGTERM)
            rest = proc.stderr.read()
            code = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert code == 143, rest
    line = [x for x in rest.splitlines() if x.startswith("volwarp batch:")]
    assert line and line[0].startswith("volwarp batch: stopped by SIGTERM with "), rest
    assert "1 stopped" in line[0] or "1 not started" in line[0] or "2 ok" in line[0]
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["stopped_by"] == "SIGTERM" and report["exit_code"] == 143
    assert report["scans"][0]["status"] == "ok"
    assert not [p for p in (tmp_path / "out").rglob(".*")
                if not bookkeeping(p)]  # no temporary left
    # a rerun finishes the job, skipping what was done
    res = volwarp("batch", manifest)
    assert res.returncode == 0
    assert re.search(r"^skipped site-a/p01$", res.stderr, re.M)


def test_changed_options_redo_the_step(warped, tmp_path):
    """Outputs looked up to date after the manifest's options changed (--iso 50 -> 60):
    times and provenance do not show options; the batch's record of each output's
    command does."""
    root = tmp_path / "tree"
    shutil.copytree(warped[0], root)  # moved: still up to date (the record is relative)
    res = volwarp("batch", root / "manifest.yaml")
    assert summary(res) == "volwarp batch: 3 scans, 0 ok, 3 skipped, 0 failed", res.stderr
    manifest = root / "manifest.yaml"
    manifest.write_text(manifest.read_text().replace('["--iso", 50]', '["--iso", 60]'))
    res = volwarp("batch", manifest)
    assert summary(res) == "volwarp batch: 3 scans, 3 ok, 0 skipped, 0 failed", res.stderr
    for scan_id in SCANS.values():  # the distance step reran; the warp was up to date
        sdf = read_volume(root / "out" / f"{scan_id}_sdf.nrrd")
        hand = tmp_path / "hand.nrrd"
        assert volwarp("distance", root / "out" / f"{scan_id}_warped.nrrd", "--iso", 60, "-o",
                       hand).returncode == 0
        assert (root / "out" / f"{scan_id}_sdf.nrrd").read_bytes() != b"" and np.array_equal(
            sdf.data, read_volume(hand).data)


@settings(max_examples=200, deadline=None)
@given(count=st.integers(min_value=0, max_value=60), n=st.integers(min_value=1, max_value=20))
def test_shards_are_a_partition(count, n):
    """Over I = 0..N-1 the shards hold every scan exactly once, in even sizes, in order."""
    from volwarp_cli.batch.manifest import Scan

    scans = [Scan(id=f"s{k:03d}", path=Path(f"s{k:03d}.nrrd"), stem=f"s{k:03d}", relpath="")
             for k in range(count)]
    parts = [shard(scans, i, n) for i in range(n)]
    flat = [s.id for p in parts for s in p]
    assert sorted(flat) == [s.id for s in scans] and len(flat) == len(set(flat))
    assert max(map(len, parts)) - min(map(len, parts)) <= 1
    assert all([s.id for s in p] == sorted(s.id for s in p) for p in parts)


def test_a_number_option_is_passed_with_every_digit_and_a_change_redoes(tmp_path):
    """``--iso 50.12344`` ran as 50.1234 ({:g}), and an edit from 50.12341 was taken for no
    change: the step skipped, its mesh stale (batch hunt)."""
    scan = tmp_path / "scans" / "a.nrrd"
    scan.parent.mkdir()
    write_volume(scan_volume(0).with_data(scan_volume(0).data.astype(np.float32) + 0.1234), scan)
    manifest = tmp_path / "m.yaml"
    text = ('version: 1\ninputs: {glob: "scans/*.nrrd"}\noutput_dir: out\nsteps:\n'
            '  - {name: s, run: mesh, output: "{stem}.ply", options: ["--iso", ISO]}\n')
    for iso in ("50.12341", "50.12344", "3.0"):
        manifest.write_text(text.replace("ISO", iso))
        res = volwarp("batch", manifest, "--report", tmp_path / "r.json")
        assert res.returncode == 0, res.stderr
        assert "1 ok" in summary(res), res.stderr  # (done again each time: not skipped)
        command = json.loads((tmp_path / "r.json").read_text())["scans"][0]["steps"][0]
        argv = command.get("command") or command.get("argv")
        assert argv[argv.index("--iso") + 1] == ("3" if iso == "3.0" else iso)
        alone = tmp_path / f"alone_{iso}.ply"
        assert volwarp("mesh", scan, "--iso", iso, "-o", alone, "-q").returncode == 0
        assert (tmp_path / "out" / "a.ply").read_bytes()[-2000:] == alone.read_bytes()[-2000:]


def test_a_scan_whose_stem_leads_out_of_output_dir_is_refused(tmp_path):
    """A scan named ``...nrrd`` has stem ``..``: ``{stem}/conv.nrrd`` wrote ``conv.nrrd``
    beside the manifest, outside the folder the batch locks."""
    (tmp_path / "scans").mkdir()
    write_volume(scan_volume(0), tmp_path / "scans" / "...nrrd")
    write_volume(scan_volume(1), tmp_path / "scans" / "b.nrrd")
    manifest = tmp_path / "m.yaml"
    manifest.write_text('version: 1\ninputs: {list: [scans/...nrrd, scans/b.nrrd], root: scans}\n'
                        'output_dir: out\nsteps:\n'
                        '  - {name: conv, run: convert, output: "{stem}/conv.nrrd"}\n')
    res = volwarp("batch", manifest)
    assert res.returncode == 2 and "which leaves output_dir" in res.stderr
    assert not list(tmp_path.rglob("conv.nrrd"))
