"""Each operation's input-region rule: the input box an output block needs.

Every function takes an output :class:`~.box.Box` (array order z, y, x) and the
operation's parameters, and returns the input box from which that block can
be computed exactly as the whole computation computes it: the kernels stay
plain functions of a block, and a blocked executor (Dask's ``map_overlap``,
or a loop over :meth:`Box.blocks`) cuts the input with these rules. Each
rule is tested against the dependence it claims (``tests/test_regions.py``):
a block computed from exactly that region equals the whole computation's
block, and where the rule is tight, a region one voxel smaller does not.

======================  ======================================================
operation               input an output block needs
======================  ======================================================
mesh (flying edges)     its cells' corner samples: one more sample on the
                        high side of each axis (two more layers for normals)
sweep                   none: the block's geometry alone
distance, banded        a halo of the band width (in voxels, per axis)
distance, one pass      whole lines along the pass's axis
warp (pushforward)      the domain voxels whose boxes can reach the block,
                        from the lattice's convex hull, region by region
======================  ======================================================

Global values are not regions: a block also needs the few numbers the whole
computation derives from the whole input (the isosurface's level shifted off
the samples and the ``--cap`` padding value; the warp's fixed-point scale
``domain_range``); pass the whole's.
"""

from __future__ import annotations

import math

import numpy as np

from .box import Box
from .volume import xyz_to_zyx


def _check_inside(out_box: Box, whole: Box, what: str) -> None:
    if not whole.contains(out_box):
        raise ValueError(f"output block {out_box} lies outside the {what} {whole}")


# -- mesh -------------------------------------------------------------------------------
def mesh_cells(shape) -> Box:
    """The cells of a volume of ``shape`` (z, y, x): ``shape - 1`` of them per axis.

    Cell ``(k, j, i)`` is the cube whose corners are the samples
    ``[k, k + 1] x [j, j + 1] x [i, i + 1]``.
    """
    return Box.from_shape(tuple(max(n - 1, 0) for n in shape))


def mesh_input(out_box: Box, shape, *, normals: bool = False) -> Box:
    """The samples the isosurface of cells ``out_box`` needs (a box of :func:`mesh_cells`).

    Marching cubes and flying edges (:func:`~.surface.isosurface.isosurface`)
    make a cell's triangles from its 8 corner samples alone: which corners
    are above the level picks the case, and each vertex lies on a cell edge,
    interpolated linearly between that edge's two samples. So the cells
    ``[lo, hi)`` need exactly the samples ``[lo, hi + 1)``: the one-sample
    overlap on the high side of each axis that neighbouring blocks share
    (both make the same vertices on their common face; a stitcher merges
    them by edge).

    With ``normals``, VTK estimates each vertex normal from the gradients at
    its edge's two samples, by central differences (one-sided at the
    volume's faces); a sample's gradient reads its neighbours, so the cells
    need the samples ``[lo - 1, hi + 2)``, clamped to the volume (where the
    whole volume ends, the one-sided difference is the whole's too).

    Not a region: a sample exactly at the level shifts the level of the
    whole volume a little (the first pass over the volume finds the shift),
    and ``cap`` pads with a value from the whole volume's range; give a block
    the whole's level.
    """
    whole = Box.from_shape(shape)
    _check_inside(out_box, mesh_cells(shape), "cells of the volume")
    if out_box.empty:
        return Box(out_box.lo, out_box.lo)
    needed = Box(out_box.lo, tuple(v + 1 for v in out_box.hi))
    return needed.grow(1, within=whole) if normals else needed


# -- sweep ------------------------------------------------------------------------------
def sweep_input(out_box: Box) -> Box:
    """No input samples: the empty box (at ``out_box.lo``).

    The sweep (:mod:`.sweep.voxelize` and :mod:`.sweep.direct`) has no input
    volume: each output voxel is computed from its own world position and the
    sweep (trajectory, frames, template images), independently of every
    other voxel (the voxeliser tests each voxel against the sub-segments
    whose index boxes hold it; the direct evaluator maps each voxel centre
    back to the templates; the CVG operators combine per voxel). The
    subdivision into templates depends on ``tau`` and the trajectory, not
    on the grid (the default ``tau``, half the smallest voxel side, is the
    same for a block). A block is therefore the sweep evaluated on the
    block's geometry, :meth:`~.geometry.Geometry.sub` of the output box,
    with the whole sweep given.
    """
    return Box(out_box.lo, out_box.lo)


