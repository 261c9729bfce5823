"""`volwarp distance --chunked` and `volwarp mesh --chunked`: the same results as in memory.

Odd sizes, blocks that do not divide them, a rotated direction, NRRD and OME-Zarr
inputs and outputs, several schedulers; the metadata of a banded field; refusals.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.surface.mesh_io import read_mesh
from volwarp_cli.volume import Volume

ROTATED = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture
def scan(tmp_path):
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (37, 41, 29)], indexing="ij")
    blob = 1000 * np.exp(-((x - 0.2) ** 2 + y * y + z * z) / 0.2)
    blob += 800 * np.exp(-((x + 0.5) ** 2 + (y - 0.4) ** 2 + (z + 0.3) ** 2) / 0.05)
    vol = Volume(blob.astype(np.int16), spacing=np.array([0.8, 0.9, 1.1]),
                 origin=np.array([10.0, -5.0, 3.0]), direction=ROTATED)
    path = tmp_path / "in.nrrd"
    write_volume(vol, path)
    return path


@pytest.mark.parametrize("extra", [["--surface", "voxel"], ["--max-distance", "4.5"],
                                   ["--surface", "voxel", "--max-distance", "3", "--unsigned"],
                                   ["--surface", "voxel", "--dtype", "int16"]])
def test_distance_by_blocks_equals_in_memory(run, scan, tmp_path, extra):
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    assert run("distance", scan, "-o", mem, "--iso", "300", *extra).code == 0
    res = run("distance", scan, "-o", blk, "--iso", "300", "--chunked", "--block", "10,7,13",
              *extra)
    assert res.code == 0, res.stderr
    a, b = read_volume(mem), read_volume(blk)
    assert a.data.dtype == b.data.dtype and np.array_equal(a.data, b.data)
    assert np.array_equal(b.direction, ROTATED)
    note = b.meta["volwarp_distance"]
    assert note == a.meta["volwarp_distance"]  # how it was computed is not in the file
    assert "chunked" not in note
    assert ("clamped outside" in note) == ("--max-distance" in extra)
    if "--dtype" not in extra:  # (and so the files are the same bytes)
        assert mem.read_bytes() == blk.read_bytes()


@pytest.mark.parametrize("scheduler", ["processes", "synchronous"])
def test_distance_to_ome_zarr_on_other_schedulers(run, scan, tmp_path, scheduler):
    zin = tmp_path / "in.ome.zarr"
    assert run("convert", scan, "-o", zin).code == 0
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.ome.zarr"
    assert run("distance", zin, "-o", mem, "--iso", "300", "--surface", "voxel").code == 0
    res = run("distance", zin, "-o", blk, "--iso", "300", "--surface", "voxel", "--chunked",
              "--scheduler", scheduler)
    assert res.code == 0, res.stderr
    assert np.array_equal(read_volume(mem).data, read_volume(blk).data)


def test_distance_refusals_by_blocks(run, scan, tmp_path):
    out = tmp_path / "o.nrrd"
    res = run("distance", scan, "-o", out, "--iso", "300", "--chunked")  # smooth: sub-voxel
    assert res.code == 1 and "--max-distance" in res.stderr
    # the voxel-step metrics need isotropic spacing by blocks as in memory (0.8, 0.9, 1.1 here)
    res = run("distance", scan, "-o", out, "--iso", "300", "--chunked", "--metric", "taxicab")
    assert res.code == 1 and "needs isotropic spacing" in res.stderr
    res = run("distance", scan, "-o", tmp_path / "o.nii.gz", "--iso", "300", "--chunked",
              "--surface", "voxel")
    assert res.code == 2 and "block by block" in res.stderr  # (a usage error)
    assert not out.exists() and not any("part" in p.name for p in tmp_path.iterdir())
    assert not (tmp_path / "o.nii.gz").exists()


@pytest.mark.parametrize("dtype,method", [("float32", "mean"), ("int16", "mean")])
def test_distance_by_blocks_with_a_pyramid_equals_in_memory(run, scan, tmp_path, dtype,
                                                            method):
    """The levels are built on commit from the blocks written, as the in-memory writer
    builds them; whether an integer output's levels take the mode is decided from the
    samples written, as in memory (an int16 field of whole voxel distances steps through
    its levels, a density by the label rule's third test: the mean, by blocks too; it was
    taken for labels before)."""
    import zarr

    common = ["--iso", "300", "--surface", "voxel", "--pyramid", "2", "--dtype", dtype]
    mem, blk = tmp_path / "m.ome.zarr", tmp_path / "b.ome.zarr"
    assert run("distance", scan, "-o", mem, *common).code == 0
    res = run("distance", scan, "-o", blk, *common, "--chunked", "--block", "10,7,13")
    assert res.code == 0, res.stderr
    a, b = zarr.open_group(mem), zarr.open_group(blk)
    for level in ("0", "1", "2"):
        assert a[level].dtype == b[level].dtype and np.array_equal(a[level][...], b[level][...])
    assert a.attrs["volwarp"] == b.attrs["volwarp"] | {"meta": a.attrs["volwarp"]["meta"]}
    assert b.attrs["volwarp"]["downsampling"] == method
    assert a.attrs["ome"]["multiscales"] == b.attrs["ome"]["multiscales"]


@pytest.mark.parametrize("version", ["0.5", "0.4"])
def test_ome_zarr_by_blocks_on_a_permuted_grid_is_stored_reindexed(run, scan, tmp_path,
                                                                   version):
    """The rotated grid's store is the in-memory writer's: flipped and transposed to the
    identity direction, block by block, on the store's own grid (counted from the far end
    along the reversed axis), with blocks that do not divide the sizes."""
    mem, blk = tmp_path / "m.ome.zarr", tmp_path / "b.ome.zarr"
    common = ["--iso", "300", "--surface", "voxel", "--ome-zarr-version", version]
    assert run("distance", scan, "-o", mem, *common).code == 0
    res = run("distance", scan, "-o", blk, *common, "--chunked", "--block", "10,7,13",
              "--scheduler", "processes")
    assert res.code == 0, res.stderr
    assert _tree(mem) == _tree(blk)  # (blocks staged, the store written on commit)
    a, b = read_volume(mem), read_volume(blk)
    assert np.array_equal(b.direction, np.eye(3)) and b.data.shape == (37, 29, 41)
    assert np.array_equal(a.data, b.data)
    assert np.allclose(a.index_to_world_matrix, b.index_to_world_matrix)
    # the same world point holds the same value as the NRRD field of the original grid
    ref = tmp_path / "r.nrrd"
    assert run("distance", scan, "-o", ref, "--iso", "300", "--surface", "voxel").code == 0
    r = read_volume(ref)
    ijk = np.array([3, 30, 17, 1.0])  # x, y, z of the original grid
    world = r.index_to_world_matrix @ ijk
    back = np.rint(np.linalg.inv(b.index_to_world_matrix) @ world).astype(int)
    assert r.data[17, 30, 3] == b.data[back[2], back[1], back[0]]


def _canonical(mesh):
    v = mesh.vertices
    order = np.lexsort(v.T[::-1])
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))
    f = inv[mesh.faces]
    f = np.stack([np.roll(t, -int(np.argmin(t))) for t in f])
    return v[order], f[np.lexsort(f.T[::-1])]


@pytest.mark.parametrize("extra", [[], ["--cap"], ["--largest-component"]])
def test_mesh_by_blocks_equals_in_memory(run, scan, tmp_path, extra):
    mem, blk = tmp_path / "m.ply", tmp_path / "b.ply"
    assert run("mesh", scan, "-o", mem, "--iso", "300", *extra).code == 0
    res = run("mesh", scan, "-o", blk, "--iso", "300", "--chunked", "--block", "10,7,13",
              *extra)
    assert res.code == 0, res.stderr
    a, b = read_mesh(mem), read_mesh(blk)
    assert (a.n_vertices, a.n_faces) == (b.n_vertices, b.n_faces) and a.n_faces > 1000
    va, fa = _canonical(a)
    vb, fb = _canonical(b)
    assert np.array_equal(va, vb) and np.array_equal(fa, fb)


def test_mesh_blocks_are_the_same_on_processes(run, scan, tmp_path):
    a, b = tmp_path / "a.ply", tmp_path / "b.ply"
    assert run("mesh", scan, "-o", a, "--iso", "300", "--chunked", "--block", "12").code == 0
    res = run("mesh", scan, "-o", b, "--iso", "300", "--chunked", "--block", "12",
              "--scheduler", "processes")
    assert res.code == 0, res.stderr
    assert a.read_bytes() == b.read_bytes()


@pytest.fixture
def seg(tmp_path):
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (21, 25, 19)], indexing="ij")
    lab = np.zeros(x.shape, np.int16)
    lab[x * x + y * y + z * z < 0.6] = 3
    lab[(np.abs(x - 0.3) < 0.25) & (np.abs(y) < 0.3) & (np.abs(z) < 0.4)] = 7
    lab[(np.abs(x + 0.4) < 0.12) & (np.abs(y + 0.1) < 0.12) & (np.abs(z) < 0.12)] = -2
    lab[0, 3:6, 4:9] = 5  # on the border: capped
    path = tmp_path / "seg.nrrd"
    write_volume(Volume(lab, spacing=np.array([0.8, 0.9, 1.1]),
                        origin=np.array([10.0, -5.0, 3.0]), direction=ROTATED), path)
    return path


@pytest.mark.parametrize("scheduler", [None, "processes"])
def test_label_meshes_by_blocks_equal_in_memory(run, seg, tmp_path, scheduler):
    """--labels and --label N by blocks: each label's indicator meshed at 0.5 and capped,
    the same vertices and faces as in memory (canonical order); absent labels refused."""
    extra = ["--chunked", "--block", "7,9,5"] + (["--scheduler", scheduler] if scheduler else [])
    assert run("mesh", seg, "--labels", "-o", tmp_path / "m_{label}.ply").code == 0
    res = run("mesh", seg, "--labels", "-o", tmp_path / "b_{label}.ply", *extra)
    assert res.code == 0, res.stderr
    for label in (-2, 3, 5, 7):
        a = read_mesh(tmp_path / f"m_{label}.ply")
        b = read_mesh(tmp_path / f"b_{label}.ply")
        assert a.n_faces > 10
        for x, y in zip(_canonical(a), _canonical(b), strict=True):
            assert np.array_equal(x, y)
    assert not (tmp_path / "b_0.ply").exists()
    one = tmp_path / "one.ply"
    res = run("mesh", seg, "--label", "7", "-o", one, *extra)
    assert res.code == 0, res.stderr
    for x, y in zip(_canonical(read_mesh(one)), _canonical(read_mesh(tmp_path / "m_7.ply")),
                    strict=True):
        assert np.array_equal(x, y)
    res = run("mesh", seg, "--label", "4", "-o", tmp_path / "none.ply", *extra)
    assert res.code == 1 and "label 4 does not occur" in res.stderr
    res = run("mesh", seg, "--labels", "-o",
              tmp_path / "x.ply", *extra)
    assert res.code == 2 and "{label}" in res.stderr


SWEEP = """version: 1
grid: {spacing: 0.5}
fields:
  opacity: {value: 0.8}
  red: 0.25
