"""The warp state: domain voxmap, control lattice, target accumulators (paper §5 main loop).

A :class:`Scene` holds the captured domain voxmap, the current control-point
offsets and the target accumulators. :meth:`Scene.set_lattice` moves control
points and updates only what they influence:

1. the regions touched by the moved points (``i - 3 <= a <= i`` per axis,
   taken as one bounding box of regions), grown by one domain voxel (the
   face centres of a voxel use its neighbours' entries);
2. subtract those voxels' old contributions from the accumulators;
3. add their new contributions and re-finalize only the touched target block.

Departures: the papers write zeros where the old contributions went (an
approximation); the accumulators here are exact fixed point, so after any
sequence of updates the target equals a full recomputation with the final
lattice bit for bit. And the deformation mapping array (offsets ``U`` of the
write map from the affine base map) is never held whole: it is evaluated
chunk by chunk along z into a small buffer with a one-voxel margin, for the
old lattice when subtracting and the new one when adding. The evaluators give
every voxel the same value whatever block it is computed in, so this is exact,
and it saves 12 bytes per domain voxel (200 MiB for a 256^3 domain).
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import VolwarpError
from ..io.common import ensure_fits_in_memory
from ..progress import log, timed
from . import basis, pushforward
from .lattice import Grid, affected_regions

#: Blocks with at least this many domain voxels are split over two threads.
PARALLEL_MIN_VOXELS = 1 << 18
#: Size of the deformation buffer of one z chunk (the array is never held whole).
CHUNK_BYTES = 32 << 20


class Scene:
    """A captured domain and its write map into a padded target grid.

    Parameters
    ----------
    domain : (Dz, Dy, Dx) float32 or float64
        The captured (pulled back) density.
    grid : lattice.Grid
    dq : (Cz, Cy, Cx, 3) float64
        Control-point offsets from the uniform lattice (input voxels, x y z).
    pad : (x, y, z) ints
        Target padding per side; target index = input index + pad.
    method : {"box", "nearest"}
    evaluator : {"separable", "table"}
    """

    def __init__(self, domain, grid: Grid, dq, pad, *, method: str = "box",
                 evaluator: str = "separable"):
        if method not in pushforward.METHODS:
            raise VolwarpError(f"unknown pushforward {method!r} (use box or nearest)")
        if evaluator not in basis.EVALUATORS:
            raise VolwarpError(f"unknown evaluator {evaluator!r} (use separable or table)")
        if tuple(domain.shape[::-1]) != grid.domain_shape:
            raise VolwarpError("domain voxmap does not match the lattice")
        self.domain = domain
        self.grid = grid
        self.dq = np.array(dq, dtype=np.float64)
        self.pad = np.array([int(p) for p in np.broadcast_to(pad, (3,))])
        if np.any(self.pad < 0):
            raise VolwarpError(f"pad must not be negative, got {self.pad.tolist()}")
        self.method = method
        self.evaluator = evaluator
        vmax = float(np.max(np.abs(domain))) if domain.size else 0.0
        self.vmax = vmax if vmax > 0 else 1.0
        self.offset = grid.affine_offset(self.pad)
        self.scale = grid.scale
        self.acc = self.out = None
        self.last_touched = None

    @property
    def target_shape(self) -> tuple[int, int, int]:
        """Target size (x, y, z)."""
        return tuple(int(i + 2 * p) for i, p in zip(self.grid.input_shape, self.pad, strict=False))

    def _contribute(self, dq, vlo, vhi, sign):
        """Add (``sign`` +1) or remove (-1) the contributions of domain voxels [vlo, vhi).

        The deformation offsets are evaluated on the fly, chunk by chunk along
        z, into a small buffer covering the voxels and their neighbours (the
        evaluators give a voxel the same value whatever block it is computed
        in, so removing a contribution recomputes exactly what was added).
        Returns the touched target bounding box or None.
        """
        grid = self.grid
        dshape = np.array(grid.domain_shape)
        g = np.array(grid.granularity)
        vlo = np.asarray(vlo, dtype=np.int64)
        vhi = np.asarray(vhi, dtype=np.int64)
        elo = np.maximum(vlo - 1, 0)
        ehi = np.minimum(vhi + 1, dshape)
        rlo = elo // g
        rhi = -(-ehi // g)
        nx = int((rhi[0] - rlo[0]) * g[0])
        ny = int((rhi[1] - rlo[1]) * g[1])
        cz = int(max(4, CHUNK_BYTES // ((nx + 2) * (ny + 2) * 12)))
        nz = int(vhi[2] - vlo[2])
        buf = np.zeros((min(cz, nz) + 4, ny + 2, nx + 2, 3), dtype=np.float32)
        evaluate = basis.EVALUATORS[self.evaluator]
        boxes = []
        for z0 in range(int(vlo[2]), int(vhi[2]), cz):
            z1 = min(z0 + cz, int(vhi[2]))
            e0, e1 = max(z0 - 1, 0), min(z1 + 1, int(dshape[2]))
            ub = buf[:e1 - e0 + 2]
            origin = (int(rlo[0] * g[0]), int(rlo[1] * g[1]), e0)
            evaluate(dq, grid, ub[1:-1, 1:-1, 1:-1], (rlo[0], rlo[1], 0), (rhi[0], rhi[1], 0),
                     z=(e0, e1), origin=origin)
            faces = [(0, 0)] if e0 == 0 else []
            if e1 == dshape[2]:
                faces.append((0, 1))
            for axis_xyz, axis in ((0, 2), (1, 1)):
                if rlo[axis_xyz] == 0:
                    faces.append((axis, 0))
                if rhi[axis_xyz] * g[axis_xyz] == dshape[axis_xyz]:
                    faces.append((axis, 1))
            pushforward.fill_halo(ub, faces)
            lo = (int(vlo[0]), int(vlo[1]), z0)
            hi = (int(vhi[0]), int(vhi[1]), z1)
            bb = pushforward.scatter(ub, self.domain, self.offset, self.scale, lo, hi, sign,
                                     self.vmax, self.method, self.acc,
                                     split_z=self._split_z(dq, lo, hi), origin=origin)
            if bb is not None:
                boxes.append(bb)
        if not boxes:
            return None
        return (np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0))

    def _split_z(self, dq, lo, hi):
        """Two domain z indices ``(z1, z2)``: halves [lo, z1) and [z2, hi) hit disjoint target z.

        The bound comes from the lattice alone: a voxel's offset is a convex
        combination of control-point offsets, and its box (face centres, halo
        extrapolation) stays within that range widened by the range itself.
        The band [z1, z2) between the halves is done afterwards. None when the
        block is small or no safe split exists.
        """
        lo = np.asarray(lo)
        hi = np.asarray(hi)
        if int(np.prod(hi - lo)) < PARALLEL_MIN_VOXELS or (os.cpu_count() or 1) < 2:
            return None
        dz = dq[..., 2]
        top, bottom = dz.max(), dz.min()
        spread = top - bottom
        s, o = self.scale[2], self.offset[2]
        mid = (int(lo[2]) + int(hi[2])) // 2
        for gap in range(2, max(3, (int(hi[2]) - int(lo[2])) // 4)):
            z1 = mid - gap // 2
            z2 = z1 + gap
            a_max = o + s * (z1 - 1) + 0.5 * s + top + spread + 0.01  # + float32 slack
            b_min = o + s * z2 - 0.5 * s + bottom - spread - 0.01
            if np.ceil(a_max + 0.5) - 1 < np.floor(b_min - 0.5) + 1:
                return z1, z2
        return None

    def render(self) -> np.ndarray:
        """Full computation with the current lattice; returns the target ``[z, y, x]``."""
        tshape = self.target_shape[::-1]
        out_dtype = np.float64 if self.domain.dtype == np.float64 else np.float32
        nbytes = int(np.prod(tshape)) * (16 + np.dtype(out_dtype).itemsize) + 2 * CHUNK_BYTES
        ensure_fits_in_memory(nbytes, "the warp's target accumulators")
        if self.acc is None:
            self.acc = np.zeros(tshape + (2,), dtype=np.int64)
            self.out = np.empty(tshape, dtype=out_dtype)
        else:
            self.acc.fill(0)
        with timed(f"deformation + {self.method} pushforward"):
            self._contribute(self.dq, (0, 0, 0), self.grid.domain_shape, 1)
        with timed("finalize"):
            pushforward.finalize(self.acc, self.vmax, (0, 0, 0), self.target_shape, self.out)
        self.last_touched = ((0, 0, 0), self.target_shape)
        return self.out

    def result(self) -> np.ndarray:
        """The target for the current lattice (computed in full on first use)."""
        if self.acc is None:
            return self.render()
        return self.out

    def set_lattice(self, dq) -> None:
        """Move control points to offsets ``dq``, updating the target locally when rendered."""
        dq = np.asarray(dq, dtype=np.float64)
        if dq.shape != self.dq.shape:
            raise VolwarpError("lattice shape changed")
        if self.acc is None:
            self.dq = dq.copy()
            return
        moved = np.argwhere(np.any(dq != self.dq, axis=-1))  # (k, j, i)
        if moved.size == 0:
            self.last_touched = None
            return
        rlo, rhi = affected_regions(moved[:, ::-1], self.grid)
        g = np.array(self.grid.granularity)
        dshape = np.array(self.grid.domain_shape)
        vlo = np.maximum(rlo * g - 1, 0)
        vhi = np.minimum(rhi * g + 1, dshape)
        bb_old = self._contribute(self.dq, vlo, vhi, -1)
        self.dq = dq.copy()
        bb_new = self._contribute(self.dq, vlo, vhi, 1)
        boxes = [b for b in (bb_old, bb_new) if b is not None]
        if not boxes:
            self.last_touched = None
            return
        tlo = np.min([b[0] for b in boxes], axis=0)
        thi = np.max([b[1] for b in boxes], axis=0)
        pushforward.finalize(self.acc, self.vmax, tlo, thi, self.out)
        self.last_touched = (tuple(int(v) for v in tlo), tuple(int(v) for v in thi))
        log.debug("local update: regions %s..%s, target block %s..%s", rlo.tolist(),
                  rhi.tolist(), tlo.tolist(), thi.tolist())

    def map_points(self, param) -> np.ndarray:
        """Target indices (x, y, z) of spline parameters (N, 3) under the current map."""
        from .handles import map_params
        return map_params(self.dq, self.grid, param) + self.pad
