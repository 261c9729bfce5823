"""`volwarp warp --labels --chunked`: label maps by slabs of target planes, the in-memory bytes.

A map of several labels (a negative one, one that vanishes under a squeeze) on a rotated
grid with odd sizes; slab depths that do not divide the target; crop, --preserve-labels,
OME-Zarr with a pyramid on another scheduler; the per-label report; the switch when
the in-memory warp does not fit; the bounding boxes read in slabs.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

ROTATED = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture
def seg(tmp_path):
    """A segmentation, and a spec that moves it and squeezes label 5 out of existence."""
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (19, 23, 17)], indexing="ij")
    lab = np.zeros(x.shape, np.int16)
    lab[x * x + y * y + z * z < 0.6] = 3
    lab[(np.abs(x - 0.3) < 0.25) & (np.abs(y) < 0.3) & (np.abs(z) < 0.4)] = 7
    lab[(np.abs(x + 0.4) < 0.12) & (np.abs(y + 0.1) < 0.12) & (np.abs(z) < 0.12)] = -2
    lab[9, 11, 8] = 5  # one voxel in the middle of the squeeze below
    path = tmp_path / "seg.nrrd"
    write_volume(Volume(lab, spacing=np.array([0.8, 0.9, 1.1]),
                        origin=np.array([10.0, -5.0, 3.0]), direction=ROTATED), path)
    moves = "\n".join(f"      - {{index: [{i}, {j}, {k}], by: [{-2.5 * (i - 2)}, "
                      f"{-2.5 * (j - 2)}, {-2.5 * (k - 2)}]}}"
                      for i in range(5) for j in range(5) for k in range(5))
    spec = tmp_path / "w.yaml"
    spec.write_text(f"version: 1\nunits: voxel\ncapture: {{lattice: 5}}\nsteps:\n  - move:\n"
                    f"{moves}\n      - {{index: [1, 3, 2], by: [1.5, -1, 0.5]}}\n")
    return path, spec


def _report(stdout):
    doc = json.loads(stdout)
    doc.pop("output")
    return doc


@pytest.mark.parametrize("extra", [[], ["--crop"], ["--preserve-labels"],
                                   ["--crop", "--preserve-labels"]])
@pytest.mark.parametrize("block", ["1", "4", "7"])
def test_label_warp_by_slabs_equals_the_in_memory_one(run, seg, tmp_path, extra, block):
    src, spec = seg
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    a = run("warp", src, "--spec", spec, "--labels", "-o", mem, "--json", *extra)
    assert a.code == 0, a.stderr
    b = run("warp", src, "--spec", spec, "--labels", "-o", blk, "--json", "--chunked",
            "--block", block, *extra)
    assert b.code == 0, b.stderr
    assert blk.read_bytes() == mem.read_bytes()
    assert _report(a.stdout) == _report(b.stdout)
    doc = json.loads(b.stdout)
    if "--preserve-labels" in extra:  # the squeezed label is kept, at one voxel
        assert doc["preserved"] == [5] and doc["vanished"] == []
        assert (read_volume(blk).data == 5).sum() == 1
    else:
        assert doc["vanished"] == [5] and not (read_volume(blk).data == 5).any()
    out = read_volume(blk).data
    assert set(np.unique(out)) <= {0, -2, 3, 5, 7}  # no invented ids
    assert {-2, 3, 7} <= set(np.unique(out))


@pytest.mark.parametrize("scheduler", ["processes", "synchronous"])
def test_label_warp_by_slabs_to_a_pyramid_on_other_schedulers(run, seg, tmp_path, scheduler):
    import zarr

    src, spec = seg
    mem, blk = tmp_path / "m.ome.zarr", tmp_path / "b.ome.zarr"
    common = ["--spec", spec, "--labels", "--preserve-labels", "--pyramid", "2"]
    assert run("warp", src, *common, "-o", mem).code == 0
    res = run("warp", src, *common, "-o", blk, "--chunked", "--block", "5", "--scheduler",
              scheduler)
    assert res.code == 0, res.stderr
    a, b = zarr.open_group(mem), zarr.open_group(blk)
    for level in ("0", "1", "2"):
        assert np.array_equal(a[level][...], b[level][...])
    assert b.attrs["volwarp"]["downsampling"] == "mode"  # labels are never averaged


def test_a_label_warp_too_big_for_the_budget_runs_by_slabs(run, seg, tmp_path, monkeypatch):
    """The switch itself: at this size the buffers a slab shares with the in-memory warp
    (the deformation's chunks, a domain chunk) outweigh the whole target, so the slab
    estimate is scaled down to let a budget refuse the in-memory warp and still hold
    two slabs."""
    from volwarp_cli import memory
    from volwarp_cli.warp.label_blocks import OneShotLabelWarp

    real = OneShotLabelWarp.slab_bytes
    monkeypatch.setattr(OneShotLabelWarp, "slab_bytes", lambda self, depth: real(self, depth) // 16)
    src, spec = seg
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    assert run("warp", src, "--spec", spec, "--labels", "-o", mem).code == 0
    monkeypatch.setattr(memory, "process_rss", lambda: 0)
    monkeypatch.setattr("volwarp_cli.execute.MIN_BLOCK_BUDGET", 64 << 10)
    res = run("warp", src, "--spec", spec, "--labels", "-o", blk, "--memory-limit", "8M")
    assert res.code == 0, res.stderr
    assert "running by blocks" in res.stderr
    assert blk.read_bytes() == mem.read_bytes()


def test_the_label_block_path_refusals(run, seg, tmp_path):
    src, spec = seg
    out = tmp_path / "o.nrrd"
    res = run("warp", src, "--spec", spec, "--labels", "-o", out, "--chunked", "--frames-to",
              str(tmp_path / "f_{frame}.nrrd"))
    assert res.code == 2 and "--frames-to" in res.stderr
    res = run("warp", src, "--spec", spec, "-o", out, "--chunked", "--preserve-labels",
              "--values", "intensity")
    assert res.code == 2 and "--values intensity" in res.stderr
    res = run("warp", src, "--spec", spec, "--labels", "-o", tmp_path / "o.nii.gz", "--chunked")
    assert res.code == 2 and "block" in res.stderr  # (a usage error)
    assert not out.exists() and not (tmp_path / "o.nii.gz").exists()


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 9))
def test_bounding_boxes_read_in_slabs_are_the_whole_maps(seed, depth):
    from volwarp_cli.warp.label_blocks import bounding_boxes_by_blocks
    from volwarp_cli.warp.labels import _bounding_boxes

    rng = np.random.default_rng(seed)
    shape = tuple(int(v) for v in rng.integers(1, 14, 3))
    lab = rng.choice([0, 0, 0, 1, 4, -3, 90], size=shape).astype(np.int16)

    def run(task, items):
        return [task(item) for item in items]

    labels, nvox, boxes = bounding_boxes_by_blocks(lab, run, depth)
    want_labels, want_nvox, want_boxes, _ = _bounding_boxes(lab)
    assert labels == want_labels and nvox == want_nvox
    assert boxes == want_boxes


def test_a_label_pyramid_takes_the_mode_in_memory_too(run, tmp_path):
    """Random labels fail the label-map hint; their levels must still not be averaged."""
    import zarr

    rng = np.random.default_rng(5)
    src = tmp_path / "r.nrrd"
    write_volume(Volume(rng.integers(1, 5, (16, 18, 14)).astype(np.int16)), src)
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 4}\nsteps:\n  - move:\n"
                    "      - {index: [1, 1, 1], by: [0.3, 0, 0]}\n")
    for name, extra in (("m", []), ("b", ["--chunked", "--block", "4"])):
        res = run("warp", src, "--spec", spec, "--labels", "--pyramid", "1",
                  "-o", tmp_path / f"{name}.ome.zarr", *extra)
        assert res.code == 0, res.stderr
    a, b = zarr.open_group(tmp_path / "m.ome.zarr"), zarr.open_group(tmp_path / "b.ome.zarr")
    assert a.attrs["volwarp"]["downsampling"] == "mode"
    assert np.array_equal(a["1"][...], b["1"][...])
    assert set(np.unique(a["1"][...])) <= {0, 1, 2, 3, 4}


def test_a_float32_segmentation_is_warped_as_labels(run, seg, tmp_path):
    """nibabel and MONAI write segmentations as floats: the defaults warped them as
    intensities (138,582 invented values on a real map). Now as labels, in memory and by
    slabs the same bytes: the integer map's ids, in the input's float type."""
    src, spec = seg
    floats = tmp_path / "seg_f.nrrd"
    assert run("convert", src, "-o", floats, "--dtype", "float32").code == 0
    ints, mem, blk = tmp_path / "i.nrrd", tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    assert run("warp", src, "--spec", spec, "-o", ints).code == 0
    a = run("warp", floats, "--spec", spec, "-o", mem, "--json")
    assert a.code == 0, a.stderr
    assert json.loads(a.stdout)["values_why"] == "looks like a label map: 5 labels"
    b = run("warp", floats, "--spec", spec, "-o", blk, "--json", "--chunked", "--block", "4")
    assert b.code == 0, b.stderr
    assert blk.read_bytes() == mem.read_bytes()
    assert _report(a.stdout)["labels"] == _report(b.stdout)["labels"]
    got = read_volume(mem).data
    assert got.dtype == np.float32
    assert np.array_equal(got, read_volume(ints).data.astype(np.float32))
    nii = tmp_path / "seg_f.nii.gz"  # (as the reviewer made it)
    assert run("convert", src, "-o", nii, "--dtype", "float32").code == 0
    res = run("warp", nii, "--spec", spec, "-o", tmp_path / "n.nii.gz")
    assert res.code == 0, res.stderr
    assert set(np.unique(read_volume(tmp_path / "n.nii.gz").data)) <= {0, -2, 3, 5, 7}


def test_a_map_without_0_gains_no_0_by_slabs_either(run, seg, tmp_path):
    """Ids 1, 3, 6, 8, 10 (3 around the anatomy), warped on the grown grid: where nothing
    lands it was 0, an id the map does not have; now its border's label 3, the same bytes
    by slabs."""
    src, spec = seg
    lab = read_volume(src)
    shifted = tmp_path / "no0.nrrd"
    write_volume(lab.with_data((lab.data + 3).astype(np.int16)), shifted)  # ids 1, 3, 6, 8, 10
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    a = run("warp", shifted, "--spec", spec, "--grid", "grow", "-o", mem, "--json")
    assert a.code == 0, a.stderr
    b = run("warp", shifted, "--spec", spec, "--grid", "grow", "-o", blk, "--json",
            "--chunked", "--block", "5")
    assert b.code == 0, b.stderr
    assert blk.read_bytes() == mem.read_bytes()
    assert _report(a.stdout) == _report(b.stdout)
    got = read_volume(mem).data
    assert got.shape != lab.data.shape  # (grown: there is empty space)
    assert 0 not in got and set(np.unique(got)) <= {1, 3, 6, 8, 10}
    assert [e["label"] for e in json.loads(a.stdout)["labels"]] == [1, 6, 8, 10]
