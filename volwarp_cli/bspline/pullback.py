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
from .basis import region_weights, run_split
from .jobs import SampleJob, replace
from .lattice import Grid, capture_axis_positions
from .pushforward import ROUND

SAMPLINGS = ("linear", "nearest")


def capture_coordinates(grid: Grid, placement: str) -> list[np.ndarray]:
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


def _subdivision_indices(grid: Grid, axis: int):
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


class Sampler:
    """The capture's gather, set up once: domain z planes on demand.

    ``shape`` ``(Dz, Dy, Dx)`` and ``dtype`` are the domain voxmap's. A
    plane's samples do not depend on which planes are gathered with it, so
    planes gathered a few at a time (:meth:`planes`, what a one-shot warp
    streams) equal the whole voxmap's (:meth:`whole`) bit for bit.
    """

    def __init__(self, data: np.ndarray, grid: Grid, placement: str = "uniform",
                 sampling: str = "linear", dtype=np.float32):
        if sampling not in SAMPLINGS:
            raise VolwarpError(f"unknown sampling {sampling!r} (use linear or nearest)")
        if tuple(data.shape[::-1]) != tuple(grid.input_shape):
            raise VolwarpError(f"input shape {data.shape[::-1]} does not match the grid "
                               f"{grid.input_shape}")
        if grid.subdivision and placement == "uniform":
            axes = [_subdivision_indices(grid, axis) for axis in range(3)]
        else:
            coords = capture_coordinates(grid, placement)
            axes = [_axis_weights(c, n, sampling)
                    for c, n in zip(coords, grid.input_shape, strict=False)]
        (x0, x1, fx), (y0, y1, fy), (z0, z1, fz) = axes
        self.shape = tuple(grid.domain_shape[::-1])
        self.dtype = np.dtype(dtype)
        src = np.ascontiguousarray(data)
        self._src = src if src.dtype == self.dtype else src.astype(self.dtype)
        self._x = tuple(np.ascontiguousarray(a, t) for a, t in
                        ((x0, np.int32), (x1, np.int32), (fx, np.float64)))
        self._y = tuple(np.ascontiguousarray(a, t) for a, t in
                        ((y0, np.int32), (y1, np.int32), (fy, np.float64)))
        self._z = tuple(np.ascontiguousarray(a, t) for a, t in
                        ((z0, np.int32), (z1, np.int32), (fz, np.float64)))

    def planes(self, g0: int, g1: int, out: np.ndarray | None = None) -> np.ndarray:
        """Domain planes [g0, g1) into ``out`` (``(g1 - g0, Dy, Dx)``, default new)."""
        if out is None:
            out = np.empty((g1 - g0,) + self.shape[1:], dtype=self.dtype)
        SampleJob(data=self._src, x=self._x, y=self._y, z=tuple(a[g0:g1] for a in self._z),
                  out=out, g0=0, g1=g1 - g0).run()
        return out

    def whole(self) -> tuple[np.ndarray, tuple[float, float]]:
        """The whole voxmap (two threads) and the (min, max) of its samples."""
        out = np.empty(self.shape, dtype=self.dtype)
        job = SampleJob(data=self._src, x=self._x, y=self._y, z=self._z, out=out, g0=0,
                        g1=out.shape[0])
        parts = run_split(lambda g0, g1: replace(job, g0=g0, g1=g1), 0, out.shape[0], out.size)
        return out, (min(p[0] for p in parts), max(p[1] for p in parts))


def pullback(data: np.ndarray, grid: Grid, placement: str = "uniform",
             sampling: str = "linear", dtype=np.float32) -> tuple[np.ndarray, tuple[float, float]]:
    """Domain voxmap ``[Dz, Dy, Dx]`` sampled from ``data[z, y, x]`` through the capture map.

    Returns the voxmap and the (min, max) of its samples (found while writing them).

    Parameters
    ----------
    data : (Iz, Iy, Ix) array
        The input samples.
    grid : lattice.Grid
    placement : {"uniform", "tripled"}
    sampling : {"linear", "nearest"}
    dtype : float32 or float64, the domain's sample type.
    """
    return Sampler(data, grid, placement, sampling, dtype).whole()
