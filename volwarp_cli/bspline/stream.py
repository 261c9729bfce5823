"""The one-shot render by streaming: the domain in z slabs, one per thread.

Each slab streams on its own: domain z chunks in order, scattered into a ring
of a few target planes; a plane is finished and dropped as soon as no later
chunk can reach it (:meth:`.reach.Reach.planes`: each domain plane's reach,
from its layer of the lattice). Where two slabs reach the same target planes
(near a cut) their integer sums are added in a shared buffer before the plane
is finished, so every voxel gets exactly the sums of a full
:meth:`.scene.Scene.render`, whatever the slabs, no domain voxel is evaluated
or scattered twice, and the whole-target accumulators (16 bytes per voxel) are
never allocated. A deferred domain (a sampler) is gathered chunk by chunk just
before its chunk is scattered, never whole, in its slab's thread.
"""

from __future__ import annotations

import numpy as np

from .. import parallel
from ..box import Box
from ..memory import ensure_fits_in_memory, memory_limit
from ..progress import timed
from . import pushforward
from .scene import Scratch

#: Target z planes covered by one step of a block's stream.
STREAM_PLANES = 16


def render_streaming(scene, sink=None, block_planes: int | None = None) -> np.ndarray | None:
    """``scene``'s target for its lattice, streamed (see the module notes).

    The domain is cut along z into one slab per thread, of equal work; each
    slab streams its own planes and scatters them once. A target plane only
    one slab reaches is finished by that slab's thread; one that two slabs
    reach (near a cut) gets their integer sums added in a shared buffer and is
    finished by whichever thread adds last: the same sums as one stream, and no
    voxel is scattered twice. Threads are fewer when the budget cannot hold
    their rings and the shared planes. ``block_planes`` forces slabs of that
    many domain planes (tests).

    ``sink(z0, z1, planes)``, if given, receives the finished target planes
    [z0, z1) (``[z1 - z0, y, x]``, a buffer reused after the call) from the
    blocks' threads, each range once, in no particular order; the whole target
    is then never held and None is returned.
    """
    import threading

    dq = scene.dq
    reach = scene.reach.planes(scene._offset_bounds(dq))  # per domain plane, from the lattice
    tx, ty, tz = scene.target_shape
    out_dtype = np.float64 if scene.dtype == np.float64 else np.float32
    s = float(scene.scale[2])
    chunk = max(1, int(STREAM_PLANES / s))  # domain planes per step
    planes = _ring_planes(reach, chunk)
    itemsize = np.dtype(out_dtype).itemsize
    plane_acc = tx * ty * 16
    # one block's accumulators and deformation buffers
    ring = planes * plane_acc + 2 * scene.chunk_bytes
    # target planes held at a time: the whole target, or each block's finished
    # planes and their converted copy
    held = (lambda n: 4 * planes * n) if sink is not None else (lambda n: tz)

    def layout(n):
        cuts = _domain_cuts(scene, dq, n, block_planes)
        ranges = []
        count = np.zeros(tz, np.int64)
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            lo = max(0, int(reach.t_lo[a:b].min())) if b > a else 0
            hi = min(tz, int(reach.t_hi[a:b].max())) if b > a else 0
            ranges.append((lo, max(lo, hi)))
            count[lo:max(lo, hi)] += 1
        need = (tx * ty * held(n) * itemsize + n * ring
                + int(np.count_nonzero(count > 1)) * plane_acc)
        return cuts, ranges, count, need

    workers = parallel.threads()
    cuts, ranges, count, need = layout(workers)
    if block_planes is None:
        budget = memory_limit()
        while workers > 1 and need > budget:
            workers -= 1
            cuts, ranges, count, need = layout(workers)
    ensure_fits_in_memory(need, "the warped target")
    out = None if sink is not None else np.empty((tz, ty, tx), dtype=out_dtype)
    dshape = scene.grid.domain_shape
    sampler = scene.sampler
    shared = np.flatnonzero(count > 1)
    slot = np.full(tz, -1, np.int64)
    slot[shared] = np.arange(len(shared))
    shared_acc = np.zeros((len(shared), ty, tx, 2), dtype=np.int64)
    remaining = count.copy()  # slabs still to add into each shared plane
    locks = [threading.Lock() for _ in shared]

    def finish(t0, acc_planes, done, clear):
        """Finalize accumulator planes of target planes [t0, t0 + len) into out or the sink."""
        k = len(acc_planes)
        dest = out[t0:t0 + k] if sink is None else done[:k]
        pushforward.finalize(acc_planes, scene.vmax, Box((0, 0, 0), (k, ty, tx)), dest,
                             parallel=False, background=scene.background, clear=clear)
        if sink is not None:
            sink(t0, t0 + k, dest)

    def stream(i):
        a, b = cuts[i], cuts[i + 1]
        t_lo, t_hi = ranges[i]
        if b <= a or t_hi <= t_lo:
            return
        # a ring of target planes: plane z in acc[z % planes]; planes [base, ...)
        # are still accumulating, those below are finished (or handed on)
        acc = np.zeros((planes, ty, tx, 2), dtype=np.int64)
        scratch = Scratch()
        base = t_lo
        gathered = None if sampler is None else np.empty((chunk,) + sampler.shape[1:],
                                                         dtype=sampler.dtype)
        done = np.empty((planes, ty, tx), dtype=out_dtype) if sink is not None else None
        # the lowest target plane this slab's planes from g on can reach
        floor = np.minimum.accumulate(reach.t_lo[a:b][::-1])[::-1]

        def flush(upto):
            nonlocal base
            while base < upto:
                s0 = base % planes
                k = min(upto - base, planes - s0)  # contiguous slots
                mine = count[base] == 1
                run = 1
                while run < k and (count[base + run] == 1) == mine:
                    run += 1
                if mine:
                    finish(base, acc[s0:s0 + run], done, clear=True)
                else:
                    ready = []
                    for r in range(run):  # one lock per plane: cuts far apart add at once
                        t = base + r
                        with locks[slot[t]]:
                            shared_acc[slot[t]] += acc[s0 + r]
                            remaining[t] -= 1
                            if remaining[t] == 0:
                                ready.append(r)
                    acc[s0:s0 + run] = 0
                    for r0, r1 in _runs(ready):
                        finish(base + r0, shared_acc[slot[base] + r0:slot[base] + r1], done,
                               clear=False)
                base += run

        for g0 in range(a, b, chunk):
            g1 = min(g0 + chunk, b)
            r_lo, r_hi = int(floor[g0 - a]), int(reach.t_hi[g0:g1].max())
            flush(min(max(r_lo, base), t_hi))  # no later chunk of the slab reaches below r_lo
            if min(r_hi, t_hi) - base > planes:  # pragma: no cover - cannot happen
                raise AssertionError("rolling accumulator too small")
            values = None
            if sampler is not None:
                values = (sampler.planes(g0, g1, out=gathered[:g1 - g0]), g0)
            scene.contribute([dq], Box((g0, 0, 0), (g1, dshape[1], dshape[0])), 1, acc=acc,
                             held=pushforward.HeldPlanes(base, min(base + planes, t_hi),
                                                         ring=True),
                             parallel=False, scratch=scratch, values=values)
        flush(t_hi)

    n_blocks = len(cuts) - 1
    with timed(f"deformation + {scene.method} pushforward + finalize "
               f"({n_blocks} slabs, {min(workers, n_blocks)} threads, "
               f"{len(shared)} shared planes)"):
        parallel.run_blocks(stream, range(n_blocks), workers)
        # the planes no slab reaches: the background
        empty = np.zeros((min(planes, max(tz, 1)), ty, tx, 2), dtype=np.int64)
        spare = np.empty((len(empty), ty, tx), dtype=out_dtype) if sink is not None else None
        for r0, r1 in _runs(np.flatnonzero(count == 0)):
            for z0 in range(r0, r1, len(empty)):
                z1 = min(z0 + len(empty), r1)
                finish(z0, empty[:z1 - z0], spare, clear=False)
    return out


