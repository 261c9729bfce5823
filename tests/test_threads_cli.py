"""Every subcommand writes the same bytes for --threads 1, 2, 3 and 5 (and VOLWARP_THREADS),
on inputs large enough that the work is split over the threads."""

from __future__ import annotations

import itertools
import os
import threading
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli import parallel
from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

THREADS = ["1", "2", "3", "5"]


def radial(n, c):
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float64)
    return np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("threads")
    n = 72
    rng = np.random.default_rng(0)
    ball = 1 / (1 + np.exp((radial(n, (35.5, 33.0, 36.5)) - 24.0) / 1.5)) * 200
    ball += rng.uniform(0, 4, ball.shape)  # no two runs of the same value: order matters
    kw = {"spacing": (1.0, 0.9, 1.2), "origin": (-30.0, 12.0, 4.0)}
    write_volume(Volume(ball.astype(np.float32), **kw), d / "ball.nrrd")
    two = np.maximum(14 - radial(n, (22, 36, 36)), 14 - radial(n, (50, 36, 36)))
    write_volume(Volume((1 / (1 + np.exp(-two / 1.5)) * 200).astype(np.float32), **kw),
                 d / "lobes.nrrd")
    (d / "warp.yaml").write_text(
        "version: 1\ncapture: {lattice: 7, oversample: 2}\nsteps:\n"
        "  - move:\n      - {index: [3, 3, 3], by: [4.0, -3.0, 5.0]}\n"
        "      - {index: [2, 4, 3], by: [-2.0, 2.5, 1.0]}\n")
    (d / "frames.yaml").write_text(
        "version: 1\ncapture: {lattice: 7, oversample: 2}\nsteps:\n"
        "  - move:\n      - {index: [3, 3, 3], by: [4.0, -3.0, 5.0]}\n    frames: 2\n"
        "  - move:\n      - {index: [2, 4, 3], by: [-2.0, 2.5, 1.0]}\n")
    (d / "sweep.yaml").write_text(
        "version: 1\ngrid: {spacing: 0.25}\nfields:\n  opacity: {value: 0.8}\n  red: 0.25\n"
        "trajectory:\n  - line: {from: [0, 0, 0], to: [12, 2, 1]}\n"
        "  - arc: {center: [12, 6, 1], radius: 4, axis: [0, 0, 1], start: -90, end: 90}\n"
        "up: [0, 0, 1]\nscale: [4, 4]\n")
    return d


def same_bytes_for_every_count(run, tmp_path, make_args, outputs):
    """Run ``make_args(suffix)`` at each thread count; the files named by ``outputs(suffix)``
    must be byte-identical to those of one thread."""
    reference = None
    for n in THREADS:
        res = run(*make_args(f"t{n}"), "--threads", n)
        assert res.code == 0, res.stderr
        got = [p.read_bytes() for p in outputs(f"t{n}")]
        assert all(got)
        if reference is None:
            reference = got
        else:
            assert got == reference, f"--threads {n} wrote other bytes than --threads 1"


def test_warp(run, inputs, tmp_path):
    same_bytes_for_every_count(
        run, tmp_path,
        lambda s: ("warp", inputs / "ball.nrrd", "--spec", inputs / "warp.yaml",
                   "-o", tmp_path / f"w_{s}.nrrd"),
        lambda s: [tmp_path / f"w_{s}.nrrd"])


def test_warp_frames_local_updates(run, inputs, tmp_path):
    same_bytes_for_every_count(
        run, tmp_path,
        lambda s: ("warp", inputs / "ball.nrrd", "--spec", inputs / "frames.yaml",
                   "-o", tmp_path / f"w_{s}.nrrd",
                   "--frames-to", tmp_path / f"f_{s}_{{frame}}.nrrd"),
        lambda s: [tmp_path / f"w_{s}.nrrd"] + [tmp_path / f"f_{s}_{i}.nrrd" for i in range(4)])


def test_distance(run, inputs, tmp_path):
    same_bytes_for_every_count(
        run, tmp_path,
        lambda s: ("distance", inputs / "ball.nrrd", "--iso", "100", "-o", tmp_path / f"d_{s}.nrrd"),
        lambda s: [tmp_path / f"d_{s}.nrrd"])


