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
from ..volume import Volume
from .mesh import Mesh

INSIDE_CHOICES = ("above", "below")


def _use_threads() -> None:
    """Run VTK's SMP filters on the threads in effect (the wheel defaults to one thread)."""
    from vtkmodules.vtkCommonCore import vtkSMPTools

    if vtkSMPTools.GetBackend() != "STDThread":
        vtkSMPTools.SetBackend("STDThread")
    vtkSMPTools.Initialize(parallel.threads())


def cap_value(lo: float, hi: float, iso: float, inside: str) -> float:
    """The "outside" value ``--cap`` pads with, from the data's range ``[lo, hi]``.

    The data's own background (its minimum for ``inside="above"``, its
    maximum for ``"below"``) when that lies outside the shape, else one unit
    beyond the level.
    """
    if inside == "above":
        return lo if lo < iso else iso - 1.0
    return hi if hi >= iso else iso + 1.0


def _wraps(dtype: np.dtype) -> bool:
    """Whether VTK's ``s1 - s0`` can wrap in this sample type (32- and 64-bit integers).

    Flying edges takes an edge's difference in the sample type: C promotes 8-
    and 16-bit integers to int, where it is exact; unsigned 32- and 64-bit
    ones wrap on every falling edge, signed ones when neighbours differ by
    more than the type's half range.
    """
    return dtype.kind in "iu" and dtype.itemsize >= 4


def cap_dtype(dtype) -> np.dtype:
    """The sample type of the padded volume ``--cap`` contours (float32 or float64)."""
    dtype = np.dtype(dtype)
    wide = dtype == np.float64 or _wraps(dtype)
    return np.dtype(np.float64 if wide else np.float32)


def work_dtype(dtype, cap: bool = False) -> np.dtype:
    """The sample type flying edges runs on: native byte order, float16 widened.

    32- and 64-bit integers run as float64 (:func:`_wraps`; exact to 2^53,
    and VTK compares any sample to the level in double anyway). With ``cap``,
    :func:`cap_dtype`. A blocked run converts every block to it, so that
    VTK's arithmetic (which is done in the sample type) is the whole's.
    """
    dtype = np.dtype(dtype)
    if cap:
        return cap_dtype(dtype)
    dtype = dtype.newbyteorder("=")
    if _wraps(dtype):
        return np.dtype(np.float64)
    return np.dtype(np.float32) if dtype == np.float16 else dtype


def level_off(iso: float, hit: bool, below_max: float | None) -> float:
    """A level that classifies every sample as ``iso`` does but equals none of them.

    A sample exactly at the level (common with integer data and an integer
    level) puts the vertices of up to six edges on the same grid point:
    zero-area triangles, duplicate vertices and undefined normals. Lowering
    the level by a thousandth of the gap to the next lower sample keeps the
    classification (a sample equal to ``iso`` is still above it) and moves
    those vertices by at most a thousandth of a voxel. From two whole-volume
    facts: ``hit``, some sample equals ``iso``; ``below_max``, the largest
    sample below ``iso`` (None: there is none), a reduction over the blocks
    (:class:`.chunked.Stats`).
    """
    if not hit:
        return iso
    gap = iso - below_max if below_max is not None else 1.0
    return iso - 1e-3 * gap


