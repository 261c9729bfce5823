"""The sweep as an operation of the executor (volwarp_cli.sweep.run), called without click.

:class:`~volwarp_cli.sweep.run.SweepOperation` run in memory (one block, the calling
threads) and by blocks (an engine's tasks) writes the same bytes, one file per field or
one multi-component file, and :func:`~volwarp_cli.sweep.run.render` of either is the same
picture.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_sweep_chunked import make_spec, write_templates

from volwarp_cli import execute
from volwarp_cli.engine import open_engine
from volwarp_cli.io import read_volume
from volwarp_cli.io.nrrd import read_nrrd
from volwarp_cli.sweep import evaluate
from volwarp_cli.sweep.model import fit_grid
from volwarp_cli.sweep.run import SweepOperation, VolumeRender, render, scale_to_dtype

BODY = {
    "fields": {"opacity": {"image": "disc.png"}, "red": {"image": "ramp.png"},
               "green": 0.5, "blue": 0.25},
    "trajectory": [{"line": {"from": [-5, 0, 0], "to": [5, 2, 1]}},
                   {"arc": {"center": [5, 5, 1], "radius": 3, "axis": [0, 0, 1],
                            "start": -90, "end": 30}}],
    "scale": [4, 3]}
META = {"volwarp_command": "sweep"}
BLOCKS = execute.How(chunked=True, block=(5, 6, 7),
                     open_engine=lambda: open_engine("threads", workers=2))
IN_MEMORY = execute.How(chunked=False)


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """(spec, grid) of a two-segment sweep on an odd grid."""
    d = tmp_path_factory.mktemp("sweep_run")
    write_templates(d)
    spec = make_spec(d, {"grid": {"shape": [31, 27, 13]}, **BODY}, "s.yaml")
    return spec, fit_grid(spec.grid, *spec.bounds())


def _op(spec, grid, folder: Path, dtype, multi=False):
    names = spec.field_names()
    paths = {None: folder / "all.nrrd"} if multi else {n: folder / f"{n}.nrrd" for n in names}
    return SweepOperation(spec, grid, paths, dtype, META, {})


@pytest.mark.parametrize("dtype", ["float32", "uint8"])
def test_in_memory_and_by_blocks_write_the_same_bytes_and_picture(swept, tmp_path, dtype):
    spec, grid = swept
    look = VolumeRender((30, 20), (41, 33), orientation_labels=True)
    runs = {}
    for name, how in (("memory", IN_MEMORY), ("blocks", BLOCKS)):
        (tmp_path / name).mkdir()
        op = _op(spec, grid, tmp_path / name, dtype)
        runs[name] = execute.run(op, how, after=lambda ran, op=op: render(ran, op, look))
    assert not runs["memory"].by_blocks and runs["blocks"].by_blocks
    fields = evaluate(spec, grid)  # the library's whole-grid evaluation
    for n in spec.field_names():
        mem, blk = tmp_path / "memory" / f"{n}.nrrd", tmp_path / "blocks" / f"{n}.nrrd"
        assert mem.read_bytes() == blk.read_bytes()
        written = read_volume(blk)
        assert written.data.dtype == np.dtype(dtype)
        assert written.meta["volwarp_sweep_field"] == n
        expected = scale_to_dtype(fields[n], dtype)
        if dtype == "uint8":
            expected = np.clip(np.rint(expected), 0, 255).astype(np.uint8)
        assert np.array_equal(written.data, expected)
    assert np.asarray(read_volume(tmp_path / "blocks" / "opacity.nrrd").data).any()
    (image, camera), (ref_image, ref_camera) = runs["blocks"].after, runs["memory"].after
    assert image.shape == (33, 41, 3) and image.any()
    assert np.array_equal(image, ref_image)  # (a rounded dtype: the fields computed again)
    for key in ("center", "right", "up", "back"):
        assert np.array_equal(getattr(camera, key), getattr(ref_camera, key))
    assert (camera.scale, camera.size) == (ref_camera.scale, ref_camera.size)


def test_one_multi_component_file_by_blocks_is_the_in_memory_file(swept, tmp_path):
    spec, grid = swept
    names = spec.field_names()
    for name, how in (("memory", IN_MEMORY), ("blocks", BLOCKS)):
        (tmp_path / name).mkdir()
        assert execute.run(_op(spec, grid, tmp_path / name, "uint16", multi=True), how).after \
            is None  # (no render asked)
    mem, blk = tmp_path / "memory" / "all.nrrd", tmp_path / "blocks" / "all.nrrd"
    assert blk.read_bytes() == mem.read_bytes()
    red = read_nrrd(blk, component=names.index("red")).data
    assert red.dtype == np.uint16 and red.any()