def test_mesh(run, inputs, tmp_path):
    same_bytes_for_every_count(
        run, tmp_path,
        lambda s: ("mesh", inputs / "ball.nrrd", "--iso", "100", "-o", tmp_path / f"m_{s}.ply"),
        lambda s: [tmp_path / f"m_{s}.ply"])


def test_sweep(run, inputs, tmp_path):
    same_bytes_for_every_count(
        run, tmp_path,
        lambda s: ("sweep", inputs / "sweep.yaml", "-o", tmp_path / f"s_{s}_{{field}}.nrrd"),
        lambda s: [tmp_path / f"s_{s}_opacity.nrrd", tmp_path / f"s_{s}_red.nrrd"])


def test_morph(run, inputs, tmp_path):
    same_bytes_for_every_count(
        run, tmp_path,
        lambda s: ("morph", inputs / "ball.nrrd", inputs / "lobes.nrrd", "--frames", "3",
                   "--iso", "100", "-o", tmp_path / f"m_{s}_{{i}}.nrrd"),
        lambda s: [tmp_path / f"m_{s}_{i}.nrrd" for i in range(3)])


def test_the_option_reaches_the_core(run, inputs, tmp_path, monkeypatch):
    """--threads N is the count the core sees, and it is undone after the command."""
    seen = []
    real = parallel.run_blocks

    def spy(task, blocks, n=None):
        seen.append((parallel.threads(), n))
        return real(task, blocks, n)

    monkeypatch.setattr(parallel, "run_blocks", spy)
    before = parallel.threads()
    res = run("warp", inputs / "ball.nrrd", "--spec", inputs / "warp.yaml",
              "-o", tmp_path / "w.nrrd", "--threads", "3")
    assert res.code == 0, res.stderr
    assert seen and {t for t, _ in seen} == {3}  # the count in effect in the core
    assert max(n or 1 for _, n in seen) > 1  # and some of the work was split
    assert parallel.threads() == before


def test_environment_variable_and_bad_values(run, inputs, tmp_path, monkeypatch):
    monkeypatch.setenv("VOLWARP_THREADS", "2")
    assert parallel.threads() == 2
    res = run("distance", inputs / "ball.nrrd", "--iso", "100", "-o", tmp_path / "d.nrrd",
              "--threads", "lots")
    assert res.code == 2 and "--threads" in res.stderr and "lots" in res.stderr
    assert not (tmp_path / "d.nrrd").exists()
    monkeypatch.setenv("VOLWARP_THREADS", "-3")
    res = run("distance", inputs / "ball.nrrd", "--iso", "100", "-o", tmp_path / "d.nrrd")
    assert res.code == 2 and "VOLWARP_THREADS" in res.stderr


def test_batch_shares_the_threads_among_its_scans():
    from volwarp_cli.batch.run import child_threads, default_jobs

    with parallel.use_threads(8):
        assert default_jobs() == 8
        assert child_threads(8) == 1
        assert child_threads(3) == 2
        assert child_threads(1) == 8
    with parallel.use_threads(1):
        assert child_threads(4) == 1


def test_blas_held_to_one_thread_and_vtk_follows_the_count():
    """Inside a command BLAS runs one thread (volwarp's own threads take the cores) and VTK's
    SMP tools take the count; BLAS's own setting comes back after."""
    import vtkmodules.vtkCommonCore as vc
    from threadpoolctl import threadpool_info

    from volwarp_cli.surface import isosurface

    def blas():
        return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]

    before = blas()
    assert before  # numpy's BLAS is loaded
    for n in (1, 2):  # (VTK's STDThread caps the count at the machine's cores)
        with parallel.library_threads(n):
            assert set(blas()) == {1}
            isosurface._use_threads()  # what the mesh filters call first
            assert vc.vtkSMPTools.GetBackend() == "STDThread"
            assert vc.vtkSMPTools.GetEstimatedNumberOfThreads() == min(n, os.cpu_count())
    assert blas() == before
    done = []
    t = threading.Thread(target=lambda: done.append(parallel.threads()))
    t.start()
    t.join()
    assert done == [parallel.threads()]


