"""Isosurfaces out of core: flying edges block by block, welded by edge ids.

The cells of the volume (:func:`~.regions.mesh_cells`) are cut into blocks
(:meth:`~.box.Box.blocks`, or a Dask array's chunks); each block runs the
very flying edges of :func:`.isosurface.isosurface` on the samples
:func:`~.regions.mesh_input` gives it (its cells' corners: one sample of
overlap on the high side; with normals one more layer around, for VTK's
central-difference gradients, and the triangles of those extra cells are
dropped). A vertex lies on one cell edge, the edge from its lower sample
``(i, j, k)`` along one axis; its **edge id** packs the two into an int64
(:func:`edge_ids`), in the indices of the whole volume. VTK tells which edge
each vertex is on exactly (:func:`.isosurface._edge_attribute`), and the
vertex is recomputed from that edge and its two samples by
:func:`.isosurface.edge_points`, VTK's own formula on global indices: two
blocks sharing an edge make the same float32 vertex, and the in-memory path
makes it too. Welding is then an integer join (``np.unique`` of the ids),
with no float comparison; faces are carried as triples of edge ids and
re-indexed to the welded vertices.

The welded mesh is put in the canonical order (:func:`canonical_mesh`):
vertices by edge id, each face rotated so that its smallest vertex comes
first (the winding kept), faces sorted. So the output does not depend on
the block shape, and equals the in-memory mesh in canonical order bit for
bit (vertices, faces and normals; ``tests/test_mesh_chunked.py``).

Whole-volume numbers are not regions: the level shifted off the samples
(:func:`.isosurface.level_off`), the ``cap`` padding value, the default
level and the NaN/infinity check come from a reduction over the blocks first
(:func:`mesh_plan`); ``cap`` pads virtually (a block reads the volume and
fills the padding layer itself).

After welding, the mesh is the whole mesh in memory, so every clean-up of
:func:`.pipeline.clean` is valid on it and is done there
(:func:`surface_mesh_blocks`): largest component, smoothing, decimation,
in that order, and the same result as the in-memory chain. Nothing of the
mesh chain needs the whole *volume* in memory, so nothing is refused for an
out-of-core input; what is refused is what the in-memory path refuses (NaN or
infinite samples, a level outside the range or never crossed unless allowed, samples
that are not numbers) and a block or a mesh that does not fit the memory
budget.

Threads: each block task runs VTK's SMP filter on one thread
(:func:`mesh_block`), so a pool of block tasks does not oversubscribe the
cores. Only :func:`isosurface_dask` imports dask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import parallel
from ..box import Box
from ..errors import VolwarpError
from ..progress import log, timed
from ..regions import mesh_cells, mesh_input
from .isosurface import (
    INSIDE_CHOICES,
    _flying_edges,
    cap_value,
    check_arguments,
    check_finite_range,
    edge_points,
    level_off,
    to_world,
    work_dtype,
)
from .mesh import Mesh

#: Default block of cells (z, y, x) for :func:`isosurface_blocks`.
DEFAULT_BLOCK = (64, 64, 64)


# -- edge ids ----------------------------------------------------------------------------
def edge_ids(lower: np.ndarray, axis: np.ndarray, shape) -> np.ndarray:
    """The int64 id of the cell edge from sample ``lower`` (N, 3) (i, j, k) along ``axis``.

    ``shape`` (z, y, x) is the contoured volume's (the padded one with
    ``cap``); the id is ``3 * (linear index of lower) + axis``, so ids sort
    by lower sample (x fastest), then axis (x, y, z).
    """
    _, ny, nx = (int(v) for v in shape)
    lower = np.asarray(lower, dtype=np.int64)
    return ((lower[:, 2] * ny + lower[:, 1]) * nx + lower[:, 0]) * 3 + np.asarray(axis, np.int64)


def edge_of(ids: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`edge_ids`: ``(lower (N, 3) int64 (i, j, k), axis (N,))``."""
    _, ny, nx = (int(v) for v in shape)
    ids = np.asarray(ids, dtype=np.int64)
    axis, lin = ids % 3, ids // 3
    lower = np.stack([lin % nx, (lin // nx) % ny, lin // (nx * ny)], axis=1)
    return lower, axis


def canonical_faces(faces: np.ndarray) -> np.ndarray:
    """Faces rotated so each starts at its smallest vertex (winding kept), then sorted."""
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return faces.reshape(0, 3)
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    at_a = (a <= b) & (a <= c)
    at_b = ~at_a & (b <= c)
    rotated = np.empty_like(faces)  # (a, b, c), (b, c, a) or (c, a, b): the winding kept
    rotated[:, 0] = np.where(at_a, a, np.where(at_b, b, c))
    rotated[:, 1] = np.where(at_a, b, np.where(at_b, c, a))
    rotated[:, 2] = np.where(at_a, c, np.where(at_b, a, b))
    n = int(faces.max()) + 1
    if n ** 3 < 2 ** 63:  # one packed key: a plain sort, no gather
        key = (rotated[:, 0] * n + rotated[:, 1]) * n + rotated[:, 2]
        key.sort()
        out = np.empty_like(rotated)
        out[:, 0], rest = np.divmod(key, n * n)
        out[:, 1], out[:, 2] = np.divmod(rest, n)
        return out
    order = np.lexsort((rotated[:, 2], rotated[:, 1], rotated[:, 0]))
    return np.ascontiguousarray(rotated[order])


def canonical_mesh(vertices: np.ndarray, faces: np.ndarray, ids: np.ndarray,
                   normals: np.ndarray | None = None):
    """``(vertices, faces, normals)`` in the canonical order of the vertices' edge ``ids``.

    Vertices (and normals) sorted by edge id, faces re-indexed to that order
    and put in :func:`canonical_faces` order. Two meshes with the same edge
    ids and the same triangles get the same arrays, whatever order their
    blocks or VTK's threads made them in.
    """
    ids = np.asarray(ids, dtype=np.int64)
    if len(np.unique(ids)) != len(ids):
        raise VolwarpError("two vertices of the mesh have the same edge id")
    order = np.argsort(ids, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    out_normals = None if normals is None else np.asarray(normals)[order]
    return (np.asarray(vertices)[order], canonical_faces(rank[np.asarray(faces, np.int64)]),
            out_normals)


# -- the whole-volume numbers -------------------------------------------------------------
@dataclass(frozen=True)
class MeshPlan:
    """What every block needs from the whole volume.

    ``shape`` (z, y, x): the contoured volume's (``cap``: the padded one);
    ``level``: the level flying edges runs at (shifted off the samples as
    the whole's); ``dtype``: the sample type it runs on; ``pad``: the
    ``cap`` value or None; ``normals``: whether blocks compute VTK normals.
    """

    shape: tuple[int, int, int]
    level: float
    dtype: np.dtype
    pad: float | None
    normals: bool

    @property
    def data_box(self) -> Box:
        """Where the volume's own samples lie in the contoured volume's indices."""
        if self.pad is None:
            return Box.from_shape(self.shape)
        return Box((1, 1, 1), tuple(n - 1 for n in self.shape))

    def source_box(self, region: Box) -> Box:
        """The samples of the input volume (its own indices) that ``region`` holds."""
        inner = region.intersect(self.data_box)
        return inner.shift(tuple(-v for v in self.data_box.lo))


@dataclass(frozen=True)
class Stats:
    """A reduction of samples: range, NaN, and what :func:`.isosurface.level_off` needs."""

    lo: float
    hi: float
    nan: bool
    hit: bool = False
    below_max: float | None = None

    @staticmethod
    def of(samples: np.ndarray, dtype, iso: float | None) -> Stats:
        """The stats of one block (converted to the type flying edges runs on)."""
        a = np.asarray(samples).astype(dtype, copy=False)
        if a.size == 0:
            return Stats(np.inf, -np.inf, False)
        if a.dtype.kind == "b":
            a = a.view(np.uint8)
        lo, hi = a.min(), a.max()  # (NaN reaches both)
        if np.isnan(lo) or np.isnan(hi):
            return Stats(np.nan, np.nan, True)
        if iso is None:
            return Stats(float(lo), float(hi), False)
        level = np.result_type(a.dtype, iso).type(iso)  # compared as numpy compares them
        hit = bool(lo <= level <= hi and np.any(a == level))
        return Stats(float(lo), float(hi), False, hit, _below_max(a, lo, hi, level))

    @staticmethod
    def merge(parts) -> Stats:
        """The stats of the union of the blocks."""
        parts = list(parts)
        belows = [p.below_max for p in parts if p.below_max is not None]
        return Stats(min((p.lo for p in parts), default=np.inf),
                     max((p.hi for p in parts), default=-np.inf),
                     any(p.nan for p in parts), any(p.hit for p in parts),
                     max(belows) if belows else None)


def _below_max(a: np.ndarray, lo, hi, level) -> float | None:
    """The largest sample of ``a`` below ``level`` (None: none), in few passes.

    For integers the candidate is the largest integer below the level: where
    it occurs (smooth data around an integer level: nearly always) one
    comparison settles it; else, and for floats, a masked maximum.
    """
    if not lo < level:
        return None
    if a.dtype.kind in "iu" and a.dtype.itemsize <= 4:  # exact in float64
        below = int(np.ceil(float(level))) - 1
        if lo <= below <= hi and np.any(a == a.dtype.type(below)):
            return float(below)
    return float(np.max(a, where=a < level, initial=lo))


def mesh_plan(stats: Stats, shape, dtype, iso: float, *, inside: str = "above",
              cap: bool = False, normals: bool = False) -> MeshPlan:
    """The :class:`MeshPlan` of a volume of ``shape`` (z, y, x) whose samples have ``stats``.

    ``stats`` must have been computed at ``iso`` (for the level shift) on the
    samples converted to :func:`.isosurface.work_dtype` ``(dtype, cap)``.
    """
    check_arguments(dtype, iso, inside)
    check_finite_range(stats.lo, stats.hi)
    iso = float(iso)
    hit, below = stats.hit, stats.below_max
    pad = None
    shape = tuple(int(v) for v in shape)
    if cap:
        pad = cap_value(stats.lo, stats.hi, iso, inside)
        pad_t = float(np.asarray(pad, dtype=work_dtype(dtype, True)))
        hit = hit or pad_t == iso
        if pad_t < iso:
            below = pad_t if below is None else max(below, pad_t)
        shape = tuple(n + 2 for n in shape)
    return MeshPlan(shape, level_off(iso, hit, below), work_dtype(dtype, cap), pad,
                    bool(normals))


# -- one block ----------------------------------------------------------------------------
def block_samples(raw: np.ndarray, region: Box, plan: MeshPlan) -> np.ndarray:
    """The contoured volume's samples in ``region``, from the input's ``plan.source_box(region)``.

    Converted to ``plan.dtype``; with ``cap`` the padding layer is filled in.
    """
    raw = np.asarray(raw)
    if plan.pad is None:
        return np.ascontiguousarray(raw, dtype=plan.dtype)
    out = np.full(region.shape, plan.pad, dtype=plan.dtype)
    inner = region.intersect(plan.data_box)
    if not inner.empty:
        out[inner.relative_to(region).slices] = raw
    return out


def mesh_block(raw: np.ndarray, region: Box, cells: Box, plan: MeshPlan):
    """The isosurface of ``cells`` as ``(edge ids, float32 index points, normals, faces)``.

    A pure function of the input samples ``raw`` (``plan.source_box(region)``
    of the input volume, ``region = mesh_input(cells, plan.shape, normals=...)``),
    fit for a Dask task. ``faces`` (T, 3) index the block's own vertices
    (their edge ids are ``ids[faces]``: an int32 index is a third of an id's
    bytes and welding gathers instead of searching), wound as flying edges
    winds them; the points are in the whole (padded) volume's indices and the
    normals VTK's index-space ones (or None). VTK runs on one SMP thread.
    """
    samples = block_samples(raw, region, plan)
    with parallel.use_threads(1):
        _, faces, grad, found = _flying_edges(samples, plan.level, plan.normals, edges=True)
    empty = (np.zeros(0, np.int64), np.zeros((0, 3), np.float32),
             np.zeros((0, 3), np.float32) if plan.normals else None, np.zeros((0, 3), np.int64))
    if len(faces) == 0:
        return empty
    lower, axis = found
    offset = np.array(region.lo[::-1], dtype=np.int64)  # (x, y, z)
    if region != Box(cells.lo, tuple(v + 1 for v in cells.hi)):
        # a halo for the normals: keep the triangles of our cells (a triangle's cell is
        # the least lower sample of its edges per axis: no triangle lies in a cell face)
        cell = lower[faces].min(axis=1) + offset
        keep = np.all((cell >= np.array(cells.lo[::-1])) & (cell < np.array(cells.hi[::-1])),
                      axis=1)
        faces = faces[keep]
        if len(faces) == 0:
            return empty
        used = np.zeros(len(lower), bool)
        used[faces] = True
        remap = np.cumsum(used) - 1
        faces = remap[faces]
        lower, axis = lower[used], axis[used]
        if grad is not None:
            grad = grad[used]
    upper = lower.copy()
    upper[np.arange(len(axis)), axis] += 1
    s0 = samples[lower[:, 2], lower[:, 1], lower[:, 0]]
    s1 = samples[upper[:, 2], upper[:, 1], upper[:, 0]]
    lower_g = lower + offset
    points = edge_points(lower_g, axis, s0, s1, plan.level)
    ids = edge_ids(lower_g, axis, plan.shape)
    normals = None if grad is None else np.ascontiguousarray(grad)
    return ids, points, normals, faces.astype(np.int32)


def weld(parts):
    """Weld block outputs of :func:`mesh_block`: ``(ids, points, normals, faces)``.

    Vertices sorted by edge id (one per id: the integer join, ``np.unique``
    of the ids), faces as indices into them (in block order). Every copy of a shared edge's vertex
    and normal must be the same bits; a difference is an internal error.
    """
    parts = [p for p in parts if len(p[3])]
    if not parts:
        return (np.zeros(0, np.int64), np.zeros((0, 3), np.float32), None,
                np.zeros((0, 3), np.int64))
    ids = np.concatenate([p[0] for p in parts])
    points = np.concatenate([p[1] for p in parts])
    uniq, first, inverse = np.unique(ids, return_index=True, return_inverse=True)
    welded = points[first]
    if not np.array_equal(welded[inverse].view(np.int32), points.view(np.int32)):
        raise VolwarpError("internal error: blocks made different vertices on a shared edge")
    normals = None
    if parts[0][2] is not None:
        allnormals = np.concatenate([p[2] for p in parts])
        normals = allnormals[first]
        if not np.array_equal(normals[inverse].view(np.int32), allnormals.view(np.int32)):
            raise VolwarpError("internal error: blocks made different normals on a shared edge")
    start = np.cumsum([0] + [len(p[0]) for p in parts])
    faces = np.concatenate([inverse[p[3] + s] for p, s in zip(parts, start, strict=False)])
    return uniq, welded, normals, faces


def welded_mesh(parts, plan: MeshPlan, geometry, *, inside: str = "above") -> Mesh:
    """The world mesh of the welded ``parts`` on ``geometry``, in canonical order."""
    _, points, grad, faces = weld(parts)
    if len(faces) == 0:
        return Mesh.empty()
    mesh = to_world(points, faces, grad, geometry, inside=inside, cap=plan.pad is not None)
    mesh.faces = canonical_faces(mesh.faces)
    return mesh


# -- whole runs ---------------------------------------------------------------------------
def cell_blocks(plan: MeshPlan, block_shape) -> list[tuple[Box, Box]]:
    """``(cells, region)`` of every block of ``block_shape`` cells (z, y, x), in C order."""
    return [(cells, mesh_input(cells, plan.shape, normals=plan.normals))
            for cells in mesh_cells(plan.shape).blocks(block_shape)]


def _sample_blocks(shape, block_shape) -> list[Box]:
    return Box.from_shape(shape).blocks(block_shape)


def source_stats(source, block_shape, iso: float | None, cap: bool = False, *,
                 threads: int | None = 1, run=None) -> Stats:
    """:class:`Stats` of an array-like ``source`` (z, y, x), read block by block.

    ``threads`` and ``run`` as :func:`isosurface_blocks` has them.
    """
    dtype = work_dtype(source.dtype, cap)

    def task(box):
        return Stats.of(source[box.slices], dtype, iso)

    blocks = _sample_blocks(source.shape, block_shape)
    return Stats.merge(parallel.run_blocks(task, blocks, threads) if run is None
                       else run(task, blocks))


def isosurface_blocks(source, geometry, level: float, *, block_shape=DEFAULT_BLOCK,
                      inside: str = "above", cap: bool = False, normals: bool = False,
                      threads: int | None = 1, run=None, stats: Stats | None = None) -> Mesh:
    """The isosurface of ``source`` at ``level``, computed block by block, in canonical order.

    Parameters
    ----------
    source : array-like (z, y, x) or Volume
        Anything with ``shape``, ``dtype`` and numpy slicing (an ndarray, a
        ``np.memmap``, a zarr or h5py array); a :class:`~.volume.Volume` gives
        its data (and its geometry when ``geometry`` is None).
    geometry : Geometry, Volume or None
        Spacing, origin and direction of the grid.
    level : float
        The isosurface level (as :func:`.isosurface.isosurface`'s ``iso``).
    block_shape : int or (z, y, x) ints
        Cells per block; need not divide the cell counts.
    inside, cap, normals
        As :func:`.isosurface.isosurface`.
    threads : int or None
        Block tasks run at once (:func:`.parallel.run_blocks`; 1: a plain
        loop, None: the thread count in effect).
    run : callable, optional
        ``run(task, blocks)`` -> the tasks' results in order, instead of
        threads: e.g. :meth:`volwarp_cli.engine.Engine.map` on a Dask scheduler.
    stats : Stats, optional
        :func:`source_stats` of ``source`` at ``level`` with ``cap``, when the
        caller has them (saves a pass over the volume).

    Returns
    -------
    Mesh
        The in-memory :func:`.isosurface.isosurface` mesh in
        :func:`canonical_mesh` order, bit for bit.
    """
    data, geometry = _source(source, geometry)
    if inside not in INSIDE_CHOICES:
        raise VolwarpError(f"inside must be one of {', '.join(INSIDE_CHOICES)}, got {inside!r}")
    check_arguments(data.dtype, level, inside)
    if stats is None:
        with timed("isosurface blocks: whole-volume stats"):
            stats = source_stats(data, block_shape, float(level), cap, threads=threads,
                                 run=run)
    plan = mesh_plan(stats, data.shape, data.dtype, level, inside=inside, cap=cap,
                     normals=normals)
    blocks = cell_blocks(plan, block_shape)

    def task(block):
        cells, region = block
        return mesh_block(data[plan.source_box(region).slices], region, cells, plan)

    with timed(f"isosurface blocks: flying edges on {len(blocks)} blocks"):
        parts = (parallel.run_blocks(task, blocks, threads) if run is None
                 else run(task, blocks))
    with timed("isosurface blocks: weld"):
        mesh = welded_mesh(parts, plan, geometry, inside=inside)
    log.debug("isosurface blocks: %d vertices, %d triangles", mesh.n_vertices, mesh.n_faces)
    return mesh


def _dask_cell_blocks(plan: MeshPlan, chunks, block_shape) -> list[tuple[Box, Box]]:
    """Cell blocks cut where the Dask array's chunks are cut (or by ``block_shape``)."""
    if block_shape is not None:
        return cell_blocks(plan, block_shape)
    ncells = mesh_cells(plan.shape).hi
    shift = plan.data_box.lo
    cuts = []
    for axis in range(3):
        starts = np.cumsum((0,) + tuple(chunks[axis]))[:-1] + shift[axis]
        c = sorted({0, ncells[axis], *(int(s) for s in starts if 0 < s < ncells[axis])})
        cuts.append(c)
    out = []
    for z0, z1 in zip(cuts[0][:-1], cuts[0][1:], strict=True):
        for y0, y1 in zip(cuts[1][:-1], cuts[1][1:], strict=True):
            for x0, x1 in zip(cuts[2][:-1], cuts[2][1:], strict=True):
                cells = Box((z0, y0, x0), (z1, y1, x1))
                out.append((cells, mesh_input(cells, plan.shape, normals=plan.normals)))
    return out


def _stats_of_block(block, dtype, iso):
    return Stats.of(block, dtype, iso)


def isosurface_dask(darr, geometry, level: float, *, block_shape=None, inside: str = "above",
                    cap: bool = False, normals: bool = False, compute: bool = True,
                    **compute_kwargs):
    """The blocked isosurface of a Dask array: per-block delayed tasks and a welding reduce.

    ``darr`` (z, y, x); blocks of cells cut at its chunks, or of
    ``block_shape`` cells. The whole-volume stats are a first computed
    reduction (per chunk, then merged); the mesh is one delayed
    :func:`welded_mesh` over the :func:`mesh_block` tasks, each reading its
    region's samples (a slice of ``darr`` with the one-sample overlap).
    ``compute``: return the :class:`~.mesh.Mesh` (``compute_kwargs`` go to
    ``dask.compute``, e.g. ``scheduler="threads", num_workers=2``), else the
    ``dask.delayed`` object. The same mesh as :func:`isosurface_blocks`.
    """
    import dask

    if inside not in INSIDE_CHOICES:
        raise VolwarpError(f"inside must be one of {', '.join(INSIDE_CHOICES)}, got {inside!r}")
    check_arguments(darr.dtype, level, inside)
    dtype = work_dtype(darr.dtype, cap)
    stats_tasks = [dask.delayed(_stats_of_block)(blk, dtype, float(level))
                   for blk in darr.to_delayed().ravel()]
    (parts_stats,) = dask.compute(stats_tasks, **compute_kwargs)
    plan = mesh_plan(Stats.merge(parts_stats), darr.shape, darr.dtype, level, inside=inside,
                     cap=cap, normals=normals)
    tasks = [dask.delayed(mesh_block)(darr[plan.source_box(region).slices], region, cells, plan)
             for cells, region in _dask_cell_blocks(plan, darr.chunks, block_shape)]
    result = dask.delayed(welded_mesh)(tasks, plan, geometry, inside=inside)
    if not compute:
        return result
    (mesh,) = dask.compute(result, **compute_kwargs)
    return mesh


def isosurface_edge_ids(vol, iso: float, *, inside: str = "above",
                        cap: bool = False) -> np.ndarray:
    """The edge id of every vertex of ``isosurface(vol, iso, inside=..., cap=...)``, in its order.

    The same flying edges on the same samples and level (VTK's output order
    does not depend on the edge attribute), so :func:`canonical_mesh` can
    put the in-memory mesh in the blocked mesh's order.
    """
    from .isosurface import _level_off_samples, _pad_for_cap, _prepared

    data, iso = _prepared(vol.data, iso, inside)
    if cap:
        data = _pad_for_cap(data, iso, inside)
    _, faces, _, (lower, axis) = _flying_edges(data, _level_off_samples(data, iso), False,
                                               edges=True)
    if len(faces) == 0:
        return np.zeros(0, np.int64)
    return edge_ids(lower, axis, data.shape)


def slab_block(shape, budget: int, tasks: int) -> tuple[int, int, int]:
    """The block of a mesh by blocks: slabs of whole planes of a volume of ``shape`` (z y x).

    Whole rows read, no halo at the sides; as deep as ``tasks`` of them fit
    ``budget`` at about 24 bytes a voxel (the samples, their float copy and
    flying edges' working arrays), within 8 to 256 planes.
    """
    nz, ny, nx = shape
    depth = budget // max(1, tasks) // max(1, 24 * ny * nx)
    return (max(8, min(nz, depth, 256)), ny, nx)


def surface_mesh_blocks(source, geometry=None, iso: float | None = None, *,
                        block_shape=DEFAULT_BLOCK, inside: str = "above", cap: bool = False,
                        allow_empty: bool = False, cleanup=None, name: str = "the volume",
                        threads: int | None = 1, run=None) -> tuple[Mesh, float]:
    """:func:`.pipeline.surface_mesh` out of core: ``(mesh, iso)``.

    The same checks, level and messages, the isosurface by
    :func:`isosurface_blocks`, then :func:`.pipeline.clean` on the welded
    mesh (every clean-up is a mesh operation, valid after welding). The
    result equals the in-memory chain's up to the order of vertices and
    faces (canonical here), which the clean-ups see: largest component and
    smoothing give the same geometry; decimation's greedy choices may break
    ties differently in another order.
    """
    from .isosurface import touches_border
    from .pipeline import Cleanup, finish_surface

    cleanup = Cleanup() if cleanup is None else cleanup
    data, geometry = _source(source, geometry)
    check_arguments(data.dtype, 0.0 if iso is None else iso, inside)
    given = iso is not None
    with timed("isosurface blocks: whole-volume stats"):
        # a given level: one pass gives the range and the level's facts, in the type flying
        # edges runs on (the range is the same values in either type)
        first = source_stats(data, block_shape, float(iso) if given else None, cap,
                             threads=threads, run=run)
    check_finite_range(first.lo, first.hi, name)
    lo, hi = first.lo, first.hi
    if iso is None:
        iso = 0.5 * (lo + hi)
        log.info("iso level not given: using the middle of the value range, %g", iso)
    empty_reason = None
    if not lo <= iso <= hi:
        empty_reason = f"iso level {iso:g} is outside the data range [{lo:g}, {hi:g}] of {name}"
        mesh = Mesh.empty()
    else:
        mesh = isosurface_blocks(data, geometry, iso, block_shape=block_shape, inside=inside,
                                 cap=cap, normals=True, threads=threads, run=run,
                                 stats=first if given else None)  # (normals: as in memory)
        if mesh.is_empty:
            empty_reason = f"no surface at level {iso:g} in {name} (the level is never crossed)"
        elif not cap and _border_touched(data, iso, inside, touches_border):
            log.warning("the shape touches the volume's border, where its surface is open "
                        "(use --cap to close it)")
    return finish_surface(mesh, empty_reason, allow_empty, cleanup), iso


def _source(source, geometry):
    """``(samples, geometry)`` of an array-like and a geometry, or of a Volume."""
    is_volume = hasattr(source, "spacing") and hasattr(source, "data")
    data = source.data if is_volume else source
    if geometry is None:
        if not is_volume:
            raise VolwarpError("a geometry is needed for an array without one")
        geometry = source
    return data, geometry


def _border_touched(data, iso: float, inside: str, touches_border) -> bool:
    """:func:`.isosurface.touches_border` reading only the six outer faces."""
    nz, ny, nx = data.shape
    faces = [data[0:1], data[nz - 1:nz], data[:, 0:1], data[:, ny - 1:ny],
             data[:, :, 0:1], data[:, :, nx - 1:nx]]
    return any(touches_border(np.asarray(f), iso, inside) for f in faces)


# -- label maps -----------------------------------------------------------------------------
class LabelIndicator:
    """The indicator of one label of a sliceable label map (1 inside, float32), read by boxes.

    Picklable when the map is (a :class:`~volwarp_cli.bspline.blocks.LazySource`);
    its surface is the isosurface at 0.5, as :func:`.pipeline.label_indicator`'s.
    """

    def __init__(self, source, label: int):
        self.source, self.label = source, int(label)
        self.shape = tuple(source.shape)
        self.dtype = np.dtype(np.float32)
        self.ndim = 3

    def __getitem__(self, key) -> np.ndarray:
        return (np.asarray(self.source[key]) == self.label).astype(np.float32)


def label_values(source, block_shape, *, threads: int | None = 1, run=None) -> list[int]:
    """The distinct values of a sliceable integer map, ascending, read block by block.

    ``threads``, ``run``: as :func:`isosurface_blocks`'.
    """
    boxes = _sample_blocks(source.shape, block_shape)

    def task(box):
        return np.unique(np.asarray(source[box.slices]))

    parts = parallel.run_blocks(task, boxes, threads) if run is None else run(task, boxes)
    values = np.unique(np.concatenate(parts)) if parts else np.empty(0, np.int64)
    return [int(v) for v in values]


def label_meshes_blocks(source, geometry, labels, *, block_shape=DEFAULT_BLOCK,
                        allow_empty: bool = False, cleanup=None, name: str = "the volume",
                        threads: int | None = 1, run=None):
    """:func:`.pipeline.label_meshes` out of core: ``(label, surface)`` for each of ``labels``.

    Each label's indicator (:class:`LabelIndicator`) meshed by
    :func:`surface_mesh_blocks` at 0.5, capped at the border, as in memory.
    """
    for label in labels:
        mesh, _ = surface_mesh_blocks(LabelIndicator(source, label), geometry, 0.5,
                                      block_shape=block_shape, inside="above", cap=True,
                                      allow_empty=allow_empty, cleanup=cleanup,
                                      name=f"{name} label {label}", threads=threads, run=run)
        yield label, mesh
