"""The ray caster by slabs of z planes (issue 19): the in-memory picture, bit for bit.

:func:`~volwarp_cli.render.raycast.render_volume_slabs` against
:func:`~volwarp_cli.render.raycast.render_volume` on odd volume sizes, views
looking along +z, along -z, across z (fwd_z = 0) and oblique, with and without
colour and geometry fields, shaded or not, slab depths 1 (less than the
gradient's halo), 3, 8 (one empty-skip block) and 13; then ``volwarp sweep
--chunked --render`` against the in-memory ``volwarp sweep --render``: the same
PNG bytes (and camera), with every output form (per-field NRRD, --multi,
OME-Zarr, a rounded --dtype) and once on the process scheduler.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from volwarp_cli.render.raycast import camera, render_volume, render_volume_slabs

SHAPE = (21, 17, 19)  # (z, y, x): none a multiple of 8
SPACING = (1.0, 0.8, 1.3)
SIZE = (37, 29)
DEPTHS = (1, 3, 8, 13)

#: (view, sign of the rays' z step)
VIEWS = [((0, -90), 1), ((0, 90), -1), ((0, 0), 0), ((30, 20), -1), ((10, -45), 1)]


def _fields(shape=SHAPE, seed=3):
    rng = np.random.default_rng(seed)
    nz, ny, nx = shape
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    r = np.sqrt(((z - nz / 2) / nz) ** 2 + ((y - ny / 2) / ny) ** 2
                + ((x - nx / 2) / nx) ** 2)
    op = (np.clip(1.2 - 3 * r, 0, 1) * (rng.random(shape) > 0.3)).astype(np.float32)
    op[op < 0.3] = 0
    op[: min(9, nz // 2)] = 0  # whole empty blocks along z: skips across slabs
    op[-1, 0, 0] = np.nan  # read as 0
    col = [rng.random(shape).astype(np.float32) for _ in range(3)]
    col[0][0, 0, 0] = 1.5  # clipped by the kernel
    geo = (rng.random(shape) * 2 + z * 0.1).astype(np.float32)
    return op, col, geo


def _reader(op, col, geo, calls=None):
    fields = {"opacity": op, "geometry": geo}
    if col is not None:
        fields.update(zip(("red", "green", "blue"), col, strict=True))
    nz = op.shape[0]

    def read(z0, z1, names):
        assert 0 <= z0 < z1 <= nz, (z0, z1)
        if calls is not None:
            calls.append((z0, z1, tuple(names)))
        return [fields[n][z0:z1].copy() for n in names]

    return read


def test_views_step_along_z_as_labelled():
    for view, sign in VIEWS:
        assert np.sign(camera(view)[0][2]) == sign, view
    assert camera((0, 0))[0][2] == 0.0


@pytest.mark.parametrize("view", [v for v, _ in VIEWS], ids=str)
@pytest.mark.parametrize("with_colour,with_geometry", [(False, False), (True, False),
                                                       (True, True), (False, True)],
                         ids=["opacity", "colour", "colour+geometry", "geometry"])
def test_slabs_equal_the_whole_render(view, with_colour, with_geometry):
    op, col, geo = _fields()
    col = col if with_colour else None
    geo = geo if with_geometry else None
    kw = dict(spacing=SPACING, view=view, size=SIZE, background=(0.1, 0.2, 0.3))
    ref = render_volume(op, colour=col, geometry=geo, **kw)
    assert ref.any() and (ref != ref[0, 0]).any()
    read = _reader(op, col, geo)
    for depth in DEPTHS:
        got = render_volume_slabs(read, op.shape, colour=col is not None,
                                  geometry=geo is not None, slab=depth, **kw)
        assert got.dtype == np.uint8 and np.array_equal(got, ref), depth


@pytest.mark.parametrize("view", ["iso", (0, 90), (0, -90)], ids=str)
def test_unshaded_and_longer_steps(view):
    op, col, _ = _fields((19, 13, 15), seed=5)
    kw = dict(view=view, size=(31, 23), shading=False, step=0.7, zoom=1.4)
    ref = render_volume(op, colour=col, **kw)
    for depth in (1, 3, 8, 13):
        got = render_volume_slabs(_reader(op, col, None), op.shape, colour=True, slab=depth,
                                  **kw)
        assert np.array_equal(got, ref), depth


def test_depth_one_reads_only_its_halo_in_the_rays_order():
    """Slabs of 1 cell: 2 planes and the gradient's one more on each side, in z order."""
    op, col, geo = _fields()
    nz = op.shape[0]
    for view, sign in [((0, -90), 1), ((30, 20), -1)]:
        calls = []
        read = _reader(op, col, geo, calls)
        got = render_volume_slabs(read, op.shape, colour=True, geometry=True, slab=1,
                                  spacing=SPACING, view=view, size=SIZE)
        assert np.array_equal(got, render_volume(op, colour=col, geometry=geo,
                                                 spacing=SPACING, view=view, size=SIZE))
        march = [c for c in calls if len(c[2]) == 5]
        assert len(march) == nz - 1  # one slab per cell
        assert all(z1 - z0 <= 4 for z0, z1, _ in march)
        starts = [z0 for z0, _, _ in march]
        assert starts == sorted(starts, reverse=sign < 0)
        # the empty-block map: the opacity alone, by whole 8-plane blocks and one plane more
        blocks = [(z0, z1) for z0, z1, names in calls if names == ("opacity",)]
        assert blocks and all(z0 % 8 == 0 for z0, _ in blocks)
        assert all(z1 == min(z0 + 9, nz) for z0, z1 in blocks)


