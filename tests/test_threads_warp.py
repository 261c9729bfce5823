"""The warp is the same bit for bit for any thread count and any block size, and the
threads really run (each test records the threads its kernels ran in)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from one_shot import one_shot

from volwarp_cli import parallel
from volwarp_cli.box import Box
from volwarp_cli.bspline import jobs, work
from volwarp_cli.bspline import scene as scene_mod
from volwarp_cli.bspline.capture import capture_volume
from volwarp_cli.bspline.scene import Scene
from volwarp_cli.volume import Header, Volume

THREADS = [1, 2, 3, 5]


def blob(shape_zyx):
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape_zyx], indexing="ij")
    return (100 * np.exp(-(x ** 2 + 1.3 * y ** 2 + 0.7 * z ** 2) / 0.3)).astype(np.float32)


class KernelThreads:
    """Wraps the C scatter and the spline evaluator, recording the threads they run in."""

    def __init__(self, monkeypatch):
        self.seen = set()
        self.lock = threading.Lock()
        real = jobs._warpkernels

        class Proxy:
            def __getattr__(_, name):
                fn = getattr(real, name)
                if name not in ("scatter", "finalize", "separable", "sample"):
                    return fn

                def wrapped(*args):
                    with self.lock:
                        self.seen.add(threading.get_ident())
                    # a pause, so that a pool's other threads take the next tasks (the
                    # first thread would otherwise finish these small ones alone)
                    time.sleep(0.002)
                    return fn(*args)
                return wrapped

        monkeypatch.setattr(jobs, "_warpkernels", Proxy())

    def reset(self):
        self.seen = set()


def moved_lattice(cap, seed=3, scale=1.5):
    rng = np.random.default_rng(seed)
    dq = cap.dq.copy()
    dq[1:-1, 1:-1, 1:-1] += rng.normal(scale=scale, size=dq[1:-1, 1:-1, 1:-1].shape)
    return dq


def test_full_render_and_local_updates_identical_for_any_thread_count(monkeypatch, small_splits,
                                                                       local_updates):
    probe = KernelThreads(monkeypatch)
    data = blob((30, 26, 28))
    rng = np.random.default_rng(5)
    moves = [((i, j, k), rng.normal(scale=1.5, size=3))
             for i, j, k in [(2, 3, 1), (4, 1, 3), (3, 3, 3), (0, 5, 0)]]

    def run_all():
        cap = capture_volume(Volume(data), lattice=(7, 8, 6), oversample=1.5)
        sc = Scene(cap.domain, cap.grid, cap.dq, 4, update=local_updates)
        outs = [sc.compute().copy()]
        dq = cap.dq.copy()
        for (i, j, k), d in moves:
            dq = dq.copy()
            dq[k, j, i] += d
            sc.set_lattice(dq)
            outs.append(sc.out.copy())
        return outs, sc.acc.copy()

    with parallel.use_threads(1):
        reference = run_all()
    assert len(probe.seen) == 1
    for n in THREADS[1:]:
        probe.reset()
        with parallel.use_threads(n):
            got = run_all()
        assert len(probe.seen) > 1, f"{n} threads asked, the kernels ran in one"
        for a, b in zip(reference[0], got[0], strict=True):
            assert np.array_equal(a, b)
        assert np.array_equal(reference[1], got[1])


def _operation(cap, dq, pad):
    """The one-shot warp of ``cap`` with lattice ``dq`` as the executor's operation."""
    from volwarp_cli.bspline.pullback import DomainSampler
    from volwarp_cli.execute import Target
    from volwarp_cli.warp.blocks import WarpOperation

    scene = Scene(cap.voxmap, cap.grid, dq, pad, domain_range=cap.stats[:2])
    window = scene.target_box
    sampler = scene.sampler if scene.sampler is not None else DomainSampler(scene.domain)
    return WarpOperation(scene, None, cap.placement, cap.sampling, window,
                         Target(None, Header(window.shape, np.float32), np.float32),
                         sampler=sampler)


