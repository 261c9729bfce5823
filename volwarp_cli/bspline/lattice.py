"""Control lattice, granularity and the capture placements (paper §3, §7; thesis §5.5).

Per axis (x, y, z): ``C`` control points (>= 4), ``R = C - 3`` regions, an
integer granularity ``G = ceil(oversample * I / R)`` and a domain of
``D = G * R`` voxels, where ``I`` is the input's size on that axis.

Coordinates used inside the warp are *input voxel indices* (continuous, x y z):
the input voxel ``(i, j, k)`` has its centre at ``(i, j, k)`` and its box is
``[i - 0.5, i + 0.5]``. The target grid is the input grid padded by ``pad``
voxels on each side, so target index = input index + pad.

Domain voxel ``e`` has its *centre* at the spline parameter ``s = (e + 0.5) / G``
(the papers use ``e / G``), so its voxel box ``[e, e + 1]`` is the parameter
range ``[e / G, (e + 1) / G]``; the fractional parts are still the same ``G``
values in every region, so the papers' table works. The affine base map is
``x(s) = origin + h * s`` (``h``: input voxels per region), and two grids
place the domain on the input:

- **Subdivision** (``subdivision = k``, an integer oversample with the
  uniform placement; the default): each domain voxel is exactly ``1/k`` of an
  input voxel per axis, ``h = G / k``. The ``D >= k I`` domain voxels are
  centred on the input, ``lead = (D - k I) // 2`` of them before it, so the
  input's voxel box ``[-0.5, I - 0.5]`` is the domain's voxels
  ``[lead, lead + k I)`` (:attr:`Lattice.data_lo`, :attr:`Lattice.data_hi`) and the
  lattice spans ``R G / k >= I`` input voxels. Domain voxel ``e`` lies inside
  input voxel ``(e - lead) // k``; the voxels outside the input are no part of
  the model (the pushforward leaves them out: the space there is the
  background), so an unmoved lattice sends every input voxel's ``k^3``
  sub-voxels exactly onto its own target voxel.
- **Spanning** (``subdivision = 0``: a non-integer oversample, the tripled
  placement, and capture files of version 1): the domain's box ``[0, D]`` is
  exactly the input's box, ``h = I / R``, a slope ``I / D`` that is not a
  whole fraction of an input voxel, so the grids are not aligned and even an
  unmoved warp resamples (about 2% of the range, RMS, at oversample 1).

Control points are stored as offsets ``dq`` from the *uniform* lattice
``P_u[i] = origin + h * (i - 1)``, whose B-spline is exactly the affine map
(uniform cubic B-splines reproduce linear functions). Keeping the affine part
analytic and the offsets small keeps float32 deformation arrays accurate to
~1e-6 voxel at any volume size.
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


def too_coarse(input_shape, lattice, oversample: float) -> str | None:
    """Why ``oversample`` leaves the domain coarser than the input on an axis, or None.

    The capture samples the input at the domain voxels' centres: with fewer
    domain voxels than input voxels along an axis (``D < I``, an oversample
    below 1 with few regions) input voxels lie between the samples and never
    reach the domain. Oversample 0.06 on 30 voxels, lattice 5: one domain
    voxel per region, 15 input voxels apart, an all-zero warp of a ball (exit 0).
    ``D >= I`` holds for ``oversample > (ceil(I / R) - 1) R / I``; the message
    gives the smallest such value at two decimals.
    """
    sizes = [(int(n), int(c) - 3) for n, c in zip(input_shape, lattice, strict=True)]
    short = [(a, n, granularity(n, r, oversample) * r) for a, (n, r) in enumerate(sizes)
             if granularity(n, r, oversample) * r < n]
    if not short:
        return None
    axis, n, d = short[0]
    bound = max((math.ceil(n / r) - 1) * r / n for n, r in sizes)
    least = (math.floor(round(bound * 100, 6)) + 1) / 100
    counts = "x".join(str(int(c)) for c in lattice)
    return (f"oversample {oversample:g} gives {d} domain voxels along {'xyz'[axis]} for the "
            f"input's {n} ({n / d:.3g} input voxels apart): the capture would skip input "
            f"voxels and the warp carry little or nothing; with lattice {counts} on this "
            f"input the smallest oversample accepted is {least:.2f}")


def subdivision_of(oversample: float, placement: str = "uniform") -> int:
    """The domain's subdivision of the input voxels.

    ``k`` for an integer oversample ``k`` with the uniform placement, else 0 (the
    spanning grid, see the module notes).
    """
    k = float(oversample)
    if placement == "uniform" and k >= 1 and k.is_integer():
        return int(k)
    return 0


@dataclass(frozen=True)
class Lattice:
    """Sizes of one warp set-up, every tuple in (x, y, z) order.

    ``subdivision``: domain voxels per input voxel (per axis) of a subdivision
    grid, or 0 for the spanning grid (see the module notes).
    """

    input_shape: tuple[int, int, int]
    lattice: tuple[int, int, int]
    granularity: tuple[int, int, int]
    subdivision: int = 0

    @classmethod
    def create(cls, input_shape, lattice, oversample: float, placement: str = "uniform") -> Lattice:
        """The grid of an input shape, lattice and oversample (a VolwarpError if invalid)."""
        input_shape = tuple(int(v) for v in input_shape)
        lattice = tuple(int(v) for v in lattice)
        if len(lattice) != 3 or min(lattice) < 4:
            raise VolwarpError(f"lattice must have at least 4 control points per axis, got {lattice}")
        if not oversample > 0:
            raise VolwarpError(f"oversample must be positive, got {oversample}")
        why = too_coarse(input_shape, lattice, oversample)
        if why is not None:
            raise VolwarpError(why)
        g = tuple(granularity(n, c - 3, oversample) for n, c in zip(input_shape, lattice, strict=False))
        return cls(input_shape, lattice, g, subdivision_of(oversample, placement))

    @property
    def regions(self) -> tuple[int, int, int]:
        """Spline regions per axis, ``R = C - 3``."""
        return tuple(c - 3 for c in self.lattice)

    @property
    def domain_shape(self) -> tuple[int, int, int]:
        """Domain voxels per axis, ``D = G * R`` (x, y, z)."""
        return tuple(g * r for g, r in zip(self.granularity, self.regions, strict=False))

    @property
    def lead(self) -> tuple[int, int, int]:
        """Domain voxels before the input's first, per axis (0 on a spanning grid)."""
        k = self.subdivision
        if not k:
            return (0, 0, 0)
        return tuple((d - k * i) // 2 for d, i in zip(self.domain_shape, self.input_shape,
                                                       strict=True))

    @property
    def data_lo(self) -> tuple[int, int, int]:
        """First domain voxel inside the input, per axis (x, y, z)."""
        return self.lead

    @property
    def data_hi(self) -> tuple[int, int, int]:
        """End (exclusive) of the domain voxels inside the input, per axis (x, y, z).

        The pushforward scatters only [data_lo, data_hi); the whole domain on a
        spanning grid.
        """
        k = self.subdivision
        if not k:
            return self.domain_shape
        return tuple(a + k * i for a, i in zip(self.lead, self.input_shape, strict=True))

    @property
    def scale(self) -> np.ndarray:
        """Input voxels per domain voxel (x, y, z): the capture map's slope."""
        if self.subdivision:
            return np.full(3, 1.0 / self.subdivision)
        return np.array([i / d for i, d in zip(self.input_shape, self.domain_shape, strict=False)])

    @property
    def origin(self) -> np.ndarray:
        """Input index (x, y, z) of the domain's low face, spline parameter 0."""
        if self.subdivision:
            return np.array([-0.5 - a / self.subdivision for a in self.lead])
        return np.full(3, -0.5)

    @property
    def spacing_h(self) -> np.ndarray:
        """Uniform control-point spacing in input voxels (x, y, z).

        ``G / k`` on a subdivision grid, ``I / R`` on a spanning one.
        """
        if self.subdivision:
            return np.array([g / self.subdivision for g in self.granularity])
        return np.array([i / r for i, r in zip(self.input_shape, self.regions, strict=False)])

    def affine_offset(self, pad) -> np.ndarray:
        """``A(e) = offset + scale * e``: target index of domain voxel e's centre (x, y, z)."""
        pad = np.asarray(pad, dtype=np.float64)
        return pad + self.origin + 0.5 * self.scale

    def uniform_axis(self, axis: int) -> np.ndarray:
        """Uniform lattice positions along one axis (0 = x), input indices."""
        return self.origin[axis] + self.spacing_h[axis] * (np.arange(self.lattice[axis]) - 1.0)

    def uniform_positions(self) -> np.ndarray:
        """Uniform lattice positions, input indices, shape (Cz, Cy, Cx, 3) (x, y, z last)."""
        px, py, pz = (self.uniform_axis(axis) for axis in range(3))
        out = np.empty(self.lattice[::-1] + (3,))
        out[..., 0] = px[None, None, :]
        out[..., 1] = py[None, :, None]
        out[..., 2] = pz[:, None, None]
        return out


