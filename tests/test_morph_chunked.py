"""`volwarp morph --chunked`: fields kept on disk, frames by blocks, the in-memory bytes.

Odd sizes, blocks that do not divide them, a rotated direction; binary shapes
(the exact passes) and smooth ones (a --max-distance band, sub-voxel); SDF,
density and source-range frames, attributes, meshes and renders; several
schedulers; the switch when the in-memory morph does not fit; what is refused.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.surface.mesh_io import read_mesh
from volwarp_cli.volume import Volume

ROTATED = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
GEOMETRY = dict(spacing=np.array([0.8, 0.9, 1.1]), origin=np.array([10.0, -5.0, 3.0]),
                direction=ROTATED)


def _grid():
    return np.meshgrid(*[np.linspace(-1, 1, n) for n in (23, 27, 19)], indexing="ij")


@pytest.fixture
def shapes(tmp_path):
    """Binary ball and box, smooth int16 blobs, and a float attribute pair."""
    z, y, x = _grid()
    ball = (x * x + y * y + z * z < 0.5).astype(np.uint8)
    box = ((np.abs(x) < 0.6) & (np.abs(y) < 0.3) & (np.abs(z) < 0.7)).astype(np.uint8)
    blob_a = 1000 * np.exp(-((x - 0.2) ** 2 + y * y + z * z) / 0.2)
    blob_b = 900 * np.exp(-(x * x + (y - 0.2) ** 2 + (z + 0.1) ** 2) / 0.15)
    paths = {}
    for name, data in (("ball", ball), ("box", box), ("blob_a", blob_a.astype(np.int16)),
                       ("blob_b", blob_b.astype(np.int16)),
                       ("heat_a", (x + 2 * y).astype(np.float32)),
                       ("heat_b", (z * z * 40).astype(np.uint8))):
        paths[name] = tmp_path / f"{name}.nrrd"
        write_volume(Volume(data, **GEOMETRY), paths[name])
    return paths


def _frames(prefix, n):
    return [read_volume(f"{prefix}_{i}.nrrd") for i in range(n)]


def _same_frames(mem, blk):
    for a, b in zip(mem, blk, strict=True):
        assert a.data.dtype == b.data.dtype and np.array_equal(a.data, b.data)
        assert np.array_equal(b.direction, ROTATED)
        assert np.allclose(a.index_to_world_matrix, b.index_to_world_matrix)
        assert a.meta["volwarp_morph_t"] == b.meta["volwarp_morph_t"]


@pytest.mark.parametrize("case", ["binary", "band", "density", "source-range", "dtype",
                                  "minnorm"])
def test_frames_by_blocks_equal_the_in_memory_frames(run, shapes, tmp_path, case):
    args = {
        "binary": [shapes["ball"], shapes["box"], "--iso", "0.5"],
        "band": [shapes["blob_a"], shapes["blob_b"], "--iso", "300", "--max-distance", "3.5"],
        "density": [shapes["ball"], shapes["box"], "--iso", "0.5", "--density"],
        "source-range": None,
        "dtype": [shapes["ball"], shapes["box"], "--iso", "0.5", "--dtype", "int16"],
        # (spacing-weighted taxicab: the distance's line passes by blocks)
        "minnorm": [shapes["ball"], shapes["box"], "--iso", "0.5", "--metric", "minnorm"],
    }[case]
    if case == "source-range":  # density mapped to the source's int16 range: a spec
        spec = tmp_path / "m.yaml"
        spec.write_text(f"version: 1\nsource: {{volume: {shapes['blob_a']}, iso: 300}}\n"
                        f"target: {{volume: {shapes['blob_b']}, iso: 300}}\nframes: 4\n"
                        "output: density\ndensity: {range: source, width: 1.5}\n"
                        "max_distance: 4\n")
        args = ["--spec", spec]
    else:
        args += ["--frames", "4"]
    assert run("morph", *args, "-o", tmp_path / "m_{i}.nrrd").code == 0
    res = run("morph", *args, "-o", tmp_path / "b_{i}.nrrd", "--chunked", "--block", "7,10,6")
    assert res.code == 0, res.stderr
    mem, blk = _frames(tmp_path / "m", 4), _frames(tmp_path / "b", 4)
    _same_frames(mem, blk)
    note = blk[0].meta["volwarp_morph"]
    assert note == mem[0].meta["volwarp_morph"] and "chunked" not in note
    if case == "source-range":
        assert blk[1].data.dtype == np.int16  # the source's type
    if case == "dtype":
        assert blk[1].data.dtype == np.int16
    # frames really move from source to target (not four copies of one field)
    assert not np.array_equal(blk[0].data, blk[3].data)


def test_meshes_and_renders_by_blocks_equal_the_in_memory_ones(run, shapes, tmp_path):
    common = [shapes["ball"], shapes["box"], "--iso", "0.5", "--frames", "3"]
    assert run("morph", *common, "-o", tmp_path / "m_{i}.nrrd", "--mesh-to",
               tmp_path / "m_{i}.ply", "--render-to", tmp_path / "m_{i}.png",
               "--render-size", "160x120").code == 0
    res = run("morph", *common, "-o", tmp_path / "b_{i}.nrrd", "--mesh-to",
              tmp_path / "b_{i}.ply", "--render-to", tmp_path / "b_{i}.png",
              "--render-size", "160x120", "--chunked", "--block", "9")
    assert res.code == 0, res.stderr

    for i in range(3):
        assert read_mesh(tmp_path / f"m_{i}.ply").n_faces > 100
        assert (tmp_path / f"m_{i}.ply").read_bytes() == (tmp_path / f"b_{i}.ply").read_bytes()
        # one camera for all frames, fitted to both shapes: the pictures are the same
        assert (tmp_path / f"m_{i}.png").read_bytes() == (tmp_path / f"b_{i}.png").read_bytes()


def test_attributes_by_blocks(run, shapes, tmp_path):
    # (heat_b, a few levels of z^2, is what the label rule takes for a label map: blended
    # as numbers as asked, values: intensity)
    spec = tmp_path / "m.yaml"
    spec.write_text(f"version: 1\nsource: {{volume: {shapes['ball']}, iso: 0.5}}\n"
                    f"target: {{volume: {shapes['box']}, iso: 0.5}}\ntimes: [0, 0.4, 1]\n"
                    f"attributes:\n  - {{name: heat, source: {shapes['heat_a']}, "
                    f"target: {shapes['heat_b']}, values: intensity}}\n"
                    f"  - {{name: code, source: {shapes['heat_b']}, target: {shapes['heat_b']},"
                    " dtype: uint8, values: intensity}\n")
    assert run("morph", "--spec", spec, "-o", tmp_path / "m_{i}.nrrd").code == 0
    res = run("morph", "--spec", spec, "-o", tmp_path / "b_{i}.nrrd", "--chunked",
              "--block", "5,27,19")
    assert res.code == 0, res.stderr
    for name, dtype in (("heat", np.float32), ("code", np.uint8)):
        for i in range(3):
            a = read_volume(tmp_path / f"m_{i}_{name}.nrrd")
            b = read_volume(tmp_path / f"b_{i}_{name}.nrrd")
            assert b.data.dtype == dtype and np.array_equal(a.data, b.data)
    heat = read_volume(tmp_path / "b_1_heat.nrrd").data
    z, y, x = _grid()
    expected = 0.6 * (x + 2 * y).astype(np.float32) + 0.4 * (z * z * 40).astype(np.uint8)
    assert np.allclose(heat, expected, atol=1e-5)  # (1 - t) a + t b at t = 0.4


@pytest.mark.parametrize("scheduler", ["processes", "synchronous"])
def test_other_schedulers_and_ome_zarr_frames(run, shapes, tmp_path, scheduler):
    """OME-Zarr frames of a rotated grid: stored reindexed, as the in-memory writer does."""
    from volwarp_cli.io.omezarr import reindex_to_identity

    common = [shapes["blob_a"], shapes["blob_b"], "--iso", "300", "--max-distance", "3",
              "--times", "0,0.5,1"]
    assert run("morph", *common, "-o", tmp_path / "m_{i}.nrrd").code == 0
    assert run("morph", *common, "-o", tmp_path / "m_{i}.ome.zarr").code == 0
    res = run("morph", *common, "-o", tmp_path / "b_{i}.ome.zarr", "--chunked",
              "--scheduler", scheduler, "--block", "12,5,7")
    assert res.code == 0, res.stderr
    for i in range(3):
        mem = read_volume(tmp_path / f"m_{i}.nrrd")
        store = read_volume(tmp_path / f"m_{i}.ome.zarr")
        blk = read_volume(tmp_path / f"b_{i}.ome.zarr")
        assert np.array_equal(store.data, blk.data)
        assert np.allclose(store.index_to_world_matrix, blk.index_to_world_matrix)
        moved = reindex_to_identity(mem)  # every sample at its world point
        assert np.array_equal(moved.data, blk.data)
        assert np.allclose(moved.index_to_world_matrix, blk.index_to_world_matrix)


def test_frames_by_blocks_with_a_pyramid(run, shapes, tmp_path):
    import zarr

    common = [shapes["ball"], shapes["box"], "--iso", "0.5", "--frames", "2", "--pyramid", "2",
              "--density"]
    assert run("morph", *common, "-o", tmp_path / "m_{i}.ome.zarr").code == 0
    res = run("morph", *common, "-o", tmp_path / "b_{i}.ome.zarr", "--chunked", "--block", "8")
    assert res.code == 0, res.stderr
    for i in range(2):
        a, b = zarr.open_group(tmp_path / f"m_{i}.ome.zarr"), zarr.open_group(
            tmp_path / f"b_{i}.ome.zarr")
        for level in ("0", "1", "2"):
            assert np.array_equal(a[level][...], b[level][...])
        # (a density of 0 and 1 is a mask, a label map: its levels take the mode, as in memory)
        assert a.attrs["volwarp"]["downsampling"] == b.attrs["volwarp"]["downsampling"] == "mode"


def test_the_band_clamps_each_field_as_distance_does(run, shapes, tmp_path):
    """Frame 0 with --max-distance D is `volwarp distance --max-distance D` of the source."""
    sdf = tmp_path / "sdf.nrrd"
    assert run("distance", shapes["blob_a"], "-o", sdf, "--iso", "300",
               "--max-distance", "2.5").code == 0
    assert run("morph", shapes["blob_a"], shapes["blob_b"], "--iso", "300", "--frames", "2",
               "--max-distance", "2.5", "-o", tmp_path / "m_{i}.nrrd").code == 0
    frame0 = read_volume(tmp_path / "m_0.nrrd").data
    assert np.array_equal(frame0, read_volume(sdf).data)
    assert frame0.min() == -2.5 and frame0.max() == 2.5
    assert "max_distance=2.5" in read_volume(tmp_path / "m_1.nrrd").meta["volwarp_morph"]


def test_a_morph_too_big_for_the_budget_runs_by_blocks(run, shapes, tmp_path, monkeypatch):
    from volwarp_cli import memory

    common = [shapes["ball"], shapes["box"], "--iso", "0.5", "--frames", "3"]
    assert run("morph", *common, "-o", tmp_path / "m_{i}.nrrd").code == 0
    monkeypatch.setattr(memory, "process_rss", lambda: 0)
    monkeypatch.setattr("volwarp_cli.execute.MIN_BLOCK_BUDGET", 64 << 10)
    res = run("morph", *common, "-o", tmp_path / "b_{i}.nrrd", "--memory-limit", "150K")
    assert res.code == 0, res.stderr
    assert "running by blocks" in res.stderr
    _same_frames(_frames(tmp_path / "m", 3), _frames(tmp_path / "b", 3))
    # --no-chunked: the refusal stands, an existing frame untouched
    (tmp_path / "c_0.nrrd").write_bytes(b"old")
    res = run("morph", *common, "-o", tmp_path / "c_{i}.nrrd", "--memory-limit", "150K",
              "--no-chunked")
    assert res.code == 1 and "needs" in res.stderr
    assert (tmp_path / "c_0.nrrd").read_bytes() == b"old"
    assert not (tmp_path / "c_1.nrrd").exists()


def test_what_the_block_path_refuses(run, shapes, tmp_path):
    out = tmp_path / "o_{i}.nrrd"
    spec = tmp_path / "m.yaml"
    spec.write_text(f"version: 1\nsource: {{volume: {shapes['ball']}, iso: 0.5}}\n"
                    f"target: {{volume: {shapes['box']}, iso: 0.5}}\nframes: 2\n"
                    "align: {target: {translate: [1, 0, 0]}}\n")
    res = run("morph", "--spec", spec, "-o", out, "--chunked")
    assert res.code == 2 and "alignment" in res.stderr
    # the voxel-step metrics need isotropic spacing, by blocks as in memory
    res = run("morph", shapes["ball"], shapes["box"], "--iso", "0.5", "--frames", "2",
              "--metric", "chessboard", "-o", out, "--chunked")
    assert res.code == 1 and "isotropic" in res.stderr
    # smooth samples need a band out of core (their sub-voxel field)
    res = run("morph", shapes["blob_a"], shapes["blob_b"], "--iso", "300", "--frames", "2",
              "-o", out, "--chunked")
    assert res.code == 1 and "max-distance" in res.stderr
    assert "--surface" not in res.stderr  # (no morph option: a spec's surface: voxel)
    # a compressed frame format: refused before any work
    res = run("morph", shapes["ball"], shapes["box"], "--iso", "0.5", "--frames", "2",
              "-o", tmp_path / "o_{i}.nii.gz", "--chunked")
    assert res.code == 2 and "block by block" in res.stderr  # (a usage error)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("o_")) == []
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no scratch left


def test_a_failing_block_leaves_no_frame_and_no_scratch(run, shapes, tmp_path, monkeypatch):
    from volwarp_cli.morph.frames import FrameOperation

    real = FrameOperation.compute
    calls = []

    def flaky(self, box, *, threads):
        calls.append(self.t)
        if self.t > 0.5 and len(calls) > 3:
            raise OSError("disk on fire")
        return real(self, box, threads=threads)

    monkeypatch.setattr(FrameOperation, "compute", flaky)
    res = run("morph", shapes["ball"], shapes["box"], "--iso", "0.5", "--frames", "3",
              "-o", tmp_path / "o_{i}.nrrd", "--chunked", "--block", "8",
              "--scheduler", "synchronous")
    assert res.code == 1 and "disk on fire" in res.stderr
    left = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("o_", ".")))
    # frames 0 and 1 were complete, but a morph's frames are one set: none is put in place
    assert left == []


@pytest.mark.parametrize("chunked", [[], ["--chunked", "--block", "8"]])
def test_a_failed_rerun_leaves_the_previous_frames_as_they_were(run, shapes, tmp_path,
                                                                 monkeypatch, chunked):
    """A rerun that fails half-way leaves the last run's set, never a mix of new and old."""
    from volwarp_cli.morph.frames import FrameOperation

    out = tmp_path / "o_{i}.nrrd"
    mesh = tmp_path / "o_{i}.ply"
    args = ["--iso", "0.5", "--frames", "3", "-o", out, "--mesh-to", mesh, *chunked]
    assert run("morph", shapes["ball"], shapes["box"], *args).code == 0
    names = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith("o_"))
    assert len(names) == 6
    before = {n: (tmp_path / n).read_bytes() for n in names}
    real = FrameOperation.compute

    def fails_last(self, box, *, threads):
        if self.t == 1.0:
            raise OSError("disk on fire")
        return real(self, box, threads=threads)

    monkeypatch.setattr(FrameOperation, "compute", fails_last)
    # the other way round: every frame but the last would differ from the first run's
    res = run("morph", shapes["box"], shapes["ball"], *args)
    assert res.code == 1 and "disk on fire" in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("o_", "."))) == names
    assert {n: (tmp_path / n).read_bytes() for n in names} == before
    monkeypatch.setattr(FrameOperation, "compute", real)
    assert run("morph", shapes["box"], shapes["ball"], *args).code == 0
    assert (tmp_path / "o_0.nrrd").read_bytes() != before["o_0.nrrd"]


