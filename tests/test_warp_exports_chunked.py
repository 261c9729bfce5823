"""`volwarp warp --chunked` with the deformation's exports: the same values as in memory.

The fields (displacement, forward, Jacobian) are computed and written by slabs; the
transform, points and mesh come from the by-blocks warp's lattice. Odd sizes, an
oblique and a flipped direction, slabs that do not divide the grid, a folding map;
the NIfTI refusal and a failing slab that leaves nothing behind.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume
from volwarp_cli.warp import export

ANG = np.deg2rad(25)
OBLIQUE = np.array([[np.cos(ANG), -np.sin(ANG), 0], [np.sin(ANG), np.cos(ANG), 0], [0, 0, 1]])
FLIPPED = np.array([[-1.0, 0, 0], [0, 1.0, 0], [0, 0, -1.0]])

SPEC = """version: 1
units: voxel
capture: {lattice: [6, 5, 7]}
steps:
  - move:
      - {index: [2, 2, 3], by: [2.5, -1.5, 2.0]}
      - {index: [3, 2, 2], by: [-1.5, 1.0, -2.5]}
"""
FOLD = """version: 1
units: voxel
capture: {lattice: 6}
steps:
  - move:
      - {index: [3, 3, 3], by: [30.0, 0.0, 0.0]}
