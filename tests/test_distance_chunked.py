"""`distance` by blocks = in memory, bit for bit, and both right (issues 19 and 29).

The band (:class:`~volwarp_cli.distance.band.BandedDistance`): any block grid
gives the one block's bytes, and the one block is the reference field clipped
(scipy's exact transform, the analytic distance of a smooth ball). The exact
passes: ``test_distance_passes.py``. The whole's scan (:mod:`~volwarp_cli.distance.scan`): the
in-memory checks and surface choice.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import ndimage as ndi

from volwarp_cli.box import Box
from volwarp_cli.distance.band import BandedDistance
from volwarp_cli.distance.exact import signed_edt
from volwarp_cli.distance.field import finish_field, signed_distance
from volwarp_cli.distance.labels import ShapeRule
from volwarp_cli.distance.scan import field_surface, scan_shape
from volwarp_cli.distance.subvoxel import subvoxel_signed_distance
from volwarp_cli.errors import VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume, zyx_to_xyz

SHAPE = (37, 41, 29)  # odd sizes; neither block grid below divides them
BLOCKS = [(10, 7, 13), (16, 16, 16), (37, 41, 5)]
SPACING = (2.5, 1.0, 0.7)  # z, y, x


def blobs(shape, seed, sigma=2.0, level=0.5):
    return ndi.gaussian_filter(np.random.default_rng(seed).random(shape), sigma) > level


def sphere(shape, centre, radius):
    z, y, x = np.ogrid[:shape[0], :shape[1], :shape[2]]
    c = centre
    return (z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2 < radius ** 2


def smooth(shape, seed, sigma=3.0):
    f = ndi.gaussian_filter(np.random.default_rng(seed).normal(size=shape), sigma)
    return (f / f.std()).astype(np.float32)


MASKS = {
    "blobs0": lambda: blobs(SHAPE, 0),
    "blobs1": lambda: blobs(SHAPE, 1, sigma=1.2),
    "sphere": lambda: sphere(SHAPE, (17.3, 21.6, 13.1), 11.0),
}
INTENSITY = ShapeRule("intensity", "given", iso=0.5)


def same(a, b):
    """Bit for bit: dtype, shape and bytes (so -0.0 vs 0.0 and NaN payloads count)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def scipy_signed(mask, spacing):
    """The reference: scipy's exact transform of both sides."""
    return (ndi.distance_transform_edt(~mask, sampling=spacing)
            - ndi.distance_transform_edt(mask, sampling=spacing))


def band_op(data, spacing, band, *, rule=INTENSITY, surface="voxel", unsigned=False):
    grid = Geometry(data.shape, zyx_to_xyz(spacing))
    return BandedDistance(data, grid, rule, surface=surface, max_distance=band,
                          unsigned=unsigned)


def one_block(op, threads=2):
    """The in-memory run's field: the whole as one block, on ``threads``."""
    return op.compute(op.grid.box, threads=threads)["field"]


def by_blocks(op, block):
    """The field computed block by block (as the engine's tasks do: one thread each)."""
    out = np.full(op.grid.shape, np.nan, np.float32)
    for box in op.grid.box.blocks(block):
        out[box.slices] = op.compute(box, threads=1)["field"]
    return out


# -- the band ---------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["blobs0", "sphere"])
@pytest.mark.parametrize("band", [2.7, 4.0, 7.5])  # 7.5: halos (3, 7, 10) exceed the blocks
def test_band_by_blocks_is_the_one_block_and_scipy_clipped(name, band):
    mask = MASKS[name]()
    op = band_op(mask, SPACING, band)
    whole = one_block(op)
    ref = scipy_signed(mask, SPACING)
    inner = np.abs(ref) <= band
    assert inner.any() and (~inner).any()
    np.testing.assert_allclose(whole[inner], ref[inner], rtol=1e-6, atol=1e-5)
    assert np.all(np.abs(whole[~inner]) == np.float32(band))  # clamped outside
    assert np.all(np.sign(whole) == np.sign(ref))
    assert same(whole, finish_field(signed_edt(mask, SPACING), max_distance=band))
    for block in BLOCKS:
        assert same(by_blocks(op, block), whole), block


def test_band_of_a_label_rule_and_unsigned():
    labels = (blobs(SHAPE, 2) * 3 + sphere(SHAPE, (10, 10, 10), 6)).astype(np.uint8)
    rule = ShapeRule("labels", "given", label=3)
    op = band_op(labels, SPACING, 3.3, rule=rule, unsigned=True)
    ref = finish_field(signed_edt(labels == 3, SPACING), unsigned=True, max_distance=3.3)
    assert same(one_block(op), ref)
    assert same(by_blocks(op, BLOCKS[0]), ref)
    assert ref.min() == 0


