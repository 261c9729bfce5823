"""How much a scatter costs, and the choices made from it.

The choices: how an update is done and how a block's work is split over threads.

The measure counts domain voxels: one in a still region (all its control
points unmoved, the scatter's shortcut) costs 1, any other ``GENERAL_COST``.
Only voxels inside the input count (a subdivision grid's others carry
nothing). Every choice made from it changes the time, never the result: all
ways give the same integer sums.
"""

from __future__ import annotations

import numpy as np

from ..box import Box
from .reach import PlaneReach, Reach, TargetBlock

#: Cost of a voxel outside the still regions (evaluated, boxed, scattered) relative
#: to one inside (the shortcut); fitted on timed updates (see the README's notes).
GENERAL_COST = 2.4
#: Blocks are split over threads with at least this many domain voxels per thread.
PARALLEL_MIN_VOXELS = 1 << 18
#: A split over threads is taken only if no thread gets more than this share of
#: the block's work (the planes whose boxes can straddle a cut are done by both).
SPLIT_MAX_SHARE = 0.8
#: The ways :func:`choose_update` picks from (ties go to the first).
UPDATES = ("full", "rebuild", "subtract")


def region_voxels(reach: Reach, block: Box) -> list[np.ndarray]:
    """Per axis (x, y, z): how many voxels of each region lie in ``block``, inside the input."""
    grid = reach.grid
    vlo, vhi = block.xyz()
    counts = []
    for axis in range(3):
        a, b = reach.region_range(axis, max(int(vlo[axis]), grid.data_lo[axis]),
                                  min(int(vhi[axis]), grid.data_hi[axis]))
        counts.append(np.clip(b - a, 0, None))
    return counts


def plane_work(reach: Reach, still, block: Box) -> np.ndarray:
    """:func:`scatter_work`'s measure of each domain z plane of ``block``, all passes.

    ``still``: uint8 ``[passes, Rz, Ry, Rx]``.
    """
    grid = reach.grid
    cx, cy, _ = region_voxels(reach, block)
    cost = np.where(still, 1.0, GENERAL_COST).sum(axis=0)  # [Rz, Ry, Rx]
    per_region_plane = np.einsum("kji,j,i->k", cost, cy, cx)
    planes = np.arange(block.lo[0], block.hi[0])
    inside = (planes >= grid.data_lo[2]) & (planes < grid.data_hi[2])
    return np.where(inside, per_region_plane[planes // grid.granularity[2]], 0.0)


def scatter_work(reach: Reach, still, passes: int, block: Box) -> float:
    """Scatter work over the domain voxels ``block`` in ``passes`` passes (lattices).

    ``still``: their still regions (or None).
    """
    counts = region_voxels(reach, block)
    n = np.einsum("k,j,i->kji", counts[2], counts[1], counts[0])  # [Rz, Ry, Rx]
    total = float(n.sum()) * passes
    if still is None:
        return total * GENERAL_COST
    k = float((still * n).sum())
    return k + (total - k) * GENERAL_COST


def choose_update(work: dict[str, float], forced: str | None = None) -> str:
    """The way of an update: ``forced``, else the cheapest of ``work`` (ties: a full pass)."""
    return forced or min(UPDATES, key=work.get)


def thread_parts(reach: Reach, planes: PlaneReach, block: Box, tzo=0, tz_hi=None, still=None,
                 threads=None) -> list[TargetBlock] | None:
    """The domain voxels ``block``'s work split by target planes over threads.

    For :func:`.pushforward.scatter`: a :class:`~.reach.TargetBlock` per
    thread. Their targets' planes cover the planes held, [tzo, tz_hi); each
    domain block (of ``block``) holds every voxel that can reach its planes,
    by ``planes``, a
    :class:`.reach.PlaneReach` (each domain plane's reach, from its own layer
    of the lattice, as a block's stream uses; :meth:`.scene.Scene.contribute`
    passes one, of its lattices together). The cuts fall where
    the cumulative work (``still``: the scatter's still regions, or None)
    reaches k/n of the whole, mapped to the target plane its domain plane's
    centre goes to. Voxels whose boxes straddle a cut are scattered by both
    parts: with a long reach (a lattice moved far in z) that can be most of
    the block, so the count of parts is the one (up to ``threads``, default
    the threads in effect) with the shortest longest part, and None (one
    thread) unless it beats one part by ``1 / SPLIT_MAX_SHARE``. None for
    small blocks.
    """
    from .. import parallel

    threads = parallel.threads() if threads is None else threads
    n_max = min(threads, block.size // max(PARALLEL_MIN_VOXELS, 1))
    if n_max < 2:
        return None
    z0, z_end = block.lo[0], block.hi[0]
    tx, ty, _ = reach.target_shape
    # general voxels cost more: balance by work, not planes
    work = plane_work(reach, still, block) if still is not None else np.ones(z_end - z0)
    cum = np.concatenate([[0.0], np.cumsum(work)])  # work of planes [lo, lo + i)
    total = cum[-1]
    if total <= 0:
        return None
    window = planes.domain_window
    tz_end = reach.target_shape[2] if tz_hi is None else tz_hi
    s, o = float(reach.scale[2]), float(reach.offset[2])
    best, best_time = None, total * SPLIT_MAX_SHARE
    for n in range(n_max, 1, -1):
        cuts = []
        for k in range(1, n):
            mid = z0 + int(np.searchsorted(cum, total * k / n)) - 0.5
            # the target plane whose centre the domain plane's centre maps to
            cuts.append(int(np.floor(o + s * mid + 0.5)))
        cuts = sorted({c for c in cuts if tzo < c < tz_end})
        if not cuts:
            continue
        edges = [int(tzo), *cuts, int(tz_end)]
        parts, longest = [], 0.0
        for t0, t1 in zip(edges[:-1], edges[1:], strict=True):
            g0, g1 = window(t0, t1)
            g0, g1 = max(g0, z0), max(min(g1, z_end), max(g0, z0))
            parts.append(TargetBlock(Box((t0, 0, 0), (t1, ty, tx)),
                                     Box((g0, *block.lo[1:]), (g1, *block.hi[1:]))))
            if g1 > g0:
                longest = max(longest, cum[g1 - z0] - cum[g0 - z0])
        if longest < best_time:
            best, best_time = parts, longest
    return best

