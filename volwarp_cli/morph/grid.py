"""The world grid the morph frames are sampled on: a :class:`~volwarp_cli.geometry.Geometry`.

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

import numpy as np

from ..errors import VolwarpError
from ..geometry import Geometry


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


def _corners(grid: Geometry) -> np.ndarray:
    """World corners of the voxel centres, homogeneous (8, 4)."""
    c = np.hstack([grid.corner_indices(), np.ones((8, 1))])
    return c @ grid.index_to_world_matrix.T


def union_geometry(source: Geometry, target: Geometry, source_matrix: np.ndarray,
                   target_matrix: np.ndarray, margin: float = 2.0) -> Geometry:
    """Source spacing/direction, on the source lattice, covering both moved input boxes."""
    to_idx = np.linalg.inv(source.index_to_world_matrix)
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
    origin = source.matrix @ lo + source.origin_array
    return Geometry.from_xyz(shape, source.spacing, origin, source.direction)


def explicit_grid(spec: dict) -> Geometry:
    """The grid a spec gives as ``{origin, spacing, size, direction}`` (a GridError if singular).

    ``size`` is written (x, y, z); ``spacing`` is one number or three.
    """
    direction = np.asarray(spec.get("direction", np.eye(3)), dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        det = np.linalg.det(direction)
    if not abs(det) >= 1e-9:  # also NaN
        raise GridError("the direction matrix is singular (its columns are the axes' "
                        "directions: three independent vectors)", key=("grid", "direction"))
    return Geometry.from_xyz(spec["size"], spec["spacing"], spec["origin"], direction)


def choose_grid(grid_spec, source: Geometry, target: Geometry, source_matrix: np.ndarray,
                target_matrix: np.ndarray, *, moved: bool, margin: float = 2.0) -> Geometry:
    """The frame grid by the rules of the module doc; ``moved``: align or warp given."""
    if isinstance(grid_spec, dict):
        return explicit_grid(grid_spec)
    if grid_spec == "source":
        return source
    if grid_spec == "target":
        return target
    if grid_spec == "union":
        return union_geometry(source, target, source_matrix, target_matrix, margin)
    if grid_spec is not None:
        raise GridError(f"unknown grid {grid_spec!r} (source, target, union or geometry)")
    if source.same_grid(target) and not moved:
        return source
    if moved:
        return union_geometry(source, target, source_matrix, target_matrix, margin)
    raise GridError(
        "source and target lie on different grids (source "
        f"{'x'.join(map(str, source.shape_xyz))} at spacing {list(source.spacing)}, origin "
        f"{list(source.origin)}; target {'x'.join(map(str, target.shape_xyz))} at spacing "
        f"{list(target.spacing)}, origin {list(target.origin)}) and no align or grid is "
        "given: say grid: union (or source/target, or explicit geometry)")