@pytest.mark.parametrize("shape", [(1, 9, 7), (2, 9, 7), (9, 1, 5), (17, 6, 1)], ids=str)
def test_thin_volumes(shape):
    op, col, geo = _fields(shape, seed=7)
    op[...] = np.maximum(op, 0.4)
    for view in [(0, -90), (20, 30), (0, 0)]:
        kw = dict(view=view, size=(19, 17))
        ref = render_volume(op, colour=col, geometry=geo, **kw)
        for depth in (1, 3):
            got = render_volume_slabs(_reader(op, col, geo), shape, colour=True,
                                      geometry=True, slab=depth, **kw)
            assert np.array_equal(got, ref), (view, depth)


def test_saved_camera_and_labels_by_slabs():
    op, col, geo = _fields()
    kw = dict(spacing=SPACING, origin=(3.0, -2.0, 1.0), size=SIZE, orientation_labels=True)
    ref, cam = render_volume(op, colour=col, geometry=geo, view=(-70, 25), return_camera=True,
                             **kw)
    got, cam2 = render_volume_slabs(_reader(op, col, geo), op.shape, colour=True, geometry=True,
                                    slab=3, view=(-70, 25), return_camera=True, **kw)
    assert np.array_equal(got, ref)
    assert all(np.array_equal(getattr(cam, f.name), getattr(cam2, f.name))
               for f in dataclasses.fields(cam))
    zoomed = render_volume(op, geometry=geo, camera=cam, spacing=SPACING, origin=kw["origin"])
    again = render_volume_slabs(_reader(op, None, geo), op.shape, geometry=True, slab=8,
                                camera=cam, spacing=SPACING, origin=kw["origin"])
    assert np.array_equal(again, zoomed)


def test_default_depth_from_the_budget_and_bad_depth():
    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.render.raycast import SLAB_BYTES_PER_VOXEL, slab_depth

    assert slab_depth((100, 10, 10), 0) == 4
    assert slab_depth((100, 10, 10), 10**12) == 99
    assert slab_depth((100, 10, 10), 20 * 100 * SLAB_BYTES_PER_VOXEL) == 17
    op, col, geo = _fields()
    ref = render_volume(op, size=SIZE)
    assert np.array_equal(render_volume_slabs(_reader(op, None, None), op.shape, size=SIZE), ref)
    with pytest.raises(VolwarpError, match="slab"):
        render_volume_slabs(_reader(op, None, None), op.shape, slab=0)