"""


def _volume(direction, shape=(18, 20, 24)):
    nz, ny, nx = shape
    z, y, x = np.mgrid[:nz, :ny, :nx].astype(float)
    data = (100 * np.exp(-((x - 11.5) ** 2 / 40 + (y - 9.5) ** 2 / 30 + (z - 8.5) ** 2 / 20))
            ).astype(np.float32)
    return Volume(data, spacing=(1.0, 1.2, 1.5), origin=(-10, 5, 3), direction=direction)


def _inputs(tmp_path, direction, spec_text=SPEC, shape=(18, 20, 24)):
    vol = _volume(direction, shape)
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    spec = tmp_path / "w.yaml"
    spec.write_text(spec_text)
    pts = tmp_path / "p.csv"
    c = vol.index_to_world([[3, 4, 5], [11.5, 9.5, 8.5], [20, 15, 2], [-30, 0, 0]])
    pts.write_text("name,x,y,z\n" + "".join(f"p{i},{float(a)!r},{float(b)!r},{float(d)!r}\n"
                                          for i, (a, b, d) in enumerate(c)))
    mesh = tmp_path / "m.ply"
    v = vol.index_to_world([[5, 5, 5], [15, 5, 5], [5, 15, 5], [5, 5, 12]])
    mesh.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                    "property float y\nproperty float z\nelement face 4\n"
                    "property list uchar int vertex_indices\nend_header\n"
                    + "".join(f"{float(a)} {float(b)} {float(d)}\n" for a, b, d in v)
                    + "3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
    return src, spec, pts, mesh


def _exports(d, pts, mesh, jac=".nrrd"):
    return ["--displacement-to", d / "disp.nrrd", "--forward-field-to", d / "fwd.nrrd",
            "--jacobian-to", d / f"jac{jac}", "--transform-to", d / "t.tfm",
            "--points-in", pts, "--points-to", d / "q.csv", "--mesh-in", mesh,
            "--mesh-to", d / "m2.ply", "--json"]


def _same_exports(mem, blk, jac=".nrrd"):
    for name in ("disp.nrrd", "fwd.nrrd"):
        fa, fb = _field(mem / name), _field(blk / name)
        assert fa.dtype == fb.dtype == np.float32
        assert np.array_equal(fa, fb, equal_nan=True), name
        assert b"encoding: raw" in (blk / name).read_bytes()[:2000]
        # (the in-memory field was gzip: the same values, another file)
        assert (mem / name).read_bytes() == (blk / name).read_bytes(), name
    ja, jb = read_volume(mem / f"jac{jac}"), read_volume(blk / f"jac{jac}")
    assert np.array_equal(ja.data, jb.data) and jb.data.dtype == np.float32
    assert np.allclose(ja.origin, jb.origin) and np.allclose(ja.direction, jb.direction)
    assert _tree(mem / f"jac{jac}") == _tree(blk / f"jac{jac}")
    for name in ("t.tfm", "q.csv", "m2.ply"):
        assert (mem / name).read_bytes() == (blk / name).read_bytes(), name


def _tree(path):
    if path.is_file():
        return path.read_bytes()
    return {p.relative_to(path).as_posix(): p.read_bytes()
            for p in sorted(path.rglob("*")) if p.is_file()}


def _field(path):
    sitk = pytest.importorskip("SimpleITK")
    img = sitk.ReadImage(str(path))
    assert img.GetNumberOfComponentsPerPixel() == 3
    return sitk.GetArrayFromImage(img)


def _figures(summary):
    out = {k: summary[k] for k in ("jacobian", "displacement", "points", "mesh", "handles",
                                   "shape")}
    for k in ("jacobian", "displacement", "points", "mesh"):
        out[k] = {**out[k], "path": out[k]["path"].rsplit("/", 1)[-1]}
    return out


@pytest.mark.parametrize("direction, crop", [(OBLIQUE, False), (FLIPPED, True)])
def test_chunked_exports_equal_the_in_memory_ones(run, tmp_path, direction, crop):
    src, spec, pts, mesh = _inputs(tmp_path, direction)
    mem, blk = tmp_path / "mem", tmp_path / "blk"
    mem.mkdir(), blk.mkdir()
    extra = ["--crop"] if crop else []
    a = run("warp", src, "--spec", spec, "-o", mem / "o.nrrd", *extra, *_exports(mem, pts, mesh))
    assert a.code == 0, a.stderr
    b = run("warp", src, "--spec", spec, "-o", blk / "o.nrrd", *extra, "--chunked",
            "--block", "7,13,17", *_exports(blk, pts, mesh))
    assert b.code == 0, b.stderr
    sa, sb = json.loads(a.stdout), json.loads(b.stdout)
    assert _figures(sa) == _figures(sb)
    assert sb["displacement"]["voxels"] == int(np.prod(sb["shape"]))
    assert sb["points"]["outside"] == 1
    assert (mem / "o.nrrd").read_bytes() == (blk / "o.nrrd").read_bytes()
    _same_exports(mem, blk)


def test_slabs_of_a_folding_map_to_an_ome_zarr_jacobian(run, tmp_path, monkeypatch):
    """Several slabs of every field (a small CHUNK), a fold, a Jacobian store."""
    monkeypatch.setattr(export, "CHUNK", 2048)  # forward/Jacobian slabs of 4 planes
    src, spec, pts, mesh = _inputs(tmp_path, FLIPPED, FOLD)
    mem, blk = tmp_path / "mem", tmp_path / "blk"
    mem.mkdir(), blk.mkdir()
    # (on a grid grown to hold the moved part: the fold lies outside the input's grid)
    a = run("warp", src, "--spec", spec, "-o", mem / "o.nrrd", "--grid", "grow",
            *_exports(mem, pts, mesh, ".ome.zarr"))
    assert a.code == 0, a.stderr
    b = run("warp", src, "--spec", spec, "-o", blk / "o.nrrd", "--chunked", "--block", "5",
            "--grid", "grow", *_exports(blk, pts, mesh, ".ome.zarr"))
    assert b.code == 0, b.stderr
    sa, sb = json.loads(a.stdout), json.loads(b.stdout)
    assert sb["displacement"]["folded"] > 0 and sb["jacobian"]["below_0"] > 0
    assert _figures(sa) == _figures(sb)
    _same_exports(mem, blk, ".ome.zarr")


def test_fold_marks_by_slabs_are_the_fold_image():
    vol = _volume(OBLIQUE)
    rng = np.random.default_rng(1)
    grid = _grid_of(vol)
    dq = rng.normal(0, 2.0, grid.lattice[::-1] + (3,))  # folds (det <= 0) in places
    fmap = export.ForwardMap(grid, dq, vol)
    shape, shift = (27, 22, 19), np.array([-2.0, -1.0, -1.0])
    whole = fmap._fold_image(shape, shift, fast=True)
    assert whole is not None and whole.any()
    for depth in (1, 4, 7, 100):
        marks = fmap.fold_marks(shape, shift, depth=depth)
        assert np.array_equal(marks, np.flatnonzero(whole))
    field, counts = fmap.resampling_field(shape, shift)
    got = np.empty_like(field)
    total = {}
    for z0, part, c in fmap.resampling_field_slabs(shape, shift, 4):
        got[z0:z0 + len(part)] = part
        for k, v in c.items():
            total[k] = total.get(k, 0) + v
    assert np.array_equal(got, field, equal_nan=True) and total == counts


def _grid_of(vol):
    from volwarp_cli.bspline.lattice import Lattice

    return Lattice.create(vol.shape_xyz, (9, 9, 9), 2)


def test_nifti_fields_are_refused_by_blocks_before_any_work(run, tmp_path):
    src, spec, _, _ = _inputs(tmp_path, OBLIQUE)
    for opt, name in (("--displacement-to", "d.nii.gz"), ("--forward-field-to", "f.nii"),
                      ("--jacobian-to", "j.nii.gz")):
        res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--chunked",
                  opt, tmp_path / name)
        assert res.code == 2, res.stderr
        assert opt in res.stderr and "block" in res.stderr
        assert not (tmp_path / "o.nrrd").exists() and not (tmp_path / name).exists()


def test_compress_goes_to_the_fields_and_is_refused_by_blocks(run, tmp_path):
    """The writer options go to every output: --compress makes gzip fields and a gzip
    Jacobian, the same values (the fields were gzip whatever it said, so the in-memory
    field and the one by blocks were different files, and a --compress Jacobian was
    raw); by blocks a compressed field or Jacobian is refused before any work."""
    src, spec, pts, mesh = _inputs(tmp_path, OBLIQUE)
    raw, gz = tmp_path / "raw", tmp_path / "gz"
    raw.mkdir(), gz.mkdir()
    assert run("warp", src, "--spec", spec, "-o", raw / "o.nrrd",
               *_exports(raw, pts, mesh)).code == 0
    res = run("warp", src, "--spec", spec, "-o", gz / "o.nrrd", "--compress",
              *_exports(gz, pts, mesh))
    assert res.code == 0, res.stderr
    for name in ("disp.nrrd", "fwd.nrrd", "jac.nrrd"):
        head = (gz / name).read_bytes()[:2000]
        assert b"encoding: gzip" in head and b"encoding: raw" in (raw / name).read_bytes()[:2000]
        read = read_volume if name == "jac.nrrd" else _field
        a, b = read(raw / name), read(gz / name)
        assert np.array_equal(getattr(a, "data", a), getattr(b, "data", b), equal_nan=True)
    for opt, name in (("--displacement-to", "d.nrrd"), ("--forward-field-to", "f.nrrd"),
                      ("--jacobian-to", "j.nrrd")):
        out = tmp_path / "o.ome.zarr"  # (a store: --compress is its own, always zstd)
        res = run("warp", src, "--spec", spec, "-o", out, "--chunked", "--compress",
                  opt, tmp_path / name)
        assert res.code == 2, res.stderr
        assert opt in res.stderr and "compressed" in res.stderr
        assert not out.exists() and not (tmp_path / name).exists()


@pytest.mark.parametrize("chunked", [False, True])
def test_the_writer_options_reach_the_fields_and_the_jacobian(run, tmp_path, chunked):
    """--ome-zarr-version and --byte-order went to the warped volume only: a Jacobian store
    was NGFF 0.5 whatever was asked (a review), the fields little-endian. They reach every
    volume the command writes, in memory as by slabs; without -o they are taken when a
    field or the Jacobian is written, and refused when no volume is."""
    src, spec, pts, mesh = _inputs(tmp_path, OBLIQUE)
    extra = ["--chunked"] if chunked else []
    d = tmp_path / ("blk" if chunked else "mem")
    d.mkdir()
    res = run("warp", src, "--spec", spec, "--displacement-to", d / "disp.nrrd",
              "--jacobian-to", d / "jac.ome.zarr", "--ome-zarr-version", "0.4",
              "--byte-order", "big", *extra)
    assert res.code == 0, res.stderr
    assert (d / "jac.ome.zarr" / ".zattrs").exists()  # (Zarr v2: NGFF 0.4)
    assert not (d / "jac.ome.zarr" / "zarr.json").exists()
    assert b"endian: big" in (d / "disp.nrrd").read_bytes()[:2000]
    res = run("warp", src, "--spec", spec, "--transform-to", d / "t.tfm", "--compress")
    assert res.code == 2 and "--compress" in res.stderr and not (d / "t.tfm").exists()
    # where a field's file has no use for one, it is said, as for -o (a review found them
    # silent); a NIfTI big-endian is refused before any work, as -o x.nii's is
    res = run("warp", src, "--spec", spec, "--displacement-to", d / "d.nii", "--compress")
    assert res.code == 0 and "--compress does not apply to" in res.stderr
    res = run("warp", src, "--spec", spec, "--forward-field-to", d / "f.nrrd",
              "--ome-zarr-version", "0.4")
    assert res.code == 0 and "--ome-zarr-version does not apply to" in res.stderr
    for option, name in (("--displacement-to", "e.nii.gz"), ("--jacobian-to", "j.nii")):
        res = run("warp", src, "--spec", spec, "-o", d / "o.nrrd", option, d / name,
                  "--byte-order", "big")
        assert res.code == 2 and "little-endian only" in res.stderr, res.stderr
        assert not (d / name).exists() and not (d / "o.nrrd").exists()


def test_a_failing_slab_leaves_no_partial_export(run, tmp_path, monkeypatch):
    src, spec, pts, mesh = _inputs(tmp_path, OBLIQUE)
    disp = tmp_path / "disp.nrrd"
    disp.write_bytes(b"old")
    calls = []
    original = export.ForwardMap.resampling_field_slabs

    def broken(self, *args, **kw):
        for item in original(self, *args, **kw):
            calls.append(item[0])
            if len(calls) == 2:
                raise export.VolwarpError("disk full (test)")
            yield item

    monkeypatch.setattr(export.ForwardMap, "resampling_field_slabs", broken)
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--chunked",
              "--block", "3,64,64", "--displacement-to", disp)
    assert res.code == 1 and "disk full (test)" in res.stderr
    assert disp.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir() if "part" in p.name or "tmp" in p.name] == []


def test_a_warp_too_big_for_memory_writes_its_exports_by_blocks(run, tmp_path, monkeypatch):
    """No --chunked: the in-memory refusal switches to blocks, exports and all; a NIfTI
    field keeps the refusal (it cannot be written by blocks)."""
    from volwarp_cli import memory

    src, spec, pts, mesh = _inputs(tmp_path, OBLIQUE, shape=(33, 35, 37))
    mem, blk = tmp_path / "mem", tmp_path / "blk"
    mem.mkdir(), blk.mkdir()
    # (the grown grid: a target larger than the input's, which 200K cannot hold)
    a = run("warp", src, "--spec", spec, "-o", mem / "o.nrrd", "--grid", "grow",
            *_exports(mem, pts, mesh))
    assert a.code == 0, a.stderr
    monkeypatch.setattr(memory, "process_rss", lambda: 0)
    monkeypatch.setattr("volwarp_cli.execute.MIN_BLOCK_BUDGET", 64 << 10)
    b = run("warp", src, "--spec", spec, "-o", blk / "o.nrrd", "--memory-limit", "200K",
            "--grid", "grow", *_exports(blk, pts, mesh))
    assert b.code == 0, b.stderr
    assert "running by blocks" in b.stderr
    assert _figures(json.loads(a.stdout)) == _figures(json.loads(b.stdout))
    _same_exports(mem, blk)
    nii = tmp_path / "d.nii.gz"
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o2.nrrd", "--memory-limit", "200K",
              "--grid", "grow", "--displacement-to", nii)
    assert res.code == 1 and "needs" in res.stderr and "running by blocks" not in res.stderr
    assert not nii.exists() and not (tmp_path / "o2.nrrd").exists()


def test_exports_too_big_for_memory_go_by_slabs_while_the_warp_runs_whole(run, tmp_path,
                                                                          monkeypatch):
    """The fields' memory is in the decision, before any work: a warp that fits writes its
    fields by slabs when they do not fit (the same values), and a field that cannot be
    written by slabs is refused with both reasons, nothing written."""
    from volwarp_cli.warp import export_outputs

    src, spec, pts, mesh = _inputs(tmp_path, OBLIQUE)
    mem, big = tmp_path / "mem", tmp_path / "big"
    mem.mkdir(), big.mkdir()
    a = run("warp", src, "--spec", spec, "-o", mem / "o.nrrd", *_exports(mem, pts, mesh))
    assert a.code == 0, a.stderr
    # (fields of a terabyte a voxel: far over any budget)
    monkeypatch.setattr(export_outputs, "WHOLE_FIELD_BYTES",
                        dict.fromkeys(("displacement", "forward", "jacobian"), 1 << 40))
    b = run("warp", src, "--spec", spec, "-o", big / "o.nrrd", *_exports(big, pts, mesh))
    assert b.code == 0, b.stderr
    assert "field exports need" in b.stderr and "written by slabs" in b.stderr
    assert "running by blocks" not in b.stderr  # (the warp itself ran whole)
    assert (mem / "o.nrrd").read_bytes() == (big / "o.nrrd").read_bytes()
    assert _figures(json.loads(a.stdout)) == _figures(json.loads(b.stdout))
    _same_exports(mem, big)
    nii = tmp_path / "d.nii.gz"
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o2.nrrd", "--displacement-to", nii)
    assert res.code == 1, res.stderr
    assert "fields whole needs" in res.stderr and ", and by slabs:" in res.stderr
    assert not nii.exists() and not (tmp_path / "o2.nrrd").exists()
