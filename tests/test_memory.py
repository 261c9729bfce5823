"""The memory budget (volwarp_cli.memory): sizes, cgroup limits, the context variable, and a
command held to --memory-limit, measured."""

from __future__ import annotations

import contextvars
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import ball
from peaks import volwarp_peak

from volwarp_cli import memory
from volwarp_cli.errors import OutOfMemoryError, VolwarpError

K, M, G = 1 << 10, 1 << 20, 1 << 30
V1_NO_LIMIT = "9223372036854771712"  # 2^63 - 1 rounded down to a 4 KiB page


@pytest.fixture(autouse=True)
def _no_env_limit(monkeypatch):
    monkeypatch.delenv(memory.MEMORY_ENV, raising=False)


@pytest.fixture
def holding(monkeypatch):
    """This process holds ``holding.rss`` bytes (0 by default): explicit limits are the
    whole process's, so what it holds is taken off them."""
    class Held:
        rss = 0

    monkeypatch.setattr(memory, "process_rss", lambda: Held.rss)
    return Held


# -- parse_size ----------------------------------------------------------------------

@pytest.mark.parametrize("text, expected", [
    ("8G", 8 * G), ("512M", 512 * M), ("1.5GiB", 3 * G // 2), ("2g", 2 * G),
    ("300MB", 300 * M), ("123456", 123456), ("8 GB", 8 * G), ("64k", 64 * K),
    ("64KiB", 64 * K), ("1Ti", 1 << 40), ("100B", 100), ("1e6", 10 ** 6), (" 4m ", 4 * M),
    ("0.5k", 512), (4096, 4096),
])
def test_parse_size_forms_are_powers_of_1024(text, expected):
    assert memory.parse_size(text) == expected


@pytest.mark.parametrize("text", ["", "abc", "8X", "G", "1iB", "8 G B", "1,5G", "nan", "inf",
                                  "8GG", "--1"])
def test_parse_size_refuses_what_is_not_a_size(text):
    with pytest.raises(ValueError, match="not a memory size") as exc:
        memory.parse_size(text)
    msg = str(exc.value)
    assert "\n" not in msg and "8G" in msg and "512M" in msg and "1024" in msg


@pytest.mark.parametrize("text", ["0", "0G", "-1", "-2G", "0.4"])
def test_parse_size_refuses_sizes_that_are_not_positive(text):
    with pytest.raises(ValueError, match="not a positive memory size"):
        memory.parse_size(text)


# -- cgroup limits on fake trees -----------------------------------------------------

def tree(root: Path, files: dict[str, str]) -> str:
    for name, text in files.items():
        p = root / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text + "\n")
    return str(root)


def test_cgroup_v2_limit_and_working_set(tmp_path):
    root = tree(tmp_path, {"user.slice/job/memory.max": str(4 * G),
                           "user.slice/job/memory.current": str(G),
                           "user.slice/job/memory.stat": f"anon 1\ninactive_file {256 * M}\n"
                                                         "active_file 5"})
    # the inactive page cache is reclaimable: not counted as used
    assert memory.cgroup_memory_limit(root, {"": "/user.slice/job"}) == (4 * G, G - 256 * M)


def test_cgroup_v2_max_means_no_limit(tmp_path):
    root = tree(tmp_path, {"a/memory.max": "max", "a/memory.current": str(G)})
    assert memory.cgroup_memory_limit(root, {"": "/a"}) is None


