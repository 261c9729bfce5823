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


#: points of a mesh at which a map's orientation is looked at
ORIENTATION_SAMPLES = 64


def map_orientation(fn, points: np.ndarray) -> int:
    """1 where the map ``fn`` keeps orientation at ``points``, -1 where it mirrors, 0 if both.

    ``fn``: points (N, 3) to their images (N, 3). Its Jacobian's determinant
    by central differences (a thousandth of the points' extent), at up to
    :data:`ORIENTATION_SAMPLES` of the finite ``points``.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    points = points[np.all(np.isfinite(points), axis=1)]
    if len(points) == 0:
        return 1
    at = points[np.linspace(0, len(points) - 1, min(len(points), ORIENTATION_SAMPLES))
                .astype(int)]
    h = max(1e-3 * float(np.ptp(points, axis=0).max()), 1e-3)
    cols = [(fn(at + h * e) - fn(at - h * e)) / (2 * h) for e in np.eye(3)]
    det = np.linalg.det(np.stack(cols, axis=-1))
    det = det[np.isfinite(det)]
    if det.size == 0 or (det > 0).all():
        return 1
    return -1 if (det < 0).all() else 0


def moved(mesh: Mesh, vertices: np.ndarray, orientation: int, what: str) -> Mesh:
    """``mesh`` with its vertices moved to ``vertices`` by a map of ``orientation``.

    A map that mirrors (-1: a left-right flip onto an atlas) turns every
    triangle inside out: the faces are turned back, so that they stay
    counter-clockwise seen from outside (a mirrored mesh came out with its
    volume negative and every normal inward). A map that mirrors in part only
    (0: it folds) is warned about. Normals recomputed.
    """
    from ..progress import log

    faces = mesh.faces
    if orientation < 0:
        faces = np.ascontiguousarray(faces[:, ::-1])
        log.info("%s: the map mirrors: its faces turned back to face outward", what)
    elif orientation == 0:
        log.warning("warning: %s: the map mirrors in part of the mesh only (it folds there): "
                    "triangles there are inside out", what)
    return Mesh(vertices, faces).with_normals()


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, (N, 3) float32.

    The normal of a vertex is the normalised sum of the cross products of its
    triangles (each proportional to the triangle's area), so it points to the
    side the triangles' winding calls "outside". Vertices used by no triangle
    get a zero normal. A triangle with a NaN corner (a vertex ``apply`` could
    not move) adds nothing: its finite corners keep their other triangles' normal.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if len(faces) and not np.isfinite(vertices).all():
        faces = np.ascontiguousarray(faces[np.isfinite(vertices).all(axis=1)[faces].all(axis=1)])
    out = np.zeros(vertices.shape, dtype=np.float64)
    if len(faces):
        from ._kernels import vertex_normals as kernel

        kernel(vertices, faces, out)
    return out.astype(np.float32)
