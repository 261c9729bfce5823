"""The warp's region rules checked against the dependence they claim.

- :func:`volwarp_cli.regions.warp_input` (the domain box a target block needs,
  from the convex-hull property of the B-spline plus the box filter's reach):
  exactly that box gives the whole computation's sums on the block, one voxel
  less on a side where the rule is tight does not, and where it has slack the
  slack is bounded by the hull's spread.
- :meth:`.reach.Reach.planes` (each domain plane's target planes): never
  smaller than the true footprint, on random lattices.
- :func:`.work.thread_parts` with the per-plane reach (and the label warp's ring
  sized from it): the same bytes for any thread count.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli import parallel
from volwarp_cli.box import Box
from volwarp_cli.bspline import jobs, pushforward, work
from volwarp_cli.bspline.capture import capture_volume
from volwarp_cli.bspline.pushforward import HeldPlanes
from volwarp_cli.bspline.reach import PlaneReach, offset_bounds
from volwarp_cli.bspline.scene import Scene
from volwarp_cli.volume import Volume
from volwarp_cli.warp import blocks, labels
from volwarp_cli.warp.labels import capture_labels, warp_labels

THREADS = [1, 2, 3, 5]


def _blob(shape_zyx, seed=0):
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape_zyx], indexing="ij")
    smooth = 100.0 * np.exp(-(x * x + y * y + z * z) / 0.3)
    return (smooth + rng.uniform(1, 5, shape_zyx)).astype(np.float32)


def _block_sums(scene, box: Box, need: Box) -> np.ndarray:
    """The integer sums on target block ``box`` from domain voxels ``need`` (z y x) alone."""
    acc = np.zeros(box.shape + (2,), np.int64)
    (tx0, ty0, tz0), (_, _, tz1) = box.xyz()
    scene.contribute([scene.dq], need, 1, acc=acc, held=HeldPlanes(tz0, tz1), window=box,
                     acc_xy=(tx0, ty0), parallel=False)
    return acc


def _plane(dshape, g) -> Box:
    """Domain plane ``g`` of a domain of ``dshape`` (x, y, z), as a Box."""
    return Box((g, 0, 0), (g + 1, dshape[1], dshape[0]))


def _cut(box: Box, axis: int, side: int, n: int) -> Box:
    lo, hi = list(box.lo), list(box.hi)
    if side == 0:
        lo[axis] += n
    else:
        hi[axis] -= n
    return Box(lo, hi)


def test_domain_box_is_exact_tight_where_the_hull_is_a_point_and_its_slack_bounded():
    """A lattice translated everywhere and moved at random on its high-x half.

    Target block: its low-x side's voxels lie in regions whose control points
    (and neighbours' points) are all the same translation, so the hull of
    their offsets is a point and the rule is tight there: one plane less
    changes the sums. Elsewhere the regions' hulls spread and the rule keeps
    voxels that happen to land outside; its slack on a side is at most the
    spread of the offsets' bounds (in domain voxels), plus the rounding.
    """
    data = _blob((30, 30, 34))
    cap = capture_volume(Volume(data), lattice=(14, 9, 9), oversample=1.0)  # regions of 4-5
    rng = np.random.default_rng(4)
    dq = cap.dq + np.array([2.3, -1.7, 0.6])
    cx = dq.shape[2]
    dq[:, :, cx // 2 + 1:] += rng.normal(scale=1.2, size=dq[:, :, cx // 2 + 1:].shape)
    scene = Scene(cap.domain, cap.grid, dq, 3, method="box", domain_range=cap.stats[:2])
    scene.compute()
    box = Box((10, 9, 7), (22, 21, 30))
    need = blocks.domain_box(scene, box)
    whole = scene.acc[box.slices]
    assert np.any(whole != 0)
    assert np.array_equal(_block_sums(scene, box, need), whole)

    lo_u, hi_u = offset_bounds(dq)
    spread = (hi_u - lo_u).max(axis=(0, 1, 2))  # x, y, z
    scale = np.asarray(scene.scale)
    domain = Box.from_xyz((0, 0, 0), cap.grid.domain_shape)
    tight = []
    for axis in range(3):
        xyz = 2 - axis
        bound = int(np.ceil(spread[xyz] / scale[xyz])) + 2
        for side in (0, 1):
            edge = need.lo[axis] if side == 0 else need.hi[axis]
            if edge in (domain.lo[axis], domain.hi[axis]):
                continue  # the domain's own face: nothing beyond it to leave out
            slack = 0  # voxels the rule keeps on this side that the block does not need
            while (slack < need.shape[axis] - 1 and np.array_equal(
                    _block_sums(scene, box, _cut(need, axis, side, slack + 1)), whole)):
                slack += 1
            assert slack <= bound, (axis, side, slack, bound)
            if slack == 0:
                tight.append((axis, side))
    assert (2, 0) in tight  # the low-x side, all translation: the hull is a point


def _random_lattice(cap, seed, scale, lift):
    rng = np.random.default_rng(seed)
    dq = cap.dq + rng.normal(scale=scale, size=cap.dq.shape)
    if lift:  # one corner of the lattice pushed far in z: its layers reach much further
        dq[:3, :3, :3, 2] += lift
    return dq


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10 ** 6), scale=st.floats(0.0, 2.5),
       lift=st.sampled_from([0.0, -5.0, 7.5]), oversample=st.sampled_from([1.0, 1.5, 2]),
       tight=st.booleans())
def test_plane_reach_holds_every_voxel_footprint(seed, scale, lift, oversample, tight):
    """Every domain voxel's contributions land within the target planes its plane is given.

    Plane by plane (a plane's touched box is the union of its voxels' boxes),
    and each target plane's domain window holds every plane that reaches it.
    (The rule rounds outwards by up to a plane, ``floor(.. - 0.5)`` and
    ``ceil(.. + 0.5) + 1``: a bound one plane short at the top can still hold
    here; two short is caught.) ``tight``: the bound from the deformation itself
    (:meth:`.reach.Reach.tight_planes`, the label warp's), else the lattice's hull.
    """
    cap = capture_volume(Volume(_blob((12, 11, 13), seed=seed % 7)), lattice=(4, 5, 4),
                         oversample=oversample)
    dq = _random_lattice(cap, seed, scale, lift)
    sc = Scene(cap.domain, cap.grid, dq, 2)
    pr = sc.tight_plane_reach(dq) if tight else sc._plane_reach([dq])
    dshape = cap.grid.domain_shape
    acc = np.zeros(tuple(sc.target_shape[::-1]) + (2,), np.int64)
    tz = sc.target_shape[2]
    footprint = []
    for g in range(dshape[2]):
        bb = sc.contribute([dq], _plane(dshape, g), 1, acc=acc, bounds=True, parallel=False)
        if bb is None:
            footprint.append(None)
            continue
        assert pr.t_lo[g] <= bb.lo[0] and bb.hi[0] <= pr.t_hi[g], (g, bb, pr.t_lo[g],
                                                                   pr.t_hi[g])
        footprint.append((bb.lo[0], bb.hi[0]))
    for t0 in range(0, tz, 3):
        t1 = min(t0 + 3, tz)
        a, b = pr.domain_window(t0, t1)
        for g, f in enumerate(footprint):
            if f is not None and f[0] < t1 and f[1] > t0:
                assert a <= g < b, (t0, t1, g, a, b)


def test_tight_plane_reach_of_a_drag_is_the_drag_not_its_handles():
    """A drag moves its handle's 4^3 control points by up to about 2.4 times itself
    (minimum norm): the hull's reach grows by that, the deformation's by the drag only.

    The bound still holds every plane's footprint (the scatter's own boxes).
    """
    from volwarp_cli.bspline.reach import _refined

    c = np.random.default_rng(0).normal(size=9)  # subdivision keeps the curve: both evaluated
    t = (np.arange(8) + 0.5) / 8
    from volwarp_cli.bspline.basis import basis
    curve = np.concatenate([basis(t) @ c[r:r + 4] for r in range(6)])
    t2 = (np.arange(4) + 0.5) / 4
    q = _refined(c, 0)
    again = np.concatenate([basis(t2) @ q[r:r + 4] for r in range(len(q) - 3)])
    np.testing.assert_allclose(again, curve, atol=1e-12)

    cap = capture_volume(Volume(_blob((40, 30, 32))), lattice=(7, 7, 7), oversample=2)
    dq = cap.dq.copy()
    w = np.array([1 / 6, 2 / 3, 1 / 6, 0.0])  # a voxel centre's basis weights (t = 0)
    weights = np.einsum("i,j,k->ijk", w, w, w)
    dq[2:6, 2:6, 2:6, 2] += 6.0 * weights / (weights ** 2).sum()  # moves that point by 6
    sc = Scene(cap.domain, cap.grid, dq, 2)
    tight, hull = sc.tight_plane_reach(dq), sc._plane_reach([dq])
    dz = np.asarray(dq[..., 2] - cap.dq[..., 2])
    assert dz.max() > 2.3 * 6.0  # (the handles' overshoot)
    base = sc.reach.offset[2] + sc.reach.scale[2] * np.arange(len(tight.t_hi))
    assert (tight.t_hi - base).max() <= 6.0 + 0.5 * sc.reach.scale[2] + 2.6
    assert (hull.t_hi - base).max() > 13.0
    acc = np.zeros(tuple(sc.target_shape[::-1]) + (2,), np.int64)
    dshape = cap.grid.domain_shape
    for g in range(dshape[2]):
        bb = sc.contribute([dq], _plane(dshape, g), 1, acc=acc, bounds=True, parallel=False)
        if bb is not None:
            assert tight.t_lo[g] <= bb.lo[0] and bb.hi[0] <= tight.t_hi[g], g


def test_thread_parts_use_the_per_plane_reach(small_splits):
    """The parts' domain ranges come from each plane's own reach: never wider than the
    lattice-wide bound's, narrower on a lattice moved unevenly, and still every plane
    whose voxels land in a part is in its range."""
    cap = capture_volume(Volume(_blob((40, 16, 18))), lattice=(5, 5, 9), oversample=1)
    dq = _random_lattice(cap, 2, 0.4, 6.0)
    sc = Scene(cap.domain, cap.grid, dq, 4)
    dshape = cap.grid.domain_shape
    with parallel.use_threads(4):
        parts = work.thread_parts(sc.reach, sc._plane_reach([dq]),
                                  Box.from_xyz((0, 0, 0), dshape), 0)
    assert parts is not None and len(parts) >= 2
    narrower = 0
    acc = np.zeros(tuple(sc.target_shape[::-1]) + (2,), np.int64)
    boxes = [sc.contribute([dq], _plane(dshape, g), 1, acc=acc, bounds=True, parallel=False)
             for g in range(dshape[2])]
    for p in parts:
        (t0, g0), (t1, g1) = (p.target.lo[0], p.domain.lo[0]), (p.target.hi[0], p.domain.hi[0])
        w0, w1 = sc.reach.domain_z_window(dq, t0, t1)
        assert w0 <= g0 and g1 <= w1
        narrower += (w1 - w0) - (g1 - g0)
        for g, bb in enumerate(boxes):
            if bb is not None and bb.lo[0] < t1 and bb.hi[0] > t0:
                assert g0 <= g < g1
    assert narrower > 0


def test_renders_and_updates_identical_bytes_for_any_thread_count(monkeypatch, small_splits):
    """Full renders and local updates (both ways, one lattice and two) split over 1, 2, 3
    and 5 threads by the per-plane parts: the same bytes (the parts are really taken)."""
    seen = []
    real = work.thread_parts

    def spy(*args, **kw):
        out = real(*args, **kw)
        seen.append(out is not None and len(out) >= 2)
        return out

    monkeypatch.setattr(work, "thread_parts", spy)
    data = _blob((30, 24, 26))
    rng = np.random.default_rng(9)
    moves = [((i, j, k), rng.normal(scale=1.5, size=3))
             for i, j, k in [(2, 3, 1), (4, 1, 3), (3, 3, 3)]]

    def run_all(update):
        cap = capture_volume(Volume(data), lattice=(6, 7, 6), oversample=1.5)
        dq = _random_lattice(cap, 1, 0.3, 3.0)
        sc = Scene(cap.domain, cap.grid, dq, 4, update=update)
        outs = [sc.compute().copy()]
        for idx, d in moves:
            dq = dq.copy()
            dq[idx] += d
            sc.set_lattice(dq)
            outs.append(sc.result().copy())
        return outs

    for update in ("subtract", "rebuild"):
        ref = None
        for n in THREADS:
            seen.clear()
            with parallel.use_threads(n):
                outs = run_all(update)
            if n > 1:
                assert any(seen), (update, n)
            if ref is None:
                ref = outs
            else:
                for a, b in zip(ref, outs, strict=True):
                    assert a.tobytes() == b.tobytes(), (update, n)


def test_label_warp_identical_for_any_thread_count_with_the_per_plane_ring():
    """The label warp's ring and domain windows from the per-plane reach (the deformation's
    own, :meth:`Reach.tight_planes`): the ring is smaller than the lattice-wide bound's,
    and the labels are those of that bound at 1, 2, 3 and 5 threads."""
    shape = (44, 12, 14)  # long in z: a ring of fewer planes than the whole target
    z, y, x = np.indices(shape)
    lab = np.zeros(shape, np.int64)
    lab[(x - 6) ** 2 + (y - 6) ** 2 + (z - 20) ** 2 < 30] = 3
    lab[(x - 9) ** 2 + (y - 5) ** 2 + (z - 8) ** 2 < 12] = 7
    lab[30:40, 3:9, 4:10] = 12
    cap = capture_labels(Volume(lab), lattice=(5, 5, 12), oversample=2)
    dq = _random_lattice(cap, 5, 0.6, 4.0)

    def loose(sc):  # the lattice-wide bound, plane by plane: what the ring was sized from
        bounds = [sc.reach.target_z_reach(dq, g, g + 1) for g in range(cap.grid.domain_shape[2])]
        return PlaneReach(np.array([b[0] for b in bounds]), np.array([b[1] for b in bounds]))

    sc = Scene(cap.voxmap, cap.grid, dq, 3, domain_range=(0.0, 1.0))
    wide = loose(sc)
    sc.tight_plane_reach = lambda dq: wide
    ref = warp_labels(lab, sc)
    wide_ring = labels.LabelStream(sc, dq, lab, 0, sc.target_shape[2], None, None).planes
    for n in THREADS:
        sc = Scene(cap.voxmap, cap.grid, dq, 3, domain_range=(0.0, 1.0))
        with parallel.use_threads(n):
            got = warp_labels(lab, sc)
        assert got.target.tobytes() == ref.target.tobytes(), n
        assert got.report == ref.report
    ring = labels.LabelStream(sc, dq, lab, 0, sc.target_shape[2], None, None).planes
    assert ring < wide_ring


def test_scatter_job_clip_is_a_box():
    """The scatter's domain block and target window are Boxes; a pair of triples where a
    Box belongs is a TypeError, and the kernel's raw clip is made from it in one place."""
    u = np.zeros((3, 4, 4, 4), np.float32)
    values = np.zeros((2, 2, 2), np.float32)
    acc = np.zeros((4, 4, 4, 2), np.int64)
    clip = Box((0, 1, 2), (4, 3, 4))  # z y x
    good = dict(u=u, u_new=None, origin=(0, 0, 0), values=values, planes=(0, 2),
                offset=(1.0, 1.0, 1.0), scale=(1.0, 1.0, 1.0),
                block=Box((0, 0, 0), (2, 2, 2)), sign=1, inv_vmax=1.0, box=True, acc=acc,
                clip=clip)
    job = jobs.ScatterJob(**good)
    assert job.clip == clip
    assert jobs.clip_ints(clip) == (2, 4, 1, 3, 0, 4)
    assert jobs.ScatterJob(**{**good, "clip": (2, 4, 1, 3, 0, 4)}).clip == clip
    with pytest.raises(TypeError):
        jobs.ScatterJob(**{**good, "block": ((0, 0, 0), (2, 2, 2))})
    with pytest.raises(TypeError):
        jobs.ScatterJob(**{**good, "clip": ((0, 4), (1, 3))})
    assert pushforward.target_clip(((2, 4), (1, 3)), (0, 0), (4, 4), 0, 4) == clip
    assert pushforward.target_clip(clip, (9, 9), (1, 1), 0, 4) == clip
    assert pushforward.with_planes(clip, 1, 0) == Box((1, 1, 2), (1, 3, 4))


