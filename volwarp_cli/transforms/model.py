"""The transforms of a chain, as ITK defines them: each maps a fixed (output) point to a moving one.

Every transform here maps LPS millimetre points, an ``(N, 3)`` float64 array,
from the output (fixed) space to the input (moving) space, as ITK's
``TransformPoint``, ANTs and transformix do: an image is resampled by
sampling the input at ``T(p)`` for each output voxel centre ``p``; points
of the input go the other way, by ``T^-1``.

- :class:`Affine`: ``p -> M p + o`` (every linear ITK transform reduces to
  it: ``M (p - c) + c + t``);
- :class:`BSplineGrid`: ITK's ``BSplineTransform`` (cubic, coefficients on a
  grid), the identity outside its valid region, as ITK;
- :class:`DisplacementField`: ``p -> p + u(p)``, ``u`` linearly interpolated
  in a vector image, zero outside the field's extent (ITK's
  ``DisplacementFieldTransform`` with its default interpolator);
- :class:`Chain`: transforms in the order they act on a point (the first
  listed acts first, as ``antsApplyTransforms -t A -t B``: ``B(A(p))``).

Each states, for a world box of its domain, a world box its images stay in
(:meth:`box`): exact for an affine (the corners), the coefficients' or the
field's range over the box for the others (convex combinations of them);
the executor's blocks read the input region it gives.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..errors import VolwarpError
from .vnl import itk_inverse

#: the edge of the tiles whose extremes bound a field's range over a box
TILE = 16

#: :meth:`DisplacementField.nonfinite` of the fields seen in this process, by token
_NONFINITE: dict = {}

#: the most one window of a field read by windows may hold for :meth:`DisplacementField.map`
#: (points spread wider are mapped a cell of them at a time)
WINDOW_BYTES = 32 << 20


def _affine(p: np.ndarray, m: np.ndarray, o: np.ndarray) -> np.ndarray:
    """``p @ m.T + o`` for points (N, 3), by the kernel (numpy's matmul is slow for 3x3).

    For any count: numpy's matmul rounds otherwise, and a block's parts of
    fewer points then mapped a point a few ULPs off the whole's (a B-spline's
    valid region's edge, a nearest sample's half-way point: other bytes).
    """
    from ._applykernels import affine

    p = np.asarray(p, dtype=np.float64)
    out = np.empty(p.shape)  # (C order, as the kernel writes)
    affine(np.ascontiguousarray(p.reshape(-1, 3)), np.asarray(m, float), np.asarray(o, float),
           out.reshape(-1, 3))
    return out


def _corners(lo, hi) -> np.ndarray:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return np.array([[(lo, hi)[a][0], (lo, hi)[b][1], (lo, hi)[c][2]]
                     for a in (0, 1) for b in (0, 1) for c in (0, 1)])


@dataclass(frozen=True)
class Affine:
    """``p -> matrix @ p + offset`` (LPS mm); ``name``: where it came from, for messages."""

    matrix: np.ndarray
    offset: np.ndarray
    name: str = "affine"

    linear = True

    @classmethod
    def centred(cls, matrix, translation, center, name: str = "affine") -> Affine:
        """ITK's ``MatrixOffsetTransformBase``: ``M (p - c) + c + t``."""
        m = np.asarray(matrix, float).reshape(3, 3)
        c = np.asarray(center, float).reshape(3)
        t = np.asarray(translation, float).reshape(3)
        return cls(m, t + c - m @ c, name)

    @classmethod
    def identity(cls) -> Affine:
        """The identity map."""
        return cls(np.eye(3), np.zeros(3), "identity")

    def map(self, p: np.ndarray) -> np.ndarray:
        """The images of points ``p`` (N, 3)."""
        return _affine(p, self.matrix, self.offset)

    def inverse(self) -> Affine:
        """The inverse map (an error for a singular matrix)."""
        if abs(np.linalg.det(self.matrix)) < 1e-12 * max(1.0, np.abs(self.matrix).max()) ** 3:
            raise VolwarpError(f"{self.name}: its matrix is singular: it has no inverse")
        inv = np.linalg.inv(self.matrix)
        return Affine(inv, -inv @ self.offset, f"the inverse of {self.name}")

    def then(self, other: Affine) -> Affine:
        """``other(self(p))`` as one affine."""
        return Affine(other.matrix @ self.matrix, other.matrix @ self.offset + other.offset,
                      other.name)

    def box(self, lo, hi):
        """The world box the images of box ``[lo, hi]`` lie in (its corners': exact)."""
        pts = self.map(_corners(lo, hi))
        return pts.min(axis=0), pts.max(axis=0)