# -- distance ---------------------------------------------------------------------------
def distance_band_input(out_box: Box, shape, spacing, max_distance: float | None, *,
                        surface: str = "voxel") -> Box:
    """The input samples a block of a distance field clipped to ``±max_distance`` needs.

    Parameters
    ----------
    out_box : Box
        The output block, inside ``shape``.
    shape : (z, y, x)
        The input's (and the field's) shape.
    spacing : (x, y, z) floats
        The voxel spacing, as :attr:`~.volume.Volume.spacing` has it.
    max_distance : float or None
        The band ``D`` (``--max-distance``); None: the unclipped field, which
        needs the whole input.
    surface : {"voxel", "subvoxel"}
        ``voxel``: the fields between voxel centres (euclidean on a binary
        shape, minnorm, taxicab, chessboard): a voxel's value is its distance
        to the nearest voxel of the other label, so ``clip(d, -D, D)`` only
        needs the labels of the voxels within world distance ``D`` (every
        metric here is at least the largest per-axis offset), and the other
        label's voxels *are* the boundary (nothing more to detect): a halo of
        ``floor(D / h)`` voxels per axis, ties included (``|dk| h = D`` gives
        ``D`` either way in exact arithmetic; float32 rounding may not).
        ``subvoxel`` (:mod:`.distance.subvoxel`): a voxel's value is its
        distance to the surface disc of a seed (a voxel next to a crossing),
        chosen by the nearest-seed transform and ``REFINE_STEPS`` steps
        among neighbours; a disc lies within ``H (1 + DISC_RADIUS)`` of its
        seed's centre (``H``: the largest spacing), so the seeds within
        ``D + H (1 + DISC_RADIUS) + 2 REFINE_STEPS H`` of a voxel decide its
        clipped value (the nearest seed of each voxel the refinement
        consults lies within that reach when any disc is within ``D``), and
        a seed's crossing test and foot point read its six neighbours: that
        reach, rounded up per axis, plus one voxel. A bound, not tight (on
        smooth test data 3 voxels suffice where it takes 8 to 12), and exact
        only up to ties: the nearest-seed transform breaks a tie between
        equidistant seeds by float rounding that depends on where the block
        starts, so a voxel with such a tie can differ from the whole's (by
        up to about 0.2 voxel; ``tests/test_regions.py`` has the case).

    Returns
    -------
    Box
        ``out_box`` grown by the halo, clamped to the volume.
    """
    whole = Box.from_shape(shape)
    _check_inside(out_box, whole, "volume")
    if out_box.empty:
        return Box(out_box.lo, out_box.lo)
    if max_distance is None:
        return whole
    d = float(max_distance)
    if not d > 0:
        raise ValueError(f"max_distance must be positive, got {max_distance}")
    h = np.array(xyz_to_zyx(tuple(float(v) for v in spacing)))
    if surface == "voxel":
        halo = [int(math.floor(d / v + 1e-9)) for v in h]
    elif surface == "subvoxel":
        from .distance.subvoxel import DISC_RADIUS, REFINE_STEPS

        big = float(h.max())
        reach = d + big * (1.0 + DISC_RADIUS) + 2 * REFINE_STEPS * big
        halo = [int(math.ceil(reach / v)) + 1 for v in h]
    else:
        raise ValueError(f"surface must be 'voxel' or 'subvoxel', got {surface!r}")
    return out_box.grow(halo, within=whole)


def distance_pass_input(out_box: Box, shape, axis: int) -> Box:
    """The input of one pass of a separable transform along array ``axis`` (0 = z).

    A pass along an axis (the lower envelopes of :mod:`.distance.exact`, the
    doubling shifts of :mod:`.distance.minnorm`) sets each value from the
    whole line through it along that axis and from nothing else: the
    block's other two ranges, and the whole volume's range on ``axis``. The
    unclipped exact transform runs its passes x, y, z in turn, so a block of
    it needs the whole volume (each pass's rule applied to the previous
    one's output); its clipped form has :func:`distance_band_input`.
    """
    whole = Box.from_shape(shape)
    _check_inside(out_box, whole, "volume")
    if axis not in (0, 1, 2):
        raise ValueError(f"axis must be 0, 1 or 2 (z, y, x), got {axis}")
    if out_box.empty:
        return Box(out_box.lo, out_box.lo)
    lo, hi = list(out_box.lo), list(out_box.hi)
    lo[axis], hi[axis] = 0, whole.hi[axis]
    return Box(lo, hi)