def crossing_edges(data: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
    """The cell edges the level cuts, in flying edges' vertex order.

    Returns ``(lower sample (N, 3) int64 (i, j, k), axis (N,) int64)``: the
    edges whose two samples lie on different sides of ``level`` (``>=`` is
    above). Flying edges makes one vertex per such edge and numbers them by
    x-row: rows in (k, j) order, in each row its x-edges, then its y-edges,
    then its z-edges, each by increasing i (VTK's pass 3 prefix sum over the
    rows' edge counts), whatever the thread count. :func:`_flying_edges`
    checks a block's points against this order, so a VTK that numbered them
    otherwise would stop a run by blocks, not give other bytes than in memory
    (``tests/test_mesh_chunked.py`` checks the whole volume's order).
    """
    above = data >= level
    nz, ny, nx = data.shape
    keys = []
    for axis in range(3):
        hi = [slice(None)] * 3
        lo = [slice(None)] * 3
        hi[2 - axis], lo[2 - axis] = slice(1, None), slice(None, -1)
        k, j, i = np.nonzero(above[tuple(lo)] != above[tuple(hi)])
        keys.append(((k * ny + j) * 3 + axis) * nx + i)
    key = np.sort(np.concatenate(keys))
    i, rest = key % nx, key // nx
    axis, row = rest % 3, rest // 3
    lower = np.stack([i, row % ny, row // ny], axis=1).astype(np.int64)
    return lower, axis.astype(np.int64)


def _flying_edges(data: np.ndarray, iso: float, normals: bool, *, edges: bool = False):
    """Flying edges on ``data[z, y, x]``.

    Returns (points in index (i, j, k) float32, faces int64, normals or None,
    edges or None): the normals are VTK's unit gradient normals in index
    space, pointing towards lower values; with ``edges``, each vertex's cell
    edge ``(lower sample (N, 3) int64 (i, j, k), axis (N,) int64)``
    (:func:`crossing_edges`), checked: :func:`edge_points` of those edges
    must be VTK's points, bit for bit.
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
        empty = (np.zeros((0, 3), np.int64), np.zeros(0, np.int64)) if edges else None
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), None, empty
    # vtk_to_numpy's arrays view VTK's memory through a buffer export that
    # keeps the VTK arrays alive: no copies of these big outputs are needed
    points = vtk_to_numpy(out.GetPoints().GetData()).astype(np.float32, copy=False)
    polys = out.GetPolys()
    conn = vtk_to_numpy(polys.GetConnectivityArray())
    faces = conn.reshape(-1, 3).astype(np.int64, copy=False)
    grad = None
    if normals:
        grad = vtk_to_numpy(out.GetPointData().GetNormals()).astype(np.float32, copy=False)
    found = None
    if edges:
        found = _checked_edges(data, iso, points)
    return points, faces, grad, found


def _checked_edges(data: np.ndarray, level: float, points: np.ndarray):
    """:func:`crossing_edges`, after checking they are where VTK put its ``points``."""
    lower, axis = crossing_edges(data, level)
    ok = len(lower) == len(points)
    if ok:
        upper = lower.copy()
        upper[np.arange(len(axis)), axis] += 1
        s0 = data[lower[:, 2], lower[:, 1], lower[:, 0]]
        s1 = data[upper[:, 2], upper[:, 1], upper[:, 0]]
        mine = edge_points(lower, axis, s0, s1, level)
        ok = np.array_equal(mine.view(np.int32), points.view(np.int32))
    if not ok:
        raise VolwarpError("internal error: VTK's flying-edges vertices are not where the "
                           "blocked isosurface expects them (a VTK version with another "
                           "vertex order or formula)")
    return lower, axis


def _sample_diff(s1: np.ndarray, s0: np.ndarray) -> np.ndarray:
    """``s1 - s0`` as VTK's flying edges computes it, in C arithmetic on the sample type.

    Integers reach VTK only as types C promotes to int (:func:`work_dtype`):
    their difference is exact. Floats: rounded in the sample type.
    """
    if s0.dtype.kind in "iu":
        return s1.astype(np.float64) - s0.astype(np.float64)
    return (s1 - s0).astype(np.float64)


def edge_points(lower: np.ndarray, axis: np.ndarray, s0: np.ndarray, s1: np.ndarray,
                level: float) -> np.ndarray:
    """Float32 index points of the level's crossings of cell edges, as flying edges makes them.

    The edge from sample ``lower`` (N, 3) (i, j, k) along ``axis`` (N,), whose
    samples are ``s0`` (at ``lower``) and ``s1``: ``t = (level - s0) / (s1 -
    s0)`` in double (the difference in the sample type, as VTK's C++ has it),
    the point ``lower + t`` along the axis, rounded once to float32. This is
    VTK's own formula for a volume whose extent starts at 0 (the in-memory
    path), written on global indices: a block's vertex depends on its edge
    and two samples only, not on where the block starts.
    """
    t = (float(level) - s0.astype(np.float64)) / _sample_diff(s1, s0)
    points = lower.astype(np.float32)  # exact: indices below 2^24
    rows = np.arange(len(lower))
    points[rows, axis] = (lower[rows, axis].astype(np.float64) + t).astype(np.float32)
    return points


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
    The whole volume is the one block of :func:`.chunked.isosurface_blocks`
    (on the threads in effect), which gives this mesh, in this order, for
    any blocks.
    """
    from .chunked import isosurface_blocks

    return isosurface_blocks(vol.data, vol, iso, inside=inside, cap=cap, normals=normals)


def check_finite_range(lo, hi, name: str | None = None) -> None:
    """Refuse samples no isosurface goes through: NaN, +inf or -inf anywhere in the volume.

    ``lo``, ``hi``: the samples' minimum and maximum (a NaN sample makes both
    NaN). A vertex on an edge to an infinite sample would be NaN (inf / inf),
    and the default level (the middle of the range) infinite: the file is
    refused by name, in one line, before any surface is made.
    """
    where = f"{name}: " if name else ""
    if np.isnan(lo) or np.isnan(hi):
        raise VolwarpError(f"{where}the volume contains NaN samples; an isosurface is not "
                           "defined there")
    signs = [s for s, bad in (("-inf", lo == -np.inf), ("+inf", hi == np.inf)) if bad]
    if signs:
        raise VolwarpError(f"{where}the volume contains infinite samples "
                           f"({' and '.join(signs)}); an isosurface is not defined there")


def check_arguments(dtype, iso: float, inside: str) -> None:
    """Refuse an unknown ``inside``, a level that is not finite, samples that are not numbers."""
    if inside not in INSIDE_CHOICES:
        raise VolwarpError(f"inside must be one of {', '.join(INSIDE_CHOICES)}, got {inside!r}")
    if not np.isfinite(float(iso)):
        raise VolwarpError(f"isosurface level must be finite, got {float(iso)}")
    if np.dtype(dtype).kind not in "uif":
        raise VolwarpError(f"cannot isosurface samples of type {dtype}")


def to_world(points: np.ndarray, faces: np.ndarray, grad: np.ndarray | None, geometry, *,
             inside: str = "above", cap: bool = False) -> Mesh:
    """The mesh of flying edges' index-space output on ``geometry``'s grid.

    ``points`` (float32 (i, j, k), in the padded volume's indices with
    ``cap``), ``faces`` as flying edges winds them (outwards from the high
    side; modified in place), ``grad`` its index-space normals or None.
    ``geometry``: anything with ``spacing``, ``origin`` and ``direction`` (a
    :class:`~.volume.Volume` or a :class:`~.geometry.Geometry`). Every step is
    per vertex or per face, so the blocked path's welded output maps to the
    same bits as the whole's.
    """
    spacing = np.asarray(geometry.spacing, dtype=np.float64)
    direction = np.asarray(geometry.direction, dtype=np.float64)
    origin = np.asarray(geometry.origin, dtype=np.float64)
    shift = 1.0 if cap else 0.0
    matrix = direction * spacing[None, :]
    vertices = _index_to_world(points, matrix, origin - shift * matrix.sum(axis=1))
    # Flying edges winds triangles outwards from the high side. A left-handed
    # index-to-world map mirrors the winding; "below" swaps the sides.
    flip = (inside == "below") != (np.linalg.det(direction) < 0)
    if flip:  # swap two corners in place (the faces are ours, no copy needed)
        first = faces[:, 0].copy()
        faces[:, 0] = faces[:, 2]
        faces[:, 2] = first
    mesh = Mesh(vertices, faces)
    if grad is not None:
        mesh.normals = _world_normals(grad, matrix, inside)
    return mesh


def _index_to_world(points: np.ndarray, matrix: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """``origin + matrix @ p`` for (N, 3) float32 index points, as (N, 3) float64.

    Written column by column, skipping zero entries: a numpy matmul with a
    3x3 matrix is four times slower on millions of points. Every vertex gets
    the same operations in the same order, wherever it sits in the array.
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


def _times3(vectors: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``vectors @ m`` for (N, 3) float32 rows and a 3x3 float32 matrix, element by element.

    Not a BLAS product: its kernels may round a row differently depending on
    where it sits in the array, and the blocked path needs every row's bits
    to depend on that row alone.
    """
    out = np.empty(vectors.shape, dtype=np.float32)
    for c in range(3):
        col = out[:, c]
        np.multiply(vectors[:, 0], m[0, c], out=col)
        col += vectors[:, 1] * m[1, c]
        col += vectors[:, 2] * m[2, c]
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
        if np.allclose(inv, inv[0, 0] * np.eye(3), rtol=1e-12, atol=0) and \
                inv[0, 0] * sign > 0:  # (-I turns every normal about: not this shortcut)
            return grad
        return _times3(grad, (sign * inv / np.sqrt(gram[0, 0])).astype(np.float32))
    n = _times3(grad, (sign * inv).astype(np.float32))
    length = np.sqrt(n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2])[:, None]
    np.divide(n, length, out=n, where=length > 0)
    return n
