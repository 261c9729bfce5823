"""The triangle mesh type shared by isosurfaces, mesh files and renders.

A :class:`Mesh` holds vertices in **world coordinates** (x, y, z), triangles
wound counter-clockwise when seen from outside (so the right-hand normal of
each triangle points outwards), and optional per-vertex unit normals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import VolwarpError


@dataclass
class Mesh:
    """A triangle mesh.

    Attributes
    ----------
    vertices : (N, 3) float64
        World coordinates (x, y, z).
    faces : (M, 3) int64
        Vertex indices, counter-clockwise seen from outside (outward normals).
    normals : (N, 3) float32 or None
        Unit outward vertex normals, when known.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None

    def __post_init__(self):
        v = np.ascontiguousarray(self.vertices, dtype=np.float64)
        f = np.ascontiguousarray(self.faces, dtype=np.int64)
        if v.size == 0:
            v = v.reshape(0, 3)
        if f.size == 0:
            f = f.reshape(0, 3)
        if v.ndim != 2 or v.shape[1] != 3:
            raise VolwarpError(f"mesh vertices must be (N, 3), got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3:
            raise VolwarpError(f"mesh faces must be (M, 3) triangles, got {f.shape}")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise VolwarpError("mesh faces refer to vertices that do not exist")
        self.vertices = v
        self.faces = f
        if self.normals is not None:
            n = np.ascontiguousarray(self.normals, dtype=np.float32)
            if n.shape != v.shape:
                raise VolwarpError(f"mesh normals must be {v.shape}, got {n.shape}")
            self.normals = n

    @property
    def n_vertices(self) -> int:
        """The number of vertices."""
        return int(len(self.vertices))

    @property
    def n_faces(self) -> int:
        """The number of triangles."""
        return int(len(self.faces))

    @property
    def is_empty(self) -> bool:
        """True for a mesh without triangles."""
        return self.n_faces == 0

    @classmethod
    def empty(cls) -> Mesh:
        """A mesh with no vertices and no triangles (normals empty too)."""
        return cls(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64),
                   np.zeros((0, 3), dtype=np.float32))

    def with_normals(self) -> Mesh:
        """The same mesh with area-weighted vertex normals computed from its faces."""
        return Mesh(self.vertices, self.faces, vertex_normals(self.vertices, self.faces))

    def flipped(self) -> Mesh:
        """The mesh with every triangle's winding (and the normals) reversed."""
        normals = None if self.normals is None else -self.normals
        return Mesh(self.vertices, self.faces[:, ::-1], normals)

    def face_normals(self) -> np.ndarray:
        """(M, 3) float64 unit normals of the triangles (zero for degenerate ones)."""
        v = self.vertices
        f = self.faces
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        np.divide(n, length, out=n, where=length > 0)
        return n


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, (N, 3) float32.

    The normal of a vertex is the normalised sum of the cross products of its
    triangles (each proportional to the triangle's area), so it points to the
    side the triangles' winding calls "outside". Vertices used by no triangle
    get a zero normal.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    out = np.zeros(vertices.shape, dtype=np.float64)
    if len(faces):
        from ._kernels import vertex_normals as kernel

        kernel(vertices, faces, out)
    return out.astype(np.float32)