@dataclass(frozen=True)
class GridFrame:
    """A grid's frame: ``world = origin + direction @ (spacing * index)``, index (x, y, z)."""

    size: tuple[int, int, int]  # (x, y, z)
    origin: np.ndarray
    spacing: np.ndarray
    direction: np.ndarray

    @property
    def matrix(self) -> np.ndarray:
        """Index steps (x, y, z) to world vectors."""
        return np.asarray(self.direction, float) * np.asarray(self.spacing, float)[None, :]

    @cached_property
    def inverse_matrix(self) -> np.ndarray:
        """World vectors to index steps: ITK's inverse, to its last bit (:mod:`.vnl`)."""
        return itk_inverse(self.matrix)

    def to_index(self, p: np.ndarray) -> np.ndarray:
        """Continuous indices (x, y, z) of world points, as ITK's images compute them.

        ``inverse_matrix @ (p - origin)`` in ITK's order of operations
        (``TransformPhysicalPointToContinuousIndex``): a point on an edge of
        a B-spline's valid region in exact arithmetic (ANTs' grids put the
        fixed image's first voxels there) is then inside or outside as in ITK.
        """
        from ._applykernels import affine_about

        flat = np.ascontiguousarray(p, dtype=np.float64).reshape(-1, 3)
        idx = np.empty_like(flat)  # (one pass: a subtraction first took twice the time)
        affine_about(flat, self.inverse_matrix, np.asarray(self.origin, float), idx)
        return idx.reshape(np.shape(p))

    def index_box(self, lo, hi) -> tuple[np.ndarray, np.ndarray]:
        """The continuous index box of world box ``[lo, hi]``."""
        idx = self.to_index(_corners(lo, hi))
        return idx.min(axis=0), idx.max(axis=0)


def _range_over(values: np.ndarray, frame: GridFrame, lo, hi, *, grow: int, inside_lo: float,
                inside_hi_less: float):
    """The min and max vector of ``values`` (z, y, x, 3) over the index box of world ``[lo, hi]``.

    ``grow``: indices added on each side (the interpolation's support);
    the zero vector is included where the box reaches beyond the valid index
    range ``[inside_lo, n - 1 - inside_hi_less]`` (the transform is the
    identity there). None: the box misses the grid (only zero).
    """
    ilo, ihi = frame.index_box(lo, hi)
    n = np.asarray(frame.size)
    outside = bool(np.any(ilo < inside_lo) or np.any(ihi > n - 1 - inside_hi_less))
    a = np.clip(np.floor(ilo).astype(np.int64) - grow, 0, n - 1)
    b = np.clip(np.ceil(ihi).astype(np.int64) + grow, 0, n - 1)
    if np.any(ihi < -0.5 - grow) or np.any(ilo > n - 0.5 + grow):
        return np.zeros(3), np.zeros(3)
    sub = values[a[2]:b[2] + 1, a[1]:b[1] + 1, a[0]:b[0] + 1].reshape(-1, 3)
    vmin = np.nanmin(sub, axis=0).astype(float)
    vmax = np.nanmax(sub, axis=0).astype(float)
    if outside:
        vmin, vmax = np.minimum(vmin, 0.0), np.maximum(vmax, 0.0)
    return vmin, vmax


