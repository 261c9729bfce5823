"""The deformation of a warp, exported: fields, Jacobian, ITK transform, points, meshes.

volwarp's native object is the forward (modelling) map ``F: input -> output``.
With the uniform placement the capture map is the affine base map, so in
input voxel indices ``F(x) = x + sum_i B_i(s(x)) dq_i`` with the spline
parameter ``s(x) = (x - grid.origin) / h`` (see :mod:`volwarp_cli.bspline.lattice`), defined on
the lattice's support ``s in [0, R]^3``. The input's ``index_to_world`` is
affine (``p = O + M x``, ``M = direction * spacing``), so in LPS millimetres
``F_w(p) = p + sum_i B_i(...) (M dq_i)``: a uniform cubic B-spline on a grid
with origin ``O + M (grid.origin - h)``, spacing ``spacing * h`` and the
input's direction, which is exactly ITK's ``BSplineTransform`` layout.

Exports:

- :meth:`ForwardMap.forward_field`: ``x -> F(x) - x`` on the input grid (world mm);
- :meth:`ForwardMap.jacobian`: ``det dF/dx`` on the input grid (the same in
  voxels and in world coordinates);
- :meth:`ForwardMap.resampling_field`: ``y -> F^-1(y) - y`` on an output
  grid, by Newton's method per voxel (vectorised), NaN where none is found or
  the map folds;
- :func:`write_tfm`: the forward map as ITK ``BSplineTransform_double_3_3``;
- :meth:`ForwardMap.map_world`: points (points files, mesh vertices).
"""

from __future__ import annotations

import csv
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..bspline.basis import basis, basis_derivative
from ..bspline.evaluate import LatticeSpline
from ..bspline.lattice import Lattice
from ..errors import VolwarpError
from ..progress import log
from ..volume import LPS, Header

#: Newton's stopping residual for the inverse (input voxels) and the accepted one
INVERSE_TOL = 1e-8
INVERSE_ACCEPT = 1e-3
INVERSE_ITERATIONS = 40
#: points evaluated at a time (bounds the scratch memory to a few tens of MB)
CHUNK = 1 << 17

FIELD_EXTENSIONS = (".nii.gz", ".nii", ".nrrd")


def field_format(path: str) -> str:
    """``nifti`` or ``nrrd`` for a displacement field output, else a VolwarpError."""
    name = str(path).lower()
    if name.endswith((".nii.gz", ".nii")):
        return "nifti"
    if name.endswith(".nrrd"):
        return "nrrd"
    raise VolwarpError(f"{path}: unknown displacement field extension "
                       f"(use {', '.join(FIELD_EXTENSIONS)})")


def points_format(path: str) -> str:
    """``csv`` or ``markups`` (Slicer ``.mrk.json``) for a points file, else a VolwarpError."""
    name = str(path).lower()
    if name.endswith(".mrk.json"):
        return "markups"
    if name.endswith(".csv"):
        return "csv"
    raise VolwarpError(f"{path}: unknown points file extension (use .csv or .mrk.json)")


def check_points_pair(points_in, points_to) -> None:
    """``--points-in`` and ``--points-to`` of one format, the output's path checked (BadUsage)."""
    from ..errors import BadUsage
    from ..io import check_output_path

    try:
        kinds = points_format(points_in), points_format(points_to)
    except VolwarpError as exc:
        raise BadUsage(str(exc)) from None
    if kinds[0] != kinds[1]:
        raise BadUsage(f"--points-to {points_to}: write the points in the format they were "
                       f"read in ({'.csv' if kinds[0] == 'csv' else '.mrk.json'})")
    check_output_path(points_to, option="--points-to")


def check_exportable(placement: str, dq0: np.ndarray, what: str) -> None:
    """Exports need the affine capture map of the uniform placement."""
    if placement != "uniform" or np.any(dq0 != 0):
        raise VolwarpError(f"{what}: the deformation can be exported for the uniform placement "
                           f"only (this capture uses {placement!r}, whose capture map is not "
                           "affine)")