trajectory:
  - line: {from: [0, 0, 0], to: [6, 1, 0]}
  - arc: {center: [6, 4, 0], radius: 3, axis: [0, 0, 1], start: -90, end: 0}
scale: [3, 2]
"""


@pytest.mark.parametrize("method,extra", [("voxelize", []), ("direct", []),
                                          ("voxelize", ["--dtype", "uint8"])])
def test_sweep_by_blocks_equals_in_memory(run, tmp_path, method, extra):
    spec = tmp_path / "s.yaml"
    spec.write_text(SWEEP if method == "voxelize" else SWEEP.split("  - arc")[0]
                    + "scale: [3, 2]\nup: [0, 0, 1]\n")
    args = ["--method", method, *extra]
    assert run("sweep", spec, "-o", tmp_path / "m_{field}.nrrd", *args).code == 0
    res = run("sweep", spec, "-o", tmp_path / "b_{field}.nrrd", "--chunked", "--block",
              "10,7,13", *args)
    assert res.code == 0, res.stderr
    for field in ("opacity", "red"):
        a = read_volume(tmp_path / f"m_{field}.nrrd")
        b = read_volume(tmp_path / f"b_{field}.nrrd")
        assert a.data.dtype == b.data.dtype and np.array_equal(a.data, b.data)
        assert a.data.any()
        assert (tmp_path / f"m_{field}.nrrd").read_bytes() == \
            (tmp_path / f"b_{field}.nrrd").read_bytes()


def test_sweep_by_blocks_to_ome_zarr_on_processes(run, tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text(SWEEP)
    assert run("sweep", spec, "-o", tmp_path / "m_{field}.nrrd").code == 0
    res = run("sweep", spec, "-o", tmp_path / "b_{field}.ome.zarr", "--chunked",
              "--scheduler", "processes", "--block", "16")
    assert res.code == 0, res.stderr
    for field in ("opacity", "red"):
        assert np.array_equal(read_volume(tmp_path / f"m_{field}.nrrd").data,
                              read_volume(tmp_path / f"b_{field}.ome.zarr").data)


@pytest.mark.parametrize("scheduler", [None, "processes"])
def test_multi_component_sweep_by_blocks_is_the_in_memory_file(run, tmp_path, scheduler):
    """--multi by blocks: every block's fields interleaved in place, the same bytes."""
    spec = tmp_path / "s.yaml"
    spec.write_text(SWEEP)
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    assert run("sweep", spec, "-o", mem, "--multi").code == 0
    extra = ["--scheduler", scheduler] if scheduler else []
    res = run("sweep", spec, "-o", blk, "--multi", "--chunked", "--block", "10,7,13", *extra)
    assert res.code == 0, res.stderr
    assert blk.read_bytes() == mem.read_bytes()
    from volwarp_cli.io.nrrd import read_nrrd

    assert run("sweep", spec, "-o", tmp_path / "m_{field}.nrrd").code == 0
    for i, field in enumerate(("opacity", "red")):  # each component is that field's file
        a = read_nrrd(blk, component=i).data
        assert a.any() and np.array_equal(a, read_volume(tmp_path / f"m_{field}.nrrd").data)
    res = run("sweep", spec, "-o", tmp_path / "o.nhdr", "--multi", "--chunked")
    assert res.code == 2 and "block" in res.stderr  # (a usage error)


