"""Isosurfaces of sampled volumes, in world coordinates, wound outwards.

The triangles come from VTK's flying edges (Schroeder, Maynard and Geveci,
"Flying edges: A high-performance scalable isocontouring algorithm", IEEE
LDAV 2015), a marching-cubes variant (Lorensen and Cline, SIGGRAPH 1987)
that visits each x-row once and writes its output in parallel without
locks; it produces the same triangles as marching cubes with shared
(merged) vertices, so a surface that does not reach the volume's border is
closed. The benchmark (``benchmarks/bench_mesh.py``) compares it with
scikit-image's marching cubes.

The volume papers (True and Hughes 1992, §1; Dinh and Carvalho 2004; Winter
and Chen 2002, §4) all end a pipeline with such an isosurface: the level set
``{p : f(p) = iso}`` of the sampled field.
"""

from __future__ import annotations

import numpy as np

from .. import parallel
from ..errors import VolwarpError
from ..memory import ensure_fits_in_memory
from ..progress import log, timed
from ..volume import Volume
from .mesh import Mesh

INSIDE_CHOICES = ("above", "below")


def _use_threads() -> None:
    """Run VTK's SMP filters on the threads in effect (the wheel defaults to one thread)."""
    from vtkmodules.vtkCommonCore import vtkSMPTools

    if vtkSMPTools.GetBackend() != "STDThread":
        vtkSMPTools.SetBackend("STDThread")
    vtkSMPTools.Initialize(parallel.threads())


def default_iso(data: np.ndarray) -> float:
    """The middle of the value range, the default isosurface level."""
    lo = float(np.min(data))
    hi = float(np.max(data))
    return 0.5 * (lo + hi)


def touches_border(data: np.ndarray, iso: float, inside: str = "above") -> bool:
    """True when a sample on the volume's outer faces is inside the shape."""
    def inside_any(a):
        return bool(np.any(a >= iso)) if inside == "above" else bool(np.any(a < iso))
    return any(inside_any(face) for face in (data[0], data[-1], data[:, 0], data[:, -1],
                                             data[:, :, 0], data[:, :, -1]))


def _pad_for_cap(data: np.ndarray, iso: float, inside: str) -> np.ndarray:
    """Surround ``data`` with one layer of "outside" samples so the surface closes.

    The padding value is the data's own background (its minimum for
    ``inside="above"``, its maximum for ``"below"``) when that lies outside
    the shape, else one unit beyond the level. The cap then sits where the
    volume would have met that background one voxel beyond its border.
    """
    if inside == "above":
        lo = float(np.min(data))
        pad = lo if lo < iso else iso - 1.0
    else:
        hi = float(np.max(data))
        pad = hi if hi >= iso else iso + 1.0
    wide = data.dtype == np.float64 or (data.dtype.itemsize >= 4 and data.dtype.kind in "iu")
    dtype = np.float64 if wide else np.float32
    nz, ny, nx = data.shape
    ensure_fits_in_memory((nz + 2) * (ny + 2) * (nx + 2) * np.dtype(dtype).itemsize,
                          "the padded volume for --cap")
    out = np.full((nz + 2, ny + 2, nx + 2), pad, dtype=dtype)
    out[1:-1, 1:-1, 1:-1] = data
    return out


def _level_off_samples(data: np.ndarray, iso: float) -> float:
    """A level that classifies every sample as ``iso`` does but equals none of them.

    A sample exactly at the level (common with integer data and an integer
    level) puts the vertices of up to six edges on the same grid point:
    zero-area triangles, duplicate vertices and undefined normals. Lowering
    the level by a thousandth of the gap to the next lower sample keeps the
    classification (a sample equal to ``iso`` is still above it) and moves
    those vertices by at most a thousandth of a voxel.
    """
    if not np.any(data == iso):
        return iso
    below = data[data < iso]
    gap = iso - float(below.max()) if below.size else 1.0
    return iso - 1e-3 * gap


def _flying_edges(data: np.ndarray, iso: float, normals: bool):
    """Flying edges on ``data[z, y, x]``.

    Returns (points in index (i, j, k) float32, faces int64, normals or None):
    the normals are VTK's unit gradient normals in index space, pointing
    towards lower values.
    """
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkFiltersCore import vtkFlyingEdges3D

    _use_threads()
    nz, ny, nx = data.shape
    image = vtkImageData()
    image.SetDimensions(nx, ny, nz)  # x fastest, as data[z, y, x] ravels
    scalars = numpy_to_vtk(data.reshape(-1), deep=False)
    image.GetPointData().SetScalars(scalars)
    fe = vtkFlyingEdges3D()
    fe.SetInputData(image)
    fe.SetValue(0, float(iso))
    fe.SetComputeNormals(bool(normals))
    fe.ComputeGradientsOff()
    fe.ComputeScalarsOff()
    fe.InterpolateAttributesOff()
    fe.Update()
    out = fe.GetOutput()
    if out.GetNumberOfPoints() == 0 or out.GetNumberOfCells() == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), None
    # vtk_to_numpy's arrays view VTK's memory through a buffer export that
    # keeps the VTK arrays alive: no copies of these big outputs are needed
    points = vtk_to_numpy(out.GetPoints().GetData())
    polys = out.GetPolys()
    conn = vtk_to_numpy(polys.GetConnectivityArray())
    faces = conn.reshape(-1, 3).astype(np.int64, copy=False)
    grad = None
    if normals:
        grad = vtk_to_numpy(out.GetPointData().GetNormals()).astype(np.float32, copy=False)
    return points.astype(np.float32, copy=False), faces, grad


