"""The warp by output blocks equals the in-memory warp bit for bit.

Each block is computed from the domain voxels :func:`volwarp_cli.regions.warp_input`
says can reach it, gathered from the input box they read, into accumulators of the
block's own size; the exact integer sums make the blocks put together equal the
whole render, whatever the block shape.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.box import Box
from volwarp_cli.bspline.capture import capture_source, capture_volume
from volwarp_cli.bspline.pullback import BoxSampler, Sampler
from volwarp_cli.bspline.pushforward import HeldPlanes
from volwarp_cli.bspline.scene import Scene
from volwarp_cli.execute import Target
from volwarp_cli.io.lazy import LazySource
from volwarp_cli.volume import Header, Volume
from volwarp_cli.warp import blocks


def _blob(shape_zyx, seed=0):
    rng = np.random.default_rng(seed)
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape_zyx], indexing="ij")
    smooth = 100.0 * np.exp(-(x * x + y * y + z * z) / 0.3)
    return (smooth + rng.uniform(0, 5, shape_zyx)).astype(np.float32)


def _general(cap, seed=1, scale=1.5):
    rng = np.random.default_rng(seed)
    return cap.dq + rng.normal(scale=scale, size=cap.dq.shape)


def _by_blocks(scene, sampler, block_shape):
    whole = scene.target_box
    out = np.full(whole.shape, np.nan, np.float32)
    for b in whole.blocks(block_shape):
        out[b.slices] = blocks.warp_block(scene, sampler, b)
    return out


@pytest.mark.parametrize("oversample,method,sampling", [
    (1.5, "box", "linear"), (2, "box", "linear"), (1.0, "nearest", "linear"),
    (1.0, "box", "nearest"), (1.3, "box", "nearest")])
@pytest.mark.parametrize("block_shape", [(10, 7, 13), (16, 32, 9), (500, 9, 11), (3, 500, 500)])
def test_blocks_equal_the_whole_render(oversample, method, sampling, block_shape):
    data = _blob((37, 29, 41))
    cap = capture_volume(Volume(data), lattice=(6, 7, 5), oversample=oversample,
                         sampling=sampling)
    dq = _general(cap)
    full = Scene(cap.domain, cap.grid, dq, 5, method=method,
                 domain_range=cap.stats[:2]).compute()
    scene = Scene(cap.domain, cap.grid, dq, 5, method=method, domain_range=cap.stats[:2])
    sampler = BoxSampler(data, cap.grid, cap.placement, cap.sampling, cap.domain.dtype)
    out = _by_blocks(scene, sampler, block_shape)
    assert np.array_equal(out, full)
    assert np.any(out != 0)


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10**6), scale=st.sampled_from([0.5, 2.0, 4.0]),
       slab=st.integers(1, 12), oversample=st.sampled_from([1.0, 2]))
def test_slabs_along_z_equal_the_whole_for_any_lattice(seed, scale, slab, oversample):
    """A block's domain planes are those the deformation itself can move into it (the
    tight plane reach), not the control points' hull: exact for lattices moved far,
    folding ones included (every block equals the whole render's)."""
    data = _blob((26, 21, 23), seed=seed % 7)
    cap = capture_volume(Volume(data), lattice=(5, 6, 5), oversample=oversample)
    dq = _general(cap, seed=seed, scale=scale)
    pad = int(np.ceil(np.abs(dq - cap.dq).max())) + 1
    full = Scene(cap.domain, cap.grid, dq, pad, domain_range=cap.stats[:2]).compute()
    scene = Scene(cap.domain, cap.grid, dq, pad, domain_range=cap.stats[:2])
    sampler = BoxSampler(data, cap.grid, cap.placement, cap.sampling, cap.domain.dtype)
    whole = scene.target_box
    assert np.array_equal(_by_blocks(scene, sampler, (slab, *whole.shape[1:])), full)


def test_a_recipe_carries_its_planes_reach_to_the_tasks(monkeypatch):
    """A block task's scene, rebuilt from a pickled recipe, takes the planes' reach the
    command computed: no task computes it again (each did, 0.05-5 s a lattice)."""
    from volwarp_cli.bspline import reach as reach_mod

    data = _blob((30, 26, 28))
    cap = capture_volume(Volume(data), lattice=(6, 6, 6), oversample=1.0)
    scene = Scene(cap.domain, cap.grid, _general(cap, scale=2.0), 6,
                  domain_range=cap.stats[:2])
    recipe = pickle.loads(pickle.dumps(blocks.SceneRecipe(scene)))
    calls = []
    real = reach_mod.Reach.tight_planes
    monkeypatch.setattr(reach_mod.Reach, "tight_planes",
                        lambda self, *a, **k: calls.append(1) or real(self, *a, **k))
    task = recipe.build(cap.domain)
    box = Box((3, 0, 0), (14, *task.target_box.hi[1:]))
    assert blocks.domain_box(task, box) == blocks.domain_box(scene, box)
    assert calls == []
    other = Scene(cap.domain, cap.grid, scene.dq, 6, domain_range=cap.stats[:2])
    assert blocks.domain_box(other, box) == blocks.domain_box(scene, box) and calls == [1]


def test_two_parts_cut_along_z_scatter_few_voxels_twice():
    """Every control point moved (N(0, 2 voxels), regions of 8 voxels): the two z halves
    of a two-thread warp scatter 1.7 times the whole's domain voxels by the control
    points' hull (110 planes of 64); by the deformation's own reach, 1.09 times."""
    data = _blob((64, 64, 64))
    cap = capture_volume(Volume(data), lattice=(9, 9, 9), oversample=1.0)
    dq = _general(cap, seed=1, scale=2.0)
    scene = Scene(cap.domain, cap.grid, dq, 9, domain_range=cap.stats[:2])
    whole = scene.target_box
    mid = whole.lo[0] + whole.shape[0] // 2
    halves = [Box(whole.lo, (mid, *whole.hi[1:])), Box((mid, *whole.lo[1:]), whole.hi)]
    assert blocks.block_work(scene, halves) <= 1.1
    assert blocks.least_time_cut(scene, whole, 2) == halves


def test_a_block_missing_domain_voxels_differs():
    """The domain box is what the block needs: one plane less on a side changes it.

    (Tight where the map is locally a translation, as here: the hull is a point.)
    """
    data = _blob((30, 30, 30))
    cap = capture_volume(Volume(data), lattice=(5, 5, 5), oversample=1.0)
    dq = cap.dq + np.array([2.3, -1.7, 0.6])
    scene = Scene(cap.domain, cap.grid, dq, 3, method="box", domain_range=cap.stats[:2])
    sampler = BoxSampler(data, cap.grid, cap.placement, cap.sampling, cap.domain.dtype)
    full = scene.compute()
    box = Box((8, 8, 8), (20, 20, 20))
    assert np.array_equal(blocks.warp_block(scene, sampler, box), full[box.slices])
    need = blocks.domain_box(scene, box)
    for axis in range(3):
        lo = list(need.lo)
        lo[axis] += 1
        cut = Box(lo, need.hi)
        acc = np.zeros(box.shape + (2,), np.int64)
        (tx0, ty0, tz0), (tx1, ty1, tz1) = box.xyz()
        (a, b, c), _ = cut.xyz()
        scene.contribute([scene.dq], cut, 1, acc=acc, held=HeldPlanes(tz0, tz1),
                         window=((tx0, tx1), (ty0, ty1)), acc_xy=(tx0, ty0), parallel=False,
                         values=(sampler.box(cut), c, (a, b)))
        part = np.empty(box.shape, np.float32)
        from volwarp_cli.bspline import pushforward
        pushforward.finalize(acc, scene.vmax, Box.from_shape(box.shape), part, parallel=False)
        assert not np.array_equal(part, full[box.slices])


@settings(max_examples=25, deadline=None)
@given(lo=st.tuples(*[st.integers(0, 20)] * 3), size=st.tuples(*[st.integers(1, 12)] * 3),
       sampling=st.sampled_from(["linear", "nearest"]), oversample=st.sampled_from([1.0, 1.7, 2]))
def test_box_sampler_equals_the_whole_gather(lo, size, sampling, oversample):
    data = _blob((19, 23, 17), seed=3)
    cap = capture_volume(Volume(data), lattice=(5, 6, 4), oversample=oversample,
                         sampling=sampling, defer=True)
    whole, _ = Sampler(data, cap.grid, "uniform", sampling).whole()
    box = Box(lo, tuple(a + b for a, b in zip(lo, size, strict=True))).intersect(
        Box.from_shape(whole.shape))
    got = BoxSampler(data, cap.grid, "uniform", sampling).box(box)
    assert np.array_equal(got, whole[box.slices])



@settings(max_examples=25, deadline=None)
@given(shape=st.tuples(*[st.integers(2, 14)] * 3), seed=st.integers(0, 99),
       dtype=st.sampled_from(["float32", "float64"]),
       sampling=st.sampled_from(["linear", "nearest"]), oversample=st.sampled_from([1.0, 1.6]))
def test_gather_is_the_blend_of_its_tables_signed_zeros_included(shape, seed, dtype, sampling,
                                                                 oversample):
    """The compiled gather (a plain copy where every weight is 0, as at oversample 1) equals
    numpy's blend of the capture tables: v0 + w (v1 - v0) per axis, so -0.0 comes out +0.0."""
    from volwarp_cli.bspline.pullback import gather_tables

    rng = np.random.default_rng(seed)
    data = rng.normal(size=shape).astype(dtype)
    data[rng.random(shape) < 0.3] = -0.0
    cap = capture_volume(Volume(data), lattice=(4, 4, 4), oversample=oversample,
                         sampling=sampling, defer=True)
    (x0, x1, wx), (y0, y1, wy), (z0, z1, wz) = gather_tables(cap.grid, "uniform", sampling)
    d = data.astype(np.float64)

    def lerp(a, b, w):
        return a + w * (b - a)

    def along_x(p):
        return lerp(p[..., x0], p[..., x1], wx)

    def along_y(p):
        return lerp(along_x(p[:, y0]), along_x(p[:, y1]), wy[:, None])

    want = lerp(along_y(d[z0]), along_y(d[z1]), wz[:, None, None]).astype(dtype)
    got, (lo, hi) = Sampler(data, cap.grid, "uniform", sampling, dtype=dtype).whole()
    assert got.tobytes() == want.tobytes()
    assert (lo, hi) == (want.min(), want.max())
    if oversample == 1.0:
        assert not (wx.any() or wy.any() or wz.any())  # the copy's case


def test_capture_source_matches_the_in_memory_capture():
    data = (_blob((21, 18, 25)) * 100).astype(np.int16)
    vol = Volume(data, spacing=np.array([0.7, 0.9, 1.3]))
    mem = capture_volume(vol, lattice=(5, 5, 6), oversample=1.5, mean=False)
    lazy = capture_source(vol, data, lattice=(5, 5, 6), oversample=1.5)
    assert lazy.domain is None and lazy.stats[:2] == mem.stats[:2]
    assert lazy.grid.domain_shape == mem.grid.domain_shape
    assert np.array_equal(lazy.sampler.box(Box.from_shape(lazy.sampler.shape)), mem.domain)


@settings(max_examples=60, deadline=None)
@given(shape=st.tuples(st.integers(1, 40), st.integers(1, 9), st.integers(1, 9)),
       slab=st.integers(1, 700), threads=st.integers(1, 3), seed=st.integers(0, 2 ** 16))
def test_scan_source_is_the_range_faces_and_sample_read_on_their_own(shape, slab, threads,
                                                                     seed):
    """One pass gives what the separate reads give: min and max, the faces' samples in
    border_samples' order and value_sample's planes, whatever the slabs and threads."""
    from volwarp_cli import parallel
    from volwarp_cli.border import border_samples
    from volwarp_cli.bspline.capture import scan_source, value_sample

    data = np.random.default_rng(seed).normal(size=shape).astype(np.float32)
    with parallel.use_threads(threads):
        scan = scan_source(data, slab_bytes=slab * 4)
    assert (scan.lo, scan.hi) == (float(data.min()), float(data.max()))
    assert np.array_equal(scan.border, border_samples(data))
    assert np.array_equal(scan.sample, value_sample(data))


def test_scan_source_of_a_file_read_lazily_is_that_of_its_samples(tmp_path):
    """The case the one pass is for: a raw NRRD read slab by slab (its x faces no longer a
    read per row), odd sizes so the slabs, faces and sample planes fall unevenly."""
    from volwarp_cli.border import border_samples
    from volwarp_cli.bspline.capture import scan_source, value_sample
    from volwarp_cli.io import write_volume

    data = np.random.default_rng(4).normal(size=(37, 23, 29)).astype(np.float32)
    write_volume(Volume(data), tmp_path / "in.nrrd")
    source = LazySource(tmp_path / "in.nrrd")
    scan = scan_source(source, slab_bytes=3 * 23 * 29 * 4)
    assert (scan.lo, scan.hi) == (float(data.min()), float(data.max()))
    assert np.array_equal(scan.border, border_samples(data))
    assert np.array_equal(scan.sample, value_sample(data))


def test_capture_source_refuses_nan():
    data = _blob((9, 10, 11))
    data[4, 5, 6] = np.nan
    with pytest.raises(Exception, match="NaN"):
        capture_source(Volume(data), data)


def test_warp_operation_pickles_without_samples_and_renders_the_same(tmp_path):
    """A worker process gets the job pickled: the input is reopened from its path there."""
    from volwarp_cli.io import write_volume

    data = (_blob((23, 19, 27)) * 50).astype(np.int16)
    path = tmp_path / "in.nrrd"
    write_volume(Volume(data), path)
    source = LazySource(path)
    cap = capture_source(Volume(data).header, source, lattice=(5, 5, 5), oversample=1.0)
    dq = _general(cap, scale=1.0)
    scene = Scene(cap.sampler, cap.grid, dq, 4, domain_range=cap.stats[:2])
    window = scene.target_box
    job = blocks.WarpOperation(scene, source, cap.placement, cap.sampling, window,
                               Target(tmp_path / "o.nrrd", Header(window.shape, np.float32),
                                      np.float32))
    blob = pickle.dumps(job)
    assert len(blob) < 64 * 1024  # the lattice and tables, not the samples
    copy = pickle.loads(blob)
    assert copy.source._array is None and copy.targets == {}  # (the writers are the tasks')
    full = Scene(cap.sampler, cap.grid, dq, 4, domain_range=cap.stats[:2]).compute()
    box = Box((3, 4, 5), (20, 17, 26))
    assert np.array_equal(copy.output_block(box), full[box.slices])


def test_kernel_partial_values_and_accumulators_equal_whole_planes():
    """The scatter's values and accumulators may hold some columns and rows only."""
    data = _blob((20, 22, 24), seed=5)
    cap = capture_volume(Volume(data), lattice=(5, 5, 5), oversample=1.0)
    dq = _general(cap, scale=1.0)
    scene = Scene(cap.domain, cap.grid, dq, 4, domain_range=cap.stats[:2])
    tshape = scene.target_shape[::-1]
    acc_whole = np.zeros(tshape + (2,), np.int64)
    lo, hi = (3, 5, 2), (19, 20, 17)  # x, y, z domain voxels
    dbox = Box.from_xyz(lo, hi)
    scene.contribute([dq], dbox, 1, acc=acc_whole, parallel=False)
    win = Box((4, 6, 9), (20, 19, 25))  # z, y, x target window
    (tx0, ty0, tz0), (tx1, ty1, tz1) = win.xyz()
    acc = np.zeros(win.shape + (2,), np.int64)
    scene.contribute([dq], dbox, 1, acc=acc, held=HeldPlanes(tz0, tz1),
                     window=((tx0, tx1), (ty0, ty1)), acc_xy=(tx0, ty0), parallel=False,
                     values=(np.ascontiguousarray(cap.domain[dbox.slices]), lo[2],
                             (lo[0], lo[1])))
    assert np.array_equal(acc, acc_whole[win.slices])
    assert acc.any()
    with pytest.raises(ValueError, match="outside"):  # a block outside the values given
        scene.contribute([dq], Box.from_xyz((2, 5, 2), hi), 1, acc=acc,
                         held=HeldPlanes(tz0, tz1),
                         window=((tx0, tx1), (ty0, ty1)), acc_xy=(tx0, ty0), parallel=False,
                         values=(np.ascontiguousarray(cap.domain[dbox.slices]), lo[2],
                                 (lo[0], lo[1])))


@pytest.mark.parametrize("dtype", [np.float32, np.int16, np.uint8])
def test_parts_write_into_the_output_as_the_whole_cast(dtype, monkeypatch):
    """warp_block(into=...) fills a view of the output, cast plane by plane as the whole
    block is by cast_samples; WarpOperation.compute over 1, 2 and 3 threads (parts
    writing straight into one output) gives those bytes, and a strided view (a part
    cut along y) the same samples."""
    from volwarp_cli.samples import cast_samples

    data = _blob((26, 21, 23), seed=3) * 3.0
    cap = capture_volume(Volume(data), lattice=(5, 6, 5), oversample=1.0)
    dq = _general(cap, scale=1.2)
    scene = Scene(cap.domain, cap.grid, dq, 4, domain_range=cap.stats[:2])
    sampler = BoxSampler(data, cap.grid, cap.placement, cap.sampling, cap.domain.dtype)
    window = scene.target_box
    expect = cast_samples(blocks.warp_block(scene, sampler, window), dtype)
    assert np.ptp(expect.astype(float)) > 10  # (the comparison is not of a constant)
    box = Box((2, 3, 1), (window.shape[0] - 1, window.shape[1] - 2, window.shape[2]))
    whole = np.full(window.shape, 7, dtype=dtype)
    strided = whole[box.slices]  # not contiguous: its planes are cast and copied
    assert not strided.flags.c_contiguous
    blocks.warp_block(scene, sampler, box, into=strided)
    assert np.array_equal(whole[box.slices], expect[box.slices])
    outside = np.ones(window.shape, bool)
    outside[box.slices] = False
    assert np.all(whole[outside] == 7)  # nothing written beside the view
    op = blocks.WarpOperation(Scene(cap.domain, cap.grid, dq, 4, domain_range=cap.stats[:2]),
                              None, cap.placement, cap.sampling, window,
                              Target(None, Header(window.shape, dtype), dtype), sampler=sampler)
    monkeypatch.setattr(blocks, "PARALLEL_VOXELS", 1)  # (this small block is cut too)
    assert [len(op.slabs(window, t)) > 1 for t in (1, 2, 3)] == [False, True, True]
    for threads in (1, 2, 3):
        got = op.compute(window, threads=threads)[op.KEY]
        assert got.dtype == dtype and np.array_equal(got, expect), threads


@pytest.mark.parametrize("dtype", [np.float32, np.int16])
@pytest.mark.parametrize("suffix", [".nrrd", ".mha"])
def test_the_whole_written_as_computed_is_the_in_memory_file(tmp_path, dtype, suffix,
                                                             monkeypatch):
    """In memory, a warp to a file written by offset places each part's planes as they
    are finished (no array of the whole): over 1 to 4 threads (parts cut along z, and
    along y, whose planes are row ranges of the file) the same bytes as the whole
    computed, then written; and the same samples as a .nii.gz output, written whole."""
    from volwarp_cli import execute
    from volwarp_cli.io import read_volume
    from volwarp_cli.samples import cast_samples

    data = _blob((26, 21, 23), seed=4) * 3.0
    cap = capture_volume(Volume(data), lattice=(5, 6, 5), oversample=1.0)
    dq = _general(cap, scale=1.2)
    sampler = BoxSampler(data, cap.grid, cap.placement, cap.sampling, cap.domain.dtype)
    scene = Scene(cap.domain, cap.grid, dq, 4, domain_range=cap.stats[:2])
    window = scene.target_box
    expect = cast_samples(blocks.warp_block(scene, sampler, window), dtype)
    header = Header(window.shape, dtype, spacing=(0.5, 0.75, 1.25), origin=(3.0, -2.0, 1.0))

    def op(path):
        return blocks.WarpOperation(
            Scene(cap.domain, cap.grid, dq, 4, domain_range=cap.stats[:2]), None,
            cap.placement, cap.sampling, window, Target(path, header, dtype), sampler=sampler)

    reference = tmp_path / f"reference{suffix}"
    Target(reference, header, dtype).write_whole(expect)
    monkeypatch.setattr(blocks, "PARALLEL_VOXELS", 1)  # (this small block is cut too)
    monkeypatch.setattr(execute, "STREAMED_FROM", 0)  # (and written as computed)
    nz, ny, nx = window.shape
    along_y = [Box((0, 0, 0), (9, 8, nx)), Box((0, 8, 0), (9, ny, nx)),
               Box((9, 0, 0), (nz, 5, nx)), Box((9, 5, 0), (nz, ny, nx))]
    for threads, cut in ((1, None), (2, None), (3, None), (4, along_y)):
        path = tmp_path / f"t{threads}{suffix}"
        job = op(path)
        if cut is not None:
            job._cuts[(window, threads)] = cut
        assert (len(job.slabs(window, threads)) > 1) == (threads > 1)
        job.compute = None  # (the whole is never computed as an array)
        ran = execute.run(job, execute.How(chunked=False, threads=threads))
        assert not ran.by_blocks and ran.results is None
        assert path.read_bytes() == reference.read_bytes(), threads
    ran = execute.run(op(tmp_path / "whole.nii.gz"), execute.How(chunked=False, threads=2))
    assert ran.results is not None  # (a compressed file is written whole)
    assert np.array_equal(read_volume(tmp_path / "whole.nii.gz").data, expect)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [reference.name, "whole.nii.gz"] + [f"t{t}{suffix}" for t in (1, 2, 3, 4)])


