"""`distance` of a label map: its labels' voxel surface, never its ids' values (issue 28).

A label map (:func:`volwarp_cli.labelmap.looks_like_labels`) is measured as the
voxels with a non-zero id (``--label N``: the voxels of N), on the voxel
surface: renaming the ids (a bijection of the non-zero ids, 0 kept) writes the
same bytes, in memory and by blocks; the field is scipy's exact transform of
that mask with the spacing, signed as volwarp signs it (negative inside). The
old rule (the ids as intensities, ``--values intensity``) is kept on request,
and it is what moved by millimetres when the ids were renamed. A real
segmentation: SimpleITK's k-means of the bundled T1 scan (the issue's case).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import DATA
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy import ndimage as ndi

from volwarp_cli.distance.labels import (
    ShapeRule,
    choose_shape,
    rule_signed_distance,
    scan_values,
)
from volwarp_cli.errors import BadUsage, VolwarpError
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.labelmap import looks_like_labels, value_counts
from volwarp_cli.volume import Volume

SPACING = np.array([1.2, 0.9, 2.0])  # x, y, z


def scipy_signed(mask, spacing_zyx):
    """The exact signed field: positive outside, negative inside (volwarp's sign)."""
    return (ndi.distance_transform_edt(~mask, sampling=spacing_zyx)
            - ndi.distance_transform_edt(mask, sampling=spacing_zyx))


def segmentation(shape=(15, 18, 21), labels=3, seed=0, sigma=2.5):
    """A piecewise-constant map: 0 and up to ``labels`` ids from smoothed noise (the argmax)."""
    rng = np.random.default_rng(seed)
    fields = np.stack([ndi.gaussian_filter(rng.random(shape), sigma) for _ in range(labels + 1)])
    return np.argmax(fields, axis=0).astype(np.uint8)


def renamed(seg, mapping, dtype=None):
    """``seg`` with each id ``k`` renamed ``mapping[k]`` (0 kept)."""
    out = np.zeros(seg.shape, dtype or seg.dtype)
    for old, new in mapping.items():
        out[seg == old] = new
    return out


SCAN = DATA / "mri_t1_head_coronal_2x2x3mm.nrrd"


@pytest.fixture(scope="module")
def kmeans():
    """SimpleITK's k-means (4 classes) of the bundled T1 head: a third-party label map."""
    sitk = pytest.importorskip("SimpleITK")
    vol = read_volume(SCAN)
    image = sitk.GetImageFromArray(vol.data.astype(np.uint8))
    seg = sitk.GetArrayFromImage(sitk.ScalarImageKmeans(image, [10, 60, 120, 200], False))
    return vol.with_data(seg.astype(np.uint8))


def write_pair(tmp_path, vol, mapping, name="seg.nrrd"):
    """The map and its renamed twin, under one file name (provenance names the file)."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    write_volume(vol, tmp_path / "a" / name)
    write_volume(vol.with_data(renamed(vol.data, mapping)), tmp_path / "b" / name)
    return tmp_path / "a" / name, tmp_path / "b" / name


# -- the rule --------------------------------------------------------------------------------

def test_the_rule_and_its_reasons(kmeans):
    seg = segmentation()
    rule = choose_shape(seg)
    assert rule == ShapeRule("labels", "looks like a label map: 4 labels", ids="ids 1, 2, 3")
    assert "values=labels labels=all (looks like a label map: 4 labels)" == rule.note()
    assert choose_shape(seg, label=2).note() == \
        "values=labels label=2 (looks like a label map: 4 labels)"
    assert choose_shape(seg, values="labels").why == "given"
    assert choose_shape(seg, values="intensity", iso=1.5).note() == \
        "iso=1.5 inside=above values=intensity (given)"
    smooth = ndi.gaussian_filter(seg.astype(np.float32), 1.0)
    assert choose_shape(smooth, iso=1.0).note() == \
        "iso=1 inside=above values=intensity (not a label map)"
    assert choose_shape(kmeans.data).labels  # the real segmentation
    assert choose_shape(read_volume(SCAN).data, iso=40).values == "intensity"  # the scan: not


def test_scan_by_boxes_is_the_whole_arrays_answer():
    """Many small boxes, as by blocks: the rule's answer and the value counts of the whole."""
    seg = renamed(segmentation(labels=4, seed=3), {1: 7, 2: 300, 3: 9, 4: 65000}, np.uint16)
    values, counts = value_counts(seg)
    for box_voxels in (1 << 22, 400, 17):  # one box; slabs of planes; pieces of rows
        scan = scan_values(seg, box_voxels=box_voxels)
        assert scan.looks_like == looks_like_labels(seg) is True
        assert np.array_equal(scan.values, values) and np.array_equal(scan.counts, counts)
    floats = scan_values(seg.astype(np.float32))  # a segmentation stored as floats
    assert floats.looks_like and np.array_equal(floats.values, values)
    assert scan_values(seg + np.float32(0.5)).values is None  # fractions: no ids


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10**6), labels=st.integers(1, 5), data=st.data(),
       spacing=st.tuples(*[st.sampled_from([0.5, 1.0, 1.3, 2.0])] * 3))