def test_band_is_tight_a_smaller_halo_differs():
    """One site just inside the rule's halo: blocks grown one voxel less miss it."""
    band = 3.5
    mask = np.zeros((24, 24, 24), bool)
    mask[12, 12, 10] = True  # 3 voxels (within D) from x = 7, the last of the block [0, 8)
    op = band_op(mask, (1.0, 1.0, 1.0), band)
    assert op.region(Box((8, 8, 0), (16, 16, 8))) == Box((5, 5, 0), (19, 19, 11))
    whole = one_block(op)
    assert same(by_blocks(op, (8, 8, 8)), whole)
    rule_region = op.region
    op.region = lambda box: rule_region(box).intersect(box.grow((3, 3, 2)))
    assert not same(by_blocks(op, (8, 8, 8)), whole)


@pytest.mark.parametrize("seed", [0, 4])
def test_subvoxel_band_by_blocks_is_the_one_block(seed):
    values = smooth(SHAPE, seed)
    band = 1.5
    op = band_op(values, SPACING, band, rule=ShapeRule("intensity", "given", iso=0.0),
                 surface="subvoxel")
    whole = one_block(op)
    ref = finish_field(subvoxel_signed_distance(values, 0.0, spacing_zyx=SPACING),
                       max_distance=band)
    assert same(whole, ref)
    assert (np.abs(ref) < band).any() and (np.abs(ref) == np.float32(band)).any()
    for block in BLOCKS[:2]:
        assert same(by_blocks(op, block), whole), block


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (1.3, 0.9, 1.1)])
def test_subvoxel_band_is_the_analytic_distance(spacing):
    """A smooth ball (samples R - r): the band's field is r - R to a tenth of a voxel, and
    the same bytes in blocks that start anywhere (the foot points are kept in the whole
    grid's coordinates: in each block's own, blocks of this ball differed by up to 0.03)."""
    shape, centre, radius = (30, 34, 32), np.array([14.3, 16.8, 15.2]), 9.3
    z, y, x = np.indices(shape, dtype=np.float64)
    r = np.sqrt(((z - centre[0]) * spacing[0]) ** 2 + ((y - centre[1]) * spacing[1]) ** 2
                + ((x - centre[2]) * spacing[2]) ** 2)
    op = band_op((radius - r).astype(np.float32), spacing, 2.0,
                 rule=ShapeRule("intensity", "given", iso=0.0), surface="subvoxel")
    whole = one_block(op)
    near = np.abs(r - radius) <= 1.5
    assert np.abs(whole[near] - (r - radius)[near]).max() < 0.1 * min(spacing)
    assert np.all(whole[r - radius > 2.5] == np.float32(2.0))
    for block in ((11, 9, 16), (30, 34, 16), (8, 8, 8)):
        assert same(by_blocks(op, block), whole), block


def test_subvoxel_band_block_without_crossing():
    # samples crossing 0 only near one corner: most blocks see no surface at all
    values = smooth(SHAPE, 1) - 2.2
    assert 0 < (values >= 0).sum() < 200
    op = band_op(values, SPACING, 2.0, rule=ShapeRule("intensity", "given", iso=0.0),
                 surface="subvoxel")
    ref = finish_field(subvoxel_signed_distance(values, 0.0, spacing_zyx=SPACING),
                       max_distance=2.0)
    assert same(by_blocks(op, (8, 8, 8)), ref)


@pytest.mark.parametrize("surface,band", [("voxel", 2.5), ("subvoxel", 4.0)])
def test_block_shape_fits_the_budget_and_gives_every_worker_a_block(surface, band):
    op = band_op(smooth((90, 70, 80), 0), (1.0, 1.0, 1.0), band, surface=surface)
    whole = op.memory(op.grid.box)
    for per_task, workers in ((whole, 2), (whole // 5, 2), (whole // 40, 4), (1, 2)):
        block = op.block_shape(per_task, workers)
        boxes = op.grid.box.blocks(block)
        assert len(boxes) >= workers
        if per_task > 1:
            assert max(op.memory(b) for b in boxes) <= per_task, (per_task, block)
    # few blocks: slabs (a halo along one axis only)
    assert sum(n > b for n, b in zip(op.grid.shape, op.block_shape(whole, 2),
                                     strict=True)) == 1


def test_band_refusals():
    with pytest.raises(VolwarpError, match="positive"):
        band_op(np.zeros((4, 4, 4), bool), (1, 1, 1), 0.0)
    with pytest.raises(ValueError, match="surface"):
        band_op(np.zeros((4, 4, 4), bool), (1, 1, 1), 1.0, surface="auto")


# -- the whole's scan -------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["two-values", "three-values", "block-binary", "bool",
                                  "nan", "constant-blocks"])
