"""`volwarp morph --chunked` with inputs on other grids and aligned inputs (issue 19).

Each field is computed by blocks on its own grid, then resampled onto the
frame grid block by block, each block reading only the input box its
voxels reach; the frames equal the in-memory frames bit for bit. Small odd
sizes, several blocks per axis, a flipped and a rotated direction.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from volwarp_cli.box import Box
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.morph.align import affine_from_params
from volwarp_cli.morph.fields import ResampleOperation
from volwarp_cli.morph.interpolate import (
    index_map,
    needed_box,
    resample_box,
)
from volwarp_cli.surface.mesh_io import read_mesh
from volwarp_cli.volume import Volume

FLIPPED = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # det -1
ROTATED = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def _world(shape_xyz, spacing, origin, direction):
    nx, ny, nz = shape_xyz
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    ijk = np.stack([i, j, k], axis=-1) * np.asarray(spacing, float)
    w = ijk @ np.asarray(direction, float).T + np.asarray(origin, float)
    return w[..., 0], w[..., 1], w[..., 2]


def _write(path, data, spacing, origin, direction):
    write_volume(Volume(data, spacing=np.asarray(spacing, float),
                        origin=np.asarray(origin, float), direction=direction), path)
    return path


@pytest.fixture
def inputs(tmp_path):
    """A big source grid (flipped direction) and a smaller target grid inside it."""
    big = ((25, 29, 19), (0.9, 0.8, 1.1), (-3.4, 17.5, 15.5), FLIPPED)
    small = ((17, 15, 13), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0), np.eye(3))
    x, y, z = _world(*big)
    ball = (((x - 8) ** 2 + (y - 7) ** 2 + (z - 6) ** 2) < 22).astype(np.uint8)
    heat_big = (x + 2 * y - z).astype(np.float32)
    x, y, z = _world(*small)
    box = ((np.abs(x - 8) < 5) & (np.abs(y - 6.5) < 3) & (np.abs(z - 6) < 4.2)).astype(np.uint8)
    heat_small = (z * 7).astype(np.uint8)
    return {
        "big_ball": _write(tmp_path / "big_ball.nrrd", ball, *big[1:]),
        "small_box": _write(tmp_path / "small_box.nrrd", box, *small[1:]),
        "big_heat": _write(tmp_path / "big_heat.nrrd", heat_big, *big[1:]),
        "small_heat": _write(tmp_path / "small_heat.nrrd", heat_small, *small[1:]),
    }


def _spec(tmp_path, name, text):
    path = tmp_path / f"{name}.yaml"
    path.write_text("version: 1\n" + text)
    return path


def _same(tmp_path, n, names=("",)):
    for i in range(n):
        for suffix in names:
            a = read_volume(tmp_path / f"m_{i}{suffix}.nrrd")
            b = read_volume(tmp_path / f"b_{i}{suffix}.nrrd")
            assert a.data.dtype == b.data.dtype and np.array_equal(a.data, b.data), (i, suffix)
            assert np.allclose(a.index_to_world_matrix, b.index_to_world_matrix)
            assert a.meta["volwarp_morph_t"] == b.meta["volwarp_morph_t"]


@pytest.mark.parametrize("scheduler", [None, "processes"])
def test_inputs_on_different_grids_by_blocks(run, inputs, tmp_path, scheduler):
    """Source on a flipped grid of other spacing and origin, resampled onto the target's grid."""
    spec = _spec(tmp_path, "m", f"source: {{volume: {inputs['big_ball']}, iso: 0.5}}\n"
                 f"target: {{volume: {inputs['small_box']}, iso: 0.5}}\n"
                 "times: [0, 0.35, 1]\ngrid: target\n")
    mesh = [] if scheduler else ["--mesh-to", "{}_{{i}}.ply"]
    assert run("morph", "--spec", spec, "-o", tmp_path / "m_{i}.nrrd",
               *[m.format(tmp_path / "m") for m in mesh]).code == 0
    extra = ["--scheduler", scheduler, "--block", "7,15,17"] if scheduler else ["--block", "5,4,6"]
    res = run("morph", "--spec", spec, "-o", tmp_path / "b_{i}.nrrd", "--chunked", *extra,
              *[m.format(tmp_path / "b") for m in mesh])
    assert res.code == 0, res.stderr
    _same(tmp_path, 3)
    assert read_volume(tmp_path / "b_0.nrrd").data.shape == (13, 15, 17)
    if mesh:
        for i in range(3):
            assert read_mesh(tmp_path / f"m_{i}.ply").n_faces > 50
            assert (tmp_path / f"m_{i}.ply").read_bytes() == (tmp_path / f"b_{i}.ply").read_bytes()