def test_renaming_the_ids_changes_no_byte(seed, labels, data, spacing):
    """Any bijection of the non-zero ids (0 kept) gives the same field, byte for byte,
    equal to scipy's exact transform of the labels' voxels; --label N with N renamed too."""
    seg = segmentation((7, 9, 11), labels, seed, sigma=1.5).astype(np.int32)
    ids = [int(v) for v in np.unique(seg) if v]
    assume(ids and (seg == 0).any())
    new = data.draw(st.lists(st.integers(-2**31, 2**31 - 1).filter(bool), min_size=len(ids),
                             max_size=len(ids), unique=True))
    mapping = dict(zip(ids, new, strict=True))
    other = renamed(seg, mapping)
    rule, rule2 = choose_shape(seg, values="labels"), choose_shape(other, values="labels")
    a, _ = rule_signed_distance(seg, spacing, rule)
    b, _ = rule_signed_distance(other, spacing, rule2)
    assert a.dtype == np.float32 and a.tobytes() == b.tobytes()
    np.testing.assert_allclose(a, scipy_signed(seg != 0, spacing), rtol=1e-6, atol=1e-4)
    # the label rule itself reads no id's value
    assert scan_values(seg).looks_like == scan_values(other).looks_like
    n = data.draw(st.sampled_from(ids))
    if (seg == n).all():
        return
    a, _ = rule_signed_distance(seg, spacing, choose_shape(seg, label=n))
    b, _ = rule_signed_distance(other, spacing, choose_shape(other, label=mapping[n]))
    assert a.tobytes() == b.tobytes()
    np.testing.assert_allclose(a, scipy_signed(seg == n, spacing), rtol=1e-6, atol=1e-4)


def test_refusals_in_the_core():
    seg = segmentation()
    with pytest.raises(BadUsage, match=r"looks like a label map \(4 labels\): "
                                       r"--iso 2 selects other voxels.*--label N.*--values "
                                       "intensity"):
        choose_shape(seg, iso=2)
    with pytest.raises(BadUsage, match="--surface subvoxel needs --values intensity"):
        choose_shape(seg, surface="subvoxel")
    with pytest.raises(BadUsage, match="--inside goes with --iso"):
        choose_shape(seg, inside="below")
    with pytest.raises(BadUsage, match="does not go with --values intensity"):
        choose_shape(seg, values="intensity", label=1, iso=0.5)
    fraction = seg + np.float32(0.5)  # (floats that are all integers are a label map)
    with pytest.raises(BadUsage, match="needs a label map \\(integer ids\\), got float32 "
                                       "samples that are not all integers"):
        choose_shape(fraction, label=1)
    with pytest.raises(BadUsage, match="--iso V is required"):
        choose_shape(fraction)
    assert choose_shape(seg.astype(np.float32)) == choose_shape(seg)
    with pytest.raises(VolwarpError, match="label 9 does not occur"):
        choose_shape(seg, label=9)
    full = seg + 1  # no background: all non-zero
    with pytest.raises(VolwarpError, match="every voxel has a non-zero label"):
        choose_shape(full)
    assert choose_shape(full, label=1).label == 1
    # an iso level selecting exactly the labels' voxels is the label rule
    assert choose_shape(seg, iso=0.5).labels and choose_shape(seg, iso=1, inside="above").labels
    assert choose_shape(seg, label=3, iso=2.5).label == 3