@dataclass
class ForwardMap:
    """The forward map of one lattice state on one input geometry."""

    grid: Lattice
    dq: np.ndarray  # (Cz, Cy, Cx, 3) offsets from the uniform lattice, input voxels
    geometry: Header  # the input's Header (a capture's geometry)

    def __post_init__(self):
        self.dq = np.asarray(self.dq, dtype=np.float64)
        g = self.geometry
        self.matrix = g.direction * g.spacing[None, :]  # index vector -> world vector
        self.inverse = np.linalg.inv(self.matrix)
        self.h = np.asarray(self.grid.spacing_h, dtype=np.float64)
        self.org = np.asarray(self.grid.origin, dtype=np.float64)
        self.regions = np.array(self.grid.regions)
        self._spline = LatticeSpline(self.dq, self.regions)  # (:mod:`.evaluate`)

    # ---- index <-> world -------------------------------------------------------------
    def to_index(self, p) -> np.ndarray:
        """Input voxel indices (x, y, z) of world (LPS mm) points ``p`` (..., 3)."""
        return (np.asarray(p, dtype=np.float64) - self.geometry.origin) @ self.inverse.T

    def to_world(self, x) -> np.ndarray:
        """World (LPS mm) points of input voxel indices ``x`` (..., 3)."""
        return np.asarray(x, dtype=np.float64) @ self.matrix.T + self.geometry.origin

    # ---- support ---------------------------------------------------------------------
    def params(self, x) -> np.ndarray:
        """The spline parameters ``s = (x - grid.origin) / h`` of input indices ``x``."""
        return (np.asarray(x, dtype=np.float64) - self.org) / self.h

    def inside(self, x, tol: float = 1e-9) -> np.ndarray:
        """Which input indices ``x`` (..., 3) lie in the support ``[0, R]^3`` (within ``tol``)."""
        s = self.params(x)
        return np.all((s >= -tol) & (s <= self.regions + tol), axis=-1)

    def support_world_box(self):
        """``(lo, hi)``: the world (LPS mm) bounding box of the lattice's support."""
        lo = self.org
        hi = self.org + self.h * self.regions
        corners = np.array([[a[0], b[1], c[2]] for a in (lo, hi) for b in (lo, hi)
                            for c in (lo, hi)])
        w = self.to_world(corners)
        return w.min(axis=0), w.max(axis=0)

    # ---- scattered evaluation ----------------------------------------------------------
    def _eval_params(self, s, derivative: bool):
        """Offsets sum B dq (N, 3) at parameters s (N, 3), and d/ds (N, 3, 3) [m, axis]."""
        return (self._spline.offsets(s),
                self._spline.jacobian(s) if derivative else None)

    def map_index(self, x) -> np.ndarray:
        """F(x) for input indices x (N, 3) inside the support."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        out = np.empty_like(x)
        for a in range(0, len(x), CHUNK):
            part = x[a:a + CHUNK]
            out[a:a + CHUNK] = part + self._eval_params(self.params(part), False)[0]
        return out

    def map_world(self, p) -> tuple[np.ndarray, np.ndarray]:
        """F of world points (N, 3); points outside the lattice's support are returned unmoved.

        Returns (mapped, inside mask).
        """
        p = np.atleast_2d(np.asarray(p, dtype=np.float64)).reshape(-1, 3)
        x = self.to_index(p)
        ok = self.inside(x)
        out = p.copy()
        if ok.any():
            out[ok] = self.to_world(self.map_index(x[ok]))
        return out, ok

    # ---- grid evaluation ------------------------------------------------------------------
    def _axis_weights(self, axis: int, n: int, derivative: bool) -> np.ndarray:
        """Dense (n, C) weights of input voxel centres 0..n-1 on one axis (d/dx if asked)."""
        c = self.grid.lattice[axis]
        s = (np.arange(n) - self.org[axis]) / self.h[axis]
        a = np.clip(np.floor(s), 0, c - 4).astype(np.intp)
        frac = s - a
        b = basis_derivative(frac) / self.h[axis] if derivative else basis(frac)
        out = np.zeros((n, c))
        rows = np.arange(n)
        for i in range(4):
            out[rows, a + i] = b[:, i]
        return out

    def _grid(self, wz, wy, wx) -> np.ndarray:
        t = np.tensordot(wz, self.dq, axes=(1, 0))  # (nz, Cy, Cx, 3)
        t = np.einsum("yj,zjim->zyim", wy, t)
        return np.einsum("xi,zyim->zyxm", wx, t)  # (nz, ny, nx, 3)

    def _slabs(self):
        nx, ny, nz = self.grid.input_shape
        step = self.slab_depth()
        wz_all = self._axis_weights(2, nz, False)
        dwz_all = self._axis_weights(2, nz, True)
        for z0 in range(0, nz, step):
            yield z0, wz_all[z0:z0 + step], dwz_all[z0:z0 + step]

    def forward_field(self) -> np.ndarray:
        """F(x) - x on the input grid, world mm, [z, y, x, 3] float32."""
        nx, ny, nz = self.grid.input_shape
        out = np.empty((nz, ny, nx, 3), np.float32)
        for z0, part in self.forward_field_slabs():
            out[z0:z0 + len(part)] = part
        return out

    def forward_field_slabs(self):
        """:meth:`forward_field` slab by slab: ``(z0, planes [k, y, x, 3] float32)`` in order of z.

        The slabs of :meth:`_slabs` (a few MB of samples each, whatever the grid's
        size); :meth:`forward_field` is their concatenation, value for value.
        """
        nx, ny, nz = self.grid.input_shape
        wy, wx = self._axis_weights(1, ny, False), self._axis_weights(0, nx, False)
        for z0, wz, _ in self._slabs():
            yield z0, (self._grid(wz, wy, wx) @ self.matrix.T).astype(np.float32)

    def jacobian(self) -> np.ndarray:
        """The det dF/dx on the input grid, [z, y, x] float32."""
        nx, ny, nz = self.grid.input_shape
        out = np.empty((nz, ny, nx), np.float32)
        for z0, part in self.jacobian_slabs():
            out[z0:z0 + len(part)] = part
        return out

    def jacobian_slabs(self):
        """:meth:`jacobian` slab by slab: ``(z0, planes [k, y, x] float32)`` in order of z."""
        nx, ny, nz = self.grid.input_shape
        wy, wx = self._axis_weights(1, ny, False), self._axis_weights(0, nx, False)
        dwy, dwx = self._axis_weights(1, ny, True), self._axis_weights(0, nx, True)
        for z0, wz, dwz in self._slabs():
            cols = [self._grid(wz, wy, dwx), self._grid(wz, dwy, wx), self._grid(dwz, wy, wx)]
            j = np.stack(cols, axis=-1)  # [..., m, axis]
            j += np.eye(3)
            yield z0, np.linalg.det(j).astype(np.float32)

    # ---- inverse ------------------------------------------------------------------------------
    def invert_index(self, y) -> tuple[np.ndarray, np.ndarray]:
        """The x with F(x) = y for input-index points y (N, 3).

        NaN where none is found in the support or the map folds there (det <= 0).
        Returns (x, status): status 0 found, 1 no inverse in the support, 2 folded.
        """
        y = np.atleast_2d(np.asarray(y, dtype=np.float64))
        x = np.full_like(y, np.nan)
        status = np.zeros(len(y), np.int8)
        for a in range(0, len(y), CHUNK):
            x[a:a + CHUNK], status[a:a + CHUNK] = self._invert_chunk(y[a:a + CHUNK])
        return x, status

    def _invert_chunk(self, y):
        h, org, regions = self.h, self.org, self.regions
        lo, hi = np.full(3, -0.5), regions + 0.5  # a little extrapolation while iterating
        s = np.clip((y - org) / h, lo, hi)  # the identity's parameters: the start
        res = np.full(len(y), np.inf)
        active = np.arange(len(y))
        for _ in range(INVERSE_ITERATIONS):
            if not len(active):
                break
            sa = s[active]
            val, jac = self._eval_params(sa, True)
            r = org + h * sa + val - y[active]  # W(s) - y, input voxels
            res[active] = np.max(np.abs(r), axis=1)
            done = res[active] < INVERSE_TOL
            keep = ~done
            active, sa, r, jac = active[keep], sa[keep], r[keep], jac[keep]
            if not len(active):
                break
            jac += np.diag(h)[None]  # dW/ds
            det = np.linalg.det(jac)
            good = np.abs(det) > 1e-12
            step = np.zeros_like(sa)
            if good.any():
                step[good] = np.linalg.solve(jac[good], r[good][..., None])[..., 0]
            # damp: at most one region per axis per iteration
            big = np.max(np.abs(step), axis=1)
            step *= np.minimum(1.0, 1.0 / np.maximum(big, 1e-300))[:, None]
            new = np.clip(sa - step, lo, hi)
            moved = np.max(np.abs(new - sa), axis=1) > 1e-13
            s[active] = new
            bad = ~good | ~moved  # singular, or held at the box's edge: no inverse here
            if bad.any():
                res[active[bad]] = np.inf
                active = active[~bad]
        # accept
        eps = 1e-9
        inside = np.all((s >= -eps) & (s <= regions + eps), axis=1)
        found = (res < INVERSE_ACCEPT) & inside
        status = np.where(found, 0, 1).astype(np.int8)
        x = np.full_like(y, np.nan)
        idx = np.flatnonzero(found)
        if len(idx):
            _, jac = self._eval_params(s[idx], True)
            jac += np.diag(h)[None]
            folded = np.linalg.det(jac) <= 0
            status[idx[folded]] = 2
            ok = idx[~folded]
            x[ok] = org + h * s[ok]
        return x, status

    def _image_box(self):
        """The image of the support lies inside the control points' bounding box."""
        pts = (self.grid.uniform_positions() + self.dq).reshape(-1, 3)
        return pts.min(axis=0) - 1e-6, pts.max(axis=0) + 1e-6

    def resampling_field(self, shape_xyz, shift, *, warm: bool = True,
                         threads: int | None = None) -> tuple[np.ndarray, dict]:
        """F^-1(y) - y on an output grid of ``shape_xyz`` voxels, world mm, [z, y, x, 3] float32.

        NaN where there is none. The output grid is the input's, shifted: output
        voxel t is the input-index point ``t + shift``.

        The numba kernel of :mod:`._export_kernels` (the same Newton iteration as
        :meth:`_invert_chunk`, per voxel, warm-started along output rows unless
        ``warm`` is false), the output's z slices split over ``threads`` threads
        (default: the CPUs). :meth:`_resampling_field_numpy` is the vectorised
        reference it is tested against.
        """
        from ._export_kernels import invert_rows

        nx, ny, nz = (int(v) for v in shape_xyz)
        shift = np.ascontiguousarray(shift, dtype=np.float64)
        box_lo, box_hi = self._image_box()
        folds = self._fold_image((nx, ny, nz), shift, fast=True, threads=threads)
        out = np.empty((nz, ny, nx, 3), np.float32)
        status = np.empty((nz, ny, nx), np.int8)
        dq = np.ascontiguousarray(self.dq)
        regions = np.ascontiguousarray(self.regions, dtype=np.int64)
        matrix = np.ascontiguousarray(self.matrix, dtype=np.float64)

        def part(z0, z1):
            invert_rows(dq, self.org, self.h, regions, shift, box_lo, box_hi, matrix, nx, ny,
                        z0, z1, INVERSE_ITERATIONS, INVERSE_TOL, INVERSE_ACCEPT, bool(warm),
                        out, status)

        _run_slabs(part, nz, nx * ny, threads)
        if folds is not None:
            hit = (status == 0) & folds.reshape(nz, ny, nx)
            status[hit] = 2
            out[hit] = np.nan
        counts = {"voxels": nx * ny * nz, "no_inverse": int(np.count_nonzero(status == 1)),
                  "folded": int(np.count_nonzero(status == 2))}
        return out, counts

    def _resampling_field_numpy(self, shape_xyz, shift) -> tuple[np.ndarray, dict]:
        """F^-1(y) - y on an output grid of ``shape_xyz`` voxels, world mm, [z, y, x, 3] float32.

        NaN where there is none: the vectorised reference of :meth:`resampling_field`
        (about 40 us per voxel; the tests' yardstick).
        """
        nx, ny, nz = (int(v) for v in shape_xyz)
        shift = np.asarray(shift, dtype=np.float64)
        out = np.empty((nz * ny * nx, 3), np.float32)
        counts = {"voxels": nx * ny * nz, "no_inverse": 0, "folded": 0}
        box_lo, box_hi = self._image_box()
        total = nx * ny * nz
        folds = self._fold_image((nx, ny, nz), shift)
        for a in range(0, total, CHUNK):
            flat = np.arange(a, min(a + CHUNK, total))
            y = np.stack([flat % nx, (flat // nx) % ny, flat // (nx * ny)], axis=1) + shift
            near = np.all((y >= box_lo) & (y <= box_hi), axis=1)
            x = np.full_like(y, np.nan)
            status = np.ones(len(y), np.int8)
            if near.any():
                x[near], status[near] = self._invert_chunk(y[near])
            if folds is not None:
                status[(status == 0) & folds[flat]] = 2
                x[status == 2] = np.nan
            counts["no_inverse"] += int(np.count_nonzero(status == 1))
            counts["folded"] += int(np.count_nonzero(status == 2))
            out[flat] = (x - y) @ self.matrix.T
        return out.reshape(nz, ny, nx, 3), counts


    def _jacobian_fast(self, threads: int | None = None) -> np.ndarray:
        """:meth:`jacobian` by the numba kernel of :mod:`._export_kernels`.

        The same values to rounding; what the fold test of :meth:`resampling_field` uses.
        """
        from ._export_kernels import jacobian_rows

        nx, ny, nz = self.grid.input_shape
        out = np.empty((nz, ny, nx), np.float32)
        dq = np.ascontiguousarray(self.dq)
        regions = np.ascontiguousarray(self.regions, dtype=np.int64)
        _run_slabs(lambda z0, z1: jacobian_rows(dq, self.org, self.h, regions, nx, ny, z0, z1,
                                                out), nz, nx * ny, threads)
        return out

    def _fold_image(self, shape_xyz, shift, fast: bool = False, threads: int | None = None):
        """Output voxels (flat bool) that the folded part of the input (det <= 0) maps onto.

        There the map has several preimages; None when nothing folds. Sampled at 27
        points per input voxel near the fold, each marking the 8 output voxels around
        its image. (``fast``: det on the input grid by the numba kernel.)
        """
        det = self._jacobian_fast(threads) if fast else self.jacobian()
        neg = det <= 0
        if not neg.any():
            return None
        from scipy.ndimage import binary_dilation

        near = np.argwhere(binary_dilation(neg, iterations=1))[:, ::-1].astype(np.float64)
        mark = np.zeros(int(np.prod(shape_xyz)), bool)
        for idx in self._fold_marks_of(near, shape_xyz, shift):
            mark[idx] = True
        return mark

    def _fold_marks_of(self, near, shape_xyz, shift) -> np.ndarray:
        """The flat output voxels the fold's samples around input voxels ``near`` map onto.

        ``near``: (N, 3: x, y, z); see :meth:`_fold_image`. Yields int64 arrays, a chunk
        of ``near`` at a time (unsorted, repeated).
        """
        offs = np.stack(np.meshgrid(*[np.array([-1, 0, 1]) / 3.0] * 3, indexing="ij"),
                        -1).reshape(-1, 3)
        nx, ny, nz = shape_xyz
        for a in range(0, len(near), CHUNK // 27 + 1):
            x = (near[a:a + CHUNK // 27 + 1, None, :] + offs[None]).reshape(-1, 3)
            x = x[self.inside(x)]
            val, jac = self._eval_params(self.params(x), True)
            j = np.eye(3)[None] + jac / self.h[None, None, :]
            x = x[np.linalg.det(j) <= 0]
            t = x + self._eval_params(self.params(x), False)[0] - shift
            base = np.floor(t).astype(np.int64)
            for c in np.ndindex(2, 2, 2):
                q = base + np.array(c)
                ok = np.all((q >= 0) & (q < np.array([nx, ny, nz])), axis=1)
                q = q[ok]
                yield (q[:, 2] * ny + q[:, 1]) * nx + q[:, 0]

    # ---- by slabs (out of core) ----------------------------------------------------------------
    def slab_depth(self) -> int:
        """The depth (input z planes) of the fields' slabs on the input grid.

        Those of :meth:`forward_field_slabs` and :meth:`jacobian_slabs`: about ``CHUNK``
        voxels (one plane, if larger), some 250 bytes of scratch a voxel for the Jacobian's.
        """
        nx, ny, _ = self.grid.input_shape
        return max(1, CHUNK // max(1, nx * ny))

    def _jacobian_fast_planes(self, z0: int, z1: int, threads: int | None = None) -> np.ndarray:
        """:meth:`_jacobian_fast`'s planes [z0, z1) only, the same values (the same kernel)."""
        from numpy.lib.stride_tricks import as_strided

        from .. import parallel
        from ._export_kernels import jacobian_rows

        nx, ny, nz = self.grid.input_shape
        out = np.empty((z1 - z0, ny, nx), np.float32)
        dq = np.ascontiguousarray(self.dq)
        regions = np.ascontiguousarray(self.regions, dtype=np.int64)

        def plane(z):
            # the kernel fills out[z] of a volume of nz planes: a view of nz planes that
            # all lie on this one (z stride 0), of which it writes plane z only
            p = out[z - z0]
            view = as_strided(p, shape=(nz, ny, nx), strides=(0, *p.strides))
            jacobian_rows(dq, self.org, self.h, regions, nx, ny, z, z + 1, view)

        n = threads if threads is not None else parallel.threads()
        n = max(1, min(int(n), z1 - z0))
        if n == 1:
            for z in range(z0, z1):
                plane(z)
        else:
            parallel.run_blocks(plane, range(z0, z1), n)
        return out

    def fold_marks(self, shape_xyz, shift, *, depth: int | None = None,
                   threads: int | None = None) -> np.ndarray | None:
        """The fold image of :meth:`resampling_field` as sorted flat output voxel indices.

        ``_fold_image(fast=True)``'s voxels (int64), computed by input slabs of ``depth``
        planes. None when nothing folds. Memory: one slab of det, and the marks (as many as
        the fold's image has voxels, none for a map that does not fold).
        """
        from scipy.ndimage import binary_dilation

        nx, ny, nz = self.grid.input_shape
        shift = np.asarray(shift, dtype=np.float64)
        depth = max(1, int(depth or self.slab_depth()))
        any_neg = False
        marks = [np.zeros(0, np.int64)]
        for z0 in range(0, nz, depth):
            z1 = min(nz, z0 + depth)
            a, b = max(0, z0 - 1), min(nz, z1 + 1)  # one plane more each side: the dilation's
            neg = self._jacobian_fast_planes(a, b, threads) <= 0
            if not neg.any():
                continue
            any_neg = True
            core = binary_dilation(neg, iterations=1)[z0 - a:z1 - a]
            near = np.argwhere(core)
            if not len(near):
                continue
            near[:, 0] += z0
            near = near[:, ::-1].astype(np.float64)
            for idx in self._fold_marks_of(near, tuple(int(v) for v in shape_xyz), shift):
                marks = [np.union1d(np.concatenate(marks), idx)]
        if not any_neg:
            return None
        return marks[0]

    def resampling_field_slabs(self, shape_xyz, shift, depth: int, *, warm: bool = True,
                               threads: int | None = None):
        """:meth:`resampling_field` by output slabs of ``depth`` planes, in order of z.

        Yields ``(z0, planes [k, y, x, 3] float32, counts)``: the same values as the
        whole field's planes (the same kernel, row by row), and each slab's counts
        (they add up to the whole field's). Memory: one slab, and :meth:`fold_marks`.
        """
        from ._export_kernels import invert_rows

        nx, ny, nz = (int(v) for v in shape_xyz)
        shift = np.ascontiguousarray(shift, dtype=np.float64)
        if np.any(shift != np.round(shift)):  # the slabs shift it by whole planes, exactly
            raise ValueError("the output grid's shift must be whole voxels")
        box_lo, box_hi = self._image_box()
        marks = self.fold_marks((nx, ny, nz), shift, threads=threads)
        dq = np.ascontiguousarray(self.dq)
        regions = np.ascontiguousarray(self.regions, dtype=np.int64)
        matrix = np.ascontiguousarray(self.matrix, dtype=np.float64)
        depth = max(1, int(depth))
        plane = nx * ny
        for z0 in range(0, nz, depth):
            z1 = min(nz, z0 + depth)
            k = z1 - z0
            out = np.empty((k, ny, nx, 3), np.float32)
            status = np.empty((k, ny, nx), np.int8)
            sh = shift.copy()
            sh[2] += z0  # slab plane i is output plane z0 + i

            def part(a, b, sh=sh, out=out, status=status):
                invert_rows(dq, self.org, self.h, regions, sh, box_lo, box_hi, matrix, nx, ny,
                            a, b, INVERSE_ITERATIONS, INVERSE_TOL, INVERSE_ACCEPT, bool(warm),
                            out, status)

            _run_slabs(part, k, plane, threads)
            if marks is not None:
                lo, hi = np.searchsorted(marks, [z0 * plane, z1 * plane])
                folds = np.zeros(k * plane, bool)
                folds[marks[lo:hi] - z0 * plane] = True
                hit = (status == 0) & folds.reshape(k, ny, nx)
                status[hit] = 2
                out[hit] = np.nan
            counts = {"voxels": k * plane, "no_inverse": int(np.count_nonzero(status == 1)),
                      "folded": int(np.count_nonzero(status == 2))}
            yield z0, out, counts


def _run_slabs(part, nz: int, per_slice: int, threads: int | None) -> None:
    """``part(z0, z1)`` over [0, nz) in slabs of a few slices, spread over ``threads`` threads.

    The default is :func:`volwarp_cli.parallel.threads`; the kernels release the GIL
    and write disjoint slices. Threads instead of numba's ``prange``, whose threading
    layer costs time to start in every process (see :func:`~volwarp_cli.parallel.run_split`).
    """
    from .. import parallel

    n = threads if threads is not None else parallel.threads()
    n = max(1, min(int(n), nz, 1 + nz * per_slice // 32768))
    if n == 1:
        part(0, nz)
        return
    # interleaved slabs: the work per slice varies (the image's edge, folds)
    step = max(1, min(8, nz // (4 * n)))
    parallel.run_blocks(lambda z0: part(z0, min(z0 + step, nz)), range(0, nz, step), n)


# ---- writers ------------------------------------------------------------------------------------

def write_field(field: np.ndarray, geometry: Header, path: str, meta: dict, kind: str, *,
                compress: bool = False, byte_order: str = "little") -> None:
    """Write a displacement field ([z, y, x, 3], LPS mm) atomically as NRRD or NIfTI.

    ``compress``: gzip NRRD (a field written by blocks is the raw file, the
    bytes of the uncompressed one; a ``.nii.gz`` is gzip either way);
    ``byte_order``: a NRRD's (NIfTI is written little-endian).

    NRRD: ``kinds: vector domain domain domain``, ``space: left-posterior-superior``,
    key/values ``volwarp_field:=KIND`` (and ``displacement field type:=resampling``
    for a resampling field). NIfTI: SimpleITK's layout, a 5-D (x, y, z, 1, 3)
    array with intent 1007 (vector), LPS components, RAS affine; ``descrip``
    says the direction and volwarp's header extension holds the key/values.
    """
    fmt = field_format(path)
    header = _field_header(geometry, field.shape[:3], meta, kind, fmt)
    if fmt == "nrrd":
        from ..io.nrrd import write_nrrd

        components = [field[..., m] for m in range(3)]
        write_nrrd(header.with_data(components[0]), path, compress=compress,
                   byte_order=byte_order,
                   components=components, component_names=["x", "y", "z"])
        return
    _write_nifti_field(field, header, path, kind)


def _field_header(geometry: Header, shape_zyx, meta: dict, kind: str, fmt: str) -> Header:
    """The Header of a displacement field file of ``fmt``, in memory and by blocks alike.

    ``geometry``'s grid, LPS, the key/values ``meta`` with the field's own.
    """
    meta = dict(meta)
    meta["volwarp_field"] = kind
    meta["volwarp_field_units"] = "mm (LPS)"
    if fmt == "nrrd":
        if kind == "resampling":
            meta["displacement field type"] = "resampling"
        meta.pop("volwarp_components", None)
    return Header(shape_zyx, np.float32, spacing=geometry.spacing, origin=geometry.origin,
                  direction=geometry.direction, space=LPS, meta=meta)


def field_block_output(path: str, geometry: Header, meta: dict, kind: str, depth: int,
                       byte_order: str = "little"):
    """The block output of a displacement field written by slabs: an uncompressed NRRD.

    A :class:`~volwarp_cli.io.blockwrite.BlockOutput` of blocks of ``depth`` z planes.

    The header is :func:`write_field`'s (``kinds: vector domain domain domain``, LPS,
    the same key/values, ``encoding: raw``): the file is the uncompressed one
    :func:`write_field` writes. A NIfTI path is a VolwarpError.
    """
    from ..io.blockwrite import open_block_output

    if field_format(path) != "nrrd":
        raise VolwarpError(f"{path}: a NIfTI displacement field cannot be written by blocks "
                           "(write .nrrd: uncompressed by blocks)")
    nz, ny, nx = geometry.shape
    return open_block_output(path, _field_header(geometry, geometry.shape, meta, kind, "nrrd"),
                             chunks_zyx=(max(1, int(depth)), ny, nx),
                             components=["x", "y", "z"], byte_order=byte_order)


def _write_nifti_field(field, grid: Header, path: str, kind: str) -> None:
    from ..io.nifti import form_codes, ras_affine, write_nifti_file

    data = np.ascontiguousarray(field.transpose(2, 1, 0, 3))[:, :, :, None, :]
    aff = ras_affine(grid)  # (scanner codes, the qform's 0 where its quaternion cannot hold it)
    write_nifti_file(path, data, aff, units=2,  # mm
                     codes=form_codes({}, aff, np.asarray(grid.spacing), grid.shape[::-1]),
                     intent=(1007, (0.0, 0.0, 0.0), ""),  # NIFTI_INTENT_VECTOR
                     descrip=f"volwarp {kind} displacement field, LPS mm", meta=grid.meta)


def _num(x: float) -> str:
    return repr(float(x))


def tfm_text(fmap: ForwardMap, meta: dict) -> str:
    """The forward map as an ITK ``BSplineTransform_double_3_3`` text transform.

    FixedParameters are the coefficient grid (ITK v4): size (C), origin, spacing
    and direction in LPS mm; Parameters the world displacement coefficients,
    all x (x fastest), then all y, then all z.
    """
    g = fmap.geometry
    size = [float(c) for c in fmap.grid.lattice]
    origin = fmap.to_world((fmap.org - fmap.h)[None])[0]
    spacing = g.spacing * fmap.h
    direction = g.direction.ravel()
    coef = fmap.dq @ fmap.matrix.T  # (Cz, Cy, Cx, 3) world mm
    params = np.concatenate([coef[..., m].ravel() for m in range(3)])
    lines = ["#Insight Transform File V1.0"]
    lines += [f"#{k}: {str(v).replace(chr(10), ' ')}" for k, v in sorted(meta.items())]
    lines += ["#Transform 0", "Transform: BSplineTransform_double_3_3",
              "Parameters: " + " ".join(_num(v) for v in params),
              "FixedParameters: " + " ".join(_num(v) for v in
                                             [*size, *origin, *spacing, *direction])]
    return "\n".join(lines) + "\n"


def write_tfm(fmap: ForwardMap, path: str, meta: dict) -> None:
    """Write the forward map as an ITK ``.tfm`` file, atomically, noted as a forward map."""
    from ..io.atomic import write_bytes_atomic

    meta = dict(meta)
    meta["volwarp_field"] = "forward"
    meta["volwarp_note"] = ("forward (modelling) map for points: ITK reads it as a resampling "
                            "transform, do not resample the input with it")
    # (UTF-8: a comment names the input, "ä"; a name that is not UTF-8 is escaped, \udce9)
    write_bytes_atomic(path, tfm_text(fmap, meta).encode("utf-8", "backslashreplace"))


# ---- points files -------------------------------------------------------------------------------

@dataclass
class PointsFile:
    """Points read from a CSV (x, y, z columns) or a Slicer markups file, LPS mm."""

    path: str
    kind: str  # csv | markups
    points: np.ndarray  # (N, 3) LPS
    rows: list | None = None  # csv: header + rows (strings)
    columns: tuple | None = None  # csv: x, y, z column numbers
    doc: dict | None = None  # markups: the document
    where: list | None = None  # markups: (markup, point, frame flip) of each point


#: memory a points file takes while read, per byte of the file: its text, the rows kept to
#: write back (a Python list of strings a row) and the points (a hunt measured 912 MiB for a
#: 2M-point, 46 MB CSV under --memory-limit 100M: about 19 bytes a byte, none charged)
POINTS_BYTES_PER_FILE_BYTE = 20


def read_points(path: str) -> PointsFile:
    """Read a CSV or Slicer markups points file (a VolwarpError naming the file if bad).

    Charged to the memory budget before it is read (:data:`POINTS_BYTES_PER_FILE_BYTE`).
    """
    from ..memory import ensure_fits_in_memory

    kind = points_format(path)
    try:
        size = os.stat(path).st_size
    except OSError as exc:
        raise VolwarpError(f"{path}: cannot read ({exc.strerror})") from None
    ensure_fits_in_memory(POINTS_BYTES_PER_FILE_BYTE * size,
                          f"{path}: its points, read with their rows,")
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise VolwarpError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError:
        raise VolwarpError(f"{path}: not a text file (UTF-8)") from None
    if kind == "csv":
        return _read_csv(path, text)
    return _read_markups(path, text)


def _read_csv(path, text) -> PointsFile:
    rows = list(csv.reader(io.StringIO(text)))
    rows = [r for r in rows if any(c.strip() for c in r)]
    if not rows:
        raise VolwarpError(f"{path}: empty points file (a header with x, y, z columns is needed)")
    header = [c.strip().lower() for c in rows[0]]
    try:
        cols = tuple(header.index(k) for k in ("x", "y", "z"))
    except ValueError:
        raise VolwarpError(f"{path}: the header has no x, y, z columns (got "
                           f"{', '.join(rows[0])[:60]!r})") from None
    twice = [k for k in ("x", "y", "z") if header.count(k) > 1]
    if twice:  # (the first was moved, the second passed through as it was: which is meant?)
        raise VolwarpError(f"{path}: the header names column {twice[0]!r} "
                           f"{header.count(twice[0])} times: which one is the point's?")
    pts = np.empty((len(rows) - 1, 3))
    for n, row in enumerate(rows[1:]):
        try:
            pts[n] = [float(row[c]) for c in cols]
        except (IndexError, ValueError):
            raise VolwarpError(f"{path}: line {n + 2}: x, y, z are not numbers") from None
        if not np.all(np.isfinite(pts[n])):
            raise VolwarpError(f"{path}: line {n + 2}: x, y, z must be finite")
    return PointsFile(path, "csv", pts, rows=rows, columns=cols)


def _read_markups(path, text) -> PointsFile:
    try:
        doc = json.loads(text)
        markups = doc["markups"]
        pts, where = [], []
        for m, mk in enumerate(markups):
            frame = str(mk.get("coordinateSystem", "LPS")).upper()
            if frame not in ("LPS", "RAS"):
                raise VolwarpError(f"{path}: markups[{m}]: unknown coordinateSystem {frame!r}")
            flip = np.array([-1.0, -1.0, 1.0]) if frame == "RAS" else np.ones(3)
            for c, cp in enumerate(mk.get("controlPoints", []) or []):
                if cp.get("positionStatus") == "undefined":  # (a point not placed: none)
                    p = np.full(3, np.nan)
                else:
                    p = np.array([float(v) for v in cp["position"]], dtype=np.float64)
                    if p.shape != (3,) or not np.all(np.isfinite(p)):
                        raise ValueError("position")
                pts.append(p * flip)
                where.append((m, c, flip))
    except VolwarpError:
        raise
    except (ValueError, KeyError, TypeError, AttributeError):
        raise VolwarpError(f"{path}: not a Slicer markups file (markups[].controlPoints[]."
                           "position)") from None
    return PointsFile(path, "markups", np.array(pts, dtype=np.float64).reshape(-1, 3), doc=doc,
                      where=where)


def points_text(pf: PointsFile, moved: np.ndarray) -> str:
    if pf.kind == "csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(pf.rows[0])
        for row, p in zip(pf.rows[1:], moved, strict=True):
            row = list(row)
            for c, v in zip(pf.columns, p, strict=True):
                row[c] = _num(v)
            w.writerow(row)
        return buf.getvalue()
    doc = json.loads(json.dumps(pf.doc))
    for (m, c, flip), p in zip(pf.where, moved, strict=True):
        point = doc["markups"][m]["controlPoints"][c]
        if np.all(np.isfinite(p)):
            point["position"] = [float(v) for v in p * flip]
            if point.get("positionStatus") == "undefined":
                point["positionStatus"] = "defined"
        else:  # (no position: Slicer's own way to say so, not a NaN JSON cannot hold)
            point["position"] = [0.0, 0.0, 0.0]
            point["positionStatus"] = "undefined"
    return json.dumps(doc, indent=4) + "\n"


def write_points(pf: PointsFile, moved: np.ndarray, path: str) -> None:
    """Write ``pf`` with its points replaced by ``moved``, in its own format, atomically."""
    from ..io.atomic import write_bytes_atomic

    write_bytes_atomic(path, points_text(pf, moved).encode("utf-8"))


def report_outside(what: str, inside: np.ndarray, fmap: ForwardMap, points=None) -> int:
    """Warn of the points outside the lattice's support (``inside`` False); their count.

    ``points``: the points, whose rows without a position (NaN: a markups point
    not placed, written back as it was) are neither inside nor outside.
    """
    if len(inside) == 0:  # (a points file of no point: written as empty, as apply does)
        return 0
    placed = (np.ones(len(inside), bool) if points is None
              else np.all(np.isfinite(np.asarray(points).reshape(len(inside), -1)), axis=1))
    n = int(np.count_nonzero(~inside & placed))
    if n:
        lo, hi = fmap.support_world_box()
        log.warning("%s: %d of %d points lie outside the lattice's support (world box %s .. "
                    "%s mm) and were left unmoved", what, n, int(np.count_nonzero(placed)),
                    np.round(lo, 2).tolist(), np.round(hi, 2).tolist())
    return n


def jacobian_stats(det: np.ndarray) -> dict:
    """The min and max of ``det``, and the fractions of voxels below 0 and below 0.1."""
    d = det.astype(np.float64, copy=False)
    return {"min": float(d.min()), "max": float(d.max()),
            "below_0": float(np.count_nonzero(d < 0) / d.size),
            "below_0.1": float(np.count_nonzero(d < 0.1) / d.size)}


def field_stats_ok(counts: dict) -> str:
    return (f"{counts['no_inverse']} of {counts['voxels']} voxels without an inverse in the "
            f"lattice's support, {counts['folded']} folded (NaN)")


__all__ = ["ForwardMap", "write_field", "write_tfm", "read_points", "write_points",
           "field_format", "points_format", "check_exportable", "jacobian_stats"]