# -- warp -------------------------------------------------------------------------------
def warp_input(out_box: Box, dq, grid, pad, bounds=None) -> Box:
    """The domain voxels (a box of the ``[Dz, Dy, Dx]`` voxmap) whose images can reach ``out_box``.

    ``out_box`` is a target block (``[z, y, x]`` of the padded target).

    Parameters
    ----------
    out_box : Box
        Target voxels (target index = input index + ``pad``).
    dq : (Cz, Cy, Cx, 3) float
        Control-point offsets from the uniform lattice (see :mod:`.bspline.lattice`).
    grid : bspline.lattice.Lattice
    pad : int or (x, y, z) ints
        The target's padding per side.

    Notes
    -----
    The pushforward sends domain voxel ``g`` to ``A(g) + U(g)`` (affine base
    map plus deformation offsets) and spreads its value over the target
    voxels its box overlaps: the bounding box of its six face centres, each
    ``A(g) +- half a domain voxel`` plus the mean offset of ``g`` and a
    neighbour, grown where thin but never past its own and its neighbours'
    offsets widened by the half voxel (:mod:`.bspline.pushforward`). By the convex-hull property of
    the B-spline, a voxel's offset lies in the hull of its region's 4x4x4
    control points; a voxel and its neighbours, in the points ``[r - 1, r +
    4]`` per axis (widened at the domain's faces, where the halo is
    extrapolated). :func:`.bspline.reach.offset_bounds` gives those
    bounds ``[lo_u, hi_u]`` per region, so along each axis the box of a
    voxel of region ``r`` lies in ``[A(g) + lo_u - half, A(g) + hi_u + half]``.
    The voxels needed are those for which that interval overlaps the
    target cells ``[tlo - 0.5, thi - 0.5]`` with positive length (a box that
    only touches a cell gives it no weight): per region, ``g > (tlo - 0.5 - o -
    half - hi_u) / s`` and ``g < (thi - 0.5 - o + half - lo_u) / s``, within the
    region's voxels and the model's (``Lattice.data_lo``/``data_hi``: on a
    subdivision grid the voxels around the input carry nothing); the answer is
    the bounding box of the regions' ranges. The ``nearest`` pushforward
    reaches less (the voxel's mapped centre), so the same box serves it.

    ``bounds``: ``offset_bounds(dq)`` where the caller has them (a scene keeps them
    per lattice; the threads' cut asks for a dozen candidate parts).

    This is the domain half of :meth:`.bspline.reach.Reach.rebuild_block`, with strict
    rounding: that method takes ``floor``/``ceil + 1``, up to two voxels more
    per side than the block needs (harmless there, it only costs work). It
    is a bound: tight where the lattice is locally a translation (the hull
    is then a point), larger where the control points spread.
    """
    from .bspline.reach import Reach, offset_bounds

    grid_box = Box.from_shape(tuple(xyz_to_zyx(grid.domain_shape)))
    if out_box.empty:
        return Box((0, 0, 0), (0, 0, 0))
    dq = np.asarray(dq, dtype=np.float64)
    pad = np.array([int(p) for p in np.broadcast_to(pad, (3,))])
    target = tuple(int(i + 2 * p) for i, p in zip(grid.input_shape, pad, strict=True))
    reach = Reach(grid, grid.affine_offset(pad), grid.scale, target)
    lo_u, hi_u = offset_bounds(dq) if bounds is None else bounds
    half = 0.5 * reach.scale
    tlo, thi = out_box.xyz()

    def along(v, axis):  # a per-region vector of x (0), y or z, broadcast on [Rz, Ry, Rx]
        shape = [1, 1, 1]
        shape[2 - axis] = -1
        return v.reshape(shape)

    first, last, inside = [], [], np.ones(lo_u.shape[:3], bool)
    for axis in range(3):
        a, b = reach.region_range(axis, grid.data_lo[axis], grid.data_hi[axis])
        s, o = float(reach.scale[axis]), float(reach.offset[axis])
        f = np.floor((tlo[axis] - 0.5 - o - half[axis] - hi_u[..., axis]) / s) + 1
        t = np.ceil((thi[axis] - 0.5 - o + half[axis] - lo_u[..., axis]) / s)
        f = np.maximum(f, along(a, axis))
        t = np.minimum(t, along(b, axis))
        inside &= f < t
        first.append(f)
        last.append(t)
    if not inside.any():
        return Box((0, 0, 0), (0, 0, 0))
    lo = [int(v[inside].min()) for v in first]
    hi = [int(v[inside].max()) for v in last]
    return Box.from_xyz(lo, hi).intersect(grid_box)