# -- the command line ------------------------------------------------------------------------

def test_cli_renamed_ids_same_bytes_and_scipy(run, tmp_path, kmeans):
    """The issue's case: the k-means map with ids renamed. Default (no --iso) and --iso 0.5
    (which today took the sub-voxel surface between the ids) give the same bytes."""
    a, b = write_pair(tmp_path, kmeans, {1: 3, 2: 1, 3: 2})
    for extra in ([], ["--iso", "0.5"]):
        outs = []
        for src in (a, b):
            out = src.parent / f"d{len(extra)}.nrrd"
            res = run("distance", src, "-o", out, *extra)
            assert res.code == 0, res.stderr
            outs.append(out.read_bytes())
        assert outs[0] == outs[1]
    assert (a.parent / "d0.nrrd").read_bytes() == (a.parent / "d2.nrrd").read_bytes()
    out = read_volume(a.parent / "d0.nrrd")
    assert out.data.dtype == np.float32 and out.same_grid(kmeans)
    np.testing.assert_allclose(out.data, scipy_signed(kmeans.data != 0, kmeans.spacing[::-1]),
                               rtol=1e-6, atol=2e-3)
    assert out.meta["volwarp_distance"] == (
        "metric=euclidean surface=voxel values=labels labels=all "
        "(looks like a label map: 4 labels)")


def test_cli_one_label_renamed(run, tmp_path, kmeans):
    a, b = write_pair(tmp_path, kmeans, {1: 3, 2: 1, 3: 2})
    assert run("distance", a, "-o", a.parent / "l.nrrd", "--label", 2).code == 0
    assert run("distance", b, "-o", b.parent / "l.nrrd", "--label", 1).code == 0
    da, db = read_volume(a.parent / "l.nrrd"), read_volume(b.parent / "l.nrrd")
    assert da.data.tobytes() == db.data.tobytes()
    np.testing.assert_allclose(da.data, scipy_signed(kmeans.data == 2, kmeans.spacing[::-1]),
                               rtol=1e-6, atol=2e-3)
    assert da.meta["volwarp_distance"].endswith("label=2 (looks like a label map: 4 labels)")


def test_cli_ids_as_intensities_on_request_moved_by_millimetres(run, tmp_path, kmeans):
    """--values intensity is the old rule (the sub-voxel surface between the ids): renaming
    the ids moved it by millimetres (the issue's 4.45 mm; 3.99 mm on this map)."""
    a, b = write_pair(tmp_path, kmeans, {1: 3, 2: 1, 3: 2})
    for src in (a, b):
        res = run("distance", src, "-o", src.parent / "i.nrrd", "--iso", "0.5",
                  "--values", "intensity")
        assert res.code == 0, res.stderr
    ia, ib = read_volume(a.parent / "i.nrrd"), read_volume(b.parent / "i.nrrd")
    assert np.abs(ia.data - ib.data).max() > 2.0
    assert ia.meta["volwarp_distance"] == (
        "metric=euclidean surface=subvoxel iso=0.5 inside=above values=intensity (given)")


