"""Capture: pull the source back into the domain voxmap (paper §3, §5 "Initialization").

Each domain voxel centre is mapped through the capture B-spline into the
source and sampled there. The capture lattice is a tensor product of per-axis
positions, so the capture map is separable: ``x`` depends only on the domain
``e`` index, ``y`` only on ``f``, ``z`` only on ``g``: the sample indices
and weights are computed per axis once, and one kernel gathers the 8 (linear)
or 1 (nearest) samples of each domain voxel.

- ``nearest``: the paper's rounding (ties down, as in the pushforward).
- ``linear``: trilinear interpolation (default).

On a subdivision grid (an integer oversample ``k``, uniform placement; see
:mod:`.lattice`) every domain voxel lies inside one input voxel, and both
samplings give it that voxel's value, exactly (integer indices, no
weights): the box model of a voxel, a constant over its box, which the box
pushforward then spreads back over the same box. An unmoved region is thus
copied exactly, and a moved one is the box model carried by the map
(trilinear samples of ``k^3`` points inside one voxel would blend in its
neighbours: an unmoved warp would blur). Domain voxels outside the input
take the nearest edge voxel's value; the pushforward leaves them out.

Departure: the papers sample a zero-padded source; on a spanning grid the
capture image is exactly the input's voxel box ``[-0.5, I - 0.5]``, so the
only points outside the voxel centres' range are the outer half voxels, which
we sample with edge clamping (the box reconstruction of the edge voxel)
instead of blending them with the zero padding, which would darken every edge
of a scan.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError
from ..parallel import run_split
from .basis import region_weights
from .jobs import SampleJob, replace
from .lattice import Lattice, capture_axis_positions
from .pushforward import ROUND

SAMPLINGS = ("linear", "nearest")


def capture_coordinates(grid: Lattice, placement: str) -> list[np.ndarray]:
    """Source coordinates (input voxel indices) of the domain voxel centres, per axis (x, y, z)."""
    out = []
    for axis in range(3):
        pos = capture_axis_positions(grid, axis, placement)
        g = grid.granularity[axis]
        w = region_weights(g)  # (g, 4)
        regions = grid.regions[axis]
        windows = np.stack([pos[a:a + 4] for a in range(regions)])  # (R, 4)
        out.append((windows[:, None, :] * w[None, :, :]).sum(-1).ravel())
    return out


def _subdivision_indices(grid: Lattice, axis: int):
    """Input voxel of each domain voxel on one axis of a subdivision grid.

    Clamped to the input outside it; as lower/upper sample index and a zero weight.
    """
    d, n, k = grid.domain_shape[axis], grid.input_shape[axis], grid.subdivision
    i0 = np.clip((np.arange(d) - grid.lead[axis]) // k, 0, n - 1).astype(np.int64)
    return i0, i0, np.zeros(d)


def _axis_weights(coords: np.ndarray, n: int, sampling: str):
    """Lower/upper sample index and upper weight of each coordinate on one axis."""
    if sampling == "nearest":
        i0 = np.clip(np.floor(coords + ROUND), 0, n - 1).astype(np.int64)
        return i0, i0, np.zeros(len(coords))
    c = np.clip(coords, 0.0, n - 1.0)
    i0 = np.floor(c).astype(np.int64)
    i1 = np.minimum(i0 + 1, n - 1)
    return i0, i1, c - i0


def gather_tables(grid: Lattice, placement: str, sampling: str):
    """The capture map per axis: ``(x, y, z)``, each (lower index, upper index, weight).

    One entry per domain voxel of the axis, int32 / int32 / float64: the input
    samples a domain voxel blends (the same two with weight 0 where it takes one).
    """
    if sampling not in SAMPLINGS:
        raise VolwarpError(f"unknown sampling {sampling!r} (use linear or nearest)")
    if grid.subdivision and placement == "uniform":
        axes = [_subdivision_indices(grid, axis) for axis in range(3)]
    else:
        coords = capture_coordinates(grid, placement)
        axes = [_axis_weights(c, n, sampling)
                for c, n in zip(coords, grid.input_shape, strict=False)]
    return tuple(tuple(np.ascontiguousarray(a, t) for a, t in
                       ((i0, np.int32), (i1, np.int32), (w, np.float64)))
                 for i0, i1, w in axes)


class BoxSampler:
    """The capture's gather from an input that is not held: any box of domain voxels.

    ``source`` is anything numpy-sliceable with a ``shape`` ``[z, y, x]`` (a zarr
    array, a memory map, a lazy volume); a box reads only the input samples its
    voxels blend (the capture map is separable, so they form a box too) and
    converts only those to the domain's type. A voxel's sample depends on its
    own input samples and weights alone, so any box equals the same voxels of
    :meth:`Sampler.whole` bit for bit. Safe to use from several threads.
    """

    def __init__(self, source, grid: Lattice, placement: str = "uniform",
                 sampling: str = "linear", dtype=np.float32):
        if tuple(source.shape[::-1]) != tuple(grid.input_shape):
            raise VolwarpError(f"input shape {tuple(source.shape[::-1])} does not match the "
                               f"grid {grid.input_shape}")
        self.source = source
        self.tables = gather_tables(grid, placement, sampling)  # x, y, z
        self.shape = tuple(grid.domain_shape[::-1])
        self.dtype = np.dtype(dtype)

    def input_box(self, box):
        """The input box (z, y, x) that the domain voxels of ``box`` (a Box, z y x) read."""
        from ..box import Box

        lo, hi = [], []
        for axis, (a, b) in zip((2, 1, 0), zip(box.lo, box.hi, strict=True), strict=True):
            low, up, _ = self.tables[axis]
            lo.append(int(low[a:b].min()))
            hi.append(int(up[a:b].max()) + 1)
        return Box(lo, hi)

    def box(self, box) -> np.ndarray:
        """The domain samples of ``box`` (a :class:`~volwarp_cli.box.Box`, z y x), contiguous."""
        out = np.empty(box.shape, dtype=self.dtype)
        if box.empty:
            return out
        src_box = self.input_box(box)
        data = np.ascontiguousarray(np.asarray(self.source[src_box.slices]), dtype=self.dtype)
        axes = []
        for axis, (a, b), first in zip((0, 1, 2), zip(box.lo[::-1], box.hi[::-1], strict=True),
                                        src_box.lo[::-1], strict=True):
            low, up, w = self.tables[axis]
            axes.append((np.ascontiguousarray(low[a:b] - first, np.int32),
                         np.ascontiguousarray(up[a:b] - first, np.int32), w[a:b]))
        SampleJob(data=data, x=axes[0], y=axes[1], z=axes[2], out=out, g0=0,
                  g1=out.shape[0]).run()
        return out

    def whole(self) -> tuple[np.ndarray, tuple[float, float]]:
        """The whole voxmap and the (min, max) of its samples (:meth:`Sampler.whole`)."""
        from ..box import Box

        out = self.box(Box.from_shape(self.shape))
        return out, (float(out.min()), float(out.max()))


class Sampler(BoxSampler):
    """The capture's gather from a held input: any box (:class:`BoxSampler`), or the whole.

    ``shape`` ``(Dz, Dy, Dx)`` and ``dtype`` are the domain voxmap's. A
    voxel's sample does not depend on which voxels are gathered with it, so
    boxes (what a one-shot warp's blocks stream) equal the whole voxmap's
    (:meth:`whole`, on the threads) bit for bit.
    """

    def __init__(self, data: np.ndarray, grid: Lattice, placement: str = "uniform",
                 sampling: str = "linear", dtype=np.float32):
        if tuple(data.shape[::-1]) != tuple(grid.input_shape):
            raise VolwarpError(f"input shape {data.shape[::-1]} does not match the grid "
                               f"{grid.input_shape}")
        dtype = np.dtype(dtype)
        src = np.ascontiguousarray(data)
        super().__init__(src if src.dtype == dtype else src.astype(dtype), grid, placement,
                         sampling, dtype)
        #: the input's samples in the domain's type (what the gather reads)
        self.samples = self.source

    def whole(self) -> tuple[np.ndarray, tuple[float, float]]:
        """The whole voxmap (two threads) and the (min, max) of its samples."""
        out = np.empty(self.shape, dtype=self.dtype)
        x, y, z = self.tables
        job = SampleJob(data=self.samples, x=x, y=y, z=z, out=out, g0=0, g1=out.shape[0])
        parts = run_split(lambda g0, g1: replace(job, g0=g0, g1=g1), 0, out.shape[0], out.size)
        return out, (min(p[0] for p in parts), max(p[1] for p in parts))


class DomainSampler:
    """A captured domain voxmap (a capture file's) served box by box.

    As a BoxSampler serves an input's: the block warp's source when the
    domain is already held.
    """

    def __init__(self, domain: np.ndarray):
        self.domain = self.source = domain
        self.shape = tuple(domain.shape)
        self.dtype = np.dtype(domain.dtype)

    def input_box(self, box):
        """No input is read for a held domain (an empty Box: the memory estimate's term)."""
        from ..box import Box

        return Box((0, 0, 0), (0, 0, 0))

    def box(self, box) -> np.ndarray:
        """The domain samples of ``box`` (z, y, x), contiguous."""
        return np.ascontiguousarray(self.domain[box.slices])


def pullback(data: np.ndarray, grid: Lattice, placement: str = "uniform",
             sampling: str = "linear", dtype=np.float32) -> tuple[np.ndarray, tuple[float, float]]:
    """Domain voxmap ``[Dz, Dy, Dx]`` sampled from ``data[z, y, x]`` through the capture map.

    Returns the voxmap and the (min, max) of its samples (found while writing them).

    Parameters
    ----------
    data : (Iz, Iy, Ix) array
        The input samples.
    grid : lattice.Lattice
    placement : {"uniform", "tripled"}
    sampling : {"linear", "nearest"}
    dtype : float32 or float64, the domain's sample type.
    """
    return Sampler(data, grid, placement, sampling, dtype).whole()
