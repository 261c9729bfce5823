"""The one-pass label warp equals the per-label passes it replaced, byte for byte.

The reference below is the former algorithm written plainly: one box
pushforward of each label's indicator over its bounding box (the scene's own
scatter, :meth:`~volwarp_cli.bspline.scene.Scene.contribute`), the
background's weight ``max(w, 1) - w_fg`` from one pass of the whole map, and
the labels taken in the former order with its tie rule (a label below the
background wins a tie, one above loses it; the smaller id wins between
labels). It accumulates whole target planes, the new warp a ring of them with
(label, weight) slots and chains: the same integer sums, so the same labels,
report, volumes and preserved voxels. ``frame="label"`` is the former code
to the bit: it computed each label's boxes in coordinates relative to its
block's corner, which rounds some box sides differently when they are not
exact (oversample 3, or offsets far below a voxel), by 2**-40 of a voxel's
weight; ``frame="target"`` (the default) computes every box in the target's
own coordinates, as the intensity warp does and the one-pass kernel does.
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volwarp_cli import parallel
from volwarp_cli.box import Box
from volwarp_cli.bspline.pushforward import HeldPlanes
from volwarp_cli.bspline.scene import Scene, Scratch
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume
from volwarp_cli.warp import labels as L
from volwarp_cli.warp.labels import capture_labels, warp_labels


def _weights(scene, dq, indicator, box, frame):
    """``(w_all, w_sel, target)``: one pass of the former warp over input box ``box``.

    Channel 0 (every domain voxel of the box) and channel 1 (those where
    ``indicator``), whole target arrays, and the block's target (None: nothing
    reaches the target).
    """
    grid = scene.grid
    k, lead = grid.subdivision, np.array(grid.lead)
    lo, hi = (np.array(v) for v in box.xyz())
    voxels = Box.from_xyz((lead + k * lo).tolist(), (lead + k * hi).tolist())
    bounds = scene._offset_bounds(dq)
    block = scene.reach.rebuild_block(bounds, bounds, voxels)
    tx, ty, tz = scene.target_shape
    if block is None:
        return None, None, None
    values = np.zeros(grid.domain_shape[::-1], np.float32)
    ind = indicator[box.slices].astype(np.float32)
    values[voxels.slices] = ind.repeat(k, 0).repeat(k, 1).repeat(k, 2)
    (z0, y0, x0), (z1, y1, x1) = block.target.lo, block.target.hi
    acc = np.zeros((z1 - z0, y1 - y0, x1 - x0, 2), np.int64)
    sc = copy.copy(scene)
    sc.scratch = Scratch()
    if frame == "label":  # the former code: coordinates from the block's corner
        sc.offset = scene.offset - np.array([x0, y0, 0.0])
        window, acc_xy = ((0, x1 - x0), (0, y1 - y0)), (0, 0)
    else:
        window, acc_xy = ((x0, x1), (y0, y1)), (x0, y0)
    sc.contribute([dq], voxels, 1, acc=acc, held=HeldPlanes(z0, z1), parallel=False,
                  values=(values, 0), window=window, acc_xy=acc_xy)
    w_all = np.zeros((tz, ty, tx), np.int64)
    w_sel = np.zeros((tz, ty, tx), np.int64)
    w_all[block.target.slices] = acc[..., 0]
    w_sel[block.target.slices] = acc[..., 1]
    return w_all, w_sel, block.target


def reference(lab, scene, *, background=None, preserve=False, frame="target"):
    """The per-label passes: ``(target labels, report)`` as the former :func:`warp_labels`."""
    from volwarp_cli.border import border_label

    b = border_label(lab) if background is None else int(background)
    labels, nvox, boxes, _ = L._bounding_boxes(lab, b)
    dq = scene.dq
    tx, ty, tz = scene.target_shape
    best_w = np.full((tz, ty, tx), L._Q, np.int64)
    best_l = np.full((tz, ty, tx), b, lab.dtype)
    full = Box.from_shape(lab.shape)
    w_all, w_fg, blk = _weights(scene, dq, lab != b, full, frame)
    if blk is not None:
        best_w[blk.slices] = np.maximum(w_all, L._Q)[blk.slices] - w_fg[blk.slices]
    order = [v for v in labels if v < b][::-1] + [v for v in labels if v > b]
    predicted, peak = {}, {}
    for lb in order:
        _, w, blk = _weights(scene, dq, lab == lb, boxes[labels.index(lb)], frame)
        predicted[lb], peak[lb] = 0, (0, None)
        if blk is None:
            continue
        bw, bl, wl = best_w[blk.slices], best_l[blk.slices], w[blk.slices]
        better = (wl >= bw) if lb < b else (wl > bw)
        bw[better] = wl[better]
        bl[better] = lb
        predicted[lb] = int(wl.sum())
        j = int(np.argmax(wl))
        if preserve and wl.flat[j] > 0:
            at = np.unravel_index(j, wl.shape)
            peak[lb] = (int(wl.flat[j]), tuple(int(a + o) for a, o in zip(at, blk.lo,
                                                                            strict=True)))
    values, counts = np.unique(best_l, return_counts=True)
    have = dict(zip(values.tolist(), counts.tolist(), strict=True))
    out_counts = {lb: int(have.get(lb, 0)) for lb in labels}

    def set_label(at, lb):
        best_l[at] = lb

    report = L.label_report(labels, nvox, predicted, peak, out_counts, 1.0, preserve=preserve,
                            label_at=lambda at: best_l[at], set_label=set_label)
    report["background"] = b
    return best_l, report


def _scene(lab, dq_fn=None, *, pad=3, lattice=(5, 5, 5), oversample=2, method="box"):
    cap = capture_labels(Volume(lab), lattice=lattice, oversample=oversample)
    dq = cap.dq.copy()
    if dq_fn is not None:
        dq_fn(dq)
    return Scene(cap.voxmap, cap.grid, dq, pad, method=method, domain_range=(0.0, 1.0))


def _smooth(amp):
    def move(dq):
        cz, cy, cx, _ = dq.shape
        k, j, i = np.meshgrid(np.arange(cz), np.arange(cy), np.arange(cx), indexing="ij")
        dq[..., 0] += amp * (np.sin(0.9 * i) + 0.5 * np.sin(0.9 * k))
        dq[..., 1] += amp * (np.cos(0.7 * j) + 0.5 * np.cos(0.7 * i))
        dq[..., 2] += 0.8 * amp * np.sin(0.8 * k + 0.3)
    return move


def _one_point(dq):
    dq[2, 2, 1] += (1.7, -1.1, 0.9)


def _voronoi(shape, cells, seed, dtype=np.int32, ids=None):
    """Touching labels: a ball cut into ``cells`` Voronoi cells (ids 1.. or ``ids``), 0 around."""
    rng = np.random.default_rng(seed)
    pts = np.stack(np.indices(shape), -1).reshape(-1, 3) + 0.5
    seeds = rng.uniform(0, 1, (cells, 3)) * np.array(shape)
    nearest = np.argmin(((pts[:, None, :] - seeds[None]) ** 2).sum(-1), axis=1)
    ids = np.arange(1, cells + 1) if ids is None else np.asarray(ids)
    out = ids[nearest].reshape(shape).astype(dtype)
    c = np.array(shape) / 2
    out[((np.indices(shape).transpose(1, 2, 3, 0) + 0.5 - c) ** 2 / c ** 2).sum(-1) > 0.8] = 0
    return out


def _same(lab, scene, **kw):
    """The one-pass warp and the reference: the same bytes and the same report."""
    frame = kw.pop("frame", "target")
    got = warp_labels(lab, scene, **kw)
    kw.pop("slots", None)
    want, report = reference(lab, scene, frame=frame, **kw)
    assert got.target.dtype == want.dtype
    assert got.target.tobytes() == want.tobytes(), int((got.target != want).sum())
    assert got.report == report
    return got


@pytest.mark.parametrize("oversample", [1, 2, 3])
@pytest.mark.parametrize("move", [_smooth(1.2), _one_point])
def test_many_touching_labels_equal_the_per_label_passes(oversample, move):
    lab = _voronoi((14, 16, 15), 60, seed=oversample)
    _same(lab, _scene(lab, move, oversample=oversample), preserve=True)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_any_thread_count_gives_the_same_bytes(threads):
    lab = _voronoi((20, 13, 14), 25, seed=4, dtype=np.uint8)
    with parallel.use_threads(threads):
        _same(lab, _scene(lab, _smooth(1.0), lattice=(6, 5, 5)))


def test_the_former_code_to_the_bit_where_its_boxes_are_exact():
    """At oversample 1 and 2 with whole-voxel and half-voxel moves every box side is
    exact: the former code's per-label coordinates change nothing there."""
    lab = _voronoi((15, 14, 16), 30, seed=7, dtype=np.int16) - 3  # ids -2..27, 0 a label
    lab[lab == -3] = 9  # (the border: background 9, labels on both sides of it)

    def halves(dq):
        dq[1:4, 1:4, 1:4] += (0.5, -1.5, 1.0)

    for oversample in (1, 2):
        _same(lab, _scene(lab, halves, oversample=oversample), frame="label", preserve=True)


