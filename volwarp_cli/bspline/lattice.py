"""Control lattice, granularity and the capture placements (paper §3, §7; thesis §5.5).

Per axis (x, y, z): ``C`` control points (>= 4), ``R = C - 3`` regions, an
integer granularity ``G = ceil(oversample * I / R)`` and a domain of
``D = G * R`` voxels, where ``I`` is the input's size on that axis.

Coordinates used inside the warp are *input voxel indices* (continuous, x y z):
the input voxel ``(i, j, k)`` has its centre at ``(i, j, k)`` and its box is
``[i - 0.5, i + 0.5]``. The target grid is the input grid padded by ``pad``
voxels on each side, so target index = input index + pad.

Departure from the papers: domain voxel ``e`` has its *centre* at the spline
parameter ``s = (e + 0.5) / G`` (the papers use ``e / G``), so the domain's
voxel box ``[0, D]`` is the parameter range ``[0, R]`` and its B-spline image is
exactly the input's voxel box ``[-0.5, I - 0.5]``. The fractional parts are
still the same ``G`` values in every region, so the papers' table works.

Control points are stored as offsets ``dq`` from the *uniform* lattice
``P_u[i] = -0.5 + (I / R) * (i - 1)``, whose B-spline is exactly the affine map
``x(s) = -0.5 + (I / R) * s`` (uniform cubic B-splines reproduce linear
functions). Keeping the affine part analytic and the offsets small keeps
float32 deformation arrays accurate to ~1e-6 voxel at any volume size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import VolwarpError

PLACEMENTS = ("uniform", "tripled")


def granularity(size: int, regions: int, oversample: float) -> int:
    """Integer granularity ``ceil(oversample * size / regions)`` (at least 1)."""
    # round first so that e.g. 2 * 30 / 6 = 10.000000000000002 does not become 11
    return max(1, int(math.ceil(round(oversample * size / regions, 9))))


@dataclass(frozen=True)
class Grid:
    """Sizes of one warp set-up, every tuple in (x, y, z) order."""

    input_shape: tuple[int, int, int]
    lattice: tuple[int, int, int]
    granularity: tuple[int, int, int]

    @classmethod
    def create(cls, input_shape, lattice, oversample: float) -> Grid:
        input_shape = tuple(int(v) for v in input_shape)
        lattice = tuple(int(v) for v in lattice)
        if len(lattice) != 3 or min(lattice) < 4:
            raise VolwarpError(f"lattice must have at least 4 control points per axis, got {lattice}")
        if not oversample > 0:
            raise VolwarpError(f"oversample must be positive, got {oversample}")
        g = tuple(granularity(n, c - 3, oversample) for n, c in zip(input_shape, lattice, strict=False))
        return cls(input_shape, lattice, g)

    @property
    def regions(self) -> tuple[int, int, int]:
        return tuple(c - 3 for c in self.lattice)

    @property
    def domain_shape(self) -> tuple[int, int, int]:
        return tuple(g * r for g, r in zip(self.granularity, self.regions, strict=False))

    @property
    def scale(self) -> np.ndarray:
        """Input voxels per domain voxel (x, y, z): the capture map's slope."""
        return np.array([i / d for i, d in zip(self.input_shape, self.domain_shape, strict=False)])

    @property
    def spacing_h(self) -> np.ndarray:
        """Uniform control-point spacing ``I / R`` in input voxels (x, y, z)."""
        return np.array([i / r for i, r in zip(self.input_shape, self.regions, strict=False)])

    def affine_offset(self, pad) -> np.ndarray:
        """``A(e) = offset + scale * e``: target index of domain voxel e's centre (x, y, z)."""
        pad = np.asarray(pad, dtype=np.float64)
        return pad - 0.5 + 0.5 * self.scale

    def uniform_positions(self) -> np.ndarray:
        """Uniform lattice positions, input indices, shape (Cz, Cy, Cx, 3) (x, y, z last)."""
        axes = [-0.5 + h * (np.arange(c) - 1.0) for h, c in zip(self.spacing_h, self.lattice, strict=False)]
        px, py, pz = axes
        out = np.empty(self.lattice[::-1] + (3,))
        out[..., 0] = px[None, None, :]
        out[..., 1] = py[None, :, None]
        out[..., 2] = pz[:, None, None]
        return out


def capture_axis_positions(size: int, count: int, placement: str) -> np.ndarray:
    """Capture control-point positions along one axis, in input voxel indices.

    ``uniform``: evenly spaced with the end points outside the data (thesis
    §5.5), an exactly affine map. ``tripled``: the first and last points
    tripled on the ends of the voxel box, the interior evenly spaced (paper §7,
    Figure 5); it needs at least 6 points.
    """
    if placement == "uniform":
        h = size / (count - 3)
        return -0.5 + h * (np.arange(count) - 1.0)
    if placement == "tripled":
        if count < 6:
            raise VolwarpError(f"the tripled placement needs at least 6 control points per axis, "
                               f"got {count}")
        pieces = count - 5
        m = np.clip(np.arange(count) - 2, 0, pieces)
        return -0.5 + size * m / pieces
    raise VolwarpError(f"unknown placement {placement!r} (use {' or '.join(PLACEMENTS)})")


def capture_offsets(grid: Grid, placement: str) -> np.ndarray:
    """Offsets ``dq`` of the capture lattice from the uniform one, shape (Cz, Cy, Cx, 3)."""
    uni = grid.uniform_positions()
    out = np.zeros_like(uni)
    for axis in range(3):
        pos = capture_axis_positions(grid.input_shape[axis], grid.lattice[axis], placement)
        delta = pos - (-0.5 + grid.spacing_h[axis] * (np.arange(grid.lattice[axis]) - 1.0))
        shape = [1, 1, 1]
        shape[2 - axis] = -1
        out[..., axis] = delta.reshape(shape)
    return out


def window_reduce(a: np.ndarray, width: int, ufunc) -> np.ndarray:
    """``ufunc`` (np.minimum, np.logical_and, ...) over every ``width``^3 window of the
    first three axes of ``a`` (shape ``(n0 - width + 1, ...)``): per axis, ``width - 1``
    elementwise calls on shifted slices (a reduce over a sliding-window view of
    a small lattice is ~50x slower)."""
    for axis in range(3):
        n = a.shape[axis] - width + 1
        shifted = [slice(None)] * a.ndim
        shifted[axis] = slice(0, n)
        out = a[tuple(shifted)].copy()
        for k in range(1, width):
            shifted[axis] = slice(k, k + n)
            ufunc(out, a[tuple(shifted)], out=out)
        a = out
    return a


def affected_regions(indices, grid: Grid) -> tuple[np.ndarray, np.ndarray] | None:
    """Region bounding box ``(lo, hi)`` (x, y, z, hi exclusive) touched by moved points.

    Control point ``i`` influences regions ``a`` with ``i - 3 <= a <= i``
    (paper §5). ``indices`` is an (N, 3) array of (i, j, k); None when empty.
    """
    idx = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    if idx.size == 0:
        return None
    regions = np.array(grid.regions)
    lo = np.clip(idx.min(axis=0) - 3, 0, regions - 1)
    hi = np.clip(idx.max(axis=0), 0, regions - 1) + 1
    return lo, hi
