"""`volwarp warp --chunked`: by output blocks on Dask, the same bytes as in memory.

Inputs with odd sizes and a direction that is not the identity, blocks that do not
divide the output, every local scheduler and a LocalCluster; the automatic switch
when the in-memory warp does not fit the budget; what the block path refuses.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

SPEC = """version: 1
capture: {lattice: 6, oversample: 1.5}
steps:
  - move:
      - {index: [2, 3, 2], by: [3, -2, 4]}
      - {index: [3, 2, 3], by: [-2, 1.5, -3]}
      - {index: [1, 4, 2], by: [0.5, 2.5, 1]}
"""

ROTATED = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture
def scan(tmp_path):
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (37, 41, 29)], indexing="ij")
    rng = np.random.default_rng(2)
    data = (1000 * np.exp(-(x * x + y * y + z * z) / 0.3) + rng.integers(0, 40, x.shape))
    vol = Volume(data.astype(np.int16), spacing=np.array([0.8, 0.9, 1.1]),
                 origin=np.array([10.0, -5.0, 3.0]), direction=ROTATED)
    path = tmp_path / "in.nrrd"
    write_volume(vol, path)
    spec = tmp_path / "warp.yaml"
    spec.write_text(SPEC)
    return path, spec


def test_chunked_nrrd_equals_the_in_memory_file(run, scan, tmp_path):
    src, spec = scan
    mem, blk = tmp_path / "mem.nrrd", tmp_path / "blk.nrrd"
    assert run("warp", src, "--spec", spec, "-o", mem).code == 0
    res = run("warp", src, "--spec", spec, "-o", blk, "--chunked", "--block", "10,7,13",
              "--json")
    assert res.code == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["blocks"] > 50 and summary["block"] == [13, 7, 10]
    assert blk.read_bytes() == mem.read_bytes()
    out = read_volume(blk)
    assert np.array_equal(out.direction, ROTATED)  # the geometry is the input's


@pytest.mark.parametrize("scheduler", ["threads", "processes", "synchronous"])
def test_chunked_ome_zarr_is_the_same_on_every_scheduler(run, scan, tmp_path, scheduler):
    src, spec = scan
    zin = tmp_path / "in.ome.zarr"
    assert run("convert", src, "-o", zin).code == 0
    mem = tmp_path / "mem.nrrd"
    assert run("warp", zin, "--spec", spec, "-o", mem).code == 0
    blk = tmp_path / "blk.ome.zarr"
    res = run("warp", zin, "--spec", spec, "-o", blk, "--chunked", "--block", "16",
              "--scheduler", scheduler)
    assert res.code == 0, res.stderr
    a, b = read_volume(mem), read_volume(blk)
    assert np.array_equal(a.data, b.data) and a.data.dtype == b.data.dtype
    assert np.allclose(a.origin, b.origin) and np.allclose(a.spacing, b.spacing)


def _tree(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("version", ["0.5", "0.4"])
def test_chunked_ome_zarr_is_the_in_memory_store_whatever_the_threads(run, scan, tmp_path,
                                                                      version):
    """A store of one shard (or of chunks larger than the blocks) cut into blocks for the
    threads: its files were laid out by the blocks, so they changed with --threads (the
    same samples, other bytes). The blocks are staged in a scratch file and the store is
    written in its in-memory layout on commit: the same files, on a rotated grid too
    (stored reindexed to the identity direction), with a pyramid."""
    src, spec = scan
    common = ["--spec", spec, "--ome-zarr-version", version, "--pyramid", "1"]
    mem = tmp_path / "mem.ome.zarr"
    assert run("warp", src, *common, "-o", mem).code == 0
    for args in (["--threads", "2"], ["--threads", "1"], ["--block", "5,7,3"],
                 ["--scheduler", "processes", "--threads", "2"]):
        blk = tmp_path / f"blk{len(args)}{args[-1]}.ome.zarr"
        res = run("warp", src, *common, "-o", blk, "--chunked", *args, "--json")
        assert res.code == 0, res.stderr
        assert json.loads(res.stdout)["blocks"] > 1
        assert _tree(blk) == _tree(mem), args
    assert not [p for p in tmp_path.iterdir() if ".vw-" in p.name]


def test_chunked_on_a_local_cluster_with_jsonl_progress(run, scan, tmp_path):
    """A LocalCluster's run, while port 8787 is taken (another run's cluster at the same
    time): no "Port 8787 is already in use" warning (here an error), the same bytes."""
    import socket

    src, spec = scan
    mem, blk = tmp_path / "mem.nrrd", tmp_path / "blk.nrrd"
    assert run("warp", src, "--spec", spec, "-o", mem).code == 0
    with socket.socket() as taken:
        taken.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            taken.bind(("127.0.0.1", 8787))
            taken.listen()
        except OSError:  # (taken already)
            pass
        res = run("warp", src, "--spec", spec, "-o", blk, "--chunked", "--block", "24",
                  "--scheduler", "local", "--workers", "2", "--progress", "jsonl")
    assert res.code == 0, res.stderr
    assert blk.read_bytes() == mem.read_bytes()
    events = [json.loads(line) for line in res.stderr.splitlines() if line.startswith("{")]
    done = [e for e in events if e["event"] == "done"]
    assert done and all(e["kind"] == "block" and e["seconds"] >= 0 and e["peak_rss"] > 0
                        for e in done)
    assert len({e["id"] for e in done}) == len(done)  # one line per block


def test_a_warp_too_big_for_the_budget_runs_by_blocks(run, scan, tmp_path, monkeypatch):
    """No --chunked: the in-memory warp's own refusal switches to blocks, with one warning."""
    from volwarp_cli import memory

    src, spec = scan
    mem, blk = tmp_path / "mem.nrrd", tmp_path / "blk.nrrd"
    assert run("warp", src, "--spec", spec, "-o", mem).code == 0

    monkeypatch.setattr(memory, "process_rss", lambda: 0)
    monkeypatch.setattr("volwarp_cli.execute.MIN_BLOCK_BUDGET", 64 << 10)
    res = run("warp", src, "--spec", spec, "-o", blk, "--memory-limit", "150K")
    assert res.code == 0, res.stderr
    assert "running by blocks" in res.stderr
    assert blk.read_bytes() == mem.read_bytes()
    # --no-chunked: the refusal stands, the old output untouched
    blk.write_bytes(b"old")
    res = run("warp", src, "--spec", spec, "-o", blk, "--memory-limit", "150K",
              "--no-chunked")
    assert res.code == 1 and "needs" in res.stderr and blk.read_bytes() == b"old"