def test_ties_go_to_the_smaller_id_and_around_the_background():
    """A half-voxel shift splits every target voxel evenly between two input voxels: exact
    ties between labels, and between labels and the background (9: ids below and above)."""
    lab = np.full((8, 9, 10), 9, np.int16)
    lab[2:6, 2:7, 1:9] = np.tile(np.array([3, 12, 7, 15, 1, 20, 9, 4], np.int16), (4, 5, 1))

    def shift(dq):
        dq[..., 0] += 0.5

    got = _same(lab, _scene(lab, shift), frame="label")
    assert got.report["background"] == 9
    row = got.target[3 + 3, 3 + 3, 3:3 + 11]  # a target row across the stripes
    # each output voxel takes the smaller of its two halves (9 the background, 15 and 20
    # above it lose to it, labels below it win)
    assert row.tolist() == [9, 3, 3, 7, 7, 1, 1, 9, 4, 4, 9][:len(row)]


def test_a_label_of_one_voxel_and_labels_that_vanish_or_are_preserved():
    lab = _voronoi((16, 16, 16), 12, seed=11)
    lab[8, 8, 8] = 77  # one voxel, in the middle of a squeeze

    def squeeze(dq):  # the control points either side of the middle moved towards it
        dq[2:4, 2:4, 2:4] += 0.9 * np.sign(0.5 - np.arange(2))[:, None, None, None]

    for preserve in (False, True):
        got = _same(lab, _scene(lab, squeeze, lattice=(6, 6, 6)), preserve=preserve)
        assert got.report["labels"][77]["input_voxels"] == 1