@pytest.mark.parametrize("chunk_bytes", [1 << 10, 200 << 10, 32 << 20])
@pytest.mark.parametrize("lo,hi", [((0, 0, 0), (4, 22, 24)), ((3, 5, 2), (19, 20, 17)),
                                   ((10, 0, 0), (11, 22, 24))])
def test_deformation_bytes_bound_the_buffers_a_contribution_holds(chunk_bytes, lo, hi):
    """What the memory estimates count for a step's deformation buffers: at least the
    Scratch a contribution over that domain block grows to, and not many times more."""
    from volwarp_cli.bspline.scene import Scratch

    data = _blob((20, 22, 24), seed=6)
    cap = capture_volume(Volume(data), lattice=(5, 5, 5), oversample=1.0)
    scene = Scene(cap.domain, cap.grid, _general(cap, scale=1.0), 4,
                  domain_range=cap.stats[:2])
    scene.chunk_bytes = chunk_bytes
    block = Box(lo, hi)
    scratch = Scratch()
    acc = np.zeros(scene.target_box.shape + (2,), np.int64)
    scene.contribute([scene.dq], block, 1, acc=acc, parallel=False, scratch=scratch)
    assert acc.any()
    held = scratch.flat.nbytes
    assert held <= scene.deformation_bytes(block) <= 4 * held