@dataclass(frozen=True, eq=False)
class DisplacementField:
    """``p -> p + u(p)``: ``u`` (z, y, x, 3) LPS mm on ``frame``, linear, zero outside.

    As ITK's ``DisplacementFieldTransform``: inside the field's buffer (a
    continuous index within ``[-0.5, n - 0.5)`` on each axis) ``u`` is the
    trilinear interpolation of the vectors, the neighbours beyond the last
    sample clamped to it; elsewhere the point is not moved.

    ``vectors``: the samples (any float type and strides), or None with
    ``source``, a field read by windows (:class:`.fields.LazyField`: a field
    larger than memory); ``offset``: the grid index (x, y, z) of
    ``vectors[0, 0, 0]`` for a window (:meth:`window`), whose points are
    mapped exactly as by the whole field (the indices are the whole grid's).
    ``nifti``: read from a NIfTI file, whose NaN vectors ITK reads as 0 (said
    where points reach them).
    """

    frame: GridFrame
    vectors: np.ndarray | None
    name: str = "displacement field"
    source: object = None
    offset: tuple = (0, 0, 0)
    nifti: bool = False
    #: this field's identity across pickled copies (a block in a worker process gets one):
    #: its NaN count is computed once per process (:meth:`nonfinite`)
    token: str = field(default_factory=lambda: os.urandom(8).hex())

    linear = False

    @property
    def itemsize(self) -> int:
        """Bytes of one component of a vector."""
        v = self.vectors if self.vectors is not None else self.source
        return int(np.dtype(v.dtype).itemsize)

    def displacement(self, p: np.ndarray) -> np.ndarray:
        """``u(p)`` for points ``p`` (N, 3), float64."""
        p = np.ascontiguousarray(p, dtype=np.float64)
        return self.map(p) - p

    def map(self, p: np.ndarray) -> np.ndarray:
        """The images of points ``p`` (N, 3).

        A field read by windows reads the window of the points' box, or,
        where that would exceed :data:`WINDOW_BYTES` (points spread over a
        large field), one window per cell of :data:`TILE` voxels that holds
        points.
        """
        p = np.ascontiguousarray(p, dtype=np.float64)
        out = np.empty_like(p)
        if self.vectors is not None:
            first = self._map_into(self, p, out)
        else:
            lo, hi = _bounds(p)
            if self.window_bytes(lo, hi) <= WINDOW_BYTES:
                first = self._map_into(self.window(lo, hi), p, out)
            else:
                first = self._map_by_cells(p, out)
        if first >= 0:
            self._warn_not_finite(p[first])
        return out

    def add_nodes(self, grid: Affine, lo, hi, p: np.ndarray) -> bool:
        """``p += u`` for the points of index box ``[lo, hi)`` (x, y, z) of ``grid`` where they are nodes.

        ``grid``: a grid's index -> world map, ``p`` (N, 3) its points of the
        box, x fastest. When ``grid``'s voxels are this field's own nodes (the
        same axes and spacing, the origin a whole number of voxels away: ANTs'
        ``1Warp.nii.gz`` applied on its fixed image's grid), the trilinear
        weights are 0 and 1 and the displacement is the node's vector: added
        without interpolation (ITK adds the neighbours of non-zero weight only);
        the box's points off the field (a whole voxel or more beyond it) are not
        moved, as ITK's rule has it. The kernel's interpolation there gives the
        same bits where its indices are whole, else differs by rounding (1e-13
        mm): so every block takes this way, whether it lies on the field or
        not (a block across the field's edge interpolated, and the blocks' bytes
        were not the whole's). False (``p`` untouched): not so, ``p`` not
        contiguous, or the box's part on the field beyond this window; map
        through :meth:`map`. A non-finite vector moves its point to NaN or
        infinity, outside every image, said as :meth:`map` says it.
        """
        shift = self._node_shift(grid)
        if shift is None or self.vectors is None or not p.flags.c_contiguous:
            return False
        lo, hi = np.asarray(lo, np.int64), np.asarray(hi, np.int64)
        a = np.maximum(lo + shift, 0)  # (the box's part on the field, its indices)
        b = np.minimum(hi + shift, np.asarray(self.frame.size, np.int64))
        if np.any(b <= a):
            return True  # (no point on the field: none moved)
        wa, wb = a - np.asarray(self.offset, np.int64), b - np.asarray(self.offset, np.int64)
        if np.any(wa < 0) or np.any(wb > np.array(self.vectors.shape[2::-1])):
            return False
        u = self.vectors[wa[2]:wb[2], wa[1]:wb[1], wa[0]:wb[0]]
        c, d = a - shift - lo, b - shift - lo  # (within the box)
        view = p.reshape(*(hi - lo)[::-1], 3)[c[2]:d[2], c[1]:d[1], c[0]:d[0]]
        np.add(view, u, out=view)
        finite = np.isfinite(p)
        if not finite.all():
            k = int(np.flatnonzero(~finite.all(axis=1))[0])
            nx, ny = int(hi[0]) - int(lo[0]), int(hi[1]) - int(lo[1])
            index = np.asarray(lo, float) + [k % nx, k // nx % ny, k // (nx * ny)]
            self._warn_not_finite(grid.map(index[None])[0])
        return True

    def _node_shift(self, grid: Affine) -> np.ndarray | None:
        """The field index minus ``grid``'s index of the same point, where whole (else None).

        Within 1e-12 of the identity for the axes and 1e-9 voxel of a whole
        number for the shift: a displacement interpolated that near a node
        differs from the node's by less than float32 resolves.
        """
        key = (grid.matrix.tobytes(), grid.offset.tobytes())
        known = self.__dict__.get("_shift_of")
        if known is not None and known[0] == key:
            return known[1]
        inv = self.frame.inverse_matrix
        m = inv @ np.asarray(grid.matrix, float)
        b = inv @ (np.asarray(grid.offset, float) - np.asarray(self.frame.origin, float))
        whole = np.rint(b)
        shift = (whole.astype(np.int64) if np.all(np.abs(m - np.eye(3)) <= 1e-12)
                 and np.all(np.abs(b - whole) <= 1e-9) else None)
        object.__setattr__(self, "_shift_of", (key, shift))
        return shift

    def _map_into(self, field: DisplacementField, p: np.ndarray, out: np.ndarray) -> int:
        """``field`` (this one or a window of it) maps ``p`` into ``out``: the first non-finite, or -1."""
        from ._applykernels import field_map

        return field_map(field.vectors, p, self.frame.inverse_matrix,
                         np.asarray(self.frame.origin, float), np.asarray(field.offset, np.int64),
                         np.asarray(self.frame.size, np.int64), out)

    def _map_by_cells(self, p: np.ndarray, out: np.ndarray) -> int:
        """:meth:`map` of points spread over a field read by windows: a window per cell of points.

        Points outside the field are not moved (no vector is read for them);
        those inside go a :data:`TILE`-voxel cell at a time, each cell's window
        its points' index box grown by one voxel (as :meth:`_window_box`).
        """
        idx, inside = self._inside(p)
        first = -1
        rest = np.flatnonzero(~inside)
        if rest.size:  # (the kernel finds them outside and reads nothing: any window)
            one = self._window_at(np.zeros(3, np.int64), np.ones(3, np.int64))
            part = np.empty((rest.size, 3))
            bad = self._map_into(one, p[rest], part)
            out[rest] = part
            first = int(rest[bad]) if bad >= 0 else -1
        for pick in self._cells_of(idx, np.flatnonzero(inside)):
            window = self._index_window(idx[pick].min(axis=0), idx[pick].max(axis=0))
            part = np.empty((len(pick), 3))
            bad = self._map_into(self._window_at(*window), p[pick], part)
            out[pick] = part
            if bad >= 0 and (first < 0 or pick[bad] < first):
                first = int(pick[bad])
        return first

    def _inside(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The continuous indices (x, y, z) of points ``p`` and whether each is on the field."""
        n = np.asarray(self.frame.size, np.int64)
        idx = self.frame.to_index(p)
        with np.errstate(invalid="ignore"):  # (NaN points: outside)
            inside = np.all((idx >= -0.5 - 1e-6) & (idx < n - 0.5 + 1e-6), axis=1)
        return idx, inside

    def _cells_of(self, idx: np.ndarray, pick: np.ndarray) -> list[np.ndarray]:
        """The points ``pick`` (on the field; ``idx`` their indices) grouped by :data:`TILE` cell."""
        if not pick.size:
            return []
        cells = -(-np.asarray(self.frame.size, np.int64) // TILE)
        cell = np.clip(np.floor(idx[pick] / TILE), 0, cells - 1).astype(np.int64)
        key = (cell[:, 2] * cells[1] + cell[:, 1]) * cells[0] + cell[:, 0]
        order = pick[np.argsort(key, kind="stable")]
        starts = np.flatnonzero(np.diff(np.sort(key, kind="stable"), prepend=-1))
        return [order[a:b] for a, b in zip(starts, [*starts[1:], len(order)], strict=True)]

    def _warn_not_finite(self, point) -> None:
        """Say, once per field and run, that points reach its NaN (or infinite) vectors.

        Such a point maps to NaN, outside every image, as in ITK: its output
        voxel takes the background value, a moved point is NaN. volwarp's own
        exports mark so where a warp has no preimage or folds; ITK says
        nothing, here the count and index box of those vectors and a point
        that reached them are said. ITK's NIfTI reader, though, reads NaN as 0
        (no move): for a NIfTI field, that ITK and ANTs differ there is said.
        """
        from ..progress import log
        from ..runscope import run_files

        key = ("not finite", self.name)  # (a block in a worker process: said by the command)
        said = run_files().said
        if key in said:
            return
        said.add(key)
        count, lo, hi = self.nonfinite()
        where = ", ".join(f"{a} {p}" if p == q else f"{a} {p}..{q}"
                          for a, p, q in zip("xyz", lo, hi, strict=True))
        total = math.prod(self.frame.size)
        at = ", ".join(f"{v:.4g}" for v in point)
        peers = ("; ITK and ANTs, reading NaN in a NIfTI file as 0 (no move), differ there"
                 if self.nifti else ", as in ITK")
        log.warning("warning: %s: %d of its %d vectors are NaN or infinite (at indices %s) and "
                    "points mapped through it reach them (the first at LPS %s mm): they map "
                    "outside the input (their voxels take the background value, moved points "
                    "are NaN)%s; fill the vectors (0 is no displacement) to move them "
                    "instead", self.name, count, total, where, at, peers, extra={"once": key})

    def nonfinite(self) -> tuple[int, tuple, tuple]:
        """The count of vectors with a NaN or infinite component and their index box (x, y, z).

        Read slab by slab (a field read by windows is never whole in memory);
        once per process (block tasks in a worker process share it).
        """
        known = _NONFINITE.get(self.token)
        if known is None:
            known = _NONFINITE[self.token] = self._nonfinite()
            while len(_NONFINITE) > 64:  # (a long-lived worker: the oldest go)
                _NONFINITE.pop(next(iter(_NONFINITE)))
        return known

    def _nonfinite(self) -> tuple[int, tuple, tuple]:
        nx, ny, nz = self.frame.size
        count, lo, hi = 0, [nx, ny, nz], [-1, -1, -1]
        for z0 in range(0, nz, TILE):
            z1 = min(nz, z0 + TILE)
            slab = (self.vectors[z0:z1] if self.vectors is not None
                    else self.source.read((z0, 0, 0), (z1, ny, nx)))
            bad = ~np.isfinite(slab).all(axis=-1)
            if not bad.any():
                continue
            count += int(bad.sum())
            for axis, where in zip((2, 1, 0), np.nonzero(bad)[::-1], strict=True):
                shift = z0 if axis == 0 else 0
                lo[2 - axis] = min(lo[2 - axis], int(where.min()) + shift)
                hi[2 - axis] = max(hi[2 - axis], int(where.max()) + shift)
        return count, tuple(lo), tuple(hi)

    def _window_box(self, lo, hi) -> tuple[np.ndarray, np.ndarray]:
        """The grid indices ``[a, b)`` (x, y, z) :meth:`window` reads for world box ``[lo, hi]``.

        The index box grown by one voxel (the neighbours and the rounding of
        the kernels' own mapping), clipped to the grid; one voxel when the
        box misses it.
        """
        return self._index_window(*self.frame.index_box(lo, hi))

    def _index_window(self, ilo, ihi) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`_window_box` of the continuous index box ``[ilo, ihi]`` (x, y, z)."""
        n = np.asarray(self.frame.size)
        a = np.clip(np.floor(ilo).astype(np.int64) - 1, 0, n - 1)
        b = np.clip(np.ceil(ihi).astype(np.int64) + 2, 1, n)
        if np.any(b <= a):
            a, b = np.zeros(3, np.int64), np.ones(3, np.int64)
        return a, b

    def window(self, lo, hi) -> DisplacementField:
        """The field for points in world box ``[lo, hi]`` only: its vectors there read.

        The field itself when its vectors are in memory.
        """
        if self.vectors is not None:
            return self
        return self._window_at(*self._window_box(lo, hi))

    def _window_at(self, a, b) -> DisplacementField:
        """The field's vectors of grid index box ``[a, b)`` (x, y, z), read."""
        vectors = self.source.read((int(a[2]), int(a[1]), int(a[0])),
                                   (int(b[2]), int(b[1]), int(b[0])))
        return DisplacementField(self.frame, vectors, self.name,
                                 offset=tuple(int(v) for v in a), nifti=self.nifti)

    def window_bytes(self, lo, hi) -> int:
        """The bytes :meth:`window` reads for world box ``[lo, hi]`` (0 when in memory)."""
        if self.vectors is not None:
            return 0
        a, b = self._window_box(lo, hi)
        return int(np.prod(b - a)) * 3 * self.itemsize * 2

    def box(self, lo, hi):
        """``[lo, hi]`` grown by the field's range over it (zero included beyond its extent).

        The range of the tiles of :data:`TILE` voxels the box's index box
        (grown by one) meets: a bound made from per-tile extremes computed
        once, so that a block's bound costs no pass over the field.
        """
        tmin, tmax = self._tiles()
        ilo, ihi = self.frame.index_box(lo, hi)
        n = np.asarray(self.frame.size)
        if np.any(ihi < -1.5) or np.any(ilo > n + 0.5):
            return np.asarray(lo, float), np.asarray(hi, float)
        a = np.clip(np.floor(ilo).astype(np.int64) - 1, 0, n - 1) // TILE
        b = np.clip(np.ceil(ihi).astype(np.int64) + 1, 0, n - 1) // TILE
        vmin = np.fmin.reduce(tmin[a[2]:b[2] + 1, a[1]:b[1] + 1, a[0]:b[0] + 1].reshape(-1, 3))
        vmax = np.fmax.reduce(tmax[a[2]:b[2] + 1, a[1]:b[1] + 1, a[0]:b[0] + 1].reshape(-1, 3))
        if np.any(ilo < -0.5) or np.any(ihi > n - 0.5):  # unmoved beyond the extent
            vmin, vmax = np.minimum(vmin, 0.0), np.maximum(vmax, 0.0)
        vmin = np.where(np.isfinite(vmin), vmin, 0.0)  # (tiles of NaN only: no value)
        vmax = np.where(np.isfinite(vmax), vmax, 0.0)
        return np.asarray(lo) + vmin, np.asarray(hi) + vmax

    def _tiles(self):
        cached = self.__dict__.get("_tile_range")
        if cached is None:
            if self.vectors is None:
                cached = self.source.tile_range(TILE)
            else:
                cached = tile_range(self.vectors, TILE)
            object.__setattr__(self, "_tile_range", cached)
        return cached


def tile_range(vectors: np.ndarray, tile: int):
    """Per-tile min and max vectors (float64) of ``vectors`` (z, y, x, 3), NaN skipped.

    (A folded field's holes are NaN; a tile of NaN only has NaN extremes.)
    """
    from .. import parallel
    from ._applykernels import tile_range as kernel

    shape = tuple(-(-n // tile) for n in vectors.shape[:3]) + (3,)
    tmin, tmax = np.full(shape, np.nan), np.full(shape, np.nan)

    def rows(a, b):  # tile rows a..b (z) on one thread
        kernel(vectors[a * tile:b * tile], tile, tmin[a:b], tmax[a:b])

    parallel.run_ranges(rows, shape[0])
    return tmin, tmax


def _bounds(p: np.ndarray):
    """The world box of points ``p`` (N, 3), NaN skipped (a point box when none)."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
    if not len(p):
        return np.zeros(3), np.zeros(3)
    with np.errstate(invalid="ignore"):
        lo, hi = np.fmin.reduce(p, axis=0), np.fmax.reduce(p, axis=0)
    if not np.all(np.isfinite(lo + hi)):
        return np.zeros(3), np.zeros(3)
    return lo, hi


@dataclass(frozen=True, eq=False)
class BSplineGrid:
    """ITK's ``BSplineTransform`` (order 3): ``p -> p + sum_k B(u - k) c_k`` in its valid region.

    ``coefficients`` (z, y, x, 3) LPS mm on the control grid ``frame`` (ITK's
    FixedParameters: size, origin, spacing, direction). As ITK, a point whose
    continuous grid index ``u`` is outside ``[1, n - 2)`` on some axis (its
    support would leave the grid) is not moved, except on the far face
    ``u = n - 2`` (``far_face``, :func:`_onto_far_face`): ITK's
    ``InsideValidRegion`` takes it as inside; elastix's B-spline and ITK's
    older ``BSplineDeformableTransform`` do not. The grid indices are ITK's
    to the bit (:meth:`GridFrame.to_index`), so that a point on an edge in
    exact arithmetic is moved where ITK moves it.
    """

    frame: GridFrame
    coefficients: np.ndarray
    name: str = "B-spline transform"
    far_face: bool = True

    linear = False

    def displacement(self, p: np.ndarray) -> np.ndarray:
        """The displacement at points ``p`` (N, 3), float64."""
        from ._applykernels import bspline_cubic

        idx = self.frame.to_index(p)
        if self.far_face:
            _onto_far_face(idx, self.frame.size)
        out = np.empty_like(idx)
        bspline_cubic(np.ascontiguousarray(self.coefficients, dtype=np.float64), idx, out)
        return out

    def map(self, p: np.ndarray) -> np.ndarray:
        """The images of points ``p`` (N, 3)."""
        return p + self.displacement(p)

    def box(self, lo, hi):
        """``[lo, hi]`` grown by the range of the coefficients whose support reaches it."""
        vmin, vmax = _range_over(self.coefficients, self.frame, lo, hi, grow=2, inside_lo=1.0,
                                 inside_hi_less=1.0)
        return np.asarray(lo) + vmin, np.asarray(hi) + vmax


#: ITK's ``InsideValidRegion``: an index this many ULPs from the far face is on it...
FAR_FACE_ULPS = 4
#: ...and is taken this many ULPs below it (``FloatAddULP(maxLimit, -6)``)
FAR_FACE_BELOW = 6


def _onto_far_face(idx: np.ndarray, size) -> None:
    """Indices ``idx`` (N, 3) on the far face ``n - 2`` of the valid region moved just inside it.

    ITK's ``BSplineTransform::InsideValidRegion`` takes an index within 4
    ULPs of ``n - 2`` (``FloatAlmostEqual``) as the index 6 ULPs below it
    (the last 4 coefficients: the spline's limit there), not as outside. A
    grid placed as ANTs places it (``SetTransformDomain*`` from the fixed
    image's first voxel centre to its last) puts the fixed grid's last
    voxels of each axis there: they were left unmoved where ITK moves them.
    The indices are ITK's own (:meth:`GridFrame.to_index`), so ITK's rule
    to the ULP: a looser one moved points ITK leaves.
    """
    hi = np.asarray(size, float) - 2.0  # (>= 2: positive, so ULPs are the bits' distance)
    bits = idx.view(np.int64)
    hi_bits = hi.view(np.int64)
    near = np.abs(bits - hi_bits) <= FAR_FACE_ULPS
    near &= idx > 0  # (a negative index's bits are not near: FloatAlmostEqual's sign test)
    if near.any():
        inside = (hi_bits - FAR_FACE_BELOW).view(np.float64)
        np.copyto(idx, np.broadcast_to(inside, idx.shape), where=near)


@dataclass(frozen=True)
class Inverted:
    """Where points of the input land: the images, the residuals, and the points not solved."""

    points: np.ndarray
    residual: np.ndarray  # |T(q) - p| in mm, per point
    unsolved: np.ndarray  # indices of the points whose residual exceeds the tolerance


#: Newton's stopping residual and the accepted one (mm) for inverting non-linear transforms
SOLVE_TOL = 1e-9
SOLVE_ACCEPT = 1e-3
SOLVE_ITERATIONS = 50


@dataclass
class Chain:
    """Transforms in the order they act on an output point (``steps[0]`` first).

    ``grid``: the output grid the first file states, where it states one
    (an elastix parameter file's fixed grid, transformix's output), else
    None; ``notes``: what the files say that volwarp does not follow (said
    to the user).
    """

    steps: list = field(default_factory=list)
    grid: object = None
    notes: list = field(default_factory=list)

    @property
    def linear(self) -> bool:
        """Whether every step is affine."""
        return all(s.linear for s in self.steps)

    def affine(self) -> Affine:
        """The whole chain as one affine (only for a linear chain)."""
        out = Affine.identity()
        for s in self.steps:
            if not s.linear:
                raise VolwarpError(f"{s.name} is not linear")
            out = out.then(s)
        return out

    def simplified(self) -> list:
        """The steps, consecutive affines merged into one (the same map, fewer passes)."""
        out: list = []
        for s in self.steps:
            if s.linear and out and out[-1].linear:
                out[-1] = out[-1].then(s)
            else:
                out.append(s)
        return out

    def map(self, p: np.ndarray) -> np.ndarray:
        """``T(p)``: the input (moving) points sampled for output (fixed) points ``p`` (N, 3)."""
        for s in self.steps:
            p = s.map(p)
        return p

    def invert_points(self, p: np.ndarray) -> Inverted:
        """Points ``q`` with ``T(q) = p``: where input points ``p`` go in the output space.

        Step by step from the last: an affine's inverse exactly, a
        non-linear step's by Newton's method (the Jacobian by central
        differences) from ``q = p - u(p)``.
        """
        p = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        q = p.copy()
        for s in reversed(self.simplified()):
            q = s.inverse().map(q) if s.linear else _solve(s, q)
        residual = np.linalg.norm(self.map(q) - p, axis=1) if len(p) else np.zeros(0)
        given = np.isfinite(p).all(axis=1)  # (a point without a position: none to solve)
        bad = np.flatnonzero(~(residual <= SOLVE_ACCEPT) & given)
        q[bad] = np.nan  # (Newton's last guess is no answer: up to several mm off)
        q[~given] = np.nan
        return Inverted(q, residual, bad)


def _solve(step, target: np.ndarray) -> np.ndarray:
    """``q`` with ``q + u(q) = target`` for a non-linear ``step`` (Newton, vectorised).

    A field read by windows is read once for the solve: one window for the
    points, or, where that would exceed :data:`WINDOW_BYTES`, one for each
    half of them (split at the median of their widest axis, again until a
    window fits): each iteration maps the points several times, and through
    the field itself each map would read their cells again. The windows give
    the field's own values (:class:`_Window`), so the points solved are those
    of the field held whole.
    """
    if getattr(step, "vectors", 0) is not None:
        return _newton(step, target)
    q = target.copy()  # (points off the field: not moved, their own solution)
    idx, inside = step._inside(target)
    groups = [np.flatnonzero(inside)]
    while groups:
        pick = groups.pop()
        if not pick.size:
            continue
        window = _Window.around(step, target[pick])
        spread = np.ptp(idx[pick], axis=0)
        if window is None and spread.max() > 0:  # (halves: each with a smaller window)
            order = pick[np.argsort(idx[pick, int(np.argmax(spread))], kind="stable")]
            groups += [order[:len(order) // 2], order[len(order) // 2:]]
            continue
        q[pick] = _newton(step if window is None else window, target[pick])
    return q


class _Window:
    """A field read by windows, mapped through one window read once, exactly.

    A point whose neighbours lie in the window is mapped through it (the
    same bits as the whole field: the kernel reads the same vectors); one
    whose neighbours leave it (a Newton step or a halving trial going far)
    through the field itself. The window: the points' box grown by the
    field's range over it (:meth:`DisplacementField.box`, per-tile extremes)
    and one millimetre.
    """

    def __init__(self, field: DisplacementField, window: DisplacementField):
        self.field, self.window = field, window
        self.lo = np.asarray(window.offset, np.int64)
        self.hi = self.lo + np.asarray(window.vectors.shape[2::-1], np.int64)

    @classmethod
    def around(cls, field: DisplacementField, points: np.ndarray):
        """The window for ``points``, or None where it would exceed :data:`WINDOW_BYTES`."""
        lo, hi = _bounds(points)
        blo, bhi = field.box(lo, hi)
        grow = np.maximum(lo - blo, bhi - hi) + 1.0  # (q = target - u(q): either way)
        if field.window_bytes(lo - grow, hi + grow) > WINDOW_BYTES:
            return None
        return cls(field, field.window(lo - grow, hi + grow))

    def map(self, p: np.ndarray) -> np.ndarray:
        p = np.ascontiguousarray(p, dtype=np.float64)
        idx, inside = self.field._inside(p)
        n = np.asarray(self.field.frame.size, np.int64)
        with np.errstate(invalid="ignore"):
            below = np.clip(np.floor(idx), 0, n - 1)  # (the kernel's neighbours: b0, b1)
            above = np.clip(np.floor(idx) + 1, 0, n - 1)
            held = np.all((below >= self.lo) & (above < self.hi), axis=1)
        near = held | ~inside  # (off the field: not moved, any window says so)
        if near.all():
            return self.window.map(p)
        out = np.empty_like(p)
        out[near] = self.window.map(p[near])
        out[~near] = self.field.map(p[~near])
        return out

    def displacement(self, p: np.ndarray) -> np.ndarray:
        p = np.ascontiguousarray(p, dtype=np.float64)
        return self.map(p) - p


def _newton(step, target: np.ndarray) -> np.ndarray:
    """:func:`_solve`'s Newton iterations through ``step`` (a field: in memory or a window).

    The Jacobian by central differences; a step that does not lower the
    residual is halved (up to 6 times: a field's cell edges and its border
    make the Jacobian jump).
    """
    q = target - step.displacement(target)
    lost = np.flatnonzero(~np.isfinite(q).all(axis=1) & np.isfinite(target).all(axis=1))
    if lost.size:  # (each over a NaN part of the field: a start from finite vectors near it)
        q[lost] = _finite_start(step, target[lost])
    h = 1e-4
    active = np.arange(len(target))
    images = step.map(q)  # (of the active points' guesses: each step's map is the next's)
    for _ in range(SOLVE_ITERATIONS):
        if not active.size:
            break
        qa, ta = q[active], target[active]
        r = images - ta
        norm = np.linalg.norm(r, axis=1)
        done = norm <= SOLVE_TOL
        active, qa, ta, r, norm, images = (active[~done], qa[~done], ta[~done], r[~done],
                                           norm[~done], images[~done])
        if not active.size:
            break
        jac = np.empty((len(qa), 3, 3))
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            jac[:, :, k] = (step.map(qa + e) - step.map(qa - e)) / (2 * h)
        try:
            dq = np.linalg.solve(jac, r[..., None])[..., 0]
        except np.linalg.LinAlgError:
            dq = r
        dq = np.where(np.isfinite(dq), dq, r)
        scale = np.ones(len(qa))
        for _ in range(6):
            trial = qa - dq * scale[:, None]
            worse = ~(np.linalg.norm(step.map(trial) - ta, axis=1) <= norm)  # (NaN: worse)
            if not worse.any():
                break
            scale[worse] *= 0.5
        step_to = qa - dq * scale[:, None]
        moved = step.map(step_to)
        # (a step onto NaN vectors is not taken: the point stays where the field is finite)
        taken = np.isfinite(moved).all(axis=1)[:, None]
        q[active] = np.where(taken, step_to, qa)
        images = np.where(taken, moved, images)
    return q


#: how far (mm) :func:`_finite_start` looks around a point for finite vectors
START_RADII = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)
_DIRECTIONS = np.array([(x, y, z) for z in (-1, 0, 1) for y in (-1, 0, 1) for x in (-1, 0, 1)
                        if (x, y, z) != (0, 0, 0)], float)
_DIRECTIONS /= np.linalg.norm(_DIRECTIONS, axis=1)[:, None]


def _finite_start(step, target: np.ndarray) -> np.ndarray:
    """Newton's start for points over NaN vectors: a point near them that maps to finite.

    A point of the input near its border lies, taken as an output point, in
    the margin where a volwarp export's field is NaN (no preimage), though its
    own image has finite vectors: ``target - u(target)`` is NaN and Newton
    never left it. Probes ``s`` in 26 directions on growing spheres
    (:data:`START_RADII`), and their fixed-point steps ``target - u(s)``: of
    those on the first sphere that lie on the field (beyond it every point is
    its own image) and map to finite points, the one mapped nearest
    ``target``. A point with none keeps NaN (it is not solved).
    """
    field = step.field if isinstance(step, _Window) else step
    start = np.full_like(target, np.nan)
    left = np.arange(len(target))
    for radius in START_RADII:
        if not left.size:
            break
        probes = target[left, None, :] + radius * _DIRECTIONS[None]  # (points, 26, 3)
        steps = target[left, None, :] - step.displacement(
            probes.reshape(-1, 3)).reshape(probes.shape)
        tried = np.concatenate([probes, steps], axis=1)  # (points, 52, 3)
        with np.errstate(invalid="ignore"):
            miss = np.linalg.norm(step.map(tried.reshape(-1, 3)).reshape(tried.shape)
                                  - target[left, None, :], axis=2)
        on = field._inside(tried.reshape(-1, 3))[1].reshape(miss.shape)  # (off it: unmoved)
        miss = np.where(np.isfinite(miss) & on, miss, np.inf)
        best = np.argmin(miss, axis=1)
        found = np.isfinite(miss[np.arange(len(left)), best])
        start[left[found]] = tried[found, best[found]]
        left = left[~found]
    return start


def check_dimension(name: str, dims: int, where: str) -> None:
    """A 2-D (or other) transform for a 3-D image: one error naming the file."""
    if dims != 3:
        raise VolwarpError(f"{where}: {name} is a {dims}-D transform; the images are 3-D")


def grid_frame(size, origin, spacing, direction, where: str) -> GridFrame:
    """A checked :class:`GridFrame` (sizes positive, spacing positive, direction invertible)."""
    size = tuple(int(round(float(v))) for v in size)
    spacing = np.asarray(spacing, float).reshape(3)
    direction = np.asarray(direction, float).reshape(3, 3)
    origin = np.asarray(origin, float).reshape(3)
    if (min(size) < 1 or not np.all(spacing > 0) or not np.all(np.isfinite(origin))
            or not np.isfinite(direction).all()
            or abs(np.linalg.det(direction)) < 1e-6 or not math.isfinite(spacing.sum())):
        raise VolwarpError(f"{where}: the transform's grid is not valid (size {size}, spacing "
                           f"{spacing.tolist()}, direction {direction.ravel().tolist()})")
    return GridFrame(size, origin, spacing, direction)
