"""The euclidean distance field as an operation of the executor: blocks grown by a halo.

Clipped to ``±D`` (``--max-distance``), a voxel's value depends only on the
samples within a halo of it (:func:`volwarp_cli.regions.distance_band_input`,
the one rule for it): so a block of the field is the field of the block grown
by that halo, clipped and cropped. :class:`BandedDistance` computes any block
that way, and :func:`volwarp_cli.execute.run` runs it as one block on the
calling threads when the whole fits the memory budget (the halo then adds
nothing: the region is the whole input), else as many blocks on an engine:
the same kernels on the same samples, so the same bytes. Exact inside the
band ``|d| <= D``, ``±D`` outside.

Two surfaces: ``voxel``, the exact field between voxel centres
(:func:`.exact.signed_edt`; a label rule's, or binary samples'), and
``subvoxel``, the distance to the samples' iso-surface (:func:`.subvoxel.subvoxel_field`),
whose halo is wider. Without a band (``D`` None) the sub-voxel field needs the
whole input for any block: it runs as the one block only
(:data:`SUBVOXEL_NEEDS_BAND` by blocks); the exact field without a band runs
by passes instead (:mod:`.passes`).

The whole's checks (an empty shape, NaNs, the surface ``auto`` picks) are
made before, once (:mod:`.scan`); nothing here reads more than a block's region.
"""

from __future__ import annotations

import math

import numpy as np

from ..box import Box
from ..errors import VolwarpError
from ..execute import Operation
from ..regions import distance_band_input
from .field import finish_field

#: Bytes per voxel of a block's region: its mask and float32 field (``voxel``); its float32
#: samples, two seed-id arrays, the field and the seeds' foot points (``subvoxel``).
REGION_BYTES = {"voxel": 5, "subvoxel": 18}

SUBVOXEL_NEEDS_BAND = ("sub-voxel distances (smooth samples) out of core need --max-distance "
                       "(overlapping blocks); give one, or use --surface voxel for the exact "
                       "field between voxel centres")


