"""Isosurfaces by blocks: flying edges on each block, welded into the whole volume's mesh.

The cells of the volume (:func:`~.regions.mesh_cells`) are cut into blocks
(:meth:`~.box.Box.blocks`); each block runs the very flying edges of
:func:`.isosurface.isosurface` on the samples :func:`~.regions.mesh_input`
gives it (its cells' corners: one sample of overlap on the high side; with
normals one more layer around, for VTK's central-difference gradients, and
the triangles of those extra cells are dropped). The whole volume is the
one-block case: :func:`.isosurface.isosurface` is this module on one block.

**The order is flying edges' own on the whole volume**, whatever the blocks.
Flying edges numbers its vertices by x-row of samples (rows in (k, j)
order; in each row its x-edges, then its y-edges, then its z-edges, each by
increasing i: :func:`.isosurface.crossing_edges`) and makes its triangles
cell by cell in (k, j, i) order. A vertex lies on one cell edge, the edge
from its lower sample ``(i, j, k)`` along one axis; its **edge id**
(:func:`edge_ids`) is its place in that order, in the indices of the whole
volume, and a block's vertices come out in the order of their ids (a box of
rows, in the same row order). VTK tells which edge each vertex is on
(:func:`.isosurface._checked_edges`), and the vertex is recomputed from that
edge and its two samples by :func:`.isosurface.edge_points`, VTK's own
formula on global indices: two blocks sharing an edge make the same float32
vertex, the whole volume's. Welding (:func:`weld`) is then an integer join
(``np.unique`` of the ids: the whole's vertex order), with no float
comparison; the faces are put in the order of their cells (a stable sort:
a cell's triangles come from one block, in the whole's order). One block
has nothing to weld: its vertices and faces are already in that order, and
the whole volume's are VTK's own, as they come.

Whole-volume numbers are not regions: the level shifted off the samples
(:func:`.isosurface.level_off`), the ``cap`` padding value, the default
level and the NaN/infinity check come from a reduction over the blocks first
(:class:`Facts`, :func:`volume_facts`), which also counts the vertices to
come (the cell edges the level crosses), so that a mesh too big for the
memory is refused before it is made; ``cap`` pads virtually (a block reads
the volume and fills the padding layer itself).

Threads: a block task runs VTK's SMP filter on one thread; the whole volume,
one block, runs it on the threads in effect.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import parallel
from ..box import Box
from ..errors import VolwarpError
from ..regions import mesh_cells, mesh_input
from .isosurface import (
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


# -- edge ids ----------------------------------------------------------------------------
def edge_ids(lower: np.ndarray, axis: np.ndarray, shape) -> np.ndarray:
    """The int64 id of the cell edge from sample ``lower`` (N, 3) (i, j, k) along ``axis``.

    ``shape`` (z, y, x) is the contoured volume's (the padded one with
    ``cap``); the id is ``((k * ny + j) * 3 + axis) * nx + i``: ids sort as
    flying edges numbers the vertices of the whole volume (by row (k, j),
    then axis (x, y, z), then i).
    """
    _, ny, nx = (int(v) for v in shape)
    lower = np.asarray(lower, dtype=np.int64)
    axis = np.asarray(axis, np.int64)
    return ((lower[:, 2] * ny + lower[:, 1]) * 3 + axis) * nx + lower[:, 0]


def edge_of(ids: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`edge_ids`: ``(lower (N, 3) int64 (i, j, k), axis (N,))``."""
    _, ny, nx = (int(v) for v in shape)
    ids = np.asarray(ids, dtype=np.int64)
    i, rest = ids % nx, ids // nx
    axis, row = rest % 3, rest // 3
    return np.stack([i, row % ny, row // ny], axis=1), axis


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
    def of(samples: np.ndarray, dtype, iso: float | None, below: bool = True) -> Stats:
        """The stats of one block (converted to the type flying edges runs on).

        ``below``: find the largest sample below ``iso`` too (a pass of its
        own, needed only where some sample equals the level).
        """
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
        return Stats(float(lo), float(hi), False, hit,
                     _below_max(a, lo, hi, level) if below else None)

    @staticmethod
    def merge(parts) -> Stats:
        """The stats of the union of the blocks (a NaN anywhere: NaN, as :meth:`of`'s)."""
        parts = list(parts)
        if any(p.nan for p in parts):
            return Stats(np.nan, np.nan, True)
        belows = [p.below_max for p in parts if p.below_max is not None]
        return Stats(min((p.lo for p in parts), default=np.inf),
                     max((p.hi for p in parts), default=-np.inf), False,
                     any(p.hit for p in parts), max(belows) if belows else None)


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


@dataclass(frozen=True)
class Facts:
    """What the mesh needs from the whole volume, reduced over its blocks.

    ``stats`` (:class:`Stats`); ``crossings``: the cell edges the level
    crosses (flying edges' vertices without ``cap``'s); ``border``: the
    samples on the volume's faces inside the shape, once per face they are on
    (``cap``'s vertices; more than 0: the shape touches the border). The
    counts are 0 unless counted (:func:`volume_facts`' ``count``).
    """

    stats: Stats
    crossings: int = 0
    border: int = 0

    def vertices(self, cap: bool) -> int:
        """The isosurface's vertex count (with ``cap``, the padded volume's)."""
        return self.crossings + (self.border if cap else 0)

    @staticmethod
    def merge(parts) -> Facts:
        """The facts of the union of the blocks."""
        parts = list(parts)
        return Facts(Stats.merge(p.stats for p in parts), sum(p.crossings for p in parts),
                     sum(p.border for p in parts))


def block_facts(samples: np.ndarray, box: Box, shape, dtype, iso: float | None, *,
                inside: str = "above", count: bool = False, below: bool = False) -> Facts:
    """The :class:`Facts` of the samples of ``box`` of a volume of ``shape`` (z, y, x).

    ``samples``: the volume's samples in ``box`` grown by one on its high
    sides (within the volume): a block counts the cell edges whose lower
    sample is its own, so that every edge is counted once. ``dtype``: the
    type flying edges runs on; ``iso`` None: the range alone; ``below``:
    :class:`Stats`' largest sample below the level too.
    """
    samples = np.asarray(samples).astype(dtype, copy=False)
    own = samples[tuple(slice(0, n) for n in box.shape)]
    stats = Stats.of(own, dtype, iso, below)
    if iso is None or not count or stats.nan:
        return Facts(stats)
    above = samples >= iso  # (a sample equal to the level is above it)
    crossings = 0
    for axis in range(3):  # (z, y, x): the edges from own samples to the next one
        reach = min(box.shape[axis], samples.shape[axis] - 1)
        lo = [slice(0, n) for n in box.shape]
        hi = list(lo)
        lo[axis], hi[axis] = slice(0, reach), slice(1, reach + 1)
        crossings += int(np.count_nonzero(above[tuple(lo)] != above[tuple(hi)]))
    inner = above[tuple(slice(0, n) for n in box.shape)]
    if inside == "below":
        inner = ~inner
    border = 0
    for axis in range(3):  # an inside sample on a face: an edge to the cap's layer
        for end, on_face in ((0, box.lo[axis] == 0), (-1, box.hi[axis] == shape[axis])):
            if on_face:
                border += int(np.count_nonzero(np.take(inner, end, axis=axis)))
    return Facts(stats, crossings, border)


def slabs(box: Box, threads: int, nbytes: int = 4 << 20) -> list[Box]:
    """``box`` as z-slabs of about ``nbytes`` voxels for ``threads`` threads (one for one)."""
    if threads <= 1:
        return [box]
    _, ny, nx = box.shape
    depth = max(1, nbytes // max(1, ny * nx))
    return box.blocks((depth, ny, nx))


def volume_facts(source, iso: float | None, *, boxes, threads: int = 1, run=None,
                 cap: bool = False, inside: str = "above", count: bool = False) -> Facts:
    """The :class:`Facts` of ``source`` (a sliceable (z, y, x)), read block by block.

    ``boxes``: the blocks of samples; each runs on ``threads`` threads (by
    z-slabs), the blocks one after the other here or by ``run(task,
    boxes)`` (an engine's map). ``cap`` sets the type the samples are taken
    in (:func:`.isosurface.work_dtype`); ``count``: count the vertices.
    Where a sample equals the level, a second pass finds the largest sample
    below it (the level's shift).
    """
    shape = tuple(source.shape)
    dtype = work_dtype(source.dtype, cap)
    whole = Box.from_shape(shape)

    def facts(**what):
        def part(box):
            region = Box(box.lo, tuple(v + 1 for v in box.hi)).intersect(whole)
            return block_facts(source[region.slices], box, shape, dtype, iso, inside=inside,
                               **what)

        def task(box):
            return Facts.merge(parallel.run_blocks(part, slabs(box, threads), threads))

        return Facts.merge(run(task, boxes) if run is not None else [task(b) for b in boxes])

    found = facts(count=count)
    if iso is None or not found.stats.hit:
        return found
    return Facts(facts(below=True).stats, found.crossings, found.border)


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
@dataclass
class MeshPart:
    """A block's isosurface: float32 index ``points``, ``faces`` into them, ``normals``.

    The points are in the whole (padded) volume's indices, the normals VTK's
    index-space ones (or None), the faces wound as flying edges winds them.
    A block that is not the whole volume also carries its vertices' edge
    ``ids`` and its faces' ``cells`` (a key that sorts as the cells do), for
    :func:`weld`.
    """

    points: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None
    ids: np.ndarray | None = None
    cells: np.ndarray | None = None

    @staticmethod
    def empty(normals: bool) -> MeshPart:
        """A block without triangles."""
        return MeshPart(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64),
                        np.zeros((0, 3), np.float32) if normals else None)


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


def mesh_block(raw: np.ndarray, region: Box, cells: Box, plan: MeshPlan) -> MeshPart:
    """The isosurface of ``cells`` (a :class:`MeshPart`), VTK on the threads in effect.

    A pure function of the input samples ``raw`` (``plan.source_box(region)``
    of the input volume, ``region = mesh_input(cells, plan.shape, normals=...)``),
    fit for a Dask task. The whole volume is VTK's output as it is (its
    points are :func:`.isosurface.edge_points` of their edges, in id order);
    a block's points are recomputed from their edges on the whole's indices.
    """
    samples = block_samples(raw, region, plan)
    whole = cells == mesh_cells(plan.shape)
    points, faces, grad, found = _flying_edges(samples, plan.level, plan.normals,
                                               edges=not whole)
    if len(faces) == 0:
        return MeshPart.empty(plan.normals)
    if whole:
        return MeshPart(points, faces, grad)
    lower, axis = found
    offset = np.array(region.lo[::-1], dtype=np.int64)  # (x, y, z)
    # a triangle's cell: the least lower sample of its edges per axis (no triangle lies
    # in a cell face)
    cell = lower[faces].min(axis=1) + offset
    if region != Box(cells.lo, tuple(v + 1 for v in cells.hi)):
        # a halo for the normals: keep the triangles of our cells
        keep = np.all((cell >= np.array(cells.lo[::-1])) & (cell < np.array(cells.hi[::-1])),
                      axis=1)
        faces, cell = faces[keep], cell[keep]
        if len(faces) == 0:
            return MeshPart.empty(plan.normals)
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
    _, ny, nx = plan.shape
    return MeshPart(edge_points(lower_g, axis, s0, s1, plan.level),
                    faces.astype(np.int32),  # (a third of an id's bytes: ids[faces] welds)
                    None if grad is None else np.ascontiguousarray(grad),
                    edge_ids(lower_g, axis, plan.shape),
                    (cell[:, 2] * ny + cell[:, 1]) * nx + cell[:, 0])


def weld(parts) -> MeshPart:
    """The blocks' :class:`MeshPart` s as one, in the whole volume's order.

    Vertices by edge id (one per id: the integer join, ``np.unique`` of the
    ids), faces by cell (stable: a cell's triangles keep their order). Every
    copy of a shared edge's vertex and normal must be the same bits; a
    difference is an internal error. One part is its own weld.
    """
    parts = [p for p in parts if len(p.faces)]
    if not parts:
        return MeshPart.empty(False)
    if len(parts) == 1:
        return parts[0]
    ids = np.concatenate([p.ids for p in parts])
    _, first, inverse = np.unique(ids, return_index=True, return_inverse=True)
    copies = np.ones(len(ids), bool)  # the second copies of shared edges' vertices
    copies[first] = False

    def joined(name, what):
        values = np.concatenate([getattr(p, name) for p in parts])
        kept = values[first]
        if not np.array_equal(kept[inverse[copies]].view(np.int32),
                              values[copies].view(np.int32)):
            raise VolwarpError(f"internal error: blocks made different {what} on a shared "
                               "edge")
        return kept

    points = joined("points", "vertices")
    normals = None if parts[0].normals is None else joined("normals", "normals")
    start = np.cumsum([0] + [len(p.ids) for p in parts])
    faces = np.concatenate([inverse[p.faces + s] for p, s in zip(parts, start, strict=False)])
    cells = np.concatenate([p.cells for p in parts])
    if np.any(cells[1:] < cells[:-1]):  # (slabs of whole planes come in order)
        faces = faces[np.argsort(cells, kind="stable")]
    return MeshPart(points, faces, normals)


def welded_mesh(parts, plan: MeshPlan, geometry, *, inside: str = "above") -> Mesh:
    """The world mesh of the :func:`weld` of ``parts`` on ``geometry``."""
    part = weld(parts)
    if len(part.faces) == 0:
        return Mesh.empty()
    return to_world(part.points, part.faces, part.normals, geometry, inside=inside,
                    cap=plan.pad is not None)


def mesh_parts(source, plan: MeshPlan, split, *, threads: int = 1, run=None) -> list[MeshPart]:
    """The :class:`MeshPart` of every block of cells of ``source`` (a sliceable (z, y, x)).

    ``split(box)``: the cells' box cut into blocks; each block runs with
    ``threads`` threads, here one after the other or by ``run(task,
    blocks)`` (an engine's map).
    """
    blocks = [(cells, mesh_input(cells, plan.shape, normals=plan.normals))
              for cells in split(mesh_cells(plan.shape))]

    def task(block):
        cells, region = block
        with parallel.use_threads(threads):
            return mesh_block(source[plan.source_box(region).slices], region, cells, plan)

    return run(task, blocks) if run is not None else [task(b) for b in blocks]


# -- whole runs ---------------------------------------------------------------------------
def isosurface_blocks(source, geometry, level: float, *, block_shape=None,
                      inside: str = "above", cap: bool = False, normals: bool = False,
                      threads: int | None = None, run=None, check=None) -> Mesh:
    """The isosurface of ``source`` at ``level``, block by block, in the whole volume's order.

    Parameters
    ----------
    source : array-like (z, y, x)
        Anything with ``shape``, ``dtype`` and numpy slicing (an ndarray, a
        ``np.memmap``, a zarr array).
    geometry : Geometry or Volume
        Spacing, origin and direction of the grid.
    level : float
        The isosurface level (as :func:`.isosurface.isosurface`'s ``iso``).
    block_shape : int or (z, y, x) ints, optional
        Cells per block; need not divide the cell counts. None: one block,
        the whole volume, on ``threads`` threads.
    inside, cap, normals
        As :func:`.isosurface.isosurface`.
    threads : int or None
        The threads of the one block, or the block tasks run at once
        (:func:`.parallel.run_blocks`, each on one thread); None: the
        thread count in effect.
    run : callable, optional
        ``run(task, blocks)`` -> the tasks' results in order, instead of
        threads: e.g. :meth:`volwarp_cli.engine.Engine.map` on a Dask scheduler.
    check : callable, optional
        ``check(vertices)`` once the surface's vertex count is known, before the
        mesh is made (a memory check that refuses it).

    Returns
    -------
    Mesh
        :func:`.isosurface.isosurface`'s mesh, bit for bit and in its order,
        whatever the blocks.
    """
    check_arguments(source.dtype, level, inside)
    threads = parallel.threads() if threads is None else int(threads)
    if block_shape is None:
        def split(box):
            return [box]
        inner = threads
    else:
        def split(box):
            return box.blocks(block_shape)
        inner = 1
        if run is None:
            def run(task, blocks):
                return parallel.run_blocks(task, blocks, threads)
    facts = volume_facts(source, float(level), boxes=split(Box.from_shape(source.shape)),
                         threads=inner, run=run, cap=cap, count=check is not None)
    check_finite_range(facts.stats.lo, facts.stats.hi)
    if check is not None:
        check(facts.vertices(cap))
    plan = mesh_plan(facts.stats, source.shape, source.dtype, level, inside=inside, cap=cap,
                     normals=normals)
    parts = mesh_parts(source, plan, split, threads=inner, run=run)
    return welded_mesh(parts, plan, geometry, inside=inside)