def _big_reach(lattice, input_shape=(512, 512, 512), oversample=2):
    from volwarp_cli.bspline.lattice import Lattice
    from volwarp_cli.bspline.reach import Reach

    grid = Lattice.create(input_shape, (lattice,) * 3, oversample)
    return Reach(grid, np.zeros(3), np.asarray(grid.scale, float), input_shape)


def test_tight_plane_reach_of_a_large_lattice_is_bounded_in_memory_and_within_the_hull():
    """A 40^3 lattice on a 512^3 input at oversample 2 (1024 domain planes): the refined
    nets are made a batch at a time (they took 1.8 GB at once), fewer refinements where
    they would be many; the bound lies within the hull's, and a non-finite lattice gives
    the hull's."""
    import tracemalloc

    reach = _big_reach(40)
    rng = np.random.default_rng(3)
    dq = rng.normal(scale=2.0, size=tuple(reach.grid.lattice[::-1]) + (3,))
    hull = reach.planes(offset_bounds(dq))
    tracemalloc.start()
    tight = reach.tight_planes(dq, hull)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 200 << 20, peak
    assert (tight.t_lo >= hull.t_lo).all() and (tight.t_hi <= hull.t_hi).all()
    dq[5, 6, 7, 2] = np.nan
    same = reach.tight_planes(dq, hull)
    assert np.array_equal(same.t_lo, hull.t_lo) and np.array_equal(same.t_hi, hull.t_hi)


def test_tight_plane_reach_computed_once_for_the_threads_that_ask():
    """The label warp's shares each ask for the bound at once: one computes it."""
    import threading

    from volwarp_cli.bspline import reach as reach_mod

    cap = capture_volume(Volume(_blob((20, 16, 18))), lattice=(5, 5, 6), oversample=2)
    dq = _random_lattice(cap, 1, 0.5, 0.0)
    sc = Scene(cap.domain, cap.grid, dq, 2)
    calls = []
    real = reach_mod.Reach.tight_planes

    def counted(self, *a, **k):
        calls.append(1)
        return real(self, *a, **k)

    reach_mod.Reach.tight_planes = counted
    try:
        got = []
        threads = [threading.Thread(target=lambda: got.append(sc.tight_plane_reach(dq)))
                   for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        reach_mod.Reach.tight_planes = real
    assert len(calls) == 1 and all(g is got[0] for g in got)