@pytest.mark.parametrize("dtype, ids", [
    (np.uint16, np.arange(300) * 211 + 5),        # > 255 labels, ids up to 63,000
    (np.int32, np.arange(400) * 40_000 - 7),      # > 65,535 apart: codes by a sorted search
    (np.float32, np.arange(280, dtype=float)),    # integer floats
])
def test_hundreds_of_labels_and_wide_ids(dtype, ids):
    rng = np.random.default_rng(3)
    lab = rng.choice(ids, size=(12, 13, 14)).astype(dtype)  # every voxel its own label
    lab[:, :, :2] = ids[0]  # the border's label: the background
    got = _same(lab, _scene(lab, _smooth(0.8)), preserve=True)
    assert len(got.report["labels"]) >= 250


@pytest.mark.parametrize("slots", [1, 2, 5])
def test_chains_past_the_slots_are_exact(slots, monkeypatch):
    """Noise with many labels a voxel: every label's weight beyond ``slots`` goes into
    chains, and the pool they come from grows (from one block) and resumes the row."""
    monkeypatch.setattr(L, "POOL_BLOCKS_MIN", 1)
    monkeypatch.setattr(L, "POOL_SHARE", 1 << 30)
    grown = []
    real = L.LabelStream.run

    def run(self):
        out = real(self)
        grown.append((self.state[2], len(self.pool)))
        return out

    monkeypatch.setattr(L.LabelStream, "run", run)
    rng = np.random.default_rng(slots)
    lab = rng.integers(0, 40, (10, 11, 12)).astype(np.int16)
    _same(lab, _scene(lab, _smooth(1.5)), slots=slots, preserve=True)
    taken, size = max(grown)
    assert taken > 100 and size > 2 * slots + 1


