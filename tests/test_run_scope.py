"""One run's files and permissions end with it (runscope): a process that runs several
commands (a test session, a Dask worker, a library caller) carries none of them into the
next run; the umask is read without being changed."""

from __future__ import annotations

import os
import stat
import threading

import numpy as np

from volwarp_cli import runscope
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

DATA = (np.arange(4 * 5 * 6, dtype=np.int16).reshape(6, 5, 4) * 3 - 50)


def _outside_header(tmp_path):
    """A detached NRRD header whose data file lies outside its folder."""
    (tmp_path / "secret.raw").write_bytes(DATA.astype("<i2").tobytes())
    (tmp_path / "hdr").mkdir()
    hdr = tmp_path / "hdr" / "h.nhdr"
    hdr.write_text("NRRD0004\ntype: short\ndimension: 3\nsizes: 4 5 6\nendian: little\n"
                   "encoding: raw\ndata file: ../secret.raw\n")
    return hdr


def test_allow_outside_data_is_one_runs_permission(run, tmp_path, monkeypatch):
    """Given to one run, it lets that run read the data file; the next run without it is
    refused again, and the environment is untouched (it was set for the process)."""
    monkeypatch.delenv("VOLWARP_ALLOW_OUTSIDE_DATA", raising=False)
    hdr = _outside_header(tmp_path)
    assert run("convert", hdr, "-o", tmp_path / "a.nrrd", "--allow-outside-data").code == 0
    np.testing.assert_array_equal(read_volume(tmp_path / "a.nrrd").data, DATA)
    assert "VOLWARP_ALLOW_OUTSIDE_DATA" not in os.environ
    res = run("convert", hdr, "-o", tmp_path / "b.nrrd")
    assert res.code == 1 and "outside the header's folder" in res.stderr
    assert not (tmp_path / "b.nrrd").exists()


def test_a_mapped_input_of_an_earlier_run_does_not_fail_later_runs(run, tmp_path):
    """A warp maps its input; the input is replaced after the warp ended. Later, unrelated
    runs in the same process write their outputs (the check is the warp's, not theirs)."""
    src = tmp_path / "in.nrrd"
    rng = np.random.default_rng(0)
    write_volume(Volume(rng.random((12, 13, 14), dtype=np.float32)), src)
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 5, oversample: 1}\nsteps:\n"
                    "  - move:\n      - {index: [2, 2, 2], by: [0.5, 0.0, 0.0]}\n")
    assert run("warp", src, "--spec", spec, "-o", tmp_path / "w.nrrd").code == 0
    write_volume(Volume(rng.random((12, 13, 14), dtype=np.float32)), src)  # replaced
    other = tmp_path / "other.nrrd"
    write_volume(Volume(np.ones((5, 6, 7), np.float32)), other)
    res = run("convert", other, "-o", tmp_path / "c.nrrd")
    assert res.code == 0, res.stderr
    assert (tmp_path / "c.nrrd").exists()
    # (outside a run, the process's own registry: the warp's input is not in it)
    assert runscope.run_files() is runscope._process
    assert str(src) not in runscope._process.mapped


def test_runs_leave_no_inputs_in_the_process(run, tmp_path):
    """Inputs are noted in the run's scope (not in a process-wide set that only grows)."""
    before = set(runscope._process.inputs)
    src = tmp_path / "in.nrrd"
    write_volume(Volume(np.ones((4, 5, 6), np.float32)), src)
    for k in range(3):
        assert run("convert", src, "-o", tmp_path / f"o{k}.nii").code == 0
    assert runscope._process.inputs == before


def test_a_scope_reaches_the_threads_it_hands_its_context_to():
    """volwarp's own threads run with the caller's context: they note into its scope."""
    from volwarp_cli import parallel

    with runscope.run_scope() as files:
        parallel.run_blocks(lambda i: runscope.run_files().inputs.add((0, i)), range(4), 2)
        assert files.inputs == {(0, 0), (0, 1), (0, 2), (0, 3)}
    seen = []
    with runscope.run_scope() as other:  # another thread's scope is its own
        t = threading.Thread(target=lambda: seen.append(runscope.run_files()))
        t.start()
        t.join()
        assert seen[0] is not other


def test_outputs_follow_the_umask_in_effect_now(tmp_path):
    """The umask is read when an output is made (not once at import), without setting it."""
    from volwarp_cli.io.atomic import current_umask

    old = os.umask(0o027)
    try:
        assert current_umask() == 0o027
        write_volume(Volume(np.ones((3, 3, 3), np.float32)), tmp_path / "a.nrrd")
        assert stat.S_IMODE(os.stat(tmp_path / "a.nrrd").st_mode) == 0o640
        os.umask(0o002)
        assert current_umask() == 0o002
        write_volume(Volume(np.ones((3, 3, 3), np.float32)), tmp_path / "b.nrrd")
        assert stat.S_IMODE(os.stat(tmp_path / "b.nrrd").st_mode) == 0o664
    finally:
        os.umask(old)


def test_allow_outside_data_reaches_the_block_workers(run, tmp_path, monkeypatch):
    """--allow-outside-data by blocks on worker processes: each reopens the input itself,
    with the run's permission (it was an environment variable the workers inherited)."""
    monkeypatch.delenv("VOLWARP_ALLOW_OUTSIDE_DATA", raising=False)
    data = (np.arange(20 * 21 * 22) % 97).astype(np.int16).reshape(22, 21, 20)
    (tmp_path / "secret.raw").write_bytes(data.astype("<i2").tobytes())
    (tmp_path / "hdr").mkdir()
    hdr = tmp_path / "hdr" / "h.nhdr"
    hdr.write_text("NRRD0004\ntype: short\ndimension: 3\nsizes: 20 21 22\nendian: little\n"
                   "encoding: raw\ndata file: ../secret.raw\n")
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    args = ("distance", hdr, "--iso", "40", "--surface", "voxel", "--allow-outside-data")
    assert run(*args, "-o", mem).code == 0
    res = run(*args, "-o", blk, "--chunked", "--block", "7", "--scheduler", "processes")
    assert res.code == 0, res.stderr
    assert blk.read_bytes() == mem.read_bytes()
    res = run("distance", hdr, "--iso", "40", "--surface", "voxel", "-o", tmp_path / "x.nrrd",
              "--chunked", "--scheduler", "processes")
    assert res.code == 1 and "outside the header's folder" in res.stderr