@pytest.mark.parametrize("oversample", [1, 2])
def test_one_shot_render_identical_for_any_threads_and_block_size(monkeypatch, oversample):
    """The whole output over any thread count, and any cut into blocks computed one by
    one, are the full render bit for bit; several threads really run."""
    probe = KernelThreads(monkeypatch)
    data = blob((40, 24, 26))
    cap = capture_volume(Volume(data), lattice=(6, 6, 7), oversample=oversample)
    dq = moved_lattice(cap)
    full = Scene(cap.domain, cap.grid, dq, 3, domain_range=cap.stats[:2]).compute().copy()
    for n in THREADS:
        probe.reset()
        op = _operation(cap, dq, 3)
        with parallel.use_threads(n):
            out = op.compute(op.grid.box, threads=n)[op.KEY]
        assert np.array_equal(out, full), n
        if n > 1:
            assert len(probe.seen) > 1
    op = _operation(cap, dq, 3)
    for block in ((1, 46, 32), (7, 5, 32), (13, 17, 9)):
        got = np.full_like(full, np.nan)
        for z in range(0, full.shape[0], block[0]):
            for y in range(0, full.shape[1], block[1]):
                for x in range(0, full.shape[2], block[2]):
                    box = Box((z, y, x), (min(z + block[0], full.shape[0]),
                                          min(y + block[1], full.shape[1]),
                                          min(x + block[2], full.shape[2])))
                    got[box.slices] = op.compute(box, threads=1)[op.KEY]
        assert np.array_equal(got, full), block


def test_deferred_gather_identical_for_any_thread_count():
    data = blob((34, 22, 24))
    vol = Volume(data)
    ref = capture_volume(vol, lattice=(6, 6, 6), oversample=2)
    dq = moved_lattice(ref, seed=4)
    full = Scene(ref.domain, ref.grid, dq, 2, domain_range=ref.stats[:2]).compute().copy()
    for n in THREADS:
        cap = capture_volume(vol, lattice=(6, 6, 6), oversample=2, defer=True)
        assert cap.domain is None  # gathered box by box as the blocks stream
        op = _operation(cap, dq, 2)
        with parallel.use_threads(n):
            out = op.compute(op.grid.box, threads=n)[op.KEY]
        assert np.array_equal(out, full), n
        assert cap.domain is None


def test_parts_cover_the_target_planes_and_each_voxel_that_reaches_them(small_splits):
    """Every target plane is in one part, and each part's domain range holds every domain
    plane whose image can reach it (checked against the per-plane reach)."""
    data = blob((40, 20, 20))
    cap = capture_volume(Volume(data), lattice=(5, 5, 8), oversample=1)
    dq = moved_lattice(cap, scale=2.5)
    sc = Scene(cap.domain, cap.grid, dq, 4)
    dshape = cap.grid.domain_shape
    planes = sc.reach.planes(sc._offset_bounds(dq))
    with parallel.use_threads(4):
        parts = work.thread_parts(sc.reach, planes, Box.from_xyz((0, 0, 0), dshape), 0, None,
                                  None)
    assert parts is not None and len(parts) >= 2
    edges = [p.target.lo[0] for p in parts] + [parts[-1].target.hi[0]]
    assert edges[0] == 0 and edges[-1] == sc.target_shape[2]
    assert all(a < b for a, b in zip(edges[:-1], edges[1:], strict=True))
    for p in parts:
        (t0, g0), (t1, g1) = (p.target.lo[0], p.domain.lo[0]), (p.target.hi[0], p.domain.hi[0])
        for g in range(dshape[2]):
            r0, r1 = int(planes.t_lo[g]), int(planes.t_hi[g])
            if r0 < t1 and r1 > t0:  # plane g can reach the part
                assert g0 <= g < g1


