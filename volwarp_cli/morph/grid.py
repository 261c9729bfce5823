"""The world grid the morph frames are sampled on.

Rules (documented in the README and the morph schema):

* ``source`` / ``target``: that input's grid.
* ``union``: the **source's spacing and direction**, extended (on the
  source's own lattice, so that a source not moved is sampled at exactly its
  own voxels) to cover the voxel boxes of both aligned inputs plus ``margin``
  voxels on every side.
* an explicit ``{origin, spacing, size, direction}``.
* not given: the common grid when source and target share one and there is no
  alignment or warp; ``union`` when an alignment or warp is given; otherwise an
  error (the inputs lie on different grids and nothing says how to combine
  them).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import VolwarpError
from ..volume import Volume, xyz_to_zyx


class GridError(VolwarpError):
    """The frame grid cannot be made.

    Source and target cannot be put on one grid without more information, or the
    grid the spec asks for cannot be made; ``key``: the spec key at fault (a path
    such as ``("align", "target")``), reported by the command line with its line.
    """

    def __init__(self, message: str, key: tuple = ("grid",)):
        super().__init__(message)
        self.key = tuple(key)


#: most voxels along one axis of a frame grid (beyond it the sizes are absurd: a scale
#: or translation many orders of magnitude off, or a margin of 1e300 voxels)
MAX_AXIS = 1 << 31


@dataclass
class Grid:
    """A frame grid: size (x, y, z), spacing, origin and direction, LPS mm."""

    shape_xyz: tuple[int, int, int]
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray

    @classmethod
    def of(cls, vol: Volume) -> Grid:
        """The grid of ``vol`` (copies of its arrays)."""
        return cls(tuple(vol.shape_xyz), vol.spacing.copy(), vol.origin.copy(),
                   vol.direction.copy())

    @property
    def shape_zyx(self) -> tuple[int, int, int]:
        """The size in array order (z, y, x)."""
        return tuple(int(n) for n in xyz_to_zyx(self.shape_xyz))

    @property
    def spacing_zyx(self) -> tuple[float, float, float]:
        """The spacing in array order (z, y, x)."""
        return tuple(float(s) for s in xyz_to_zyx(self.spacing))

    @property
    def index_to_world(self) -> np.ndarray:
        """The 4x4 matrix from voxel indices (x, y, z, 1) to world points."""
        m = np.eye(4)
        m[:3, :3] = self.direction * self.spacing[None, :]
        m[:3, 3] = self.origin
        return m

    @property
    def voxels(self) -> int:
        """The number of voxels."""
        return int(np.prod(self.shape_xyz))

    def volume(self, data: np.ndarray, meta: dict | None = None) -> Volume:
        """A :class:`Volume` of ``data`` (``[z, y, x]``) on this grid, with ``meta``."""
        return Volume(data, spacing=self.spacing, origin=self.origin, direction=self.direction,
                      meta=meta or {})


def _corners(grid: Grid) -> np.ndarray:
    n = np.array(grid.shape_xyz) - 1
    c = np.array([[a, b, d, 1.0] for a in (0, n[0]) for b in (0, n[1]) for d in (0, n[2])])
    return c @ grid.index_to_world.T


def union_grid(source: Grid, target: Grid, source_matrix: np.ndarray,
               target_matrix: np.ndarray, margin: float = 2.0) -> Grid:
    """Source spacing/direction, on the source lattice, covering both moved input boxes."""
    to_idx = np.linalg.inv(source.index_to_world)
    pts = np.vstack([_corners(source) @ source_matrix.T, _corners(target) @ target_matrix.T])
    with np.errstate(over="ignore", invalid="ignore"):
        idx = pts @ to_idx.T
        lo = np.floor(idx[:, :3].min(axis=0) + 1e-6)
        hi = np.ceil(idx[:, :3].max(axis=0) - 1e-6)
        span = hi - lo + 1
    if not np.all(np.isfinite(span)) or span.max() > MAX_AXIS:
        key = (("align", "target") if not np.allclose(target_matrix, np.eye(4))
               else ("align", "source") if not np.allclose(source_matrix, np.eye(4))
               else ("grid",))
        axis = "xyz"[int(np.argmax(np.where(np.isfinite(span), span, np.inf)))]
        raise GridError(f"the aligned shapes would need a frame grid {float(span.max()):.3g} "
                        f"voxels long along {axis} (the limit is {MAX_AXIS}): the alignment is "
                        "far too large or too far away", key=key)
    pad = float(np.ceil(margin))
    if span.max() + 2 * pad > MAX_AXIS:
        raise GridError(f"a margin of {margin:g} voxels makes the frame grid longer than "
                        f"{MAX_AXIS} voxels", key=("margin",))
    lo, hi = lo - pad, hi + pad
    shape = tuple(int(v) for v in (hi - lo + 1))
    origin = source.index_to_world[:3, :3] @ lo + source.origin
    return Grid(shape, source.spacing.copy(), origin, source.direction.copy())


def explicit_grid(spec: dict) -> Grid:
    """The grid a spec gives as ``{origin, spacing, size, direction}`` (a GridError if singular)."""
    spacing = np.asarray(spec["spacing"], dtype=np.float64)
    spacing = np.full(3, float(spacing)) if spacing.shape == () else spacing
    direction = np.asarray(spec.get("direction", np.eye(3)), dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        det = np.linalg.det(direction)
    if not abs(det) >= 1e-9:  # also NaN
        raise GridError("the direction matrix is singular (its columns are the axes' "
                        "directions: three independent vectors)", key=("grid", "direction"))
    return Grid(tuple(int(v) for v in spec["size"]), spacing,
                np.asarray(spec["origin"], dtype=np.float64), direction)


def choose_grid(grid_spec, source: Grid, target: Grid, source_matrix: np.ndarray,
                target_matrix: np.ndarray, *, moved: bool, margin: float = 2.0) -> Grid:
    """The frame grid by the rules of the module doc; ``moved``: align or warp given."""
    if isinstance(grid_spec, dict):
        return explicit_grid(grid_spec)
    if grid_spec == "source":
        return source
    if grid_spec == "target":
        return target
    if grid_spec == "union":
        return union_grid(source, target, source_matrix, target_matrix, margin)
    if grid_spec is not None:
        raise GridError(f"unknown grid {grid_spec!r} (source, target, union or geometry)")
    same = (source.shape_xyz == target.shape_xyz
            and np.allclose(source.spacing, target.spacing, atol=1e-6)
            and np.allclose(source.origin, target.origin, atol=1e-6)
            and np.allclose(source.direction, target.direction, atol=1e-6))
    if same and not moved:
        return source
    if moved:
        return union_grid(source, target, source_matrix, target_matrix, margin)
    raise GridError(
        "source and target lie on different grids (source "
        f"{'x'.join(map(str, source.shape_xyz))} at spacing {source.spacing.tolist()}, origin "
        f"{source.origin.tolist()}; target {'x'.join(map(str, target.shape_xyz))} at spacing "
        f"{target.spacing.tolist()}, origin {target.origin.tolist()}) and no align or grid is "
        "given: say grid: union (or source/target, or explicit geometry)")