@settings(max_examples=60, deadline=None)
@given(length=st.integers(0, 40), n=st.integers(1, 6), parts=st.none() | st.integers(1, 12))
def test_run_ranges_covers_every_index_once(length, n, parts):
    hits = np.zeros(length, np.int64)
    lock = threading.Lock()

    def task(a, b):
        assert 0 <= a < b <= length
        with lock:
            hits[a:b] += 1

    parallel.run_ranges(task, length, n, parts)
    assert np.all(hits == 1)


def test_beside_runs_in_a_thread_of_its_own_in_the_callers_context():
    """parallel.beside: another thread with two or more threads, this one with one; the
    caller's thread count goes with it; an error is raised by result(), not at the start."""
    seen = []

    def job(x):
        seen.append((threading.get_ident(), parallel.threads()))
        if x < 0:
            raise ValueError("negative")
        return 2 * x

    with parallel.use_threads(3):
        assert parallel.beside(job, 21).result(timeout=30) == 42
        failed = parallel.beside(job, -1)
        with pytest.raises(ValueError, match="negative"):
            failed.result(timeout=30)
    with parallel.use_threads(1):
        assert parallel.beside(job, 4).result() == 8
    main = threading.get_ident()
    assert [t == main for t, _ in seen] == [False, False, True]
    assert [n for _, n in seen] == [3, 3, 1]


def test_run_blocks_gives_results_in_order_and_the_first_error_after_all_ran():
    """parallel.run_blocks on plain threads: each block once, results in block order
    whatever the finishing order, each task in a copy of the caller's context, and of
    several errors the first block's, raised once every block has run."""
    import time

    ran = []

    def task(b):
        time.sleep(0.002 * (7 - b % 8))  # (later blocks finish first)
        ran.append(b)
        if b in (5, 11):
            raise ValueError(f"block {b}")
        return b * b, parallel.threads()

    with parallel.use_threads(3):
        assert parallel.run_blocks(lambda b: task(b % 5), range(20)) == [
            ((b % 5) ** 2, 3) for b in range(20)]
        ran.clear()
        with pytest.raises(ValueError, match="block 5"):
            parallel.run_blocks(task, range(16))
    assert sorted(ran) == list(range(16))


@pytest.mark.parametrize("command", ["distance", "sweep-render", "subvoxel"])
def test_numba_kernels_run_on_the_commands_threads(run, inputs, tmp_path, monkeypatch, command):
    """The numba kernels (no prange pool) split their ranges over --threads, in that many
    threads at once, and the PNG or field is the one thread's."""
    seen, idents = [], set()
    real = parallel.run_blocks
    # The first three tasks of a 3-thread split wait for each other: they can only
    # meet if they run at once (a pool reusing an idle thread would time out here).
    together = threading.Barrier(3, timeout=20)
    started = itertools.count()

    def spy(task, blocks, n=None):
        blocks = list(blocks)
        seen.append((n, len(blocks)))
        meet = n == 3 and len(blocks) >= 3

        def tracked(b):
            if meet:
                idents.add(threading.get_ident())
            if meet and next(started) < 3:
                together.wait()
            return task(b)

        return real(tracked, blocks, n)

    monkeypatch.setattr(parallel, "run_blocks", spy)
    args = {"distance": ("distance", inputs / "ball.nrrd", "--iso", "100", "--surface", "voxel"),
            "subvoxel": ("distance", inputs / "ball.nrrd", "--iso", "100", "--surface",
                         "subvoxel"),
            "sweep-render": ("sweep", inputs / "sweep.yaml", "--render", tmp_path / "{t}.png")}
    outs = []
    for t in ("1", "3"):
        out = tmp_path / (f"{t}_{{field}}.nrrd" if command == "sweep-render" else f"{t}.nrrd")
        argv = [str(a).replace("{t}", t) for a in args[command]]
        res = run(*argv, "-o", out, "--threads", t)
        assert res.code == 0, res.stderr
        outs.append((tmp_path / f"{t}.png") if command == "sweep-render"
                    else Path(str(out)))
    assert outs[0].read_bytes() == outs[1].read_bytes()
    assert any(n == 3 and k > 1 for n, k in seen)  # the kernels' ranges were split
    assert next(started) >= 3  # three tasks met at the barrier: three threads at once
    assert len(idents) >= 3 and threading.get_ident() not in idents  # the split runs none on the main thread
