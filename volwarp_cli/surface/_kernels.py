"""numba kernels of triangle meshes: vertex normals, area and enclosed volume, triangle normals.

Imported lazily (numba costs about 0.3 s to import; the kernels are cached on
disk, ``cache=True``). The inlined helpers (:func:`cross`, :func:`offset`,
:func:`triangle_normal`) are shared with the decimation
(:mod:`._decimate_kernel`): one formula for a triangle's normal. numba's disk
cache checks the decimation's compiled code against ``_decimate_kernel.py``
alone: after changing a helper here, touch that file too.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True, inline="always")
def cross(ux, uy, uz, vx, vy, vz):
    """The cross product u x v, as three numbers."""
    return uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx


@njit(cache=True, nogil=True, inline="always")
def offset(verts, i, p):
    """``verts[i] - p`` (``p``: three numbers), as three numbers."""
    return verts[i, 0] - p[0], verts[i, 1] - p[1], verts[i, 2] - p[2]


@njit(cache=True, nogil=True, inline="always")
def triangle_normal(verts, a, b, c):
    """``(b - a) x (c - a)`` of vertices ``a``, ``b``, ``c``: twice the area long, outward."""
    ux = verts[b, 0] - verts[a, 0]
    uy = verts[b, 1] - verts[a, 1]
    uz = verts[b, 2] - verts[a, 2]
    vx = verts[c, 0] - verts[a, 0]
    vy = verts[c, 1] - verts[a, 1]
    vz = verts[c, 2] - verts[a, 2]
    return cross(ux, uy, uz, vx, vy, vz)


@njit(cache=True, nogil=True)
def vertex_normals(vertices, faces, out):
    """Area-weighted unit vertex normals into ``out`` (zeros; see :func:`.mesh.vertex_normals`)."""
    # Each triangle adds its (area-weighted) cross product to its corners.
    for t in range(faces.shape[0]):
        a = faces[t, 0]
        b = faces[t, 1]
        c = faces[t, 2]
        nx, ny, nz = triangle_normal(vertices, a, b, c)
        for k in (a, b, c):
            out[k, 0] += nx
            out[k, 1] += ny
            out[k, 2] += nz
    for i in range(out.shape[0]):
        s = (out[i, 0] ** 2 + out[i, 1] ** 2 + out[i, 2] ** 2) ** 0.5
        if s > 0:
            out[i, 0] /= s
            out[i, 1] /= s
            out[i, 2] /= s


@njit(cache=True, nogil=True)
def face_sums(vertices, faces, center):
    """(area, enclosed volume) of a mesh, its coordinates taken relative to ``center``."""
    area = 0.0
    volume = 0.0
    for t in range(faces.shape[0]):
        ax, ay, az = offset(vertices, faces[t, 0], center)
        bx, by, bz = offset(vertices, faces[t, 1], center)
        cx, cy, cz = offset(vertices, faces[t, 2], center)
        nx, ny, nz = cross(bx - ax, by - ay, bz - az, cx - ax, cy - ay, cz - az)
        area += (nx * nx + ny * ny + nz * nz) ** 0.5
        volume += ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
    return 0.5 * area, volume / 6.0