@pytest.mark.parametrize("align", [
    "{rotate: [5, -8, 20], scale: 1.1, translate: [0.5, -0.3, 0.2]}",  # centre: the centroid
    "{scale: [0.9, 1.05, 1.2], center: [8, 7, 6]}",
    "{translate: [1.3, -0.6, 0.25]}",
])
def test_an_alignment_by_blocks(run, inputs, tmp_path, align):
    """The target (flipped grid) aligned onto the source's grid, with attributes.

    (small_heat, 13 levels of z, is what the label rule takes for a label map: blended as
    numbers as asked, values: intensity.)"""
    spec = _spec(tmp_path, "m", f"source: {{volume: {inputs['small_box']}, iso: 0.5}}\n"
                 f"target: {{volume: {inputs['big_ball']}, iso: 0.5}}\n"
                 f"times: [0, 0.5, 0.8, 1]\ngrid: source\nalign: {{target: {align}}}\n"
                 f"attributes:\n  - {{name: heat, source: {inputs['small_heat']}, "
                 f"target: {inputs['big_heat']}, values: intensity}}\n")
    assert run("morph", "--spec", spec, "-o", tmp_path / "m_{i}.nrrd").code == 0
    res = run("morph", "--spec", spec, "-o", tmp_path / "b_{i}.nrrd", "--chunked",
              "--block", "4,6,5")
    assert res.code == 0, res.stderr
    _same(tmp_path, 4, ("", "_heat"))
    one = read_volume(tmp_path / "b_3.nrrd").data  # the moved target: not the source
    assert not np.array_equal(one < 0, read_volume(tmp_path / "b_0.nrrd").data < 0)


def test_what_moved_inputs_by_blocks_refuse(run, inputs, tmp_path):
    out = tmp_path / "o_{i}.nrrd"
    base = (f"source: {{volume: {inputs['small_box']}, iso: 0.5}}\n"
            f"target: {{volume: {inputs['big_ball']}, iso: 0.5}}\nframes: 2\n")
    # the union grid reaches beyond the small grid: its field would be filled in memory
    spec = _spec(tmp_path, "u", base + "align: {target: {translate: [1, 0, 0]}}\n")
    res = run("morph", "--spec", spec, "-o", out, "--chunked")
    assert res.code == 2 and "uncovered" in res.stderr and "alignment" in res.stderr
    # one sentence: the cause, where it runs, then the way out (the advice was nested
    # inside "a morph with ... by blocks" before)
    assert re.search(r"--chunked does not run this morph by blocks: its frame grid reaches "
                     r"beyond the (source|target)'s grid through its alignment or grid "
                     r"\(\d+ of \d+ frame voxels uncovered\), .* \(without --chunked it runs in "
                     r"memory\); choose a grid the aligned inputs cover", res.stderr), res.stderr
    spec = _spec(tmp_path, "w", base + "grid: source\nwarp: {source_points: [[4, 4, 4]], "
                 "target_points: [[5, 4, 4]]}\n")
    res = run("morph", "--spec", spec, "-o", out, "--chunked")
    assert res.code == 2 and "landmark warp" in res.stderr
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(("o_", "."))]


def _case():
    rng = np.random.default_rng(7)
    values = rng.standard_normal((11, 13, 9)).astype(np.float32)
    vgeo = Geometry.from_xyz((9, 13, 11), (0.9, 0.8, 1.1), (-1.0, -0.5, -0.7), FLIPPED)
    grid = Geometry.from_xyz((10, 9, 8), (0.7, 0.75, 0.8), (0.5, -9.0, -10.0), np.eye(3))
    mat = affine_from_params({"rotate": [10, 25, -15], "scale": 1.15, "translate": [0.3, 0, 1]},
                             default_center=(2.0, -5.0, -5.0))
    return values, vgeo, grid, mat