@pytest.mark.parametrize("high", [1, 255])
def test_cli_binary_mask_at_half_is_todays_field(run, tmp_path, high):
    """A 0/1 or 0/255 mask with --iso 0.5: the samples it always gave (the intensity rule)."""
    seg = segmentation()
    write_volume(Volume(((seg == 1) * high).astype(np.uint8), spacing=SPACING), tmp_path / "m.nrrd")
    res = run("distance", tmp_path / "m.nrrd", "-o", tmp_path / "new.nrrd", "--iso", "0.5", "-v")
    assert res.code == 0 and "values: labels (looks like a label map: 2 labels)" in res.stderr
    assert run("distance", tmp_path / "m.nrrd", "-o", tmp_path / "old.nrrd", "--iso", "0.5",
               "--values", "intensity").code == 0
    new, old = read_volume(tmp_path / "new.nrrd"), read_volume(tmp_path / "old.nrrd")
    assert new.data.tobytes() == old.data.tobytes()
    assert "surface=voxel" in old.meta["volwarp_distance"]


def test_cli_usage_errors_are_one_line_and_write_nothing(run, tmp_path):
    seg = segmentation()
    write_volume(Volume(seg, spacing=SPACING), tmp_path / "s.nrrd")
    # (floats with fractions: integer-valued floats are a label map)
    write_volume(Volume(seg + np.float32(0.25), spacing=SPACING), tmp_path / "f.nrrd")
    out = tmp_path / "o.nrrd"
    cases = [
        (["s.nrrd", "--iso", "2"], 2, ["looks like a label map", "--label N",
                                       "--values intensity"]),
        (["s.nrrd", "--surface", "subvoxel"], 2, ["looks like a label map", "voxel surface"]),
        (["s.nrrd", "--label", "1", "--surface", "subvoxel"], 2, ["--surface subvoxel"]),
        (["s.nrrd", "--inside", "below"], 2, ["--inside goes with --iso"]),
        (["s.nrrd", "--values", "intensity"], 2, ["needs --iso V"]),
        (["s.nrrd", "--values", "intensity", "--label", "1", "--iso", "1"], 2,
         ["does not go with --values intensity"]),
        (["f.nrrd", "--values", "labels"], 2, ["needs a label map", "not all integers"]),
        (["f.nrrd"], 2, ["--iso V is required", "does not look like a label map"]),
        (["s.nrrd", "--label", "9"], 1, ["label 9 does not occur"]),
    ]
    for args, code, words in cases:
        for chunked in ([], ["--chunked"]):
            res = run("distance", tmp_path / args[0], *args[1:], "-o", out, *chunked)
            lines = res.stderr.strip().splitlines()
            assert res.code == code and len(lines) == 1, (args, res)
            assert all(w in lines[0] for w in words), (args, lines)
            assert not out.exists()
    res = run("distance", "--update", tmp_path / "f.nrrd", "--transform", tmp_path / "t.yaml",
              "--label", "1", "-o", out)
    assert res.code == 2 and "--label does not apply to --update" in res.stderr


def test_cli_a_float32_segmentation_is_measured_by_its_labels(run, tmp_path, kmeans):
    """A segmentation written as float32 (`convert --dtype float32`, as nibabel and MONAI
    write them) demanded --iso; it is a label map: the integer map's field, in memory and
    by blocks the same bytes."""
    src = tmp_path / "seg.nrrd"
    write_volume(kmeans, src)
    floats = tmp_path / "seg_f.nii.gz"
    assert run("convert", src, "-o", floats, "--dtype", "float32").code == 0
    ints, mem, blk = tmp_path / "i.nrrd", tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    assert run("distance", src, "-o", ints).code == 0
    res = run("distance", floats, "-o", mem, "-v")
    assert res.code == 0, res.stderr
    assert "values: labels (looks like a label map: 4 labels)" in res.stderr
    assert np.array_equal(read_volume(mem).data, read_volume(ints).data)
    res = run("distance", floats, "-o", blk, "--chunked", "--block", "7,6,9")
    assert res.code == 0, res.stderr
    assert blk.read_bytes() == mem.read_bytes()
    res = run("distance", floats, "--label", "2", "-o", tmp_path / "two.nrrd")
    assert res.code == 0, res.stderr


