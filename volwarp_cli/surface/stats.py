"""Measurements of a triangle mesh: counts, area, enclosed volume, bounds, topology."""

from __future__ import annotations

from .mesh import Mesh
from .topology import is_closed, topology

__all__ = ["surface_area", "enclosed_volume", "is_closed", "mesh_stats"]

_KERNELS: dict = {}


def _sums_kernel():
    import numba

    @numba.njit(cache=True, nogil=True)
    def face_sums(vertices, faces, center):
        area = 0.0
        volume = 0.0
        for t in range(faces.shape[0]):
            a = faces[t, 0]
            b = faces[t, 1]
            c = faces[t, 2]
            ax = vertices[a, 0] - center[0]
            ay = vertices[a, 1] - center[1]
            az = vertices[a, 2] - center[2]
            bx = vertices[b, 0] - center[0]
            by = vertices[b, 1] - center[1]
            bz = vertices[b, 2] - center[2]
            cx = vertices[c, 0] - center[0]
            cy = vertices[c, 1] - center[1]
            cz = vertices[c, 2] - center[2]
            ux, uy, uz = bx - ax, by - ay, bz - az
            vx, vy, vz = cx - ax, cy - ay, cz - az
            nx = uy * vz - uz * vy
            ny = uz * vx - ux * vz
            nz = ux * vy - uy * vx
            area += (nx * nx + ny * ny + nz * nz) ** 0.5
            volume += ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        return 0.5 * area, volume / 6.0

    return face_sums


def _face_sums(mesh: Mesh) -> tuple[float, float]:
    if mesh.is_empty:
        return 0.0, 0.0
    if "sums" not in _KERNELS:
        _KERNELS["sums"] = _sums_kernel()
    center = 0.5 * (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0))
    area, volume = _KERNELS["sums"](mesh.vertices, mesh.faces, center)
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