def test_blocks_are_weighed_as_their_tasks_run_them(tmp_path, monkeypatch):
    """A block task runs on one thread and streams its whole box: a user's --block is
    weighed so (not as the in-memory run's threads would cut it), its placed samples
    left out for an NRRD and counted for a store written by shards."""
    from volwarp_cli import execute, parallel

    data = _blob((26, 21, 23), seed=4) * 3.0
    cap = capture_volume(Volume(data), lattice=(5, 6, 5), oversample=1.0)
    sampler = BoxSampler(data, cap.grid, cap.placement, cap.sampling, cap.domain.dtype)
    scene = Scene(cap.domain, cap.grid, _general(cap, scale=1.2), 4, domain_range=cap.stats[:2])
    window = scene.target_box
    header = Header(window.shape, np.float32)
    monkeypatch.setattr(blocks, "PARALLEL_VOXELS", 1)
    block = (window.shape[0], 8, window.shape[2])
    weighed = {}
    for suffix in (".nrrd", ".ome.zarr"):
        op = blocks.WarpOperation(scene, None, cap.placement, cap.sampling, window,
                                  Target(tmp_path / f"o{suffix}", header, np.float32),
                                  sampler=sampler)
        for threads in (1, 4):
            with parallel.use_threads(threads):
                weighed[suffix, threads] = execute._heaviest(op, block)
        boxes = window.blocks(block)  # (the first, middle and last are weighed)
        one = max(op.block_bytes(b) for b in (boxes[0], boxes[len(boxes) // 2], boxes[-1]))
        # (and a store's shard encoding: zarr keeps its frames and their join)
        one += execute.writes_bytes(op, block)
        assert weighed[suffix, 1] == weighed[suffix, 4] == one, suffix
    samples = window.shape[0] * 8 * window.shape[2] * 4
    # (slabs smaller than the store's one shard are staged: placed in a scratch file by
    # offset, no encoding; a block of the whole shard carries its encoding)
    assert execute.writes_bytes(op, block) == 0
    assert execute.writes_bytes(op, window.shape) >= 2 * window.size * 4
    assert weighed[".ome.zarr", 1] - weighed[".nrrd", 1] == samples
