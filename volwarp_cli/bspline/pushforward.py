"""Pushforward of the domain density into the target (paper §5–§6, thesis §5.4).

Each domain voxel ``(e, f, g)`` is sent to ``T = A(e, f, g) + U[g, f, e]``
(affine base map plus the deformation offsets, target voxel indices), then:

- ``nearest``: map and round (the papers' Figure 4/6 baseline): weight 1 to
  the target voxel holding ``T`` (ties round down, see ``ROUND``).
- ``box``: the papers' antialiasing: the six face centres are averages of
  neighbouring entries of the deformation array (paper §6), their bounding
  box stands in for the transformed voxel, and its overlap volume with each
  target voxel (as a fraction of the target voxel) is the weight.

Weights and weighted values are accumulated per target voxel; the papers'
result is ``v`` where the total weight is below 1 and ``v / w`` otherwise
(paper §6): a voxel partly covered by the model keeps the partial sum, i.e.
is blended with the (zero) space around it.

Departures:

- The accumulators are int64 fixed point (weights and normalised weighted
  values in units of 2**-40), so adding and later *subtracting* a region's
  contribution is exact: the incremental updates of :mod:`.scene` equal a
  full recomputation bit for bit, instead of the papers' "write zeros".
- The box's overlaps are scaled by (Jacobian volume of the voxel's image) /
  (box volume). The papers' proxy box of a voxel rotated by theta covers only
  about cos^2(theta) of it (2-D), so rotated parts of a model came out that
  much darker (about 30% at 33 degrees) under "v where w < 1"; with the
  scale every voxel carries its true volume and the inside of a rotated
  region sums to w = 1 on average. Axis-aligned stretches, and shears of
  less than one voxel per voxel, are unchanged.
- A box holding less than ``GROW_BELOW`` (0.8) of its voxel's image volume
  grows to that share: each side from the face centres' box towards the box
  of the image's 8 corners, one fraction k for the three, within the
  voxel's and its neighbours' offsets widened by the half voxel (the reach
  bounds of :mod:`.reach` hold every box). A rotation about an oblique axis
  shrinks the face centres' box to 35% of the voxel (45 degrees about x,
  then z): the scaled mass alone left gaps between the boxes, and a constant
  came out at 41% inside (a label map's interior got the background label).
  Boxes of 0.8 and over, identity, axis-aligned stretches, rotations about
  one axis up to 26.6 degrees (cos^2 = 0.8), are untouched (the same bytes).
- Per target voxel, box weights still scatter around 1 inside a rotated or
  strongly deformed region (down to about 0.83 at 45 degrees, oversample 1),
  and the papers' "v where w < 1" darkened those voxels (or, with a non-zero
  ``background``, pulled them towards it). volwarp normalises (``v / w``)
  wherever ``w >= COVERED_HI`` and blends with the background (``v + b (1 -
  w)``) only where ``w <= COVERED_LO``, the model's silhouette, with a linear
  ramp between.
- At the domain's outer faces the missing neighbour is extrapolated linearly
  (``1.5 U[e] - 0.5 U[e+1]``) so border voxels get a box too.

The loops are in ``_warpkernels.c``: per row of domain voxels, the boxes and
their Jacobian mass are computed as vectors, then scattered. Voxels whose
regions' control points are all unmoved (:func:`still_regions`) have exactly
zero offsets, so their boxes are the affine images of the voxels and their
overlaps are found once per axis; the sums are bit-identical to the general
path (tested).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The kernels' constants, defined once in _warpkernels.c:
# ROUND: rounding offset of the nearest modes: round half *down*, with a 1e-6
# voxel tolerance, the same in pullback and pushforward, so that a point on a
# tie computed two slightly different ways still lands in the same voxel.
# COVERED_HI, COVERED_LO: weights from which a target voxel counts as inside
# the model (normalised) and up to which it counts as on its silhouette
# (blended with the background).
# QUANTUM: fixed-point unit of the accumulators (2**40 per unit weight).
# GROW_BELOW: a box holding less of its voxel's image volume grows to it.
from ._warpkernels import COVERED_HI, COVERED_LO, GROW_BELOW, QUANTUM, ROUND  # noqa: F401

METHODS = ("box", "nearest")


@dataclass(frozen=True)
class HeldPlanes:
    """The target z planes an accumulator buffer ``acc`` holds.

    Planes ``[lo, hi)`` (``hi`` None: ``lo + len(acc)``), plane ``z`` in
    ``acc[z - lo]``; or, a ``ring``, plane ``z`` in ``acc[z % len(acc)]``, the
    planes ``[lo, hi)`` being those still accumulating (a stream's).
    """

    lo: int = 0
    hi: int | None = None
    ring: bool = False

    def end(self, acc) -> int:
        """The plane after the last one held in ``acc``."""
        return self.lo + len(acc) if self.hi is None else self.hi


def domain_faces(e0: int, e1: int, ext, dshape) -> list[tuple[int, int]]:
    """The halo faces of a chunk's deformation that lie on the domain's own border.

    ``(axis, side)`` pairs for :func:`fill_halo` (axis 0 = z of the array):
    the z planes ``[e0, e1)`` and the chunk's box ``ext`` (z, y, x) against
    the domain's shape ``dshape`` (x, y, z); inner faces hold real neighbours.
    """
    faces = [(0, 0)] if e0 == 0 else []
    if e1 == dshape[2]:
        faces.append((0, 1))
    for axis in (2, 1):  # the array's x and y
        if ext.lo[axis] == 0:
            faces.append((axis, 0))
        if ext.hi[axis] == dshape[2 - axis]:
            faces.append((axis, 1))
    return faces


def fill_halo(uh, faces=None):
    """Extrapolate the one-voxel halo of a deformation array linearly (``2 U[0] - U[1]``).

    With it, a border voxel's outer face centre is ``1.5 U[0] - 0.5 U[1]``.
    ``faces``: (axis, side) pairs to refresh (axis 0 = z of the array, side 0 =
    low end); default all six.
    """
    if faces is None:
        faces = [(a, side) for a in range(3) for side in (0, 1)]
    for axis, side in faces:
        n = uh.shape[axis] - 2

        def sl(i, axis=axis):
            idx = [slice(None)] * 4
            idx[axis] = i
            return tuple(idx)

        if n == 1:
            uh[sl(0 if side == 0 else 2)] = uh[sl(1)]
        elif side == 0:
            uh[sl(0)] = 2 * uh[sl(1)] - uh[sl(2)]
        else:
            uh[sl(n + 1)] = 2 * uh[sl(n)] - uh[sl(n - 1)]


def scatter(u, values, off, scale, block, sign, vmax, method, acc, parts=None,
            origin=(0, 0, 0), held: HeldPlanes | None = None, u_new=None, bounds=True,
            still=None, granularity=None, window=None, planes=None, values_xy=None,
            acc_xy=(0, 0)):
    """Add (``sign`` +1) or remove (-1) the contributions of the domain voxels ``block``.

    ``block``: a :class:`~volwarp_cli.box.Box` (z, y, x) of domain voxels.

    With ``u_new`` (deformation offsets of another lattice, same layout as
    ``u``) the block's ``u_new`` contributions are added with ``-sign`` in the
    same pass: ``sign`` -1 replaces the old map's contributions by the new one's.

    ``u`` holds the deformation offsets, planar float32 ``[3, z, y, x]``,
    with a one-voxel margin (see :func:`fill_halo`): component ``c`` of domain
    voxel (e, f, g) is ``u[c, g - oz + 1, f - oy + 1, e - ox + 1]`` with
    ``origin = (ox, oy, oz)``; the margin and every neighbour of the block's
    voxels must be filled.
    ``acc`` holds the target z planes ``held`` (a :class:`HeldPlanes`;
    default: from plane 0, ``len(acc)`` of them); contributions to other
    planes are left out, and
    with ``window`` ``((x0, x1), (y0, y1))`` (or a
    :class:`~volwarp_cli.box.Box`, whose y and x ranges count) those outside
    target columns [x0, x1) and rows [y0, y1) too.
    ``values`` holds the domain's samples ``[z, y, x]``, or with ``planes``
    ``(z0, dz)`` only some z planes of a domain of ``dz`` planes, plane ``g``
    in ``values[g - z0]`` (those of the block at least); with ``values_xy``
    ``(x0, y0, dx, dy)`` only some columns and rows of them too, voxel
    ``(e, f)`` of a plane at ``[f - y0, e - x0]`` in a domain of ``dx`` by
    ``dy``. ``acc_xy``: the target column and row of ``acc[:, 0, 0]`` (an
    out-of-core block's accumulators hold its own columns and rows only).
    ``parts``: :class:`~.reach.TargetBlock` s (:func:`.work.thread_parts`),
    target planes covering the planes held, each with the domain voxels that
    can reach them: one thread per part then scatters those of ``block``,
    keeping only their contributions to its target planes (the voxels whose
    boxes straddle two parts are done by both; integer sums: the result does
    not depend on the parts). Not with a ring.
    ``still`` (uint8 ``[passes, Rz, Ry, Rx]``, with the lattice's
    ``granularity`` (x, y, z)) marks the regions whose control points all
    have zero offset, for ``u`` and (second) ``u_new``: voxels there take a
    faster path with the same result (see :func:`still_regions`).
    Returns the touched target block (a Box, z y x), or None when nothing
    landed in the target; always None without ``bounds`` (which saves a few
    percent of the scatter).
    """
    from ..box import Box
    from .jobs import ScatterJob, replace

    held = HeldPlanes() if held is None else held
    ax, ay = (int(v) for v in acc_xy)
    clip = target_clip(window, (ax, ay), acc.shape[1:3], held.lo, held.end(acc))
    vxy = {} if values_xy is None else {"values_xy": values_xy[:2], "domain_xy": values_xy[2:]}
    job = ScatterJob(u=u, u_new=u_new, origin=origin, values=values,
                     planes=(0, values.shape[0]) if planes is None else planes,
                     offset=off, scale=scale, block=block, sign=int(sign),
                     inv_vmax=1.0 / vmax if vmax > 0 else 0.0, box=method == "box", acc=acc,
                     clip=clip, ring=held.ring, bounds=bool(bounds),
                     still=still, granularity=(1, 1, 1) if granularity is None else granularity,
                     acc_xy=(ax, ay), **vxy)

    if parts is None or held.ring or len(parts) < 2:
        boxes = [job.run()]
    else:
        from .. import parallel

        def part(p):
            t0, t1 = p.target.lo[0], p.target.hi[0]
            voxels = block.intersect(p.domain)
            if t1 <= t0 or voxels.empty:
                return np.array([0, 0, 0, -1, -1, -1])
            return replace(job, block=voxels, acc=acc[t0 - held.lo:],
                           clip=with_planes(clip, t0, t1)).run()

        boxes = parallel.run_blocks(part, parts, len(parts))
    boxes = [b for b in boxes if b[3] >= 0]
    if not boxes:
        return None
    return Box.from_xyz(np.min([b[:3] for b in boxes], axis=0).tolist(),
                        (np.max([b[3:] for b in boxes], axis=0) + 1).tolist())


def target_clip(window, acc_xy, acc_yx, z0, z1):
    """The target window a scatter keeps: a :class:`~volwarp_cli.box.Box` (z, y, x).

    Planes [z0, z1); columns and rows from ``window``: a Box (its y and x
    ranges), ``((x0, x1), (y0, y1))``, or None: the accumulator's own
    (``acc_yx`` of them from ``acc_xy``). A range ending before its start is
    empty (the kernel keeps nothing there either).
    """
    from ..box import Box

    if isinstance(window, Box):
        (_, y0, x0), (_, y1, x1) = window.lo, window.hi
    elif window is None:
        ax, ay = (int(v) for v in acc_xy)
        x0, x1, y0, y1 = ax, ax + int(acc_yx[1]), ay, ay + int(acc_yx[0])
    else:
        (x0, x1), (y0, y1) = window
    lo = (int(z0), int(y0), int(x0))
    return Box(lo, tuple(max(a, int(b)) for a, b in zip(lo, (z1, y1, x1), strict=True)))


def with_planes(box, z0, z1):
    """``box`` (z, y, x) cut to planes [z0, z1) (empty if z1 <= z0)."""
    from ..box import Box

    return Box((z0, *box.lo[1:]), (max(z0, z1), *box.hi[1:]))


def still_regions(dqs) -> np.ndarray | None:
    """uint8 ``[len(dqs), Rz, Ry, Rx]``: 1 where every control point of the region is unmoved.

    One mask per lattice of ``dqs`` (the scatter's passes). There the
    deformation offsets are exactly zero, every voxel's box is its affine
    image (half a voxel either side of its base position) and the scatter
    skips the per-voxel box computation. None when no region is still.
    """
    still = np.stack([still_mask(dq) for dq in dqs])
    return np.ascontiguousarray(still, dtype=np.uint8) if still.any() else None


def still_mask(dq) -> np.ndarray:
    """A bool ``[Rz, Ry, Rx]``: the still regions of lattice ``dq``.

    A region is still when its 4^3 control points are all unmoved.
    """
    from .lattice import window_reduce

    return window_reduce(np.all(np.asarray(dq) == 0, axis=-1), 4, np.logical_and)


def finalize(acc, vmax, block, out, parallel=True, background=0.0, clear=False):
    """``out = v / w`` inside the model, ``v + b (1 - w)`` on its silhouette, on ``block``.

    ``block``: a :class:`~volwarp_cli.box.Box` (z, y, x) of ``acc`` and ``out``;
    see the module notes for the two weight levels.

    ``acc[z, y, x, 0]`` is the fixed-point weight, ``acc[..., 1]`` the weighted value;
    ``parallel`` lets large blocks use the threads in effect. ``background`` ``b`` is the
    value of the space around the model (the papers': 0): a partly covered
    voxel is blended with it and an uncovered one gets it, exactly what
    pushing ``data - b`` and adding ``b`` would give.
    ``clear`` also sets the block's accumulators back to zero (in the same pass).
    """
    from ..parallel import run_split
    from .jobs import FinalizeJob

    def job(z0, z1):
        return FinalizeJob(acc=acc, vmax=vmax, block=with_planes(block, z0, z1), out=out,
                           background=background, clear=bool(clear))

    run_split(job, block.lo[0], block.hi[0], block.size if parallel else 0)
    return out
