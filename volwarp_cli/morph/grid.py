"""The world grid the morph frames are sampled on: a :class:`~volwarp_cli.geometry.Geometry`.

Rules (documented in the README and the morph schema):

* ``source`` / ``target``: that input's grid.
* ``union``: the **source's spacing and direction**, extended (on the
  source's own lattice, so that a source not moved is sampled at exactly its
  own voxels) to cover the voxel boxes of both aligned inputs plus ``margin``
  voxels on every side.
* an explicit ``{origin, spacing, size, direction}``; the direction's
  columns unit vectors at right angles (within the tolerance a volume's
  grid is taken as not sheared), as every reader gives them: the fields'
  fill of uncovered voxels and the density's default width measure along
  the axes by the spacing, a world distance only then.
* not given: the common grid when source and target share one and there is no
  alignment or warp; ``union`` when an alignment or warp is given; otherwise an
  error (the inputs lie on different grids and nothing says how to combine
  them).
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError
from ..geometry import Geometry
from ..samples import MAX_AXIS
from .align import affine_from_params


class GridError(VolwarpError):
    """The frame grid cannot be made.

    Source and target cannot be put on one grid without more information, or the
    grid the spec asks for cannot be made; ``key``: the spec key at fault (a path
    such as ``("align", "target")``), reported by the command line with its line.
    """

    def __init__(self, message: str, key: tuple = ("grid",)):
        super().__init__(message)
        self.key = tuple(key)


def _corners(grid: Geometry) -> np.ndarray:
    """World corners of the voxel centres, homogeneous (8, 4)."""
    c = np.hstack([grid.corner_indices(), np.ones((8, 1))])
    return c @ grid.index_to_world_matrix.T


def _lattice_bounds(source: Geometry, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last index (x, y, z) of ``source``'s lattice covering world points ``pts``."""
    to_idx = np.linalg.inv(source.index_to_world_matrix)
    with np.errstate(over="ignore", invalid="ignore"):
        idx = pts @ to_idx.T
        lo = np.floor(idx[:, :3].min(axis=0) + 1e-6)
        hi = np.ceil(idx[:, :3].max(axis=0) - 1e-6)
    return lo, hi