@pytest.mark.parametrize("oversample", [1, 2, 3])
@pytest.mark.parametrize("move", [_smooth(2.0), _one_point])
def test_a_sparse_map_leaves_out_what_no_label_reaches(oversample, move, monkeypatch):
    """Small labels in a large background: the tiles whose voxels reach no target voxel a
    label can reach are left out (fewer than all), and the bytes are the reference's."""
    lab = np.zeros((30, 28, 32), np.int16)
    lab[4:7, 5:9, 6:9] = 3
    lab[6:8, 8:10, 8:12] = 11  # (touching 3)
    lab[22:25, 20:22, 25:28] = 7
    lab[15, 14, 16] = 20  # one voxel
    lab[lab == 0] = 5  # the background, between the labels' ids
    needs = []
    real = L.needed_tiles

    def spy(*args):
        needs.append(real(*args))
        return needs[-1]

    monkeypatch.setattr(L, "needed_tiles", spy)
    _same(lab, _scene(lab, move, lattice=(6, 6, 6), oversample=oversample), preserve=True)
    if move is _one_point:  # (the smooth move's bounds, lattice-wide, reach everywhere)
        assert 0 < needs[0].mean() < 0.9


def test_needed_tiles_hold_every_voxel_that_reaches_a_label():
    """The bound itself: every input voxel whose boxes overlap a target voxel some
    labelled voxel's boxes overlap lies in a needed tile (the overlaps found with the
    scene's own scatter, voxel by voxel)."""
    lab = np.zeros((18, 17, 19), np.uint8)
    lab[3:5, 4:6, 12:15] = 1
    def move(dq):  # two points moved far: the bounds are loose around them, tight elsewhere
        dq[2, 2, 3] += (2.5, -2.0, 1.5)
        dq[3, 2, 3] += (-1.0, 2.5, 2.0)

    scene = _scene(lab, move, lattice=(9, 9, 9), oversample=1)
    tile = 4
    need = L.needed_tiles(scene, scene.dq, L.label_tiles(lab != 0, tile), tile)
    reached = _weights(scene, scene.dq, lab != 0, Box.from_shape(lab.shape), "target")[1] > 0
    # each input voxel's own reach (its indicator pushed alone)
    missing = []
    for z, y, x in np.argwhere(~need.astype(bool).repeat(tile, 0).repeat(tile, 1).repeat(
            tile, 2)[:18, :17, :19]):
        one = np.zeros(lab.shape, bool)
        one[z, y, x] = True
        w = _weights(scene, scene.dq, one, Box((z, y, x), (z + 1, y + 1, x + 1)), "target")[1]
        if w is not None and (reached & (w > 0)).any():
            missing.append((z, y, x))
    assert not missing
    assert need.mean() < 1


@pytest.mark.parametrize("oversample", [1, 2])
def test_nearest_pushforward(oversample):
    lab = _voronoi((12, 14, 13), 20, seed=5)
    _same(lab, _scene(lab, _smooth(1.3), oversample=oversample, method="nearest"))


def test_no_label_and_labels_moved_out_of_the_target():
    lab = np.zeros((8, 8, 8), np.uint8)
    got = _same(lab, _scene(lab, _one_point))
    assert not got.target.any() and got.report["labels"] == {}
    lab[3:5, 3:5, 3:5] = 4

    def away(dq):
        dq[..., 0] += 40.0

    got = _same(lab, _scene(lab, away))
    assert got.report["vanished"] == [4] and (got.target == 0).all()


def test_label_codes_by_table_and_by_search_agree():
    ids = [-7, 90, 2 ** 25 + 1]  # (the background, 3, apart)
    wide = L.LabelCodes(ids, 3, np.int64)  # a range over 65,536 ids: a sorted search
    narrow = L.LabelCodes(ids[:2], 3, np.int64)
    sample = np.array([[[3, -7, 90, 3]]], np.int64)
    a, c = np.empty(sample.shape, np.int32), np.empty(sample.shape, np.int32)
    wide.codes(sample, a)
    narrow.codes(sample, c)
    assert a.tolist() == c.tolist() == [[[0, 1, 2, 0]]]
    assert wide._lut is None and narrow._lut is not None
    assert wide.table.tolist() == [3, -7, 90, 2 ** 25 + 1] and wide.below == 2