class BandedDistance(Operation):
    """The signed field of ``rule``'s shape in ``source``, block by block (module notes).

    Parameters
    ----------
    source : (Z, Y, X) array or sliceable lazy source
        The input samples (a :class:`~volwarp_cli.io.lazy.LazySource` by blocks).
    grid : Geometry
        The output grid (the input's).
    rule : ShapeRule
        What the field is of (:func:`.labels.choose_shape`).
    surface : {"voxel", "subvoxel"}
        As resolved by :func:`.scan.field_surface`.
    max_distance : float or None
        The band ``D``; None: the whole field (``subvoxel`` only, one block).
    unsigned : bool
        Distance to the shape, 0 inside.
    target : Target, optional
        The output (its ``dtype``: the samples cast to it); None: the
        float32 field of a block, for a caller's own use.
    """

    def __init__(self, source, grid, rule, *, surface: str, max_distance: float | None,
                 unsigned: bool = False, target=None):
        if surface not in REGION_BYTES:
            raise ValueError(f"surface must be 'voxel' or 'subvoxel', got {surface!r}")
        if max_distance is not None and not max_distance > 0:
            raise VolwarpError(f"max distance must be positive, got {max_distance:g}")
        self.source, self.grid, self.rule = source, grid, rule
        if max_distance is None:  # the sub-voxel field of the whole needs the whole input
            self.no_blocks = SUBVOXEL_NEEDS_BAND
        self.surface, self.unsigned = surface, unsigned
        self.max_distance = None if max_distance is None else float(max_distance)
        self.spacing_zyx = tuple(float(s) for s in grid.spacing_zyx)
        self.targets = {} if target is None else {None: target}
        self.out_dtype = np.dtype(np.float32 if target is None else target.dtype)
        nx, ny, nz = grid.shape_xyz
        kind = "sub-voxel" if surface == "subvoxel" else "voxel-centre"
        self.what = (f"the {kind} distance field of {nx}x{ny}x{nz} samples"
                     + ("" if self.max_distance is not None
                        else " (without --max-distance: in memory only)"))

    def region(self, box: Box) -> Box:
        """The input samples ``box`` of the field needs (:func:`~volwarp_cli.regions.distance_band_input`)."""
        return distance_band_input(box, self.grid.shape, self.grid.spacing, self.max_distance,
                                   surface=self.surface)

    def memory(self, box: Box) -> int:
        """The bytes of ``box``'s region (its samples and the kernels' arrays) and of its field."""
        per_region, per_out = self._per_voxel()
        return self.region(box).size * per_region + box.size * per_out

    def _per_voxel(self) -> tuple[int, int]:
        # a region voxel: its sample and the kernels' arrays; a block voxel: the field
        # cropped, and cast to the output's type
        out = 4 + (self.out_dtype.itemsize if self.out_dtype != np.float32 else 0)
        return np.dtype(self.source.dtype).itemsize + REGION_BYTES[self.surface], out

    def compute(self, box: Box, *, threads: int) -> dict:
        """``{"field": float32 [z, y, x]}`` of ``box``: clipped to the band, ``--unsigned`` applied."""
        from .. import parallel

        region = self.region(box)
        data = np.asarray(self.source[region.slices])
        inner = box.relative_to(region).slices
        with parallel.use_threads(threads):
            if self.surface == "subvoxel":
                field = self._subvoxel(data, region.lo, inner, threads)
            else:
                from .exact import signed_edt

                field = signed_edt(self.rule.mask(data), self.spacing_zyx)[inner]
        field = np.ascontiguousarray(field)
        return {"field": finish_field(field, unsigned=self.unsigned,
                                      max_distance=self.max_distance)}

    def _subvoxel(self, data, origin, inner, threads):
        # a region without a crossing lies farther than the band from the surface: ±D by side
        from .subvoxel import subvoxel_field

        values = data if data.dtype.kind == "f" else data.astype(np.float32)
        field = subvoxel_field(np.ascontiguousarray(values), self.rule.iso,
                               self.rule.inside == "above", self.spacing_zyx, threads=threads,
                               origin=origin)
        if field is None:
            d = np.float32(self.max_distance)
            return np.where(self.rule.mask(values[inner]), -d, d)
        return field[inner]

    def output(self, results: dict, key) -> np.ndarray:
        """The field in the output's type."""
        from ..samples import cast_samples

        field = results["field"]
        if self.out_dtype == np.float32:
            return field
        return cast_samples(field, self.out_dtype, what=str(self.targets[key].path))

    def load(self) -> None:
        """The kernels on a small ball, so that the budget counts their loaded code."""
        from .field import warm_kernels

        rule = self.rule
        if rule.labels:
            warm_kernels("euclidean", "voxel", np.dtype(bool), 0.5, "above")
        else:
            warm_kernels("euclidean", self.surface, self.source.dtype, rule.iso, rule.inside)

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """The blocks that read the fewest samples, halos counted, within ``per_task`` bytes.

        At least one block per worker. A block's region is at most its shape
        grown by the halo on both sides (:meth:`region` of a voxel in the
        middle of the grid), so few blocks favour slabs (a halo along one
        axis), many blocks cubes; among equals, whole rows and planes.
        """
        shape = self.grid.shape
        mid = Box(tuple(n // 2 for n in shape), tuple(n // 2 + 1 for n in shape))
        region = self.region(mid)
        halo = [max(m - a, b - m - 1) for m, a, b in zip(mid.lo, region.lo, region.hi,
                                                           strict=True)]
        per_region, per_out = self._per_voxel()
        best = None
        counts = [_counts(n) for n in shape]
        for kz in counts[0]:
            for ky in counts[1]:
                for kx in counts[2]:  # fewest first: the first that fits is the cheapest
                    block = [-(-n // k) for n, k in zip(shape, (kz, ky, kx), strict=True)]
                    reach = [min(b + 2 * h, n) for b, h, n in zip(block, halo, shape,
                                                                   strict=True)]
                    count = math.prod(-(-n // b) for n, b in zip(shape, block, strict=True))
                    if (count >= workers and math.prod(reach) * per_region
                            + math.prod(block) * per_out <= per_task):
                        cost = (count * math.prod(reach), kx, ky)
                        if best is None or cost < best[0]:
                            best = (cost, tuple(block))
                        break
        return best[1] if best is not None else (1, 1, 1)


def _counts(n: int) -> list[int]:
    """Block counts to try along an axis of ``n``: 1 to ``n``, each about 1/8 more than the last."""
    out = [1]
    while out[-1] < n:
        out.append(min(n, max(out[-1] + 1, out[-1] * 9 // 8)))
    return out