def _runs(indices) -> list[tuple[int, int]]:
    """Sorted integers as runs ``[(first, last + 1), ...]`` of consecutive values."""
    indices = np.asarray(indices)
    if indices.size == 0:
        return []
    breaks = np.flatnonzero(np.diff(indices) != 1)
    starts = np.concatenate([[indices[0]], indices[breaks + 1]])
    ends = np.concatenate([indices[breaks], [indices[-1]]]) + 1
    return [(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


def _domain_cuts(scene, dq, n: int, block_planes: int | None) -> list[int]:
    """Domain z cuts into ``n`` slabs of equal scatter work (or of ``block_planes`` planes)."""
    dz = scene.grid.domain_shape[2]
    if block_planes is not None:
        return list(range(0, dz, max(1, int(block_planes)))) + [dz]
    from . import work

    still = scene._still([dq])
    if still is not None:
        per_plane = work.plane_work(scene.reach, still, Box.from_xyz((0, 0, 0), scene.grid.domain_shape))
    else:
        z = np.arange(dz)
        per_plane = ((z >= scene.grid.data_lo[2]) & (z < scene.grid.data_hi[2])).astype(float)
    cum = np.concatenate([[0.0], np.cumsum(per_plane)])
    if n <= 1 or cum[-1] <= 0:
        return [0, dz]
    inner = [int(np.searchsorted(cum, cum[-1] * k / n)) for k in range(1, n)]
    return sorted({0, dz, *[c for c in inner if 0 < c < dz]})


def _ring_planes(reach, chunk: int) -> int:
    """Target planes a block's ring must hold.

    The most that one step of ``chunk`` domain planes, starting anywhere, can
    reach above what is already final (+ rounding).
    """
    dz = len(reach.t_hi)
    if dz == 0:
        return 2
    k = min(chunk, dz)
    windows = np.lib.stride_tricks.sliding_window_view(
        np.concatenate([reach.t_hi, np.full(k - 1, reach.t_hi[-1])]), k)
    return int((windows.max(axis=1) - reach.floor_from).max()) + 2