def test_scan_picks_the_surface_signed_distance_picks(kind):
    rng = np.random.default_rng(5)
    data = np.where(blobs(SHAPE, 0), 9.0, 2.0).astype(np.float32)
    if kind == "three-values":
        data[3, 4, 5] = 5.0
    elif kind == "block-binary":  # every box has two values, the volume three
        data[:, :, 16:] = np.where(data[:, :, 16:] == 9.0, 9.0, 4.0)
    elif kind == "bool":
        data = data > 5
    elif kind == "nan":
        data[0, 0, 0] = np.nan
    elif kind == "constant-blocks":  # every 16^3 block constant, two values overall
        data = np.kron(rng.integers(0, 2, (3, 3, 2)), np.ones((16, 16, 16)))[:37, :41, :29]
        data = data.astype(np.uint16) * 300
    iso = 0.5 if data.dtype == bool else 5.0
    _, ref = signed_distance(data, SPACING, iso=iso, surface="auto")
    rule = ShapeRule("intensity", "given", iso=iso)
    for box_voxels in (16 ** 3, 10 ** 6):
        got = field_surface(data, rule, metric="euclidean", surface="auto", max_distance=2.0,
                            box_voxels=box_voxels)
        assert got == ref["surface"], (kind, box_voxels)
    # (two values and a NaN are binary: the NaN counts as outside, it is no third value)
    expect = "subvoxel" if kind in ("three-values", "block-binary") else "voxel"
    assert ref["surface"] == expect


def test_scan_refuses_and_warns_in_the_in_memory_words(caplog):
    data = smooth(SHAPE, 3)
    for iso in (50.0, -50.0):
        with pytest.raises(VolwarpError) as mem:
            signed_distance(data, SPACING, iso=iso)
        with pytest.raises(VolwarpError) as scan:
            scan_shape(data, iso, "above", box_voxels=5000)
        assert str(scan.value) == str(mem.value)
    nans = np.full((5, 6, 7), np.nan, np.float32)
    with pytest.raises(VolwarpError) as mem:  # (the same scan: no numpy warning either)
        signed_distance(nans, SPACING, iso=0.0)
    with pytest.raises(VolwarpError) as scan:
        scan_shape(nans, 0.0, "above", box_voxels=20)
    assert str(scan.value) == str(mem.value)
    data[1, 2, 3] = np.nan
    caplog.clear()
    with caplog.at_level("WARNING", logger="volwarp"):
        scan_shape(data, 0.0, "above", box_voxels=5000)
    assert "1 NaN samples" in caplog.text and "outside" in caplog.text
    with pytest.raises(VolwarpError, match="type complex"):
        scan_shape(np.zeros((4, 4, 4), complex), 0.0, "above", box_voxels=10)


# -- refusals --------------------------------------------------------------------------
def threads_engine():
    """An engine of three threads (a context manager)."""
    from volwarp_cli.engine import open_engine

    return open_engine("threads", workers=3)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"surface": "subvoxel"}, "need --max-distance"),
    ({"metric": "nope"}, "unknown metric"),
    ({"surface": "subvoxel", "metric": "minnorm"}, "need the euclidean metric"),
    ({"max_distance": 0.0}, "positive"),
])
def test_field_by_blocks_refusals(tmp_path, kwargs, match):
    from volwarp_cli import execute
    from volwarp_cli.distance.operation import field_operation

    args = {"metric": "euclidean", "surface": "voxel", **kwargs}
    data = smooth(SHAPE, 0)
    target = execute.Target(tmp_path / "f.nrrd", Volume(data).header, np.dtype(np.float32))
    with pytest.raises(VolwarpError, match=match) as err:
        op = field_operation(data, Geometry(SHAPE, (1.0, 1.0, 1.0)),
                             ShapeRule("intensity", "given", iso=0.0), target=target, **args)
        execute.run(op, execute.How(chunked=True, open_engine=threads_engine))
    assert "\n" not in str(err.value)
    assert not (tmp_path / "f.nrrd").exists()


