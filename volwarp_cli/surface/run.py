"""``volwarp mesh`` as an operation of the executor: isosurfaces, cleaned up, written.

:class:`MeshOperation` is a :class:`~volwarp_cli.execute.Reduction`: its
blocks make parts of a mesh and :func:`.chunked.weld` reduces them to the
whole volume's mesh, in flying edges' own order on the whole volume, so the
in-memory run (one block, the whole, on the calling threads) and a run by
blocks write the same bytes. :func:`volwarp_cli.execute.run` decides which,
before any sample is read, from :meth:`MeshOperation.memory` (the volume's
side: its samples and flying edges' working memory); the mesh, held either
way, is counted exactly by the first pass (the cell edges the level
crosses) and refused before it is made when it does not fit.

The chain of one surface: the whole-volume facts (range, NaN, the level's
shift; a first pass for the default level, the middle of the range), a
level outside the range or never crossed refused (or an empty mesh, when
allowed), the isosurface, the clean-ups in their fixed order
(:func:`.ops.clean`), the mesh file, its statistics. A label map's surfaces
are those of its labels' indicators (:mod:`.labels`). Nothing here parses
options.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..box import Box
from ..errors import BadUsage, VolwarpError
from ..execute import Blocks, Reduction
from ..geometry import Geometry
from ..progress import log, timed
from ..volume import Volume
from .chunked import mesh_parts, mesh_plan, volume_facts, welded_mesh
from .isosurface import check_arguments, check_finite_range, isosurface, work_dtype
from .labels import LabelIndicator, check_label_map, label_values
from .mesh import Mesh
from .ops import Cleanup, clean

#: Peak bytes of the mesh chain, over what the process held before it (measured on a
#: 160^3 gyroid, 1.2M triangles; the libraries and compiled kernels already loaded):
#: per voxel (flying edges' per-edge cases), per triangle for the extraction (the mesh
#: as held, about 42 bytes, and its conversion to world coordinates), and per triangle
#: of each clean-up's own work beside it (the largest of those in the chain counts).
CHAIN_BYTES_PER_VOXEL = 4
EXTRACT_BYTES_PER_TRIANGLE = 64
CLEANUP_BYTES_PER_TRIANGLE = {"largest_component": 64, "smooth": 128, "decimate": 208}
#: By blocks, per triangle: the blocks' parts (points, normals, edge ids, faces and their
#: cells), their weld (the joined copies, the sort, the faces re-indexed and re-ordered)
#: and the world mesh.
WELD_BYTES_PER_TRIANGLE = 160
#: A block's flying-edges output and part, per voxel, on a dense surface (a gyroid of a
#: 32-voxel period makes 0.3 triangles a voxel): what a block's shape is chosen for.
PART_BYTES_PER_VOXEL = 32
#: The side of the ball the chain runs on to load its kernels (:meth:`MeshOperation.load`).
_WARM_SIZE = 8


@dataclass(frozen=True)
class Level:
    """The surface asked for.

    ``iso`` (None: the middle of the value range), which side is ``inside``
    (``"above"`` or ``"below"``: the outward normals), ``cap`` (closed where
    the shape touches the volume's border).
    """

    iso: float | None = None
    inside: str = "above"
    cap: bool = False


#: A label's surface: its indicator's isosurface at 0.5, closed at the border.
LABEL_LEVEL = Level(0.5, "above", True)
#: ``labels`` for every label other than 0.
ALL_LABELS = "all"
#: ``labels`` for the surface of every voxel with a label other than 0 (one mesh).
NONZERO_LABELS = "nonzero"


@dataclass(frozen=True)
class MeshFile:
    """Where a mesh is written.

    ``path`` (with ``{label}`` for every label's), and the key/values it
    records (provenance).
    """

    path: str
    comments: dict = field(default_factory=dict)


@dataclass
class Surface:
    """One mesh the operation made.

    ``label``: the label (None: the volume's isosurface); ``iso``: the level
    used; ``mesh``: the mesh (None for every label's, which are not kept);
    ``stats``: its statistics, when asked for.
    """

    label: int | None
    iso: float
    mesh: Mesh | None = None
    stats: dict | None = None


class MeshOperation(Reduction):
    """The isosurface of a volume, or the surfaces of a label map's labels, as a reduction.

    Parameters
    ----------
    header : Header
        The input's geometry and type (:class:`~volwarp_cli.volume.Header`).
    source : sliceable (z, y, x)
        The input's samples (an array, or a
        :class:`~volwarp_cli.io.lazy.LazySource` read box by box).
    level : Level
        The surface of the samples (not of a label map's labels).
    cleanup : Cleanup
        What is done to each surface after it is made.
    labels : None, int, ``"all"`` or ``"nonzero"``
        A label map's label (its surface: :data:`LABEL_LEVEL` of its
        indicator), every label other than 0 (``"all"``: a mesh each), the
        union of those (``"nonzero"``: one mesh, as
        :func:`.labels.mesh_values` chooses for a label map), or None
        (``level``).
    allow_empty : bool
        An empty surface is a warning (an empty mesh) instead of an error.
    name : str
        The input, in messages.
    to : MeshFile, optional
        Where the meshes are written.
    stats : bool
        Compute each mesh's statistics (:func:`.stats.mesh_stats`).
    keep_labels : bool
        With ``labels="all"``, keep every label's mesh in its :class:`Surface`
        (the API's); else each is let go once written and measured.

    :attr:`~volwarp_cli.execute.Ran.output` is the list of :class:`Surface`.
    """

    def __init__(self, header, source, level: Level = Level(), *,
                 cleanup: Cleanup = Cleanup(), labels=None, allow_empty: bool = False,
                 name: str = "the volume", to: MeshFile | None = None, stats: bool = False,
                 keep_labels: bool = False):
        self.source, self.name, self.to, self.stats = source, str(name), to, bool(stats)
        self.keep_labels = bool(keep_labels)
        self.level = LABEL_LEVEL if labels is not None else level
        self.labels, self.cleanup, self.allow_empty = labels, cleanup, bool(allow_empty)
        self.grid = Geometry.of(header)
        self.shape = tuple(int(n) for n in source.shape)
        self.dtype = np.dtype(source.dtype)
        if labels is not None and labels != NONZERO_LABELS:  # (the rule's: integers' values)
            check_label_map(self.dtype, self.name,
                            "--labels" if labels == ALL_LABELS else "--label")
        else:
            iso = level.iso
            check_arguments(self.dtype, 0.0 if iso is None else iso, level.inside)
        nx, ny, nz = self.grid.shape_xyz
        self.what = f"the isosurface of {self.name} ({nx}x{ny}x{nz})"

    # -- what it states before any sample is read -------------------------------------------
    def memory(self, box: Box) -> int:
        """The bytes of a block of ``box`` samples, its part of the mesh aside.

        The samples read (none for an input already in memory), a label's
        indicator, the copy flying edges runs on (converted: 32- and 64-bit
        integers widen to 8 bytes a voxel; or padded for ``cap``) and flying
        edges' working memory.
        """
        per_voxel = 0 if isinstance(self.source, np.ndarray) else self.dtype.itemsize
        dtype = self.dtype
        if self.labels is not None:
            per_voxel += 4 + 1  # the indicator, and its comparison
            dtype = np.dtype(np.float32)
        work = work_dtype(dtype, self.level.cap)
        if self.level.cap or work != dtype:
            per_voxel += work.itemsize
        return int(box.size) * (per_voxel + CHAIN_BYTES_PER_VOXEL)

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """Slabs of whole planes (whole rows read, no halo at the sides) within ``per_task``.

        As deep as a block's samples and part fit (:data:`PART_BYTES_PER_VOXEL`),
        two slabs a worker at least, 8 to 256 planes.
        """
        nz, ny, nx = self.shape
        plane = self.memory(Box((0, 0, 0), (1, ny, nx))) + PART_BYTES_PER_VOXEL * ny * nx
        depth = min(nz, per_task // max(1, plane), 256, -(-nz // (2 * max(1, workers))))
        return (max(8, depth), ny, nx)

    def load(self) -> None:
        """The chain on a small ball: VTK's filters and the kernels (over 100 MiB) count."""
        n = _WARM_SIZE
        z, y, x = np.ogrid[:n, :n, :n]
        inside = (x - n / 2) ** 2 + (y - n / 2) ** 2 + (z - n / 2) ** 2 < (n / 4) ** 2
        up = self.level.inside == "above"
        ball = np.where(inside == up, 1.0, 0.0).astype(np.float32)
        clean(isosurface(Volume(ball), 0.5, inside=self.level.inside, cap=self.level.cap),
              self.cleanup)

    # -- the run -----------------------------------------------------------------------------
    def reduce(self, blocks: Blocks) -> list[Surface]:
        """The surfaces, their passes on ``blocks`` (in memory: the samples read once)."""
        source = self.source
        whole = Box.from_shape(self.shape)
        if blocks.whole:
            with timed(f"read {self.name}"):
                source = np.asarray(source[whole.slices])
        if self.labels is None:
            return [self._surface(source, blocks, self.level, self.name)]
        if self.labels == NONZERO_LABELS:  # (the rule found non-zero labels: one pass less)
            return [self._surface(LabelIndicator(source, None), blocks, LABEL_LEVEL,
                                  f"{self.name}'s non-zero labels")]
        with timed("labels (one pass)"):
            values = label_values(source, blocks.split(whole), _runner(blocks, "labels"),
                                  name=self.name)
        if self.labels != ALL_LABELS:
            if self.labels not in values:
                missing = f"{self.name}: label {self.labels} does not occur in the volume"
                if not self.allow_empty:
                    raise VolwarpError(f"{missing} (--allow-empty writes an empty mesh)")
                log.warning("warning: %s: its surface is empty", missing)
            return [self._surface(LabelIndicator(source, self.labels), blocks, LABEL_LEVEL,
                                  self.name, self.labels)]
        found = [v for v in values if v != 0]
        if not found:
            raise VolwarpError(f"{self.name}: no label other than 0 in the volume")
        if self.to is not None:  # every label's file its own, before any mesh is made
            _distinct_label_files(self.to.path, found)
        log.info("%d labels: %s", len(found), " ".join(map(str, found[:20])))
        # (written label by label, each mesh let go unless kept as asked: the API's)
        return [self._surface(LabelIndicator(source, label), blocks, LABEL_LEVEL,
                              f"{self.name} label {label}", label, keep=self.keep_labels)
                for label in found]

    def _surface(self, source, blocks: Blocks, level: Level, name: str,
                 label: int | None = None, keep: bool = True) -> Surface:
        """One surface of ``source``: checked, made, cleaned up, written, measured."""
        run = _runner(blocks, "mesh")
        boxes = blocks.split(Box.from_shape(self.shape))

        def facts(iso):
            return volume_facts(source, iso, boxes=boxes, threads=blocks.threads, run=run,
                                cap=level.cap, inside=level.inside, count=iso is not None)

        iso = level.iso
        if iso is None:
            with timed("value range"):
                first = facts(None).stats
            check_finite_range(first.lo, first.hi, name)
            iso = 0.5 * (first.lo + first.hi)
            log.info("iso level not given: using the middle of the value range, %g", iso)
        iso = float(iso)
        with timed("whole-volume facts"):
            found = facts(iso)
        lo, hi = found.stats.lo, found.stats.hi
        check_finite_range(lo, hi, name)
        empty = None
        if lo == hi:  # (a label filling the grid said "iso level 0.5 is outside [1, 1]")
            empty = f"every voxel of {name} is {lo:g}: there is no surface at any level"
            mesh = Mesh.empty()
        elif not lo <= iso <= hi:
            empty = f"iso level {iso:g} is outside the data range [{lo:g}, {hi:g}] of {name}"
            mesh = Mesh.empty()
        else:
            _say_level_at_top(found.stats, iso, name)
            self._check_memory(found.vertices(level.cap), blocks, name)
            plan = mesh_plan(found.stats, self.shape, source.dtype, iso, inside=level.inside,
                             cap=level.cap, normals=True)
            with timed("isosurface (flying edges)"):
                parts = mesh_parts(source, plan, blocks.split, threads=blocks.threads, run=run)
            with timed("weld" if len(parts) > 1 else "world coordinates"):
                mesh = welded_mesh(parts, plan, self.grid, inside=level.inside)
            del parts
            if mesh.is_empty:
                empty = f"no surface at level {iso:g} in {name} (the level is never crossed)"
            elif not level.cap and found.border:
                log.warning("the shape touches the volume's border, where its surface is "
                            "open (use --cap to close it)")
        if empty:
            if not self.allow_empty:
                raise VolwarpError(f"{empty}; nothing written (--allow-empty writes an empty "
                                   "mesh)")
            log.warning("%s: the mesh is empty", empty)
        mesh = clean(mesh, self.cleanup)
        log.info("mesh: %d vertices, %d triangles", mesh.n_vertices, mesh.n_faces)
        self._write(mesh, iso, label)
        return Surface(label, iso, mesh if keep else None, self._stats(mesh))

    def _check_memory(self, vertices: int, blocks: Blocks, name: str) -> None:
        """Refuse a mesh of ``vertices`` that would not fit the memory budget, before it is made.

        A surface has about twice as many triangles as vertices, a capped one
        up to 2.2 times: 2.25 are counted. In memory the one block's working
        memory is held beside it (its samples are read: the process holds
        them); by blocks, the blocks in flight and the weld.
        """
        from ..memory import ensure_fits_once_loaded

        steps = [s for s in CLEANUP_BYTES_PER_TRIANGLE if getattr(self.cleanup, s)]
        extra = max((CLEANUP_BYTES_PER_TRIANGLE[s] for s in steps), default=0)
        triangles = (9 * vertices) // 4 + 8
        if blocks.whole:
            whole = Box.from_shape(self.shape)
            read = 0 if isinstance(self.source, np.ndarray) else whole.size * self.dtype.itemsize
            need = self.memory(whole) - read + triangles * (EXTRACT_BYTES_PER_TRIANGLE + extra)
        else:
            need = blocks.in_flight + triangles * (WELD_BYTES_PER_TRIANGLE + extra)
        ensure_fits_once_loaded(need, f"the isosurface of {name} ({vertices} vertices)",
                                self.load if np.prod(self.shape) > _WARM_SIZE ** 3 else None)

    def _write(self, mesh: Mesh, iso: float, label: int | None) -> None:
        """Write ``mesh`` where :attr:`to` says (every label's: its name and its label)."""
        if self.to is None:
            return
        from .mesh_io import write_mesh

        path = self.to.path.format(label=label) if self.labels == ALL_LABELS else self.to.path
        comments = dict(self.to.comments, **surface_keys(self.labels, iso, label))
        with timed(f"write {path}"):
            write_mesh(mesh, path, comments=comments)

    def _stats(self, mesh: Mesh) -> dict | None:
        if not self.stats:
            return None
        from .stats import mesh_stats

        with timed("statistics"):
            return mesh_stats(mesh)


def surface_keys(labels, iso: float, label: int | None) -> dict:
    """The key/values a mesh file records of its surface (``labels`` as :class:`MeshOperation`'s).

    Every label's file, and one label's (``--label N``): its label; else the
    level (to 9 digits), and for the non-zero labels' union that it is a label
    map's surface, not a level of samples.
    """
    if labels == ALL_LABELS:
        return {"volwarp_label": str(label)}
    if labels is not None and labels != NONZERO_LABELS:  # (one label: its file says which)
        return {"volwarp_label": str(int(labels))}
    keys = {"volwarp_iso": f"{iso:.9g}"}
    if labels == NONZERO_LABELS:
        keys["volwarp_values"] = "labels"
    return keys


def _say_level_at_top(stats, iso: float, name: str) -> None:
    """Warn when the level is the samples' largest value: a surface of points, not of a shape.

    The level then crosses only the edges of the samples at that value, so
    the surface wraps them through their centres (a thousandth of a voxel
    off, :func:`.isosurface.level_off`): a 0/1 mask at --iso 1 lost half a
    voxel all round (12% of a 10-voxel ball), a one-voxel one became a speck
    of 4e-9 mm^3, exit 0. ``stats``: the whole volume's at ``iso``.
    """
    if not stats.lo < iso == stats.hi or stats.below_max is None:
        return
    log.warning("warning: --iso %g is the largest sample of %s: its surface wraps the samples "
                "at %g through their centres, not the shape they bound; a level between two "
                "values (e.g. --iso %g) gives that", iso, name, iso,
                0.5 * (stats.below_max + stats.hi))


def _distinct_label_files(pattern: str, labels) -> None:
    """A :class:`BadUsage` where ``pattern`` gives two labels one file (``{label:.1}``)."""
    from ..io.inputs import one_file_twice

    def name(label):
        try:
            return pattern.format(label=label)
        except (ValueError, OverflowError, TypeError, KeyError, IndexError,
                AttributeError) as exc:  # ('{label:c}' beyond Unicode, '{label[0]}')
            raise BadUsage(f"-o: {pattern!r} cannot name label {label}: {exc}") from None

    twice = one_file_twice((label, name(label)) for label in labels)
    if twice is not None:
        raise BadUsage(f"-o: {pattern!r} names labels {twice[0]} and {twice[1]} both "
                       f"{twice[2]}; give each label its own file (e.g. 'seg_{{label}}.ply')")


def _runner(blocks: Blocks, label: str):
    """``run(task, items)`` where ``blocks`` run (an engine's tasks labelled ``label``)."""
    def run(task, items):
        return blocks.map(task, items, label=label)
    return run
