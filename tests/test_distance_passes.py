"""The distance fields in passes (:mod:`volwarp_cli.distance.passes`), against references.

In memory and by blocks run the same pass functions, so equal bytes alone
would prove little: each way is checked against an independent reference
(scipy's exact transform; scipy's KD-tree for the taxicab, chessboard and
spacing-weighted taxicab distances to the nearest voxel of the other side),
and the two ways against each other bit for bit, on blocks of whole lines,
on slabs of planes, and where a plane does not fit the budget.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys

import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from volwarp_cli import execute
from volwarp_cli.distance.exact import x_pass, y_pass, z_pass
from volwarp_cli.distance.labels import ShapeRule
from volwarp_cli.distance.operation import field_operation
from volwarp_cli.engine import open_engine
from volwarp_cli.errors import OutOfMemoryError, VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.passes import last_pass_block, run_by_blocks
from volwarp_cli.volume import Volume, zyx_to_xyz

SHAPE = (23, 17, 19)  # z, y, x: odd; no block below divides them
ANISO = (1.7, 0.6, 1.1)
RULE = ShapeRule("intensity", "given", iso=0.5)


def blobs(shape, seed, sigma=1.5, level=0.52):
    return ndi.gaussian_filter(np.random.default_rng(seed).random(shape), sigma) > level


def same(a, b):
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def nearest_other(mask, spacing, p):
    """Signed distance to the nearest voxel of the other side, in the Minkowski ``p`` norm."""
    pts = np.indices(mask.shape).reshape(3, -1).T * np.asarray(spacing, float)
    flat = mask.ravel()
    out = np.empty(mask.size)
    for side, sign in ((flat, -1.0), (~flat, 1.0)):
        d, _ = cKDTree(pts[~side]).query(pts[side], p=p)
        out[side] = sign * d
    return out.reshape(mask.shape)


REFERENCES = {
    "euclidean": lambda m, h: (ndi.distance_transform_edt(~m, sampling=h)
                               - ndi.distance_transform_edt(m, sampling=h)),
    "minnorm": lambda m, h: nearest_other(m, h, 1),
    "taxicab": lambda m, h: nearest_other(m, (1, 1, 1), 1) * h[0],
    "chessboard": lambda m, h: nearest_other(m, (1, 1, 1), np.inf) * h[0],
}
CASES = [("euclidean", ANISO), ("euclidean", (1.0, 1.0, 1.0)), ("minnorm", ANISO),
         ("taxicab", (0.7,) * 3), ("chessboard", (1.3,) * 3)]


def _op(data, spacing, metric, path, *, max_distance=None, unsigned=False, dtype=np.float32,
        rule=RULE):
    grid = Geometry(data.shape, zyx_to_xyz(spacing))
    target = execute.Target(path, grid.header(dtype), np.dtype(dtype))
    return field_operation(data, grid, rule, metric=metric, surface="voxel",
                           max_distance=max_distance, unsigned=unsigned, target=target)


def _run(op, *, chunked, block=None, scheduler="threads"):
    @contextlib.contextmanager
    def engine():
        with open_engine(scheduler, workers=3) as eng:
            yield eng

    ran = execute.run(op, execute.How(chunked=chunked, block=block, open_engine=engine))
    return np.asarray(read_volume(op.targets["field"].path).data), ran


@pytest.mark.parametrize("metric,spacing", CASES)
def test_in_memory_and_by_blocks_equal_the_reference(tmp_path, metric, spacing):
    mask = blobs(SHAPE, 1)
    data = mask.astype(np.float32) * 3  # intensities: the shape is >= 0.5
    ref = REFERENCES[metric](mask, spacing)
    mem, ran = _run(_op(data, spacing, metric, tmp_path / "m.nrrd"), chunked=False)
    assert not ran.by_blocks
    np.testing.assert_allclose(mem, ref, rtol=1e-6, atol=1e-5)
    for i, block in enumerate([(5, 6, 7), (1, 17, 2), None]):
        blk, ran = _run(_op(data, spacing, metric, tmp_path / f"b{i}.nrrd"), chunked=True,
                        block=block)
        assert ran.by_blocks and ran.blocks > 3
        assert same(blk, mem), (metric, block)


@pytest.mark.parametrize("metric,spacing", CASES)
def test_a_plane_over_the_budget_runs_x_then_y(tmp_path, metric, spacing):
    """Blocks of a few lines (x, then y, through the scratch): the in-memory bytes."""
    mask = blobs(SHAPE, 2)
    mem, _ = _run(_op(mask, spacing, metric, tmp_path / "m.nrrd"), chunked=False)
    op = _op(mask, spacing, metric, tmp_path / "s.nrrd")
    budget = 60 * SHAPE[2]  # a couple of x lines
    assert [p.name for p in op.passes(budget)] == ["x", "y", "z"]
    block = last_pass_block(op, block_bytes=budget, workers=3)
    with open_engine("threads", workers=3) as eng, \
            op.targets["field"].open_blocks(block) as out:
        count = run_by_blocks(op, eng, {"field": out}, block_bytes=budget)
    assert count > 3 * 20
    assert same(np.asarray(read_volume(tmp_path / "s.nrrd").data), mem)


@pytest.mark.parametrize("metric", ["minnorm", "chessboard"])
def test_band_unsigned_and_type_are_applied_per_block(tmp_path, metric):
    mask = blobs(SHAPE, 3)
    spacing = (1.0, 1.0, 1.0)
    ref = np.clip(np.maximum(REFERENCES[metric](mask, spacing), 0), -2.5, 2.5)
    kw = dict(max_distance=2.5, unsigned=True, dtype=np.float64)
    mem, _ = _run(_op(mask, spacing, metric, tmp_path / "m.nrrd", **kw), chunked=False)
    blk, _ = _run(_op(mask, spacing, metric, tmp_path / "b.nrrd", **kw), chunked=True,
                  block=(4, 5, 6), scheduler="processes")
    assert mem.dtype == np.float64 and same(blk, mem)
    np.testing.assert_allclose(mem, ref, atol=1e-6)


def test_a_label_rule_is_its_voxels_never_its_ids(tmp_path):
    ids = blobs(SHAPE, 4).astype(np.int16) * 7 + blobs(SHAPE, 5).astype(np.int16) * 3
    rule = ShapeRule("labels", "given", label=None)
    ref = REFERENCES["euclidean"](ids != 0, ANISO)
    for chunked in (False, True):
        got, _ = _run(_op(ids, ANISO, "euclidean", tmp_path / f"{chunked}.nrrd", rule=rule),
                      chunked=chunked, block=(6, 5, 4))
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-5)


def test_a_pass_on_cut_lines_is_wrong():
    """The tests above can fail: an x pass on blocks that cut the x lines gives other values."""
    mask = blobs(SHAPE, 0).view(np.uint8)
    field = np.empty(SHAPE, np.float32)
    for lo in range(0, SHAPE[2], 7):
        out = np.empty((*SHAPE[:2], min(7, SHAPE[2] - lo)), np.float32)
        x_pass(np.ascontiguousarray(mask[:, :, lo:lo + 7]), ANISO[2], out)
        field[:, :, lo:lo + 7] = out
    y_pass(field, mask, ANISO[1])
    z_pass(field, ANISO[0])
    ref = REFERENCES["euclidean"](mask.view(bool), ANISO)
    assert not np.allclose(field, ref, rtol=1e-6, atol=1e-5)


def test_the_c_passes_check_their_buffers():
    """A wrong call is an exception, and writes nothing (the passes are C: ``_edtkernels.c``)."""
    mask = blobs(SHAPE, 1).view(np.uint8)
    out = np.full(SHAPE, 7, np.float32)
    with pytest.raises(TypeError, match="float32"):
        x_pass(mask, 1.0, out.astype(np.float64))
    with pytest.raises(TypeError, match="uint8"):
        x_pass(mask.astype(np.int16), 1.0, out)
    with pytest.raises(TypeError, match="float32"):  # (the other byte order: not read as ours)
        x_pass(mask, 1.0, out.astype(out.dtype.newbyteorder()))
    with pytest.raises(ValueError, match="shapes differ"):
        x_pass(mask[:, :, 1:], 1.0, out)
    with pytest.raises(ValueError, match="3 dimensions"):
        y_pass(out[0], mask[0], 1.0)
    with pytest.raises(ValueError, match="shapes differ"):
        y_pass(out[:, 1:], mask, 1.0)
    with pytest.raises((ValueError, BufferError), match="read-only|not writable"):
        z_pass(np.broadcast_to(np.float32(1), SHAPE), 1.0)
    assert (out == 7).all()
    # any strides: the z pass on a view (a block of whole z lines) = on its copy
    x_pass(mask, ANISO[2], out)
    y_pass(out, mask, ANISO[1])
    part = np.ascontiguousarray(out[:, 3:11, ::2])
    z_pass(out[:, 3:11, ::2], ANISO[0])
    z_pass(part, ANISO[0])
    assert np.array_equal(out[:, 3:11, ::2], part)


def test_the_exact_distance_loads_no_numba(tmp_path):
    """The exact field's command path imports no numba (its start-up was half the command)."""
    mask = np.zeros((12, 13, 14), np.uint8)
    mask[3:9, 2:10, 4:11] = 1
    write_volume(Volume(mask), tmp_path / "m.nrrd")
    code = ("import sys\n"
            "from volwarp_cli.cli.main import main\n"
            "for extra in ([], ['--chunked', '--block', '5,6,7']):\n"
            f"    assert main(['distance', r'{tmp_path / 'm.nrrd'}', '-o', r'{tmp_path / 'd.nrrd'}',"
            " '--surface', 'voxel', *extra]) == 0\n"
            "assert 'numba' not in sys.modules, 'numba imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    got = read_volume(tmp_path / "d.nrrd").data
    np.testing.assert_allclose(got, REFERENCES["euclidean"](mask.view(bool), (1, 1, 1)),
                               rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("chunked", [False, True])
def test_the_whole_is_checked_in_the_first_pass(tmp_path, chunked, caplog):
    data = np.zeros(SHAPE, np.float32)
    with pytest.raises(VolwarpError, match="the shape is empty"):
        _run(_op(data, ANISO, "euclidean", tmp_path / "e.nrrd"), chunked=chunked)
    data[:] = 1
    with pytest.raises(VolwarpError, match="fills the whole grid"):
        _run(_op(data, ANISO, "minnorm", tmp_path / "f.nrrd"), chunked=chunked)
    data[0, 0, 0] = np.nan  # outside: now a shape with a surface, and a warning
    field, _ = _run(_op(data, ANISO, "minnorm", tmp_path / "n.nrrd"), chunked=chunked)
    assert "1 NaN samples" in caplog.text and field[0, 0, 0] > 0 > field[5, 5, 5]
    assert not (tmp_path / "e.nrrd").exists()


def test_anisotropic_voxel_step_metrics_are_refused(tmp_path):
    with pytest.raises(VolwarpError, match="needs isotropic spacing"):
        _op(blobs(SHAPE, 1), ANISO, "chessboard", tmp_path / "c.nrrd")


def test_a_block_task_pickles_small(tmp_path):
    """By processes every pass task pickles the operation: its output (its Header, of the
    whole grid) must not travel as an array (it did: 64 MiB a task)."""
    import pickle

    shape = (96, 96, 96)
    data = np.zeros(shape, np.uint8)
    op = _op(data, (1.0, 1.0, 1.0), "euclidean", tmp_path / "o.nrrd")
    op.masks.source = None  # (a lazy reader by blocks; here only the op's own weight)
    size = len(pickle.dumps(op.passes(1 << 20)[-1].block))
    assert size < 20_000, size
    header = op.targets["field"].header
    assert len(pickle.dumps(header)) < 2_000
    again = pickle.loads(pickle.dumps(header))
    assert again.shape == shape and Geometry.of(again) == Geometry.of(header)


@pytest.mark.parametrize("metric", ["euclidean", "minnorm"])
def test_a_user_block_over_a_task_s_budget_is_refused_before_any_work(tmp_path, monkeypatch,
                                                                       metric):
    """``--block`` is weighed as warp's, apply's and sweep's are: one pass's block (its lines
    made whole) over a task's share is refused in their words, nothing computed or written."""
    spacing = (1.0, 1.0, 1.0)
    monkeypatch.setattr(execute, "block_budget", lambda: 3 * 20_000)  # 3 workers: 20 kB each
    data = blobs(SHAPE, 1).astype(np.float32)
    old = tmp_path / "o.nrrd"
    old.write_bytes(b"an earlier output")
    op = _op(data, spacing, metric, old)
    with pytest.raises(OutOfMemoryError) as err:
        _run(op, chunked=True, block=SHAPE)
    msg = str(err.value)
    assert msg.startswith(f"{op.what}: a block of 23x17x19 (z, y, x) needs "), msg
    assert "more than the 19.5 KiB each of 3 workers may use" in msg and "\n" not in msg
    assert old.read_bytes() == b"an earlier output"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.nrrd"]
    # a block within the share runs: the in-memory bytes
    mem, _ = _run(_op(data, spacing, metric, tmp_path / "m.nrrd"), chunked=False)
    blk, ran = _run(_op(data, spacing, metric, tmp_path / "b.nrrd"), chunked=True,
                    block=(2, 3, 4))
    assert ran.by_blocks and same(blk, mem)