def isosurface(vol: Volume, iso: float, *, inside: str = "above", cap: bool = False,
               normals: bool = True) -> Mesh:
    """Triangulated level set ``{f = iso}`` of a volume, in world coordinates.

    Parameters
    ----------
    vol : Volume
        Samples ``data[z, y, x]`` with spacing, origin and direction.
    iso : float
        The level.
    inside : {"above", "below"}
        Which side is the shape: samples ``>= iso`` (bright objects, default)
        or ``< iso`` (e.g. signed distance fields negative inside).
    cap : bool
        Pad the volume with one layer of outside samples so that a shape
        touching the border is closed there (the cap lies one voxel beyond
        the border at most). Without it such a surface is open at the border.
    normals : bool
        Compute outward unit vertex normals (from the field's gradient, as
        flying edges estimates it by central differences).

    Returns
    -------
    Mesh
        Vertices ``origin + direction @ (spacing * (i, j, k))``; triangles wound
        counter-clockwise seen from outside the shape, whatever the sign of
        ``det(direction)`` (a left-handed index frame is corrected for).
        Empty (no triangles) when the level is not crossed.

    Notes
    -----
    The level is crossed on a voxel edge whose ends lie on different sides
    of ``iso``; a sample equal to ``iso`` counts as above it. Departure from
    plain marching cubes: when samples equal the level exactly, the level
    is lowered by a thousandth of the gap to the next lower sample, so
    those vertices move by at most 0.001 voxel instead of collapsing into
    zero-area triangles with duplicate vertices and undefined normals.
    """
    if inside not in INSIDE_CHOICES:
        raise VolwarpError(f"inside must be one of {', '.join(INSIDE_CHOICES)}, got {inside!r}")
    iso = float(iso)
    if not np.isfinite(iso):
        raise VolwarpError(f"isosurface level must be finite, got {iso}")
    data = vol.data
    if data.dtype.kind not in "uif":
        raise VolwarpError(f"cannot isosurface samples of type {data.dtype}")
    # a reduction propagates NaN: one pass, no temporary array
    if data.dtype.kind == "f" and np.isnan(np.min(data)):
        raise VolwarpError("the volume contains NaN samples; an isosurface is not defined there")
    data = np.ascontiguousarray(data, dtype=data.dtype.newbyteorder("="))
    if data.dtype == np.float16:
        data = data.astype(np.float32)
    shift = 0.0
    if cap:
        data = _pad_for_cap(data, iso, inside)
        shift = 1.0
    with timed("isosurface (flying edges)"):
        points, faces, grad = _flying_edges(data, _level_off_samples(data, iso), normals)
    if len(faces) == 0:
        return Mesh.empty()
    matrix = vol.direction * vol.spacing[None, :]
    vertices = _index_to_world(points, matrix, vol.origin - shift * matrix.sum(axis=1))
    # Flying edges winds triangles outwards from the high side. A left-handed
    # index-to-world map mirrors the winding; "below" swaps the sides.
    flip = (inside == "below") != (np.linalg.det(vol.direction) < 0)
    if flip:  # swap two corners in place (the faces are ours, no copy needed)
        first = faces[:, 0].copy()
        faces[:, 0] = faces[:, 2]
        faces[:, 2] = first
    log.debug("isosurface: %d vertices, %d triangles", len(vertices), len(faces))
    mesh = Mesh(vertices, faces)
    if grad is not None:
        mesh.normals = _world_normals(grad, matrix, inside)
    return mesh


def _index_to_world(points: np.ndarray, matrix: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """``origin + matrix @ p`` for (N, 3) float32 index points, as (N, 3) float64.

    Written column by column, skipping zero entries: a numpy matmul with a
    3x3 matrix is four times slower on millions of points.
    """
    out = np.empty(points.shape, dtype=np.float64)
    for r in range(3):
        col = out[:, r]
        terms = [(matrix[r, c], c) for c in range(3) if matrix[r, c] != 0.0]
        if len(terms) == 1 and terms[0][0] == 1.0:
            col[...] = points[:, terms[0][1]]
        else:
            col[...] = 0.0
            for m, c in terms:
                col += m * points[:, c].astype(np.float64)
        col += origin[r]
    return out


def _world_normals(grad: np.ndarray, matrix: np.ndarray, inside: str) -> np.ndarray:
    """Index-space gradient normals to unit outward world normals (float32).

    A gradient is a covector: it maps to world space by the inverse transpose
    of the index-to-world matrix, which also handles mirrored frames.
    """
    sign = -1.0 if inside == "below" else 1.0
    inv = np.linalg.inv(matrix)
    # a scaled rotation (isotropic spacing) keeps unit normals unit
    gram = inv.T @ inv
    if np.allclose(gram, gram[0, 0] * np.eye(3), rtol=1e-12, atol=0):
        if np.allclose(inv, inv[0, 0] * np.eye(3), rtol=1e-12, atol=0) and sign > 0:
            return grad
        return (grad @ (sign * inv / np.sqrt(gram[0, 0])).astype(np.float32)).astype(np.float32)
    n = grad @ (sign * inv).astype(np.float32)
    length = np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
    np.divide(n, length, out=n, where=length > 0)
    return n