@pytest.mark.parametrize("outside", ["nan", "nearest"])
def test_the_input_box_is_exactly_enough(outside):
    """A block from its needed box equals the whole resampling's block; one voxel less does not."""
    values, vgeo, grid, mat = _case()
    whole = ResampleOperation(values, vgeo.index_to_world_matrix, mat, grid,
                              outside=outside).compute(grid.box, threads=1)["values"]
    m = index_map(vgeo.index_to_world_matrix, mat, grid)
    vbox = Box.from_shape(values.shape)
    changed = set()
    for block in Box.from_shape(grid.shape).blocks((3, 4, 3)):
        need = needed_box(m, block, values.shape)
        part = resample_box(values[need.slices], need, m, block, values_shape=values.shape,
                            outside=outside)
        assert np.array_equal(part, whole[block.slices], equal_nan=True)
        for axis in range(3):
            for side in (0, 1):
                lo, hi = list(need.lo), list(need.hi)
                if side == 0:
                    lo[axis] += 1
                else:
                    hi[axis] -= 1
                smaller = Box(lo, hi)
                if smaller.empty or smaller.lo[axis] == vbox.lo[axis] and side == 0:
                    continue
                # (a side on the input's own border is not the rule's: nothing lies beyond)
                if side == 1 and smaller.hi[axis] == vbox.hi[axis]:
                    continue
                cut = resample_box(values[smaller.slices], smaller, m, block,
                                   values_shape=values.shape, outside=outside)
                if not np.array_equal(cut, whole[block.slices], equal_nan=True):
                    changed.add((axis, side))
    assert changed == {(a, s) for a in range(3) for s in (0, 1)}


def test_strong_scalings_split_the_blocks_or_are_refused():
    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.morph.chunked import resample_chunks

    values, vgeo, grid, _ = _case()
    shrink = affine_from_params({"scale": 0.2}, default_center=(2.0, -5.0, -5.0))
    m = index_map(vgeo.index_to_world_matrix, shrink, grid)
    roomy = resample_chunks(grid.shape, grid.shape, [(m, values.shape)], 1 << 30)
    assert roomy == tuple(grid.shape)
    tight = resample_chunks(grid.shape, grid.shape, [(m, values.shape)], 12 * 400 + 32 * 8)
    assert np.prod(tight) < np.prod(grid.shape)
    for block in Box.from_shape(grid.shape).blocks(tight):
        assert needed_box(m, block, values.shape).size * 12 + block.size * 32 <= 12 * 400 + 256
    with pytest.raises(VolwarpError, match="single voxel"):
        resample_chunks(grid.shape, grid.shape, [(m, values.shape)], 64)


def test_the_alignment_centre_by_blocks_is_the_whole_mask_centroid():
    """Counted box by box in integers, the centroid is the whole mask's, bit for bit."""
    from volwarp_cli.distance.labels import ShapeRule
    from volwarp_cli.morph.align import shape_centroid
    from volwarp_cli.morph.fields import Steps, alignment_matrices
    from volwarp_cli.morph.spec import MorphJob, ShapeRef

    class SmallBlocks(Steps):
        def chunks(self, shape):
            return (3, 4, 5)

    rng = np.random.default_rng(3)
    samples = rng.random((17, 19, 23)).astype(np.float32)
    geo = Geometry.from_xyz((23, 19, 17), (0.9, 1.3, 0.7), (4.0, -2.0, 1.5), FLIPPED)
    template = geo.volume(samples)
    job = MorphJob(source=ShapeRef("a.nrrd", 0.7), target=ShapeRef("b.nrrd", 0.7),
                   times=[0.0], align_source={"rotate": [5, 10, 15]},
                   align_target={"scale": 1.2})
    inputs = {"source": (template, samples), "target": (template, samples)}
    rules = dict.fromkeys(inputs, ShapeRule("intensity", "given", iso=0.7))
    whole = alignment_matrices(job, inputs, Steps(), rules)
    blocks = alignment_matrices(job, inputs, SmallBlocks(), rules)
    for name in ("source", "target"):
        assert np.array_equal(whole[name], blocks[name])
    centre = shape_centroid(samples >= 0.7, geo.index_to_world_matrix)
    # a scaling about the centroid leaves the centroid where it is
    moved = whole["target"] @ np.append(centre, 1.0)
    np.testing.assert_allclose(moved[:3], centre, atol=1e-9)
    assert not np.allclose(whole["target"][:3, 3], 0.0)