def test_a_budget_the_process_itself_fills_is_refused(run, scan, tmp_path):
    """A limit the interpreter already fills leaves no room for blocks: the in-memory
    refusal stands (no fallback that would crawl in tiny blocks); --chunked says why."""
    src, spec = scan
    out = tmp_path / "o.nrrd"
    res = run("warp", src, "--spec", spec, "-o", out, "--memory-limit", "40M")
    assert res.code == 1 and "needs" in res.stderr and "running by blocks" not in res.stderr
    res = run("warp", src, "--spec", spec, "-o", out, "--memory-limit", "40M", "--chunked")
    assert res.code == 1 and "memory limit" in res.stderr and "\n" not in res.stderr.strip()
    assert not out.exists()


def test_what_the_block_path_refuses(run, scan, tmp_path):
    src, spec = scan
    out = tmp_path / "o.nrrd"
    res = run("warp", src, "--spec", spec, "-o", out, "--chunked", "--frames-to",
              str(tmp_path / "f_{frame}.nrrd"))
    assert res.code == 2 and "--frames-to" in res.stderr
    gz = tmp_path / "o.nii.gz"
    res = run("warp", src, "--spec", spec, "-o", gz, "--chunked")
    assert res.code == 2 and "block" in res.stderr and not gz.exists()  # (usage)
    res = run("warp", src, "--spec", spec, "-o", out, "--chunked", "--block", "0")
    assert res.code == 2
    res = run("warp", src, "--spec", spec, "-o", out, "--chunked", "--scheduler", "nope")
    assert res.code == 2 and "unknown scheduler" in res.stderr
    assert not out.exists()