def _check_span(span: np.ndarray, margin: float, source_matrix: np.ndarray,
                target_matrix: np.ndarray) -> None:
    """Refuse a union grid of ``span`` voxels (x, y, z) before its margin: a GridError.

    ``span`` beyond :data:`MAX_AXIS` (or not finite) is the alignment's fault,
    a margin that takes it there the margin's.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        finite = bool(np.all(np.isfinite(span)))
    if not finite or span.max() > MAX_AXIS:
        key = (("align", "target") if not np.allclose(target_matrix, np.eye(4))
               else ("align", "source") if not np.allclose(source_matrix, np.eye(4))
               else ("grid",))
        axis = "xyz"[int(np.argmax(np.where(np.isfinite(span), span, np.inf)))]
        raise GridError(f"the aligned shapes would need a frame grid {float(span.max()):.3g} "
                        f"voxels long along {axis} (the limit is {MAX_AXIS}): the alignment is "
                        "far too large or too far away", key=key)
    if span.max() + 2 * float(np.ceil(margin)) > MAX_AXIS:
        raise GridError(f"a margin of {margin:g} voxels makes the frame grid longer than "
                        f"{MAX_AXIS} voxels", key=("margin",))


def union_geometry(source: Geometry, target: Geometry, source_matrix: np.ndarray,
                   target_matrix: np.ndarray, margin: float = 2.0) -> Geometry:
    """Source spacing/direction, on the source lattice, covering both moved input boxes."""
    pts = np.vstack([_corners(source) @ source_matrix.T, _corners(target) @ target_matrix.T])
    lo, hi = _lattice_bounds(source, pts)
    with np.errstate(over="ignore", invalid="ignore"):
        span = hi - lo + 1
    _check_span(span, margin, source_matrix, target_matrix)
    pad = float(np.ceil(margin))
    lo, hi = lo - pad, hi + pad
    shape = tuple(int(v) for v in (hi - lo + 1))
    origin = source.matrix @ lo + source.origin_array
    return Geometry.from_xyz(shape, source.spacing, origin, source.direction)


def explicit_grid(spec: dict) -> Geometry:
    """The grid a spec gives as ``{origin, spacing, size, direction}`` (a GridError: the module doc).

    ``size`` is written (x, y, z); ``spacing`` is one number or three. A
    direction whose columns are not unit vectors at right angles (the module
    doc) is refused: a scaled column, a sheared grid (a gantry tilt's) put
    errors of a quarter to a half of the distance in the fill of uncovered
    voxels, and it is not the grid the spacing says.
    """
    direction = np.asarray(spec.get("direction", np.eye(3)), dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        det = np.linalg.det(direction)
    if not abs(det) >= 1e-9:  # also NaN
        raise GridError("the direction matrix is singular (its columns are the axes' "
                        "directions: three independent vectors)", key=("grid", "direction"))
    grid = Geometry.from_xyz(spec["size"], spec["spacing"], spec["origin"], direction)
    if not grid.orthonormal:
        lengths = np.linalg.norm(direction, axis=0)
        unit = direction / lengths
        angles = [float(np.degrees(np.arccos(np.clip(unit[:, a] @ unit[:, b], -1, 1))))
                  for a, b in ((0, 1), (0, 2), (1, 2))]
        raise GridError(
            "its columns must be the index axes' unit vectors at right angles (a voxel's size "
            f"is the spacing): their lengths are x {lengths[0]:.6g}, y {lengths[1]:.6g}, "
            f"z {lengths[2]:.6g}, the angles x-y {angles[0]:.6g}, x-z {angles[1]:.6g}, "
            f"y-z {angles[2]:.6g} degrees (the frames' fields are measured along the axes by "
            "the spacing)", key=("grid", "direction"))
    return grid


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


def header_matrix(params) -> np.ndarray | None:
    """An alignment's matrix where its parameters fix it; None where it needs the samples.

    A scale or rotation without ``center`` turns about the shape's centroid,
    which only the samples give.
    """
    if not params:
        return np.eye(4)
    try:
        return affine_from_params(params)
    except VolwarpError:
        return None


def least_frame_shape(job, source: Geometry, target: Geometry) -> tuple[int, int, int]:
    """The frame grid's shape (x, y, z) before any sample is read: exact, or a lower bound.

    Exact where the spec and the inputs' headers fix the grid. Where an
    alignment turns or scales about its shape's centroid, the union grid still
    holds each aligned input's whole box wherever the centroid lies (a box's
    extent does not depend on where it is moved): the larger box, less one
    voxel for where the lattice cuts it, is the bound. For refusing, before
    any work, a grid that cannot be made (:func:`choose_grid`'s GridError too).
    """
    params = {"source": job.align_source, "target": job.align_target}
    matrices = {k: header_matrix(v) for k, v in params.items()}
    union = job.grid == "union" or (job.grid is None and job.moved)
    if not union or all(m is not None for m in matrices.values()):
        eye = np.eye(4)
        return choose_grid(job.grid, source, target, *(eye if m is None else m
                                                       for m in matrices.values()),
                           moved=job.moved, margin=job.margin).shape_xyz
    for name, m in matrices.items():
        if m is None:  # (any centre: the moved box's extent is the same)
            matrices[name] = affine_from_params(params[name], default_center=(0.0, 0.0, 0.0))
    spans = []
    for m, geo in zip(matrices.values(), (source, target), strict=True):
        lo, hi = _lattice_bounds(source, _corners(geo) @ m.T)
        with np.errstate(over="ignore", invalid="ignore"):
            spans.append(hi - lo)
    span = np.maximum(np.maximum(*spans), 1.0)  # (NaN stays NaN: refused below)
    _check_span(span, job.margin, *matrices.values())  # (the union's, which is larger)
    return tuple(int(v + 2 * np.ceil(job.margin)) for v in span)