def test_hypothesis_random_masks_and_blocks():
    from hypothesis import given, settings
    from hypothesis import strategies as st
    from hypothesis.extra.numpy import arrays

    @st.composite
    def cases(draw):
        shape = draw(st.tuples(st.integers(1, 9), st.integers(1, 11), st.integers(1, 13)))
        mask = draw(arrays(bool, shape))
        block = tuple(draw(st.integers(1, n)) for n in shape)
        spacing = draw(st.tuples(*[st.floats(0.25, 4.0)] * 3))
        band = draw(st.floats(0.3, 6.0))
        return mask, block, spacing, band

    @settings(max_examples=60, deadline=None)
    @given(cases())
    def check(case):
        mask, block, spacing, band = case
        ref = finish_field(signed_edt(mask, spacing), max_distance=band)
        op = band_op(mask, spacing, band)
        assert same(one_block(op), ref)
        assert same(by_blocks(op, block), ref)

    check()


# -- the command ------------------------------------------------------------------------
@pytest.fixture
def inputs(tmp_path):
    mask = sphere(SHAPE, (17.3, 21.6, 13.1), 11.0) | blobs(SHAPE, 3, level=0.56)
    spacing = np.array(zyx_to_xyz(SPACING))
    write_volume(Volume(mask.astype(np.float32) * 7, spacing=spacing), tmp_path / "mask.nrrd")
    write_volume(Volume(smooth(SHAPE, 2), spacing=spacing), tmp_path / "smooth.nrrd")
    return tmp_path, mask


@pytest.mark.parametrize("extra", [
    ["mask.nrrd", "--iso", "3", "--max-distance", "4.5"],
    ["mask.nrrd", "--iso", "3", "--max-distance", "3", "--unsigned", "--dtype", "int16"],
    ["smooth.nrrd", "--iso", "0.2", "--max-distance", "2"],
    ["smooth.nrrd", "--iso", "0.2", "--max-distance", "2", "--inside", "below"],
])
def test_command_by_blocks_writes_the_in_memory_bytes(run, inputs, extra):
    folder, mask = inputs
    mem, outs = folder / "m.nrrd", []
    assert run("distance", folder / extra[0], "-o", mem, *extra[1:]).code == 0
    for i, blocks in enumerate((["--block", "10,7,13"], ["--block", "37,41,4"], [])):
        out = folder / f"b{i}.nrrd"
        res = run("distance", folder / extra[0], "-o", out, *extra[1:], "--chunked", *blocks)
        assert res.code == 0, res.stderr
        outs.append(out)
    for out in outs:
        assert out.read_bytes() == mem.read_bytes(), out
    field = read_volume(mem).data
    if extra[0] == "mask.nrrd" and "--unsigned" not in extra:  # and the bytes are right
        band = float(extra[extra.index("--max-distance") + 1])
        ref = scipy_signed(mask, SPACING)
        inner = np.abs(ref) <= band
        np.testing.assert_allclose(field[inner], ref[inner], rtol=1e-6, atol=1e-5)
        assert np.all(np.abs(field[~inner]) == np.float32(band))


def test_command_subvoxel_without_a_band_runs_in_memory_only(run, inputs):
    folder, _ = inputs
    out = folder / "s.nrrd"
    assert run("distance", folder / "smooth.nrrd", "-o", out, "--iso", "0.2").code == 0
    ref = subvoxel_signed_distance(smooth(SHAPE, 2), 0.2, spacing_zyx=SPACING)
    assert same(read_volume(out).data, ref)
    assert "surface=subvoxel" in read_volume(out).meta["volwarp_distance"]
    res = run("distance", folder / "smooth.nrrd", "-o", folder / "c.nrrd", "--iso", "0.2",
              "--chunked")
    assert res.code == 1 and "need --max-distance" in res.stderr
    assert not (folder / "c.nrrd").exists()


def test_in_memory_path_does_not_import_dask(tmp_path):
    write_volume(Volume(smooth((12, 13, 14), 0)), tmp_path / "s.nrrd")
    code = ("import sys, numpy as np\n"
            "from volwarp_cli.distance.field import signed_distance\n"
            "d = np.zeros((8, 9, 10), np.uint8); d[3:6, 2:7, 4:8] = 1\n"
            "signed_distance(d, (1, 1, 1), iso=0.5)\n"
            "from volwarp_cli.cli.main import cli\n"
            f"cli(['distance', r'{tmp_path / 's.nrrd'}', '-o', r'{tmp_path / 'o.nrrd'}',"
            " '--iso', '0', '--max-distance', '2'], standalone_mode=False)\n"
            "assert 'dask' not in sys.modules, 'dask imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    assert (tmp_path / "o.nrrd").exists()