def test_a_failing_block_leaves_no_output(run, scan, tmp_path, monkeypatch):
    """A block task that fails (a worker's error): one line, exit 1, nothing at -o."""
    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.warp import blocks

    src, spec = scan
    out = tmp_path / "o.nrrd"
    out.write_bytes(b"old")
    calls = []

    def broken(scene, sampler, box, *args, **kwargs):
        calls.append(box)
        if len(calls) == 5:
            raise VolwarpError("disk full (test)")
        return original(scene, sampler, box, *args, **kwargs)

    original = blocks.warp_block  # (a block task's, whether it places its planes or not)
    monkeypatch.setattr(blocks, "warp_block", broken)
    res = run("warp", src, "--spec", spec, "-o", out, "--chunked", "--block", "12",
              "--scheduler", "synchronous")
    assert res.code == 1 and "disk full (test)" in res.stderr
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir() if "part" in p.name] == []


def test_a_worker_killed_in_a_chunked_warp_loses_nothing(tmp_path):
    """A cluster worker SIGKILLed while it computes blocks: Dask runs its blocks again on
    the other worker; the output is byte for byte the in-memory warp's and no temporary is
    left (a block task writes whole blocks at fixed places, so a rerun rewrites the same
    bytes, and the output appears only when every block is in)."""
    import os
    import signal
    import subprocess
    import sys

    pytest.importorskip("distributed")
    from distributed import Client, LocalCluster

    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (48, 52, 44)], indexing="ij")
    data = (1000 * np.exp(-(x * x + y * y + z * z) / 0.3)).astype(np.int16)
    src = tmp_path / "in.nrrd"
    write_volume(Volume(data, spacing=np.array([0.8, 0.9, 1.1])), src)
    spec = tmp_path / "warp.yaml"
    spec.write_text(SPEC)
    mem, blk = tmp_path / "mem.nrrd", tmp_path / "blk.nrrd"
    cmd = [sys.executable, "-m", "volwarp_cli", "warp", str(src), "--spec", str(spec)]
    assert subprocess.run(cmd + ["-o", str(mem)], capture_output=True).returncode == 0
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None, silence_logs=50) as cluster, \
            Client(cluster) as client:
        pids = client.run(os.getpid)
        proc = subprocess.Popen(cmd + ["-o", str(blk), "--chunked", "--block", "10",
                                       "--scheduler", cluster.scheduler_address,
                                       "--progress", "jsonl"],
                                stderr=subprocess.PIPE, text=True)
        killed, done, other = None, 0, []
        for line in proc.stderr:
            if not line.startswith("{"):
                other.append(line)
                continue
            done += '"done"' in line
            if killed is None and done == 3:
                killed = next(iter(pids.values()))
                os.kill(killed, signal.SIGKILL)
        code = proc.wait(timeout=300)
        proc.stderr.close()
    assert killed is not None, "the warp ended before a worker could be killed"
    assert code == 0, "".join(other)
    assert blk.read_bytes() == mem.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blk.nrrd", "in.nrrd", "mem.nrrd",
                                                         "warp.yaml"]
    assert done >= 3


def test_scale_options_that_do_not_apply_are_refused(run, scan, tmp_path):
    src, spec = scan
    out = tmp_path / "o.nrrd"
    res = run("warp", src, "--spec", spec, "-o", out, "--chunked", "--threads-per-worker", "2")
    assert res.code == 2 and "--threads-per-worker" in res.stderr
    res = run("warp", src, "--spec", spec, "-o", out, "--chunked", "--workers", "2",
              "--scheduler", "tcp://127.0.0.1:1")
    assert res.code == 2 and "--workers" in res.stderr
    assert not out.exists()
