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
from volwarp_cli.bspline import _warpkernels as K
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
        # (in input voxels: the nearest's weight 1 a domain voxel, k^3 of them in one)
        per = 1 if scene.method == "box" else max(1, scene.grid.subdivision) ** 3
        predicted[lb] = int(wl.sum()) if per == 1 else int(wl.sum()) / per
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
    assert len(calls) >= 3 and res.code == 1 and "memory" in res.stderr, (
        len(calls), res.code, res.stderr)
    assert out.read_bytes() == b"an earlier result"
    assert [p.name for p in tmp_path.iterdir()] == ["o.nrrd"]


# -- the C kernels themselves ---------------------------------------------------------------
#
# _warpkernels.scatter_labels and resolve_planes on blocks whose numbers are exact and known:
# domain voxels = input voxels (k = 1), the deformation a translation by dyadic offsets (or
# none: the still shortcut), so every box side, overlap and product is exact and each
# label's weight at a target voxel can be written down here with numpy.

_Q40 = 1 << 40


def _kernel_args(codes, *, scale, off=(0.5, 1.25, 0.75), shift=(0.0, 0.0, 0.0), still=False,
                 box=True, slots=1, pool_blocks=64, tile=4):
    """``(args, target shape z y x)`` of a scatter_labels call on the whole block of ``codes``.

    ``scale``, ``off``, ``shift``: x y z. The target: every voxel the boxes can reach, one
    ring of all its planes.
    """
    nz, ny, nx = codes.shape
    u = np.empty((3, nz + 2, ny + 2, nx + 2), np.float32)
    for c in range(3):
        u[c] = shift[c]
    dom = (nx, ny, nz)
    t = tuple(int(np.ceil(off[a] + scale[a] * dom[a] + abs(shift[a]) + scale[a])) + 2
              for a in range(3))  # x y z
    ring = t[2]
    size = ring * t[1] * t[0]
    need = np.ones([-(-n // tile) for n in codes.shape], np.uint8)
    st = np.ones((1, 1, 1), np.uint8) if still else np.zeros((0, 0, 0), np.uint8)
    args = [u, (0, 0, 0), np.ascontiguousarray(codes, np.int32), (0, 0, 0), 1, (0, 0, 0),
            tuple(map(float, off)), tuple(map(float, scale)), (0, nx, 0, ny, 0, nz), box, 1.0,
            st, dom, dom, (0, t[0], 0, t[1], 0, t[2]), ring, (0, 0), (t[1], t[0]),
            np.zeros(size, np.int64), np.zeros(size * slots, np.int32),
            np.zeros(size * slots, np.int64), np.full(size, -1, np.int32),
            np.zeros(pool_blocks * (2 * slots + 1), np.int64), np.array([-1, 0, 0, 0], np.int64),
            slots, need, tile, (0, 0)]
    return args, t[::-1]


def _expected_weights(codes, ncodes, tshape, *, scale, off=(0.5, 1.25, 0.75),
                      shift=(0.0, 0.0, 0.0), box=True):
    """``W[code, z, y, x]``: each code's weight (2**-40 units) by the box (or nearest) filter."""
    from volwarp_cli.bspline.pushforward import ROUND

    W = np.zeros((ncodes, *tshape), np.int64)
    per_axis = []
    for a in range(3):  # x, y, z: each voxel's overlaps with the target voxels along the axis
        n = codes.shape[2 - a]
        centre = off[a] + scale[a] * np.arange(n) + shift[a]
        tv = np.arange(tshape[2 - a])
        if box:
            lo, hi = centre - scale[a] / 2, centre + scale[a] / 2
            ov = np.clip(np.minimum(hi[:, None], tv + 0.5) - np.maximum(lo[:, None], tv - 0.5),
                         0, None)
        else:
            ov = (np.floor(centre + ROUND)[:, None] == tv).astype(float)
        per_axis.append(ov)
    ox, oy, oz = per_axis
    for (z, y, x), c in np.ndenumerate(codes):
        w = (oz[z][:, None, None] * oy[y][None, :, None]) * ox[x][None, None, :]
        W[c] += (w * _Q40).astype(np.int64)  # (exact: dyadic overlaps)
    return W


def _scatter_all(args):
    """scatter_labels from the block's first row, the pool doubled whenever it stops."""
    stops = 0
    start = args[27]
    while True:
        start = K.scatter_labels(*args[:27], start)
        if start[0] < 0:
            return stops
        stops += 1
        args[22] = np.concatenate([args[22], np.zeros_like(args[22])])


def _ring_weights(args, ncodes, tshape):
    """``(wall, W[code, z, y, x])`` read from a ring (its slots and chains) as the kernel left it."""
    wall, head_l, head_w, head_next, pool = args[18:23]
    slots = args[24]
    W = np.zeros((ncodes, int(np.prod(tshape))), np.int64)
    hl, hw = head_l.reshape(-1, slots), head_w.reshape(-1, slots)
    for t, j in zip(*np.nonzero(hl), strict=True):
        assert W[hl[t, j], t] == 0  # (a label once a voxel)
        W[hl[t, j], t] = hw[t, j]
    stride = 2 * slots + 1
    for t in np.flatnonzero(head_next >= 0):
        assert (hl[t] != 0).all()  # (a chain only past full slots)
        blk = head_next[t]
        while blk >= 0:
            b = pool[blk * stride:(blk + 1) * stride]
            for j in range(slots):
                if b[1 + j]:
                    assert W[b[1 + j], t] == 0
                    W[b[1 + j], t] = b[1 + slots + j]
            blk = b[0]
    return wall.reshape(tshape), W.reshape(ncodes, *tshape)


def _resolve(args, ncodes, tshape, below):
    z0, z1 = args[14][4], args[14][5]
    out = np.full((z1 - z0, *tshape[1:]), -1, np.int32)
    counts, total_hi, total_lo, peak_w = (np.zeros(ncodes, np.int64) for _ in range(4))
    peak_at = np.zeros((ncodes, 3), np.int64)
    K.resolve_planes(z0, z1, args[15], args[16], args[17], *args[18:24], args[24], below, out,
                     counts, total_hi, total_lo, peak_w, peak_at)
    return out, counts, (total_hi << 32) + total_lo, peak_w, peak_at


KERNEL_CASES = [  # scale, shift (x y z), still, box
    ((1.0, 1.0, 1.0), (0.25, -0.5, 0.125), False, True),     # narrow boxes
    ((0.5, 0.5, 0.5), (0.375, 0.25, -0.125), False, True),   # an oversample of 2's
    ((2.0, 1.5, 1.0), (0.125, 0.25, 0.5), False, True),      # wide boxes (splat)
    ((0.5, 0.5, 0.5), (0.0, 0.0, 0.0), True, True),          # still voxels, narrow
    ((2.0, 2.0, 0.5), (0.0, 0.0, 0.0), True, True),          # still voxels, wide
    ((1.0, 0.5, 1.0), (0.0, -0.75, 0.5), False, False),      # nearest (ties: half voxels)
]


@pytest.mark.parametrize("scale, shift, still, box", KERNEL_CASES)
@pytest.mark.parametrize("slots", [1, 3])
def test_the_kernel_adds_each_labels_exact_weights(scale, shift, still, box, slots):
    """Every label's weight at every target voxel, its slots and chains, the total weight,
    then the winners, totals and peaks resolve_planes reads: as computed here."""
    rng = np.random.default_rng(slots)
    ncodes = 7
    codes = rng.integers(0, ncodes, (5, 6, 7))
    args, tshape = _kernel_args(codes, scale=scale, shift=shift, still=still, box=box,
                                slots=slots)
    _scatter_all(args)
    W = _expected_weights(codes, ncodes, tshape, scale=scale, shift=shift, box=box)
    wall, got = _ring_weights(args, ncodes, tshape)
    assert np.array_equal(wall, W.sum(axis=0))
    assert np.array_equal(got[1:], W[1:]) and not got[0].any()  # (the background: no slot)
    if slots == 1:
        assert args[23][2] > 0  # (chains taken: labels beyond the slots)
    below = 4
    out, counts, totals, peak_w, peak_at = _resolve(args, ncodes, tshape, below)
    # the winner: the largest label weight (ties: the smaller code), against the background's
    w_fg = W[1:].sum(axis=0)
    w_b = np.maximum(W.sum(axis=0), _Q40) - w_fg
    best = np.argmax(W[1:], axis=0) + 1
    best_w = W[1:].max(axis=0)
    wins = (best_w > 0) & ((best_w > w_b) | ((best_w == w_b) & (best < below)))
    assert np.array_equal(out, np.where(wins, best, 0))
    assert counts.tolist() == np.bincount(out.ravel(), minlength=ncodes).tolist()
    assert totals[1:].tolist() == W[1:].reshape(ncodes - 1, -1).sum(axis=1).tolist()
    for c in range(1, ncodes):
        assert peak_w[c] == W[c].max()
        assert tuple(peak_at[c]) == np.unravel_index(np.argmax(W[c]), tshape)
    # the ring cleared for its next turn, the chains' blocks all back on the free list
    assert not args[18].any() and not args[19].any() and (args[21] == -1).all()
    assert args[23][3] == args[23][1]


@pytest.mark.parametrize("slots", [1, 2])
def test_a_tiny_pool_grows_to_the_same_weights(slots):
    """From one block, the pool runs short mid-block: the kernel stops before a row, the
    pool doubles and the kernel resumes there; the weights are those of a large pool."""
    rng = np.random.default_rng(5)
    codes = rng.integers(0, 30, (6, 7, 8))
    kw = dict(scale=(1.5, 1.0, 2.0), shift=(0.25, 0.5, -0.25), slots=slots)
    small, tshape = _kernel_args(codes, pool_blocks=1, **kw)
    large, _ = _kernel_args(codes, pool_blocks=1 << 14, **kw)
    assert _scatter_all(small) >= 3 and _scatter_all(large) == 0
    assert small[23][2] == large[23][2] > 100  # (as many blocks taken)
    a, b = _ring_weights(small, 30, tshape), _ring_weights(large, 30, tshape)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    for x, y in zip(_resolve(small, 30, tshape, 1), _resolve(large, 30, tshape, 1),
                    strict=True):
        assert np.array_equal(x, y)


def _bad_scatter(mutate):
    args, _ = _kernel_args(np.arange(60).reshape(3, 4, 5) % 4, scale=(1.0, 1.0, 1.0))
    mutate(args)
    return args


@pytest.mark.parametrize("mutate, error", [
    (lambda a: a.__setitem__(18, a[18][:-1]), ValueError),                 # wall short
    (lambda a: a.__setitem__(19, a[19][:-1]), ValueError),                 # head_l short
    (lambda a: a.__setitem__(21, a[21][:-1]), ValueError),                 # head_next short
    (lambda a: a.__setitem__(19, a[19].astype(np.int64)), TypeError),      # head_l's type
    (lambda a: a.__setitem__(0, a[0][:, :, :, :-1]), ValueError),          # u: not contiguous
    (lambda a: a.__setitem__(0, np.ascontiguousarray(a[0][:, :-1])), ValueError),  # u short
    (lambda a: a.__setitem__(2, np.ascontiguousarray(a[2][:, :, :-1])), ValueError),  # codes
    (lambda a: a.__setitem__(25, np.ones((1, 1, 1), np.uint8)), ValueError),  # need short
    (lambda a: a.__setitem__(11, np.ones((1, 2, 1), np.uint8)), ValueError),  # still regions
    (lambda a: a.__setitem__(23, np.array([-1, 0, 0], np.int64)), ValueError),  # state
    (lambda a: a.__setitem__(23, np.array([-1, 65, 0, 0], np.int64)), ValueError),  # used
    (lambda a: a.__setitem__(23, np.array([64, 0, 0, 0], np.int64)), ValueError),  # free list
    (lambda a: a.__setitem__(14, (0, a[17][1] + 1, 0, 2, 0, 2)), ValueError),  # clip > window
    (lambda a: a.__setitem__(14, (0, 2, 0, 2, 0, a[15] + 1)), ValueError),  # clip > ring
    (lambda a: a.__setitem__(8, (0, 6, 0, 4, 0, 3)), ValueError),          # block > domain
    (lambda a: a.__setitem__(27, (5, 0)), ValueError),                     # start
    (lambda a: a.__setitem__(24, 0), ValueError),                          # slots
])
def test_scatter_labels_refuses_a_bad_call(mutate, error):
    args = _bad_scatter(mutate)
    with pytest.raises(error):
        K.scatter_labels(*args)


def test_a_chain_leaving_the_pool_is_an_error_not_a_read():
    args = _bad_scatter(lambda a: None)
    args[19][:] = 99  # every voxel's slot taken by a code the block has not: chains
    args[21][:] = 1000  # (beyond the pool's 64 blocks)
    with pytest.raises(ValueError, match="pool"):
        K.scatter_labels(*args)
    args = _bad_scatter(lambda a: None)
    args[21][:] = 1 << 30
    with pytest.raises(ValueError, match="chain"):
        _resolve(args, 4, (args[15], *args[17]), 1)
    args = _bad_scatter(lambda a: None)
    _scatter_all(args)
    with pytest.raises(ValueError, match="code"):  # (codes up to 3, totals for 3)
        _resolve(args, 3, (args[15], *args[17]), 1)


def test_resolve_planes_refuses_a_bad_call():
    args = _bad_scatter(lambda a: None)
    _scatter_all(args)
    tshape = (args[15], *args[17])
    z0, z1 = args[14][4], args[14][5]

    def call(out_shape=(z1 - z0, *tshape[1:]), n=4, z=(z0, z1), peak=3):
        out = np.zeros(out_shape, np.int32)
        v = [np.zeros(n, np.int64) for _ in range(4)]
        K.resolve_planes(*z, args[15], args[16], args[17], *args[18:24], args[24], 1, out, *v,
                         np.zeros((n, peak), np.int64))

    with pytest.raises(ValueError):
        call(out_shape=(z1 - z0 - 1, *tshape[1:]))  # out: a plane short
    with pytest.raises(ValueError):
        call(out_shape=(z1 - z0, tshape[1] - 1, tshape[2]))  # a row short
    with pytest.raises(ValueError):
        call(z=(z0, z0 + args[15] + 1))  # more planes than the ring's
    with pytest.raises(ValueError):
        call(z=(-1, 1))
    with pytest.raises(ValueError):
        call(peak=2)
    call()  # (and the good call reads and clears it)
    assert not args[18].any()


def test_a_label_warp_imports_no_numba():
    """The label warp's kernels are C: numba (0.4 s of a command to import) stays out."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from volwarp_cli.warp.labels import capture_labels, warp_labels\n"
        "from volwarp_cli.bspline.scene import Scene\n"
        "from volwarp_cli.volume import Volume\n"
        "lab = np.zeros((10, 11, 12), np.uint8); lab[3:7, 2:8, 4:9] = 3; lab[5:9, 5:9, 5:9] = 7\n"
        "for method in ('box', 'nearest'):\n"
        "    cap = capture_labels(Volume(lab), lattice=(5, 5, 5), oversample=2)\n"
        "    dq = cap.dq.copy(); dq[2, 2, 2] += (1.2, -0.7, 0.4)\n"
        "    sc = Scene(cap.voxmap, cap.grid, dq, 2, method=method, domain_range=(0.0, 1.0))\n"
        "    assert warp_labels(lab, sc).report['labels'][3]['output_voxels'] > 0\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('numba', 'llvmlite')))\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "[]"


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
