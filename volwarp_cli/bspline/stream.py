"""The one-shot render by streaming: the target in z blocks, one per thread.

Each block goes through a rolling accumulator of a few planes.

Each block streams on its own: domain z chunks in order, scattered into a
ring of target planes; a plane is finalized and dropped as soon as no later
chunk can reach it (:meth:`.reach.Reach.target_z_reach`). Contributions are
integer sums clipped to the planes held, so every voxel gets exactly the sums
of a full :meth:`.scene.Scene.render`, whatever the blocks, and the
whole-target accumulators (16 bytes per voxel) are never allocated. A
deferred domain (a sampler) is gathered chunk by chunk just before its chunk
is scattered, never whole: its gather runs in the block's thread (the domain
planes near a cut are gathered by both blocks).
"""

from __future__ import annotations

import numpy as np

from .. import parallel
from ..memory import ensure_fits_in_memory, memory_limit
from ..progress import timed
from . import pushforward
from . import scene as scene_module
from .scene import Scratch

#: Target z planes covered by one step of a block's stream.
STREAM_PLANES = 16


def render_streaming(scene, sink=None, block_planes: int | None = None) -> np.ndarray | None:
    """``scene``'s target for its lattice, streamed (see the module notes).

    Each block also scatters the domain planes reaching past its ends, so
    blocks are at least a step's reach long; the thread count shrinks to keep
    them so, and to keep the blocks' rings within the memory budget.
    ``block_planes`` forces blocks of that many target planes (tests).

    ``sink(z0, z1, planes)``, if given, receives the finished target planes
    [z0, z1) (``[z1 - z0, y, x]``, a buffer reused after the call) from the
    blocks' threads, each range once, in no particular order; the whole target
    is then never held and None is returned.
    """
    reach = scene.reach
    dq = scene.dq
    tx, ty, tz = scene.target_shape
    out_dtype = np.float64 if scene.dtype == np.float64 else np.float32
    s = float(scene.scale[2])
    chunk = max(1, int(STREAM_PLANES / s))  # domain planes per step
    r_lo, r_hi = reach.target_z_reach(dq, 0, chunk)
    planes = r_hi - r_lo + 2  # target planes one step can reach (+ rounding)
    itemsize = np.dtype(out_dtype).itemsize
    # one block's accumulators and deformation buffers
    ring = planes * tx * ty * 16 + 2 * scene_module.CHUNK_BYTES
    # target planes held at a time: the whole target, or each block's finished
    # planes and their converted copy
    held = (lambda n: 4 * planes * n) if sink is not None else (lambda n: tz)
    if block_planes is not None:
        edges = list(range(0, tz, max(1, int(block_planes)))) + [tz]
        workers = parallel.threads()
    else:
        budget = memory_limit()
        workers = max(1, min(parallel.threads(), tz // max(planes, 1)))
        while workers > 1 and tx * ty * held(workers) * itemsize + workers * ring > budget:
            workers -= 1
        edges = parallel.cuts(0, tz, workers)
    workers = min(workers, len(edges) - 1)
    ensure_fits_in_memory(tx * ty * held(workers) * itemsize + workers * ring,
                          "the warped target")
    out = None if sink is not None else np.empty((tz, ty, tx), dtype=out_dtype)
    dshape = scene.grid.domain_shape
    sampler = scene.sampler

    def stream(t_lo, t_hi):
        # a ring of target planes: plane z in acc[z % planes]; planes [base, ...)
        # are still accumulating, those below are finalized
        acc = np.zeros((planes, ty, tx, 2), dtype=np.int64)
        scratch = Scratch()
        base = t_lo
        gathered = None if sampler is None else np.empty((chunk,) + sampler.shape[1:],
                                                         dtype=sampler.dtype)
        done = None if sink is None else np.empty((planes, ty, tx), dtype=out_dtype)

        def flush(upto):
            nonlocal base
            while base < upto:
                s0 = base % planes
                k = min(upto - base, planes - s0)  # contiguous slots
                dest = out[base:base + k] if sink is None else done[:k]
                pushforward.finalize(acc[s0:s0 + k], scene.vmax, (0, 0, 0), (tx, ty, k), dest,
                                     parallel=False, background=scene.background, clear=True)
                if sink is not None:
                    sink(base, base + k, dest)
                base += k

        g_lo, g_hi = reach.domain_z_window(dq, t_lo, t_hi)
        for g0 in range(g_lo, g_hi, chunk):
            g1 = min(g0 + chunk, g_hi)
            r_lo, r_hi = reach.target_z_reach(dq, g0, g1)
            flush(min(max(r_lo, base), t_hi))  # no later chunk reaches below r_lo
            if min(r_hi, t_hi) - base > planes:  # pragma: no cover - cannot happen
                raise AssertionError("rolling accumulator too small")
            values = None
            if sampler is not None:
                values = (sampler.planes(g0, g1, out=gathered[:g1 - g0]), g0)
            scene.contribute([dq], (0, 0, g0), (dshape[0], dshape[1], g1), 1, acc=acc,
                             tzo=base, tz_hi=min(base + planes, t_hi), ring=True,
                             parallel=False, scratch=scratch, values=values)
        flush(t_hi)

    with timed(f"deformation + {scene.method} pushforward + finalize "
               f"({len(edges) - 1} blocks, {workers} threads)"):
        parallel.run_blocks(lambda i: stream(edges[i], edges[i + 1]), range(len(edges) - 1),
                            workers)
    return out