def test_distance_passes_take_the_block_size(run, scan, tmp_path):
    """--block Z,Y,X for the exact field: slabs of Z planes for the x/y passes, columns of
    Y by X for the z pass (whole lines either way); the same field as in memory."""
    import json

    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    assert run("distance", scan, "-o", mem, "--iso", "300", "--surface", "voxel").code == 0
    res = run("distance", scan, "-o", blk, "--iso", "300", "--surface", "voxel", "--chunked",
              "--block", "10,7,13", "--progress", "jsonl", "--scheduler", "synchronous")
    assert res.code == 0, res.stderr
    ids = {json.loads(line)["id"] for line in res.stderr.splitlines() if line.startswith("{")}
    assert {i for i in ids if i.startswith("distance-xy-")} == {
        f"distance-xy-{z}-0-0" for z in range(0, 37, 10)}
    assert {i for i in ids if i.startswith("distance-z-")} == {
        f"distance-z-0-{y}-{x}" for y in range(0, 41, 7) for x in range(0, 29, 13)}
    assert np.array_equal(read_volume(mem).data, read_volume(blk).data)


def _tree(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("version", ["0.5", "0.4"])
def test_ome_zarr_by_blocks_is_the_in_memory_store_byte_for_byte(run, tmp_path, version):
    """Blocks made of the store's own shards (chunks in 0.4): the same files, not only values."""
    z, y, x = np.mgrid[:40, :300, :290].astype(np.float32)
    tube = ((x - 140) ** 2 + (y - 150) ** 2) / 100 + ((z - 20) / 8) ** 2 < 100
    src = tmp_path / "in.nrrd"
    write_volume(Volume(tube.astype(np.uint8) * 100, spacing=np.array([0.8, 0.8, 1.5]),
                        direction=ROTATED), src)
    mem, blk, own = (tmp_path / f"{n}.ome.zarr" for n in ("m", "b", "u"))
    common = ["--iso", "50", "--max-distance", "4", "--ome-zarr-version", version,
              "--pyramid", "1"]
    assert run("distance", src, "-o", mem, *common).code == 0
    res = run("distance", src, "-o", blk, *common, "--chunked", "--memory-limit", "4G")
    assert res.code == 0, res.stderr
    assert _tree(mem) == _tree(blk)
    # a block of the user's that is not made of the store's units: placed in a raw
    # scratch file and written in the in-memory layout on commit (its own layout before)
    res = run("distance", src, "-o", own, *common, "--chunked", "--block", "40,100,100")
    assert res.code == 0, res.stderr
    assert _tree(own) == _tree(mem)
    assert not [p for p in tmp_path.iterdir() if "scratch" in p.name]


@pytest.mark.parametrize("version", ["0.5", "0.4"])
def test_a_distance_by_passes_to_a_store_keeps_its_lines_whole(run, tmp_path, version):
    """A block made of whole shards (or one covering an axis longer than a shard) made the
    store's shards the last pass's blocks, cutting its lines along z at a shard's edge:
    the planes beyond 256 came out inf, exit 0 (a review). The caller's blocks are the
    output's grid: the in-memory store, file for file."""
    z, y, x = np.mgrid[:300, :20, :24].astype(np.float32)
    blob = ((x - 12) ** 2 + (y - 10) ** 2) / 40 + ((z - 150) / 120) ** 2 < 1
    src = tmp_path / "in.nrrd"
    write_volume(Volume(blob.astype(np.uint8) * 100), src)
    common = ["--iso", "50", "--surface", "voxel", "--ome-zarr-version", version]
    mem = tmp_path / "m.ome.zarr"
    assert run("distance", src, "-o", mem, *common).code == 0
    for block in ("256", "24,8,300"):
        blk = tmp_path / f"b{block.replace(',', '_')}.ome.zarr"
        res = run("distance", src, "-o", blk, *common, "--chunked", "--block", block)
        assert res.code == 0, res.stderr
        assert np.isfinite(read_volume(blk).data).all()
        assert _tree(blk) == _tree(mem), block
