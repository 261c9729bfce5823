"""Affine placement of a shape: scale, Euler rotation, translation, or a full matrix.

Dinh & Carvalho (2004), §0.4: the initial conditions of a morph are the size,
position and orientation of source and target; the user scales, rotates and
translates them. volwarp reads these as a small mapping (the ``align.source`` /
``align.target`` entries of a morph spec, and the ``transform`` spec of
``distance --update``)::

    scale: 1.1 | [sx, sy, sz]     # about the centre
    rotate: [rx, ry, rz]          # degrees about x, then y, then z (fixed axes)
    translate: [tx, ty, tz]       # world units
    center: [cx, cy, cz]          # default: the shape's centroid (world)
    matrix: 4x4                   # instead of all of the above

The map takes a world point of the shape to its new place:
``x' = c + R S (x - c) + t`` with ``R = Rz Ry Rx``. ``matrix`` is used as given
(row-major, last row ``0 0 0 1``).
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError


def euler_matrix(degrees) -> np.ndarray:
    """3x3 rotation ``Rz @ Ry @ Rx`` for angles (rx, ry, rz) in degrees."""
    rx, ry, rz = np.radians(np.asarray(degrees, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    mz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return mz @ my @ mx


def affine_from_params(params: dict, default_center=None) -> np.ndarray:
    """The 4x4 world matrix described by ``params`` (keys as in the module doc).

    ``default_center`` is used when ``params`` has no ``center`` (it is only
    needed when there is a scale or a rotation).
    """
    params = params or {}
    if "matrix" in params:
        other = sorted(set(params) & {"scale", "rotate", "translate", "center"})
        if other:
            raise VolwarpError(f"matrix cannot be combined with {', '.join(other)}")
        m = np.asarray(params["matrix"], dtype=np.float64)
        if m.shape != (4, 4):
            raise VolwarpError(f"matrix must be 4x4, got shape {m.shape}")
        if not np.allclose(m[3], [0, 0, 0, 1]):
            raise VolwarpError("matrix: last row must be 0 0 0 1 (an affine transform)")
        if abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise VolwarpError("matrix is singular")
        return m
    scale = np.asarray(params.get("scale", 1.0), dtype=np.float64)
    scale = np.full(3, float(scale)) if scale.shape == () else scale
    if scale.shape != (3,) or np.any(scale <= 0):
        raise VolwarpError(f"scale must be positive (one value or three), got {scale.tolist()}")
    rot = euler_matrix(params.get("rotate", (0.0, 0.0, 0.0)))
    trans = np.asarray(params.get("translate", (0.0, 0.0, 0.0)), dtype=np.float64)
    linear = rot @ np.diag(scale)
    needs_center = not np.allclose(linear, np.eye(3))
    if "center" in params:
        center = np.asarray(params["center"], dtype=np.float64)
    elif needs_center:
        if default_center is None:
            raise VolwarpError("a scale or rotation needs a center")
        center = np.asarray(default_center, dtype=np.float64)
    else:
        center = np.zeros(3)
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = center - linear @ center + trans
    return m


def shape_centroid(mask: np.ndarray, index_to_world: np.ndarray) -> np.ndarray:
    """World centroid (x, y, z) of the ``True`` voxels of a ``[z, y, x]`` mask."""
    return centroid_from_counts(axis_counts(mask), index_to_world)


def axis_counts(mask: np.ndarray) -> list[np.ndarray]:
    """The mask's ``True`` voxels per index along x, y and z (int64 arrays).

    Integer counts: those of a mask's blocks add up (placed at the blocks'
    offsets) to exactly the whole mask's, so :func:`centroid_from_counts` of
    the sums is the whole mask's :func:`shape_centroid`, bit for bit.
    """
    out = []
    for axis in (2, 1, 0):  # x, y, z index sums without building coordinate arrays
        other = tuple(a for a in range(3) if a != axis)
        out.append(np.count_nonzero(mask, axis=other).astype(np.int64))
    return out


def centroid_from_counts(counts, index_to_world: np.ndarray) -> np.ndarray:
    """World centroid (x, y, z) from :func:`axis_counts` ``[per x, per y, per z]``."""
    count = int(np.asarray(counts[0]).sum())
    if count == 0:
        raise VolwarpError("the shape is empty: it has no centre")
    sums = []
    for per in counts:
        per = np.asarray(per).astype(np.float64)
        sums.append(float(per @ np.arange(per.size)))
    ijk = np.array(sums) / count
    return index_to_world[:3, :3] @ ijk + index_to_world[:3, 3]


def linear_scale(matrix: np.ndarray) -> float:
    """The mean scale of an affine map, ``|det A|^(1/3)``: exact for similarities."""
    return float(abs(np.linalg.det(matrix[:3, :3])) ** (1.0 / 3.0))