# -- the CLI ----------------------------------------------------------------------------

SPEC = """version: 1
grid: {spacing: 0.5}
fields:
  opacity: {value: 0.6}
  red: 0.25
  green: {value: 0.7}
  blue: 0.9
  geometry: 0.3
trajectory:
  - bezier: {points: [[-6, -5, -3], [8, -6, 2], [-8, 6, 3], [6, 5, -2]]}
up: [0, 0, 1]
scale: [3, 2]
"""

PLAIN = """version: 1
grid: {spacing: 0.45}
fields:
  opacity: {value: 0.8}
trajectory:
  - line: {from: [0, 0, -2], to: [6, 1, 3]}
up: [0, 0, 1]
scale: [3, 3]
"""


@pytest.fixture(scope="module")
def refs(tmp_path_factory):
    """In-memory renders (PNG bytes, camera JSON) of the two specs for a few views."""
    from click.testing import CliRunner

    from volwarp_cli.cli.main import cli

    d = tmp_path_factory.mktemp("sweep_render")
    out = {}
    for name, text in (("spec", SPEC), ("plain", PLAIN)):
        (d / f"{name}.yaml").write_text(text)
        for view in ("iso", "0,-90", "0,90", "0,0"):
            png, cam = d / f"{name}_{view}.png", d / f"{name}_{view}.json"
            res = CliRunner().invoke(cli, ["sweep", str(d / f"{name}.yaml"), "-o",
                                           str(d / f"{name}_{{field}}.nrrd"), "--render",
                                           str(png), "--render-size", "48x40", "--view",
                                           view, "--camera-to", str(cam)],
                                     catch_exceptions=False)
            assert res.exit_code == 0, res.stderr
            out[name, view] = (png.read_bytes(), cam.read_bytes())
    return d, out


@pytest.mark.parametrize("name,view,output,extra", [
    ("spec", "iso", "b_{field}.nrrd", ["--block", "5"]),
    ("spec", "0,-90", "b_{field}.nrrd", ["--block", "1,40,40"]),
    ("spec", "0,90", "b.nrrd", ["--multi", "--block", "8,16,16"]),
    ("spec", "0,0", "b_{field}.ome.zarr", ["--block", "13"]),
    ("spec", "iso", "b_{field}.mha", ["--dtype", "uint8", "--block", "3,20,20"]),
    ("plain", "iso", "b_{field}.nrrd", ["--block", "3"]),
    ("plain", "0,90", "b_{field}.raw", []),
    ("spec", "0,-90", "b_{field}.nrrd", ["--block", "7", "--scheduler", "processes"]),
], ids=lambda v: str(v).replace(" ", ""))
def test_cli_chunked_render_is_the_in_memory_png(run, refs, tmp_path, name, view, output,
                                                 extra):
    d, out = refs
    png, cam = tmp_path / "r.png", tmp_path / "r.json"
    res = run("sweep", d / f"{name}.yaml", "-o", tmp_path / output, "--render", png,
              "--render-size", "48x40", "--view", view, "--camera-to", cam, "--chunked", *extra)
    assert res.code == 0, res.stderr
    want_png, want_cam = out[name, view]
    assert png.read_bytes() == want_png
    assert cam.read_bytes() == want_cam
    assert not list(tmp_path.glob("*.tmp*")) and not list(tmp_path.glob(".*"))


def test_cli_chunked_render_refusals_keep_their_codes(run, refs, tmp_path):
    d, _ = refs
    # a compressed NRRD cannot be written by blocks: a one-line error, nothing written
    res = run("sweep", d / "spec.yaml", "-o", tmp_path / "c_{field}.nrrd", "--compress",
              "--render", tmp_path / "r.png", "--chunked")
    assert res.code == 2 and res.stderr.strip().count("\n") == 0, res.stderr  # (usage)
    assert not list(tmp_path.iterdir())
