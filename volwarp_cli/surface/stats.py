"""Measurements of a triangle mesh: counts, area, enclosed volume, bounds, topology."""

from __future__ import annotations

from .mesh import Mesh
from .topology import is_closed, topology

__all__ = ["surface_area", "enclosed_volume", "is_closed", "mesh_stats"]

def _face_sums(mesh: Mesh) -> tuple[float, float]:
    if mesh.is_empty:
        return 0.0, 0.0
    from ._kernels import face_sums

    center = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    area, volume = face_sums(mesh.vertices, mesh.faces, center)
    return float(area), float(volume)


def surface_area(mesh: Mesh) -> float:
    """Sum of the triangles' areas (world units squared)."""
    return _face_sums(mesh)[0]


def enclosed_volume(mesh: Mesh) -> float:
    """Signed volume by the divergence theorem: sum of det(v0, v1, v2) / 6.

    Positive for a closed, outward-wound surface; only meaningful when the
    mesh is closed. Coordinates are taken relative to the bounding box centre
    to keep the sum accurate far from the origin.
    """
    return _face_sums(mesh)[1]


def mesh_stats(mesh: Mesh) -> dict:
    """The ``volwarp mesh --json`` measurements of a mesh.

    Keys: ``vertices``, ``triangles``, ``area``, ``volume`` (signed enclosed
    volume, meaningful when ``closed``), ``bbox_min``, ``bbox_max`` (x, y, z;
    null when empty), ``components``, ``closed`` (watertight and consistently
    wound, see :mod:`volwarp_cli.surface.topology`).
    """
    if mesh.is_empty:
        lo = hi = None
    else:
        lo = [float(x) for x in mesh.vertices.min(axis=0)]
        hi = [float(x) for x in mesh.vertices.max(axis=0)]
    count, _, closed = topology(mesh)
    area, volume = _face_sums(mesh)
    return {
        "vertices": mesh.n_vertices,
        "triangles": mesh.n_faces,
        "area": area,
        "volume": volume,
        "bbox_min": lo,
        "bbox_max": hi,
        "components": count,
        "closed": closed,
    }
