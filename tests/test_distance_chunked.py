"""`distance` out of core on Dask: chunked = in-memory, bit for bit (issue 19)."""

from __future__ import annotations

import subprocess
import sys

import dask
import dask.array as da
import numpy as np
import pytest
from scipy import ndimage as ndi

from volwarp_cli.distance import chunked
from volwarp_cli.distance.chunked import (
    band_halo,
    banded_signed_distance_dask,
    line_chunks,
    signed_distance_dask,
    signed_edt_dask,
)
from volwarp_cli.distance.exact import signed_edt
from volwarp_cli.distance.field import finish_field, signed_distance
from volwarp_cli.distance.subvoxel import subvoxel_signed_distance
from volwarp_cli.errors import VolwarpError

SHAPE = (37, 41, 29)  # odd sizes; neither chunking below divides them
CHUNKS = [(10, 7, 13), (16, 16, 16)]
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


def same(a, b):
    """Bit for bit: dtype, shape and bytes (so -0.0 vs 0.0 and NaN payloads count)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def compute(x, scheduler="threads"):
    if scheduler == "threads":
        return x.compute(scheduler="threads", num_workers=3)
    return x.compute(scheduler="synchronous")


# -- exact by passes -------------------------------------------------------------------
@pytest.mark.parametrize("name", list(MASKS))
@pytest.mark.parametrize("chunks", CHUNKS)
@pytest.mark.parametrize("spacing", [SPACING, (1.0, 1.0, 1.0)])
def test_passes_equal_in_memory_bit_for_bit(name, chunks, spacing):
    mask = MASKS[name]()
    assert 0.05 < mask.mean() < 0.8
    ref = signed_edt(mask, spacing)
    # a small budget: each pass cuts the volume into many blocks of whole lines
    got = compute(signed_edt_dask(da.from_array(mask, chunks=chunks), spacing,
                                  block_bytes=20_000))
    assert same(got, ref)


def test_passes_take_uint8_and_any_nonzero_and_keep_inf():
    mask = blobs(SHAPE, 2)
    ref = signed_edt(mask, SPACING)
    labels = (mask * 7).astype(np.uint8)  # nonzero inside, not 0/1
    assert same(compute(signed_edt_dask(da.from_array(labels, chunks=(9, 20, 8)), SPACING)), ref)
    # empty and full masks: +inf / -inf everywhere, as in memory (the caller checks first)
    for m in (np.zeros(SHAPE, bool), np.ones(SHAPE, bool)):
        got = compute(signed_edt_dask(da.from_array(m, chunks=CHUNKS[0]), SPACING,
                                      block_bytes=30_000))
        assert same(got, signed_edt(m, SPACING))
        assert np.isinf(got).all()


def test_passes_depend_on_whole_lines():
    """The test above can fail: a pass on blocks that cut its lines gives other values."""
    mask = blobs(SHAPE, 0)
    ref = signed_edt(mask, SPACING)
    m = da.from_array(mask.view(np.uint8), chunks=(SHAPE[0], SHAPE[1], 13))  # x lines cut
    d = m.map_blocks(chunked._x_block, SPACING[2], dtype=np.float32)
    c_y = line_chunks(SHAPE, 1, 10**9)
    d = da.map_blocks(chunked._y_block, d.rechunk(c_y), m.rechunk(c_y), SPACING[1],
                      dtype=np.float32)
    c_z = line_chunks(SHAPE, 0, 10**9)
    d = da.map_blocks(chunked._z_block, d.rechunk(c_z), m.rechunk(c_z), SPACING[0],
                      dtype=np.float32)
    assert not np.array_equal(compute(d), ref)


def test_threaded_and_synchronous_schedulers_give_the_same_bytes():
    mask = sphere(SHAPE, (18.0, 20.5, 14.2), 12.5) | blobs(SHAPE, 3, level=0.56)
    ref = signed_edt(mask, SPACING)
    x = signed_edt_dask(da.from_array(mask, chunks=CHUNKS[0]), SPACING, block_bytes=50_000)
    a = compute(x, "threads")
    b = compute(x, "synchronous")
    with dask.config.set(scheduler="threads", num_workers=2):
        c = x.compute()
    assert same(a, ref) and same(b, ref) and same(c, ref)
    band = banded_signed_distance_dask(da.from_array(mask, chunks=CHUNKS[1]), SPACING, 3.3)
    assert same(compute(band, "threads"), compute(band, "synchronous"))


def test_line_chunks_keep_whole_lines_within_the_budget():
    shape = (37, 41, 29)
    for axis in range(3):
        for budget in (1, 5_000, 60_000, 10**9):
            c = line_chunks(shape, axis, budget)
            assert c[axis] == shape[axis]
            assert all(1 <= v <= n for v, n in zip(c, shape, strict=True))
            voxels = c[0] * c[1] * c[2]
            assert voxels == shape[axis] or voxels * chunked.PASS_BYTES_PER_VOXEL <= budget
    assert line_chunks(shape, 0, 10**9) == shape
    # enough blocks for the threads
    c = line_chunks(shape, 2, 10**9, min_blocks=4)
    assert c[2] == 29 and c[1] == 41 and -(-37 // c[0]) >= 4


# -- band by overlapping blocks ------------------------------------------------------------
@pytest.mark.parametrize("name", ["blobs0", "sphere"])
@pytest.mark.parametrize("band", [2.7, 4.0, 7.5])  # 7.5: halos (3, 8, 11) exceed the chunks
@pytest.mark.parametrize("chunks", CHUNKS)
def test_band_equals_the_clamped_whole(name, band, chunks):
    mask = MASKS[name]()
    whole = signed_edt(mask, SPACING)
    ref = finish_field(whole.copy(), max_distance=band)
    got = compute(banded_signed_distance_dask(da.from_array(mask, chunks=chunks), SPACING,
                                              band))
    assert same(got, ref)
    inner = np.abs(whole) <= band
    assert inner.any() and (~inner).any()
    assert same(got[inner], whole[inner])  # exact inside the band
    assert np.all(np.abs(got[~inner]) == np.float32(band))  # clamped outside
    assert np.all(np.sign(got[~inner]) == np.sign(whole[~inner]))


def test_band_halo_follows_the_region_rule():
    # distance_band_input's floor(D / h) ... and at least ceil(D / h) for float32 rounding
    assert band_halo((1.25, 0.8, 1.0), 2.7) == (3, 4, 3)
    assert band_halo((0.1, 0.1, 0.1), 0.3) == (3, 3, 3)
    assert band_halo((1.0, 1.0, 1.0), 4.0) == (4, 4, 4)
    sub = band_halo((1.25, 0.8, 1.0), 1.5, "subvoxel")
    assert all(s > v for s, v in zip(sub, band_halo((1.25, 0.8, 1.0), 1.5), strict=True))
    with pytest.raises(VolwarpError, match="positive"):
        band_halo((1, 1, 1), 0.0)


def test_band_is_tight_a_smaller_halo_differs():
    """One site just inside the halo: blocks grown one voxel less miss it."""
    spacing, band = (1.0, 1.0, 1.0), 3.5
    shape = (24, 24, 24)
    mask = np.zeros(shape, bool)
    mask[12, 12, 10] = True  # 3 voxels (within D) from x = 7, the last of the block [0, 8)
    ref = finish_field(signed_edt(mask, spacing), max_distance=band)
    m = da.from_array(mask.view(np.uint8), chunks=8)

    def task(block):
        return chunked._edt_block(block, 1.0, 1.0, 1.0, band)

    halo = band_halo(spacing, band)
    assert halo == (4, 4, 4)  # floor(3.5) = 3 by the region rule, one more for rounding
    for depth, equal in ((halo, True), ((4, 4, 3), True), ((4, 4, 2), False)):
        got = compute(m.map_overlap(task, depth=depth, boundary="none", dtype=np.float32))
        assert same(got, ref) is equal, depth


@pytest.mark.parametrize("seed", [0, 4])
def test_subvoxel_band_equals_the_clamped_whole(seed):
    values = smooth(SHAPE, seed)
    band = 1.5
    ref = finish_field(subvoxel_signed_distance(values, 0.0, spacing_zyx=SPACING),
                       max_distance=band)
    got, info = signed_distance_dask(da.from_array(values, chunks=CHUNKS[0]), SPACING,
                                     iso=0.0, max_distance=band)
    assert info == {"metric": "euclidean", "surface": "subvoxel", "chunked": "band",
                    "max_distance": band}
    assert same(compute(got), ref)
    assert (np.abs(ref) < band).any() and (np.abs(ref) == np.float32(band)).any()


def test_subvoxel_band_block_without_crossing():
    # samples crossing 0 only near one corner: most blocks see no surface at all
    values = smooth(SHAPE, 1) - 2.2
    assert 0 < (values >= 0).sum() < 200
    ref = finish_field(subvoxel_signed_distance(values, 0.0, spacing_zyx=SPACING),
                       max_distance=2.0)
    got = banded_signed_distance_dask(da.from_array(values, chunks=(8, 8, 8)), SPACING, 2.0,
                                      iso=0.0, surface="subvoxel")
    assert same(compute(got), ref)


# -- the chunked signed_distance ---------------------------------------------------------------
def test_signed_distance_dask_matches_signed_distance():
    data = (200 - 150 * sphere(SHAPE, (17.3, 21.6, 13.1), 11.0)).astype(np.int16)
    ref, _ = signed_distance(data, SPACING, iso=120, inside="below")
    got, info = signed_distance_dask(da.from_array(data, chunks=CHUNKS[0]), SPACING, iso=120,
                                     inside="below")
    assert info == {"metric": "euclidean", "surface": "voxel", "chunked": "passes",
                    "max_distance": None}
    assert same(compute(got), ref)
    got, info = signed_distance_dask(da.from_array(data, chunks=CHUNKS[1]), SPACING, iso=120,
                                     inside="below", max_distance=3.0)
    assert info["chunked"] == "band" and info["max_distance"] == 3.0
    assert same(compute(got), finish_field(ref.copy(), max_distance=3.0))
    # smooth samples forced to voxel surfaces: the threshold's exact field
    values = smooth(SHAPE, 2)
    ref, _ = signed_distance(values, SPACING, iso=0.3, surface="voxel")
    got, info = signed_distance_dask(da.from_array(values, chunks=CHUNKS[0]), SPACING,
                                     iso=0.3, surface="voxel")
    assert info["surface"] == "voxel" and same(compute(got), ref)


@pytest.mark.parametrize("kind", ["two-values", "three-values", "block-binary", "bool",
                                  "nan", "constant-blocks"])
def test_binary_check_agrees_with_field(kind):
    """The one-pass chunked is_binary picks the surface signed_distance picks."""
    rng = np.random.default_rng(5)
    data = np.where(blobs(SHAPE, 0), 9.0, 2.0).astype(np.float32)
    if kind == "three-values":
        data[3, 4, 5] = 5.0
    elif kind == "block-binary":  # every block has two values, the volume three
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
    for chunks in CHUNKS:
        darr = da.from_array(data, chunks=chunks)
        _, info = signed_distance_dask(darr, SPACING, iso=iso, max_distance=2.0)
        assert info["surface"] == ref["surface"], (kind, chunks)
    expect = "subvoxel" if kind in ("three-values", "block-binary", "nan") else "voxel"
    assert ref["surface"] == expect


def test_empty_full_and_nan_messages_are_the_in_memory_ones(caplog):
    data = smooth(SHAPE, 3)
    darr = da.from_array(data, chunks=CHUNKS[0])
    messages = []
    for iso in (50.0, -50.0):
        with pytest.raises(VolwarpError) as mem:
            signed_distance(data, SPACING, iso=iso)
        with pytest.raises(VolwarpError) as out:
            signed_distance_dask(darr, SPACING, iso=iso, max_distance=1.0)
        assert str(out.value) == str(mem.value)
        messages.append(str(out.value))
    assert "empty" in messages[0] and "range" in messages[0] and "fills" in messages[1]
    # all NaN: empty, with the range of nothing (nan), as in memory
    nans = np.full((5, 6, 7), np.nan, np.float32)
    with pytest.raises(VolwarpError) as mem, np.errstate(all="ignore"), \
            pytest.warns(RuntimeWarning, match="All-NaN"):  # field.py's nanmin of nothing
        signed_distance(nans, SPACING, iso=0.0)
    with pytest.raises(VolwarpError) as out:
        signed_distance_dask(da.from_array(nans, chunks=3), SPACING, iso=0.0)
    assert str(out.value) == str(mem.value)
    data[1, 2, 3] = np.nan
    darr = da.from_array(data, chunks=CHUNKS[0])
    caplog.clear()
    with caplog.at_level("WARNING", logger="volwarp"):
        signed_distance_dask(darr, SPACING, iso=0.0, max_distance=1.0)
    assert "1 NaN samples" in caplog.text and "outside" in caplog.text
    # a NaN sample is outside: below-the-iso with everything else inside is not full
    filled = np.full(SHAPE, -1.0, np.float32)
    filled[5, 5, 5] = np.nan
    _, info = signed_distance_dask(da.from_array(filled, chunks=CHUNKS[1]), SPACING, iso=0.0,
                                   inside="below", max_distance=2.0)
    assert info["surface"] == "subvoxel"  # NaN makes the samples non-binary, as in memory


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"metric": "minnorm"}, "minnorm metric has no out-of-core"),
    ({"metric": "taxicab"}, "taxicab metric has no out-of-core"),
    ({"metric": "chessboard", "max_distance": 2.0}, "chessboard metric has no out-of-core"),
    ({"surface": "subvoxel"}, "need --max-distance"),
    ({}, "need --max-distance"),  # smooth samples, auto: sub-voxel
    ({"metric": "nope"}, "unknown metric"),
    ({"surface": "subvoxel", "metric": "minnorm"}, "need the euclidean metric"),
    ({"max_distance": 0.0}, "positive"),
    ({"inside": "left"}, "inside must be"),
])
def test_refusals(kwargs, match):
    darr = da.from_array(smooth(SHAPE, 0), chunks=CHUNKS[0])
    with pytest.raises(VolwarpError, match=match) as err:
        signed_distance_dask(darr, SPACING, iso=0.0, **kwargs)
    assert "\n" not in str(err.value)


def test_refuses_complex_and_non_3d():
    with pytest.raises(VolwarpError, match="type complex"):
        signed_distance_dask(da.zeros((4, 4, 4), dtype=complex, chunks=2), iso=0.0)
    with pytest.raises(VolwarpError, match="3-D"):
        signed_edt_dask(da.zeros((4, 4), bool, chunks=2))


def test_hypothesis_random_masks_and_chunkings():
    from hypothesis import given, settings
    from hypothesis import strategies as st
    from hypothesis.extra.numpy import arrays

    @st.composite
    def cases(draw):
        shape = draw(st.tuples(st.integers(1, 9), st.integers(1, 11), st.integers(1, 13)))
        mask = draw(arrays(bool, shape))
        chunks = tuple(draw(st.integers(1, n)) for n in shape)
        spacing = draw(st.tuples(*[st.floats(0.25, 4.0)] * 3))
        budget = draw(st.integers(1, 4000))
        band = draw(st.floats(0.3, 6.0))
        return mask, chunks, spacing, budget, band

    @settings(max_examples=40, deadline=None)
    @given(cases())
    def check(case):
        mask, chunks, spacing, budget, band = case
        ref = signed_edt(mask, spacing)
        darr = da.from_array(mask, chunks=chunks)
        got = signed_edt_dask(darr, spacing, block_bytes=budget).compute(scheduler="sync")
        assert same(got, ref)
        got = banded_signed_distance_dask(darr, spacing, band).compute(scheduler="sync")
        assert same(got, finish_field(ref, max_distance=band))

    check()


def test_in_memory_path_does_not_import_dask():
    code = ("import sys, numpy as np\n"
            "from volwarp_cli.distance.field import signed_distance\n"
            "d = np.zeros((8, 9, 10), np.uint8); d[3:6, 2:7, 4:8] = 1\n"
            "signed_distance(d, (1, 1, 1), iso=0.5)\n"
            "assert 'dask' not in sys.modules, 'dask imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)