def test_a_failing_block_leaves_no_store_temporary_while_others_still_write(run, shapes,
                                                                          tmp_path,
                                                                          monkeypatch):
    """The blocks still running when one fails finish before the outputs are removed.

    (A late block wrote into an OME-Zarr temporary already removed, re-creating
    it: a .partdir was left behind.)
    """
    import time

    from volwarp_cli.morph.frames import FrameOperation

    real = FrameOperation.compute

    def slow_or_failing(self, box, *, threads):
        if box.lo == (0, 0, 0):
            raise OSError("disk on fire")
        time.sleep(0.2)
        return real(self, box, threads=threads)

    monkeypatch.setattr(FrameOperation, "compute", slow_or_failing)
    res = run("morph", shapes["ball"], shapes["box"], "--iso", "0.5", "--frames", "2",
              "-o", tmp_path / "o_{i}.ome.zarr", "--chunked", "--block", "6,7,5",
              "--scheduler", "threads", "--workers", "2")
    assert res.code == 1 and "disk on fire" in res.stderr
    time.sleep(0.5)  # (what a late block would write, it would have written by now)
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith((".o_", "o_"))]


def test_every_frame_by_blocks_is_cut_as_the_first(run, shapes, tmp_path, monkeypatch):
    """The frames' blocks are chosen once: a budget that shrinks meanwhile changes no store.

    (Each frame re-planned its blocks from the budget left, so identical runs
    wrote OME-Zarr stores of other chunks as the process's memory varied.)
    """
    import json

    from volwarp_cli import execute

    real = execute.block_budget
    calls = []

    def shrinking():
        calls.append(1)
        return max(execute.MIN_BLOCK_BUDGET, real() // len(calls))

    monkeypatch.setattr(execute, "block_budget", shrinking)
    from volwarp_cli.morph import frames  # (blocks of a few thousand voxels, on a small grid)

    monkeypatch.setattr(frames, "FRAME_BYTES_PER_VOXEL", 100_000)
    res = run("morph", shapes["ball"], shapes["box"], "--iso", "0.5", "--frames", "3",
              "-o", tmp_path / "o_{i}.ome.zarr", "--chunked")
    assert res.code == 0, res.stderr
    assert len(calls) >= 3
    layouts = {json.dumps(json.loads((tmp_path / f"o_{i}.ome.zarr" / "0" / "zarr.json")
                                     .read_text())["chunk_grid"]) for i in range(3)}
    assert len(layouts) == 1


def test_a_source_with_nan_has_the_range_of_its_finite_samples(run, tmp_path):
    """density: {range: source} of a source with NaN samples (outside the shape, as said)."""
    z, y, x = np.mgrid[:20, :20, :20].astype(np.float32)
    src = 100 - 5 * np.sqrt((x - 9) ** 2 + (y - 10) ** 2 + (z - 10) ** 2)
    src[:3] = np.nan
    write_volume(Volume(src.astype(np.float32)), tmp_path / "s.nrrd")
    write_volume(Volume((100 - 5 * np.sqrt((x - 11) ** 2 + (y - 9) ** 2 + (z - 10) ** 2))
                        .astype(np.float32)), tmp_path / "t.nrrd")
    (tmp_path / "m.yaml").write_text(
        "version: 1\nsource: {volume: s.nrrd, iso: 50}\ntarget: {volume: t.nrrd, iso: 50}\n"
        "times: [0, 1]\noutput: density\ndensity: {range: source}\n")
    res = run("morph", "--spec", tmp_path / "m.yaml", "-o", tmp_path / "f_{i}.nrrd")
    assert res.code == 0, res.stderr
    f0 = read_volume(tmp_path / "f_0.nrrd").data
    assert f0.dtype == np.float32 and np.isfinite(f0).all()
    assert f0.min() >= np.nanmin(src) and f0.max() <= np.nanmax(src)
    assert np.array_equal(f0[3:] >= 50, src[3:] >= 50)
