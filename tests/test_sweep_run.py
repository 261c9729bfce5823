"""The sweep's output core (volwarp_cli.sweep.run), called without click.

:func:`~volwarp_cli.sweep.run.sweep_by_blocks` writes, block by block, the
volumes the in-memory sweep writes (:func:`~volwarp_cli.sweep.evaluate`, then
:func:`~volwarp_cli.sweep.run.sweep_volume`), one file per field or one
multi-component file, and its render by slabs is the in-memory render
(:func:`~volwarp_cli.sweep.run.render_fields`) bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_sweep_chunked import make_spec, write_templates

from volwarp_cli.engine import open_engine
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import read_volume
from volwarp_cli.io.blockwrite import committed, open_block_output
from volwarp_cli.io.nrrd import read_nrrd, write_nrrd
from volwarp_cli.sweep import evaluate
from volwarp_cli.sweep.model import fit_grid
from volwarp_cli.sweep.run import (
    VolumeRender,
    block_shape,
    render_fields,
    sweep_by_blocks,
    sweep_volume,
)

BODY = {
    "fields": {"opacity": {"image": "disc.png"}, "red": {"image": "ramp.png"},
               "green": 0.5, "blue": 0.25},
    "trajectory": [{"line": {"from": [-5, 0, 0], "to": [5, 2, 1]}},
                   {"arc": {"center": [5, 5, 1], "radius": 3, "axis": [0, 0, 1],
                            "start": -90, "end": 30}}],
    "scale": [4, 3]}
META = {"volwarp_command": "sweep"}


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """(spec, grid, in-memory fields) of a two-segment sweep on an odd grid."""
    d = tmp_path_factory.mktemp("sweep_run")
    write_templates(d)
    spec = make_spec(d, {"grid": {"shape": [31, 27, 13]}, **BODY}, "s.yaml")
    grid = fit_grid(spec.grid, *spec.bounds())
    return spec, grid, evaluate(spec, grid)


def _open_output(path, template, dtype, block, components):
    return committed(open_block_output(path, Geometry.of(template), dtype, chunks_zyx=block,
                                       metadata=template.meta, space=template.space,
                                       components=components))


def _by_blocks(spec, grid, paths, dtype, render=None, block=(5, 6, 7)):
    return sweep_by_blocks(spec, grid, paths=paths, names=spec.field_names(), dtype=dtype,
                           meta=META, open_output=_open_output,
                           open_engine=lambda: open_engine("threads", workers=2),
                           budget=lambda: 64 << 20, block=block, render=render)


@pytest.mark.parametrize("dtype", ["float32", "uint8"])
def test_fields_and_render_by_blocks_are_the_in_memory_ones(swept, tmp_path, dtype):
    spec, grid, fields = swept
    names = spec.field_names()
    render = VolumeRender((30, 20), (41, 33), orientation_labels=True)
    paths = {n: str(tmp_path / f"{n}.nrrd") for n in names}
    image, camera = _by_blocks(spec, grid, paths, dtype, render=render)
    for name in names:
        expected = sweep_volume(fields[name], grid, dtype, META, name)
        written = read_volume(paths[name])
        assert written.data.dtype == np.dtype(dtype)
        assert np.array_equal(written.data, expected.data)
        assert written.meta["volwarp_sweep_field"] == name
    assert np.asarray(read_volume(paths["opacity"]).data).any()
    ref_image, ref_camera = render_fields(fields, grid, render)
    assert image.shape == (33, 41, 3) and image.any()
    assert np.array_equal(image, ref_image)  # (a rounded dtype: the fields computed again)
    for key in ("center", "right", "up", "back"):
        assert np.array_equal(getattr(camera, key), getattr(ref_camera, key))
    assert (camera.scale, camera.size) == (ref_camera.scale, ref_camera.size)


def test_one_multi_component_file_by_blocks_is_the_in_memory_file(swept, tmp_path):
    spec, grid, fields = swept
    names = spec.field_names()
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    comps = [sweep_volume(fields[n], grid, "uint16", META).data for n in names]
    write_nrrd(sweep_volume(fields[names[0]], grid, "uint16", META), mem, components=comps,
               component_names=names)
    assert _by_blocks(spec, grid, {None: str(blk)}, "uint16") is None  # (no render asked)
    assert blk.read_bytes() == mem.read_bytes()
    assert np.array_equal(read_nrrd(blk, component=1).data, comps[1])


def test_blocks_fit_the_task_memory_and_feed_every_worker():
    shape = (40, 50, 60)
    for workers in (1, 2, 8, 64):  # (plenty of memory: the blocks shrink for the workers only)
        block = block_shape(shape, 1 << 30, workers, 4, "float32")
        count = math.prod(math.ceil(n / b) for n, b in zip(shape, block, strict=True))
        assert count >= 2 * workers or min(block) <= 16
    per_voxel = 4 * (4 + 1) + 16  # four fields as float32 and as uint8, and slack
    for per_task in (per_voxel * 9 ** 3, per_voxel * 23 ** 3 + 5, per_voxel * 30 ** 3):
        edge = block_shape(shape, per_task, 1, 4, "uint8")[0]
        assert edge ** 3 * per_voxel <= per_task < (edge + 2) ** 3 * per_voxel  # (a float root)
    assert block_shape(shape, 1, 1, 4, "float32") == (8, 8, 8)  # never below 8