def test_cli_verbose_says_the_choice(run, tmp_path):
    seg = segmentation()
    write_volume(Volume(seg, spacing=SPACING), tmp_path / "s.nrrd")
    res = run("distance", tmp_path / "s.nrrd", "-o", tmp_path / "o.nrrd", "-v")
    assert ("values: labels (looks like a label map: 4 labels): the distance of the voxels "
            "with a non-zero label (ids 1, 2, 3), on the voxel surface") in res.stderr
    res = run("distance", tmp_path / "s.nrrd", "-o", tmp_path / "o.nrrd", "-v", "--values",
              "intensity", "--iso", "2")
    assert "values: intensity (given): the distance of the samples above 2" in res.stderr


# -- by blocks -------------------------------------------------------------------------------

@pytest.mark.parametrize("extra,label", [
    ([], None), (["--label", "2"], 2), (["--max-distance", "3"], None),
    (["--label", "1000", "--max-distance", "2.5"], 1000), (["--metric", "minnorm"], None),
    (["--unsigned"], None)], ids=["exact", "label", "band", "label-band", "minnorm", "unsigned"])
def test_by_blocks_writes_the_in_memory_bytes(run, tmp_path, extra, label):
    """A renamed label map by blocks (odd blocks, 2 threads) = the map in memory, byte for byte."""
    seg = renamed(segmentation(labels=3, seed=5), {1: 40, 2: 2, 3: 1000}, np.int16)
    vol = Volume(seg, spacing=SPACING, origin=np.array([3.0, -1.0, 7.5]))
    write_volume(vol, tmp_path / "s.nrrd")
    mem, blk = tmp_path / "mem.nrrd", tmp_path / "blk.nrrd"
    assert run("distance", tmp_path / "s.nrrd", "-o", mem, *extra).code == 0
    res = run("distance", tmp_path / "s.nrrd", "-o", blk, *extra, "--chunked",
              "--block", "7,6,9", "--threads", "2")
    assert res.code == 0, res.stderr
    assert mem.read_bytes() == blk.read_bytes()
    ref = scipy_signed(seg != 0 if label is None else seg == label, SPACING[::-1])
    if "--max-distance" in extra:
        d = float(extra[extra.index("--max-distance") + 1])
        ref = np.clip(ref, -d, d)
    got = read_volume(mem).data
    if "--metric" in extra:  # the spacing-weighted taxicab distance: no closer than scipy's
        assert np.all(np.abs(got) >= np.abs(ref) - 1e-4) and np.all(np.sign(got) == np.sign(ref))
    elif "--unsigned" in extra:
        np.testing.assert_allclose(got, np.maximum(ref, 0), atol=1e-4)
    else:
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-4)


def test_by_blocks_label_ids_renamed(run, tmp_path):
    seg = segmentation(labels=3, seed=6)
    a, b = write_pair(tmp_path, Volume(seg, spacing=SPACING), {1: 2, 2: 3, 3: 1})
    for src in (a, b):
        assert run("distance", src, "-o", src.parent / "c.nrrd", "--chunked", "--block", "5",
                   "--threads", "2").code == 0
    assert (a.parent / "c.nrrd").read_bytes() == (b.parent / "c.nrrd").read_bytes()


def test_help_says_float32(run):
    res = run("distance", "--help")
    assert res.code == 0
    head = res.stdout.split("Options:")[0]
    assert "float32" in head.split("\n\n")[1]  # the first line of the description
    assert "default: float32" in " ".join(res.stdout.split("--dtype", 1)[1].split())


def test_labels_asked_of_a_scan_say_so_once(run, tmp_path):
    """As warp says it: --label N on a volume that does not look like a label map warns."""
    scan = Path(__file__).parent / "data" / "mri_t1_head_coronal_2x2x3mm.nrrd"
    res = run("distance", scan, "--label", "40", "-o", tmp_path / "d.nrrd")
    assert res.code == 0
    assert res.stderr.count("does not look like a label map") == 1, res.stderr
    ball = Path(__file__).parent / "data" / "ball_30_uint8.nrrd"
    res = run("distance", ball, "--label", "200", "-o", tmp_path / "b.nrrd")
    assert res.code == 0 and res.stderr == "", res.stderr