LABELS = st.lists(st.integers(-4, 300), min_size=1, max_size=7, unique=True)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(labels=LABELS, seed=st.integers(0, 2 ** 16),
       moves=st.lists(st.tuples(st.integers(0, 4), st.integers(0, 4), st.integers(0, 4),
                                st.floats(-2.5, 2.5), st.floats(-2.5, 2.5), st.floats(-2.5, 2.5)),
                      min_size=1, max_size=4),
       method=st.sampled_from(["box", "nearest"]), oversample=st.sampled_from([1, 2, 3]),
       slots=st.integers(1, 3), blocky=st.booleans())
def test_random_maps_and_moves_equal_the_per_label_passes(labels, seed, moves, method,
                                                          oversample, slots, blocky):
    rng = np.random.default_rng(seed)
    shape = (7, 8, 9)
    if blocky:  # labels in 2x2x2 blocks: ties and long runs; else noise
        small = np.asarray(labels)[rng.integers(0, len(labels), (4, 4, 5))]
        lab = small.repeat(2, 0).repeat(2, 1).repeat(2, 2)[:7, :8, :9].astype(np.int16)
    else:
        lab = np.asarray(labels, np.int16)[rng.integers(0, len(labels), shape)]

    def move(dq):
        for i, j, k, *d in moves:
            dq[k, j, i] += d

    _same(lab, _scene(lab, move, lattice=(5, 5, 5), oversample=oversample, method=method),
          slots=slots, preserve=bool(seed % 2))


def test_a_label_warp_failing_midway_leaves_the_existing_output(run, data_dir, tmp_path,
                                                                monkeypatch):
    """The ball (a 0/200 mask: a label map) fails in its third step of domain planes."""
    from pathlib import Path

    from volwarp_cli.warp import _label_kernels as K

    out = tmp_path / "o.nrrd"
    out.write_bytes(b"an earlier result")
    calls = []
    real = K.scatter_labels

    def failing(*args):
        calls.append(1)
        if len(calls) == 3:
            raise MemoryError("out of memory midway")
        return real(*args)

    monkeypatch.setattr(K, "scatter_labels", failing)
    monkeypatch.setattr(L, "STREAM_PLANES", 1)  # many steps: some planes done
    spec = Path(__file__).parent.parent / "specs" / "warp-ball.yaml"
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", out)
    assert len(calls) >= 3 and res.code == 1 and "memory" in res.stderr
    assert out.read_bytes() == b"an earlier result"
    assert [p.name for p in tmp_path.iterdir()] == ["o.nrrd"]


# -- by slabs: the in-memory bytes ------------------------------------------------------------

@pytest.fixture
def many(tmp_path):
    """A 300-label uint16 map (ids above 255, touching), and a spec that moves it."""
    lab = _voronoi((21, 19, 23), 300, seed=2, dtype=np.uint16,
                   ids=np.arange(300, dtype=np.int64) * 97 + 1000)
    lab[10, 9, 11] = 7  # a label of one voxel
    path = tmp_path / "many.nrrd"
    write_volume(Volume(lab, spacing=np.array([0.8, 0.9, 1.1])), path)
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 5}\nsteps:\n  - move:\n"
                    "      - {index: [2, 2, 2], by: [1.6, -1.2, 0.7]}\n"
                    "      - {index: [1, 3, 2], by: [-0.8, 0.5, 1.4]}\n")
    return path, spec


@pytest.mark.parametrize("extra", [[], ["--preserve-labels", "--grid", "grow"]])
@pytest.mark.parametrize("block", ["3", "8"])
def test_many_labels_by_slabs_equal_the_in_memory_warp(run, many, tmp_path, extra, block):
    src, spec = many
    mem, blk = tmp_path / "m.nrrd", tmp_path / "b.nrrd"
    a = run("warp", src, "--spec", spec, "--labels", "-o", mem, "--json", *extra)
    assert a.code == 0, a.stderr
    b = run("warp", src, "--spec", spec, "--labels", "-o", blk, "--json", "--chunked",
            "--block", block, *extra)
    assert b.code == 0, b.stderr
    assert blk.read_bytes() == mem.read_bytes()
    ja, jb = json.loads(a.stdout), json.loads(b.stdout)
    ja.pop("output")
    jb.pop("output")
    assert ja == jb
    out = read_volume(mem).data
    assert out.dtype == np.uint16 and len(np.unique(out)) > 150