def test_cgroup_v2_a_limit_on_an_ancestor_counts(tmp_path):
    """A Slurm job's limit sits on the job's cgroup; the task's own says max."""
    root = tree(tmp_path, {"job/memory.max": str(2 * G), "job/memory.current": str(3 * G // 2),
                           "job/task/memory.max": "max", "job/task/memory.current": str(M)})
    assert memory.cgroup_memory_limit(root, {"": "/job/task"}) == (2 * G, 3 * G // 2)
    # the level that leaves least wins, not the smallest limit
    tree(tmp_path, {"job/task/memory.max": str(G), "job/task/memory.current": str(M)})
    assert memory.cgroup_memory_limit(root, {"": "/job/task"}) == (2 * G, 3 * G // 2)


def test_cgroup_v2_path_not_mounted_under_its_name(tmp_path):
    """In a container the process's cgroup is the mount's root."""
    root = tree(tmp_path, {"memory.max": str(G), "memory.current": str(100 * M)})
    assert memory.cgroup_memory_limit(root, {"": "/docker/0123abcd"}) == (G, 100 * M)


def test_cgroup_v1_limit(tmp_path):
    root = tree(tmp_path, {"memory/docker/abc/memory.limit_in_bytes": str(2 * G),
                           "memory/docker/abc/memory.usage_in_bytes": str(G),
                           "memory/docker/abc/memory.stat":
                               f"cache 9\ninactive_file {M}\ntotal_inactive_file {64 * M}",
                           "memory/memory.limit_in_bytes": V1_NO_LIMIT,
                           "memory/memory.usage_in_bytes": str(8 * G)})
    paths = {"memory": "/docker/abc", "cpu": "/docker/abc"}
    assert memory.cgroup_memory_limit(root, paths) == (2 * G, G - 64 * M)


def test_cgroup_v1_page_rounded_2_63_means_no_limit(tmp_path):
    root = tree(tmp_path, {"memory/x/memory.limit_in_bytes": V1_NO_LIMIT,
                           "memory/x/memory.usage_in_bytes": str(G),
                           "memory/memory.limit_in_bytes": V1_NO_LIMIT,
                           "memory/memory.usage_in_bytes": str(G)})
    assert memory.cgroup_memory_limit(root, {"memory": "/x"}) is None
    # a 64 KiB page rounds it differently
    tree(tmp_path, {"memory/x/memory.limit_in_bytes": str((1 << 63) - (1 << 16))})
    assert memory.cgroup_memory_limit(root, {"memory": "/x"}) is None


def test_cgroup_v1_path_not_mounted_under_its_name(tmp_path):
    root = tree(tmp_path, {"memory/memory.limit_in_bytes": str(512 * M),
                           "memory/memory.usage_in_bytes": str(12 * M)})
    assert memory.cgroup_memory_limit(root, {"memory": "/docker/abc"}) == (512 * M, 12 * M)


def test_cgroup_hybrid_reads_v1_when_the_unified_tree_has_no_memory_files(tmp_path):
    root = tree(tmp_path, {"unified/cgroup.procs": "1",
                           "memory/s/memory.limit_in_bytes": str(G),
                           "memory/s/memory.usage_in_bytes": str(M)})
    assert memory.cgroup_memory_limit(root, {"": "/", "memory": "/s"}) == (G, M)


def test_no_cgroup_files_no_limit(tmp_path):
    assert memory.cgroup_memory_limit(str(tmp_path), {"": "/a", "memory": "/a"}) is None
    assert memory.cgroup_memory_limit(str(tmp_path), {}) is None
    # this process's own (whatever the machine has): a pair of ints or None
    own = memory.cgroup_memory_limit()
    assert own is None or (len(own) == 2 and all(isinstance(v, int) for v in own))


# -- available_memory and the budget -------------------------------------------------

@pytest.fixture
def machine(monkeypatch, holding):
    """A machine with 8 GiB available and no cgroup limit (set ``cgroup`` to add one)."""
    state = {"cgroup": None}
    monkeypatch.setattr(memory, "meminfo_available", lambda path="/proc/meminfo": 8 * G)
    monkeypatch.setattr(memory, "cgroup_memory_limit", lambda *a, **k: state["cgroup"])
    return state


def test_available_memory_is_the_lower_of_meminfo_and_the_cgroup(machine):
    assert memory.available_memory() == 8 * G
    machine["cgroup"] = (3 * G, G)
    assert memory.available_memory() == 2 * G
    machine["cgroup"] = (64 * G, G)
    assert memory.available_memory() == 8 * G
    machine["cgroup"] = (G, 2 * G)  # over its limit already (cache): nothing left
    assert memory.available_memory() == 0


def test_available_memory_capped_by_the_variable(machine, monkeypatch):
    monkeypatch.setenv(memory.MEMORY_ENV, "512M")
    assert memory.available_memory() == 512 * M
    monkeypatch.setenv(memory.MEMORY_ENV, "100000")  # a plain byte count, as before
    assert memory.available_memory() == 100000
    monkeypatch.setenv(memory.MEMORY_ENV, "64G")  # does not raise the machine's
    assert memory.available_memory() == 8 * G
    monkeypatch.setenv(memory.MEMORY_ENV, "lots")
    with pytest.raises(VolwarpError, match=memory.MEMORY_ENV) as exc:
        memory.available_memory()
    assert "\n" not in str(exc.value) and not isinstance(exc.value, ValueError)


def test_use_memory_limit_caps_available_memory_and_nests(machine, monkeypatch):
    with memory.use_memory_limit(G) as budget:
        assert budget == G
        assert memory.available_memory() == memory.memory_limit() == G
        with memory.use_memory_limit(4 * G) as inner:  # a callee cannot raise it
            assert inner == G and memory.memory_limit() == G
        with memory.use_memory_limit(256 * M):
            assert memory.memory_limit() == 256 * M
            monkeypatch.setenv(memory.MEMORY_ENV, "100M")
            assert memory.memory_limit() == 100 * M
            monkeypatch.delenv(memory.MEMORY_ENV)
        with memory.use_memory_limit(None) as same:
            assert same == G
        assert memory.memory_limit() == G
    assert memory.memory_limit() == 8 * G
    with memory.use_memory_limit(None) as none:
        assert none is None
    with pytest.raises(ValueError), memory.use_memory_limit(0):
        pass
    with memory.use_memory_limit(64 * G):  # above what the machine leaves
        assert memory.memory_limit() == 8 * G


def test_the_budget_is_per_thread_unless_the_context_is_copied(machine):
    from volwarp_cli import parallel

    seen = {}

    def look(key):
        seen[key] = memory.memory_limit()

    with memory.use_memory_limit(16 * M):
        t = threading.Thread(target=look, args=("plain",))
        t.start()
        t.join()
        ctx = contextvars.copy_context()
        t = threading.Thread(target=ctx.run, args=(look, "copied"))
        t.start()
        t.join()
        blocks = parallel.run_blocks(lambda b: memory.memory_limit(), range(4), n=2)
    assert seen == {"plain": 8 * G, "copied": 16 * M}
    assert blocks == [16 * M] * 4

    # a thread's own budget does not leak to the caller's
    def set_own():
        with memory.use_memory_limit(M):
            seen["own"] = memory.memory_limit()

    t = threading.Thread(target=set_own)
    t.start()
    t.join()
    assert seen["own"] == M and memory.memory_limit() == 8 * G


def test_ensure_fits_in_memory_says_where_the_limit_comes_from(machine, monkeypatch, holding):
    memory.ensure_fits_in_memory(8 * G, "exactly all")
    with pytest.raises(OutOfMemoryError, match=r"^big needs 9.0 GiB but only 8.0 GiB of "
                                                r"memory is available on this machine$"):
        memory.ensure_fits_in_memory(9 * G, "big")
    machine["cgroup"] = (4 * G, G)
    with pytest.raises(OutOfMemoryError, match=r"only 3.0 GiB .* cgroup \(its limit 4.0 GiB, "
                                                r"1.0 GiB in use\)"):
        memory.ensure_fits_in_memory(4 * G, "big")
    monkeypatch.setenv(memory.MEMORY_ENV, "2G")
    with pytest.raises(OutOfMemoryError, match=r"only 2.0 GiB is left under the memory limit "
                                                r"\(VOLWARP_MEMORY_LIMIT: 2.0 GiB"):
        memory.ensure_fits_in_memory(3 * G, "big")
    with memory.use_memory_limit(512 * M), pytest.raises(
            OutOfMemoryError, match=r"^big needs 1.0 GiB but only 512.0 MiB is left under the "
                                    r"memory limit \(--memory-limit: 512.0 MiB, of which this "
                                    r"process holds 0 B\)$"):
        memory.ensure_fits_in_memory(G, "big")
    holding.rss = 100 * M  # an explicit limit is the whole process's
    with memory.use_memory_limit(512 * M), pytest.raises(
            OutOfMemoryError, match=r"only 412.0 MiB is left .* holds 100.0 MiB\)$"):
        memory.ensure_fits_in_memory(450 * M, "big")
    holding.rss = 0
    with memory.use_memory_limit(512 * M, source="the worker's budget"), pytest.raises(
            OutOfMemoryError, match=r"the memory limit \(the worker's budget: "):
        memory.ensure_fits_in_memory(G, "big")


def test_block_bytes_follows_budget_and_threads_within_bounds(machine):
    with memory.use_memory_limit(G):
        assert memory.block_bytes(4) == 128 * M  # 1 GiB * 0.5 / 4
        assert memory.block_bytes(4, fraction=0.25) == 64 * M
        assert memory.block_bytes(1) == memory.BLOCK_CEILING == 256 * M
        assert memory.block_bytes(1000) == memory.BLOCK_FLOOR == 8 * M
        from volwarp_cli import parallel

        with parallel.use_threads(2):
            assert memory.block_bytes() == 256 * M
    with memory.use_memory_limit(16 * M):
        assert memory.block_bytes(2) == 8 * M  # the floor wins over a tiny budget
    with pytest.raises(ValueError):
        memory.block_bytes(0)
    with pytest.raises(ValueError):
        memory.block_bytes(2, fraction=0)


def test_human_bytes():
    assert memory.human_bytes(512) == "512 B"
    assert memory.human_bytes(15 * M + M // 5) == "15.2 MiB"
    assert memory.human_bytes(3 * G // 2) == "1.5 GiB"


def test_old_names_still_importable_from_io_common():
    from volwarp_cli import samples
    from volwarp_cli.io import common

    assert common.ensure_fits_in_memory is memory.ensure_fits_in_memory
    assert common.available_memory is memory.available_memory
    assert common.cast_samples is samples.cast_samples
    assert common.check_dtype is samples.check_dtype
    assert common.voxel_count is samples.voxel_count
    assert common.SUPPORTED_DTYPES is samples.SUPPORTED_DTYPES


_PKG = Path(memory.__file__).parent
_CORE = sorted(str(f.relative_to(_PKG)) for sub in ("bspline", "distance", "morph", "render",
                                                     "surface", "sweep")
               for f in (_PKG / sub).glob("*.py"))


@pytest.mark.parametrize("module", _CORE)
def test_no_core_module_imports_io_common(module):
    """Memory checks and sample casting come from memory.py and samples.py, not io/."""
    assert "io.common import" not in (_PKG / module).read_text()


# -- the command line ----------------------------------------------------------------

def test_cli_memory_limit_bad_value_is_a_usage_error(run, tmp_path):
    r = run("distance", tmp_path / "b.nrrd", "-o", tmp_path / "d.nrrd", "--iso", 1,
            "--memory-limit", "lots")
    assert r.code == 2 and "--memory-limit" in r.stderr and "not a memory size" in r.stderr


def test_cli_memory_limit_ends_with_the_command(run, tmp_path, holding):
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    write_volume(Volume(ball(12) * 200), tmp_path / "b.nrrd")
    before = memory.memory_limit()
    r = run("distance", tmp_path / "b.nrrd", "-o", tmp_path / "d.nrrd", "--iso", 100,
            "--memory-limit", "8M")
    assert r.code == 0, r.stderr
    assert memory.memory_limit() >= min(before, 64 * M)  # not left at 8 MiB


def _distance(src: Path, out: Path, limit: str, *extra):
    """``volwarp distance`` in a fresh process: its exit code, stderr and peak RSS in bytes."""
    return volwarp_peak("distance", src, "-o", out, "--iso", "100", "--memory-limit", limit,
                        *extra, timeout=60)


def test_distance_held_to_its_memory_limit_measured(tmp_path):
    """160^3 needs 43 MiB by the distance field's own count (11 bytes a voxel: the float32
    field, the uint8 samples, the mask and the scan's temporaries): refused at 64M (the
    interpreter alone holds more) with the budget named and nothing written; at 320M it
    runs, and the whole process (interpreter and libraries included) peaks below 320 MiB."""
    from volwarp_cli.distance.field import signed_distance
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    signed_distance(ball(8), iso=1)  # numba's kernels compiled and cached, here, not timed
    write_volume(Volume(ball(16) * 200), tmp_path / "small.nrrd")
    write_volume(Volume(ball(160) * 200), tmp_path / "big.nrrd")
    out = tmp_path / "d.nrrd"

    code, err, _ = _distance(tmp_path / "big.nrrd", out, "64M")
    assert code == 1, err
    line = err.strip()
    assert "\n" not in line and line.startswith("volwarp: error: ")
    assert "needs 43.0 MiB" in line and "memory limit (--memory-limit: 64.0 MiB" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.nrrd", "small.nrrd"]

    # (with room for the kernels' code: compiled here, from a cold cache, it takes more)
    code, err, base = _distance(tmp_path / "small.nrrd", tmp_path / "s.nrrd", "320M")
    assert code == 0, err
    code, err, peak = _distance(tmp_path / "big.nrrd", out, "320M")
    assert code == 0, err
    assert out.exists()
    assert peak < 320 * M, f"peak RSS {peak / M:.0f} MiB"
    # and what the command allocated for 160^3 (over the 16^3 run's) is within its own count
    need = 160 ** 3 * 11
    assert peak - base < need, f"{(peak - base) / M:.0f} MiB over {need / M:.0f} MiB"


def test_the_budget_counts_the_kernels_the_work_loads(tmp_path):
    """A smooth 160^3 input (the sub-voxel field, whose numba kernels take about 60 MiB
    once loaded, beside 80 MiB of libraries): at two budgets, a run that succeeds peaks
    below its budget, and one that cannot fit is refused with nothing written. (The
    kernels used to load after the check: at 200M the field ran and peaked at 234 MiB.)"""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    z, y, x = np.ogrid[:160, :160, :160]
    smooth = 200 * np.exp(-((x - 80.0) ** 2 + (y - 80.0) ** 2 + (z - 80.0) ** 2) / 2000.0)
    write_volume(Volume(smooth.astype(np.float32)), tmp_path / "smooth.nrrd")
    # the kernels compiled into the cache first (a fresh clone compiles them on first use,
    # holding compiler memory the budget then counts: this test is about the field's own)
    write_volume(Volume(smooth[40:120:3, 40:120:3, 40:120:3].astype(np.float32)), tmp_path / "warm.nrrd")
    assert _distance(tmp_path / "warm.nrrd", tmp_path / "warm_d.nrrd", "2G",
                     "--max-distance", "20")[0] == 0
    ran = []
    for limit in (200, 320):
        out = tmp_path / f"d{limit}.nrrd"
        code, err, peak = _distance(tmp_path / "smooth.nrrd", out, f"{limit}M",
                                    "--max-distance", "20")
        if code == 0:
            assert peak < limit * M, f"{limit}M: peak RSS {peak / M:.0f} MiB"
            ran.append(limit)
        else:
            assert code == 1 and err.strip().count("\n") <= 1, err  # (a fallback's warning)
            assert "memory limit" in err and not out.exists()
    assert 320 in ran


def test_the_sweep_keeps_within_its_limit(tmp_path):
    """A 190x145x55 sweep under --memory-limit: refused with nothing written where even
    its start does not fit (30M), within the limit where it runs (150M: it peaked at 173
    MiB when numba's voxeliser, over 100 MiB once loaded, went uncounted; the C one
    peaks near 42 MiB)."""
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\ngrid: {spacing: 0.1}\nfields:\n  opacity: {value: 0.8}\n"
                    "trajectory:\n  - line: {from: [0, 0, 0], to: [12, 2, 1]}\n"
                    "  - arc: {center: [12, 6, 1], radius: 4, axis: [0, 0, 1], start: -90, "
                    "end: 90}\nup: [0, 0, 1]\nscale: [4, 4]\n")
    for limit in (30, 150):
        out = tmp_path / f"s{limit}_{{field}}.nrrd"
        code, err, peak = volwarp_peak("sweep", spec, "-o", out, "--memory-limit", f"{limit}M",
                                       timeout=120)
        written = tmp_path / f"s{limit}_opacity.nrrd"
        if limit == 30:
            assert code == 1 and not written.exists()
            assert "memory" in err and err.strip().count("\n") == 0
        else:
            assert code == 0 and written.exists()
            assert peak < limit * M, f"peak RSS {peak / M:.0f} MiB"


# -- convert: the write's copies count --------------------------------------------------------

@pytest.mark.parametrize("name, extra, refused_at, runs_at", [
    ("o.nrrd", ["--dtype", "float64", "--compress"], "4M", "12M"),  # cast, gzip stream
    ("o.nii.gz", [], "2M", "8M"),                                   # the gzip stream
    ("o.mha", ["--compress"], "1.5M", "8M"),                        # zlib, made whole
    ("o.nrrd", ["--dtype", "int16", "--values", "intensity"], "1M", "8M"),  # rint + cast
])
def test_convert_refuses_a_write_whose_copies_do_not_fit(run, tmp_path, holding, name, extra,
                                                         refused_at, runs_at):
    """The read of a 64^3 float32 scan (1 MiB) fits both limits; what writing it holds (a
    cast, a compressed stream) does not fit the lower one: one line, nothing written. The
    higher one writes what an unlimited convert writes."""
    from volwarp_cli.io import read_volume, write_volume
    from volwarp_cli.volume import Volume

    data = (np.random.default_rng(0).random((64, 64, 64)) * 1000).astype(np.float32)
    write_volume(Volume(data, spacing=np.array([0.5, 0.7, 1.1])), tmp_path / "in.nrrd")
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / name
    r = run("convert", tmp_path / "in.nrrd", "-o", out, *extra, "--memory-limit", refused_at)
    assert r.code == 1, r.stderr
    line = r.stderr.strip()
    assert "\n" not in line and line.startswith(f"volwarp: error: writing {out} (64x64x64 ")
    assert "beside the 1.0 MiB read) needs " in line and "under the memory limit" in line
    assert list((tmp_path / "out").iterdir()) == []
    r = run("convert", tmp_path / "in.nrrd", "-o", out, *extra, "--memory-limit", runs_at)
    assert r.code == 0, r.stderr
    ref = tmp_path / f"ref{''.join(out.suffixes)}"
    assert run("convert", tmp_path / "in.nrrd", "-o", ref, *extra).code == 0
    assert out.read_bytes() == ref.read_bytes()
    assert read_volume(out).data.shape == (64, 64, 64)


@pytest.mark.parametrize("name", ["o.nii.gz", "o.nii"])
def test_convert_near_its_limit_is_refused_or_stays_under_it_measured(tmp_path, name):
    """Around the least limit a convert needs, each run is refused with nothing written or
    peaks under its limit (the process's whole peak, measured). ISA-L, loaded by the NIfTI
    writer after the check, and the writer's own objects went uncounted: a .nii.gz of a
    256^3 scan peaked 1.6 MiB over a limit it had passed (0.7 MiB for a .nii)."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    data = (np.random.default_rng(1).random((96, 96, 96)) * 1000).astype(np.float32)
    write_volume(Volume(data), tmp_path / "in.nrrd")
    def convert(limit_bytes, out):
        return volwarp_peak("convert", tmp_path / "in.nrrd", "-o", out, "--memory-limit",
                            int(limit_bytes), timeout=60)

    code, err, peak = convert(2 << 30, tmp_path / f"free_{name}")
    assert code == 0, err
    ran = refused = 0
    for step in range(-3, 5):  # (the limit from 3 MiB under the free run's peak to 4 over)
        limit = peak + step * M
        out = tmp_path / f"l{step + 3}_{name}"
        code, err, got = convert(limit, out)
        if code == 0:
            assert got <= limit, f"{(got - limit) / M:.2f} MiB over {limit / M:.1f} MiB"
            ran += 1
        else:
            assert code == 1 and "memory limit" in err and not out.exists(), err
            refused += 1
    assert ran and refused  # (the sweep crossed the least limit)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's libc.so.6")
def test_libc_loads_without_running_ldconfig(monkeypatch):
    """glibc is loaded by its name: ctypes.util.find_library would fork the whole process to
    run ``ldconfig -p`` (2 ms of a command, in the middle of its warp); its functions found."""
    import ctypes.util

    def forbidden(name):
        raise AssertionError(f"find_library({name!r}) runs ldconfig")

    if not os.path.exists("/lib/x86_64-linux-gnu/libc.so.6") and not any(
            Path(d, "libc.so.6").exists() for d in ("/lib64", "/usr/lib64", "/lib", "/usr/lib")):
        pytest.skip("no glibc")
    monkeypatch.setattr(ctypes.util, "find_library", forbidden)
    monkeypatch.setattr(memory, "_loaded", None)
    lib = memory.libc()
    assert lib is not None and getattr(lib, "malloc_trim", None) is not None
    assert getattr(lib, "sync_file_range", None) is not None


def test_a_local_cluster_too_small_for_its_workers_is_refused_not_hung(tmp_path):
    """`--scheduler local` with 2 workers under 200 MiB: each got about 55 MiB, a Dask worker
    holds about 70 MiB before any block, and Dask paused it at 80% of its share: the run
    never ended (a Slurm job until its walltime), or ended in 'internal error: KilledWorker'.
    Refused now, before any work, saying what each worker would get."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    write_volume(Volume(ball(24)), tmp_path / "in.nrrd")
    env = {k: v for k, v in os.environ.items() if k != "VOLWARP_MEMORY_LIMIT"}
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "distance",
                          str(tmp_path / "in.nrrd"), "--iso", "0.5", "-o", str(tmp_path / "d.nrrd"),
                          "--chunked", "--scheduler", "local", "--workers", "2",
                          "--memory-limit", "200M"], capture_output=True, text=True, env=env,
                         timeout=120)
    assert res.returncode == 1, res.stderr
    assert "--scheduler local: 2 worker process(es)" in res.stderr
    assert "give each at least 100 MiB" in res.stderr
    assert not (tmp_path / "d.nrrd").exists()


def test_a_metric_whose_kernels_do_not_fit_is_refused_before_the_blocks(tmp_path):
    """A taxicab distance under 150M: numba's load was tried while warming the kernels, the
    refusal swallowed, and tried again in a block task, which refused it against the
    task's share ("--memory-limit: 52.4 MiB, of which this process holds 94.9 MiB ... 0 B
    left") after the first pass's work. Now refused at once, with the command's budget."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    write_volume(Volume(ball(24)), tmp_path / "in.nrrd")
    env = {k: v for k, v in os.environ.items() if k != "VOLWARP_MEMORY_LIMIT"}
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "distance", str(tmp_path / "in.nrrd"),
                          "--metric", "taxicab", "-o", str(tmp_path / "d.nrrd"), "--chunked",
                          "--memory-limit", "150M"], capture_output=True, text=True, env=env,
                         timeout=120)
    assert res.returncode == 1, res.stderr
    assert "loading numba" in res.stderr and "(--memory-limit: 150.0 MiB," in res.stderr
    assert not (tmp_path / "d.nrrd").exists()


@pytest.mark.parametrize("chunked", [(), ("--chunked",)], ids=["in-memory", "by-blocks"])
def test_a_morph_surface_too_large_for_the_budget_is_refused_before_it_is_made(
        tmp_path, chunked):
    """The frames' surfaces (--mesh-to) were made with no check: a review measured a morph
    under 250M at 273 MiB. A surface whose triangles cannot fit is refused with its vertex
    count before it is made, and no frame is left."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    noise = (np.random.default_rng(3).random((96, 96, 96)) < 0.5).astype(np.uint8)
    write_volume(Volume(noise), tmp_path / "n.nrrd")
    env = {k: v for k, v in os.environ.items() if k != "VOLWARP_MEMORY_LIMIT"}
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "morph", str(tmp_path / "n.nrrd"),
                          str(tmp_path / "n.nrrd"), "--frames", "2", "-o",
                          str(tmp_path / "f_{i}.nrrd"), "--mesh-to", str(tmp_path / "f_{i}.ply"),
                          "--memory-limit", "250M", *chunked], capture_output=True, text=True,
                         env=env, timeout=300)
    assert res.returncode == 1, res.stderr
    assert "the surface of frame 0 (" in res.stderr and "vertices) needs" in res.stderr
    assert not list(tmp_path.glob("f_*"))