def capture_axis_positions(grid: Lattice, axis: int, placement: str) -> np.ndarray:
    """Capture control-point positions along one axis (0 = x), in input voxel indices.

    ``uniform``: evenly spaced with the end points outside the data (thesis
    §5.5), an exactly affine map (:meth:`Lattice.uniform_axis`). ``tripled``: the
    first and last points tripled on the ends of the voxel box, the interior
    evenly spaced (paper §7, Figure 5); it needs at least 6 points.
    """
    count = grid.lattice[axis]
    if placement == "uniform":
        return grid.uniform_axis(axis)
    if placement == "tripled":
        if count < 6:
            raise VolwarpError(f"the tripled placement needs at least 6 control points per axis, "
                               f"got {count}")
        size = grid.input_shape[axis]
        pieces = count - 5
        m = np.clip(np.arange(count) - 2, 0, pieces)
        return -0.5 + size * m / pieces
    raise VolwarpError(f"unknown placement {placement!r} (use {' or '.join(PLACEMENTS)})")


def capture_offsets(grid: Lattice, placement: str) -> np.ndarray:
    """Offsets ``dq`` of the capture lattice from the uniform one, shape (Cz, Cy, Cx, 3)."""
    uni = grid.uniform_positions()
    out = np.zeros_like(uni)
    for axis in range(3):
        delta = capture_axis_positions(grid, axis, placement) - grid.uniform_axis(axis)
        shape = [1, 1, 1]
        shape[2 - axis] = -1
        out[..., axis] = delta.reshape(shape)
    return out


def window_reduce(a: np.ndarray, width: int, ufunc) -> np.ndarray:
    """``ufunc`` (np.minimum, np.logical_and, ...) over every ``width``^3 window of ``a``.

    The windows are of the first three axes of ``a`` (shape ``(n0 - width + 1, ...)``):
    per axis, ``width - 1`` elementwise calls on shifted slices (a reduce over a
    sliding-window view of a small lattice is ~50x slower).
    """
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


def affected_regions(indices, grid: Lattice) -> tuple[np.ndarray, np.ndarray] | None:
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