def test_available_cores_honours_affinity_and_quota(monkeypatch, tmp_path):
    monkeypatch.setattr(parallel.os, "sched_getaffinity", lambda pid: {0, 1, 2, 3, 4, 5})
    monkeypatch.setattr(parallel, "cgroup_cpu_quota", lambda root="/sys/fs/cgroup": None)
    assert parallel.available_cores() == 6
    monkeypatch.setattr(parallel, "cgroup_cpu_quota", lambda root="/sys/fs/cgroup": 2.5)
    assert parallel.available_cores() == 3
    monkeypatch.setattr(parallel, "cgroup_cpu_quota", lambda root="/sys/fs/cgroup": 64.0)
    assert parallel.available_cores() == 6


def test_cgroup_quota_files(monkeypatch, tmp_path):
    v2 = tmp_path / "v2"
    (v2 / "job").mkdir(parents=True)
    (v2 / "job" / "cpu.max").write_text("250000 100000\n")
    monkeypatch.setattr(parallel, "_read", lambda p, real=parallel._read: "0::/job"
                        if p == "/proc/self/cgroup" else real(p))
    assert parallel.cgroup_cpu_quota(str(v2)) == 2.5
    (v2 / "job" / "cpu.max").write_text("max 100000\n")
    assert parallel.cgroup_cpu_quota(str(v2)) is None
    v1 = tmp_path / "v1"
    (v1 / "cpu").mkdir(parents=True)  # the container's cgroup seen as the mount's root
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("300000")
    (v1 / "cpu" / "cpu.cfs_period_us").write_text("100000")
    monkeypatch.setattr(parallel, "_read", lambda p, real=parallel._read: "4:cpu,cpuacct:/docker/x"
                        if p == "/proc/self/cgroup" else real(p))
    assert parallel.cgroup_cpu_quota(str(v1)) == 3.0
    (v1 / "cpu" / "cpu.cfs_quota_us").write_text("-1")
    assert parallel.cgroup_cpu_quota(str(v1)) is None


def test_cgroup_quota_of_an_ancestor_counts(monkeypatch, tmp_path):
    """A Slurm job's (or a pod's) quota sits above the task's own cgroup: the smallest
    quota of the cgroup and its ancestors holds (v2 and v1)."""
    v2 = tmp_path / "v2"
    (v2 / "job" / "step" / "task").mkdir(parents=True)
    (v2 / "job" / "cpu.max").write_text("150000 100000\n")
    (v2 / "job" / "step" / "cpu.max").write_text("max 100000\n")
    (v2 / "job" / "step" / "task" / "cpu.max").write_text("400000 100000\n")
    monkeypatch.setattr(parallel, "_read", lambda p, real=parallel._read: "0::/job/step/task"
                        if p == "/proc/self/cgroup" else real(p))
    assert parallel.cgroup_cpu_quota(str(v2)) == 1.5
    v1 = tmp_path / "v1"
    (v1 / "cpu" / "slurm" / "job").mkdir(parents=True)
    (v1 / "cpu" / "slurm" / "cpu.cfs_quota_us").write_text("200000")
    (v1 / "cpu" / "slurm" / "cpu.cfs_period_us").write_text("100000")
    (v1 / "cpu" / "slurm" / "job" / "cpu.cfs_quota_us").write_text("-1")
    (v1 / "cpu" / "slurm" / "job" / "cpu.cfs_period_us").write_text("100000")
    monkeypatch.setattr(parallel, "_read", lambda p, real=parallel._read: "4:cpu:/slurm/job"
                        if p == "/proc/self/cgroup" else real(p))
    assert parallel.cgroup_cpu_quota(str(v1)) == 2.0


def test_thread_count_sources(monkeypatch):
    monkeypatch.delenv(parallel.THREADS_ENV, raising=False)
    monkeypatch.setattr(parallel, "available_cores", lambda: 7)
    assert parallel.threads() == 7
    monkeypatch.setenv(parallel.THREADS_ENV, "3")
    assert parallel.threads() == 3
    with parallel.use_threads(2):
        assert parallel.threads() == 2
        # a thread started here has its own context: the default, unless handed ours
        seen = []
        t = threading.Thread(target=lambda: seen.append(parallel.threads()))
        t.start()
        t.join()
        assert seen == [3]
        assert parallel.run_blocks(lambda _: parallel.threads(), range(4), 2) == [2] * 4
    assert parallel.threads() == 3
    monkeypatch.setenv(parallel.THREADS_ENV, "auto")
    assert parallel.threads() == 7
    monkeypatch.setenv(parallel.THREADS_ENV, "many")
    with pytest.raises(Exception, match="VOLWARP_THREADS"):
        parallel.threads()


def test_cuts_are_an_exact_partition():
    for lo, hi, parts in [(0, 10, 3), (5, 6, 4), (0, 100, 7), (3, 3, 2)]:
        c = parallel.cuts(lo, hi, parts)
        assert c[0] == lo and c[-1] == hi
        assert all(a <= b for a, b in zip(c[:-1], c[1:], strict=True))
        assert len(c) - 1 <= max(1, min(parts, hi - lo))


def test_per_plane_reach_holds_every_box_and_is_tighter_than_the_global_one():
    """Each domain plane's contributions land inside the target planes PlaneReach gives it
    (checked plane by plane with the scatter's own touched box), on a lattice moved far and
    unevenly in z; and the bound is tighter than the lattice-wide one."""
    data = blob((30, 18, 20))
    cap = capture_volume(Volume(data), lattice=(5, 5, 9), oversample=1.5)
    dq = moved_lattice(cap, seed=11, scale=0.5)
    dq[2:4, 2:4, 2:4, 2] += 6.0  # one part pushed far up: other layers reach less
    sc = Scene(cap.domain, cap.grid, dq, 8)
    pr = sc.reach.planes(sc._offset_bounds(dq))
    dshape = cap.grid.domain_shape
    acc = np.zeros(tuple(sc.target_shape[::-1]) + (2,), np.int64)
    looser = 0
    for g in range(dshape[2]):
        bb = sc.contribute([dq], Box((g, 0, 0), (g + 1, dshape[1], dshape[0])), 1, acc=acc,
                           bounds=True, parallel=False)
        if bb is None:
            continue
        assert pr.t_lo[g] <= bb.lo[0] and bb.hi[0] <= pr.t_hi[g], g
        g0, g1 = sc.reach.target_z_reach(dq, g, g + 1)
        assert g0 <= pr.t_lo[g] and pr.t_hi[g] <= g1
        looser += (g1 - g0) - (pr.t_hi[g] - pr.t_lo[g])
    assert looser > 0
    # a window asks for every plane that reaches the target planes, and the stream's
    # monotone floor never passes a later plane's reach
    for t0 in range(0, sc.target_shape[2], 7):
        a, b = pr.domain_window(t0, t0 + 7)
        need = [g for g in range(dshape[2]) if pr.t_hi[g] > t0 and pr.t_lo[g] < t0 + 7]
        assert not need or (a <= min(need) and max(need) < b)
    assert np.all(pr.floor_from <= pr.t_lo)
    assert np.all(np.diff(pr.floor_from) >= 0)


def test_chunks_follow_the_memory_budget_and_change_nothing():
    """The deformation buffers of a chunk take the budget's share of a thread (at most
    CHUNK_BYTES): a tight budget makes them smaller, the target stays the same bit for bit."""
    from volwarp_cli import memory

    data = blob((30, 24, 26))
    cap = capture_volume(Volume(data), lattice=(6, 6, 6), oversample=2)
    dq = moved_lattice(cap, seed=2)
    free = Scene(cap.domain, cap.grid, dq, 3)
    assert free.chunk_bytes == min(scene_mod.CHUNK_BYTES, memory.block_bytes())
    reference = free.compute().copy()
    with memory.use_memory_limit(memory.process_rss() + (40 << 20)), parallel.use_threads(2):
        tight = Scene(cap.domain, cap.grid, dq, 3)
        assert tight.chunk_bytes == memory.block_bytes() < scene_mod.CHUNK_BYTES
        assert np.array_equal(tight.compute(), reference)
        assert np.array_equal(one_shot(Scene(cap.domain, cap.grid, dq, 3)), reference)
