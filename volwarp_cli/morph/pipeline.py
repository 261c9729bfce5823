"""From loaded volumes to a ready :class:`~.interpolate.Morph`: fields, alignment, grid, warp.

Every distance field is computed once (on its input's grid); frames only
interpolate. Nothing here reads or writes files.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..distance.field import finish_field, inside_mask, signed_distance
from ..errors import OutOfMemoryError, VolwarpError
from ..geometry import Geometry
from ..memory import ensure_fits_in_memory
from ..progress import log, timed
from ..volume import Volume, xyz_to_zyx
from .align import affine_from_params, shape_centroid
from .grid import GridError, choose_grid
from .interpolate import Morph, grid_field, resample_to_grid
from .landmarks import LandmarkWarp
from .spec import MorphJob


@dataclass
class Prepared:
    """A morph ready for its frames (:func:`prepare`).

    Both fields on the frame grid, the alignment matrices, the landmark warp back,
    the voxels of each field's grid its input did not cover, and each attribute's
    source and target on the grid.
    """

    morph: Morph
    grid: Geometry
    source_matrix: np.ndarray
    target_matrix: np.ndarray
    warp_back: LandmarkWarp | None
    uncovered: dict
    attributes: dict = field(default_factory=dict)  # name -> (source on grid, target on grid)
    attribute_types: dict = field(default_factory=dict)  # name -> its source's type


def _matrix(params, vol: Volume, iso: float, inside: str) -> np.ndarray:
    if not params:
        return np.eye(4)
    center = None
    if "center" not in params and "matrix" not in params:
        center = shape_centroid(inside_mask(vol.data, iso, inside), vol.index_to_world_matrix)
    return affine_from_params(params, default_center=center)


def prepare(job: MorphJob, source: Volume, target: Volume,
            attributes: dict[str, tuple[Volume, Volume]] | None = None) -> Prepared:
    """Compute both fields, align them, pick the grid, fit the warp."""
    fields = {}
    for name, vol, ref in (("source", source, job.source), ("target", target, job.target)):
        with timed(f"{name} distance ({job.metric})"):
            try:
                fields[name], _ = signed_distance(vol.data, xyz_to_zyx(vol.spacing), iso=ref.iso,
                                                  inside=ref.inside, metric=job.metric,
                                                  surface=job.surface)
                finish_field(fields[name], max_distance=job.max_distance)
            except VolwarpError as exc:  # (named after its input; a refusal stays one)
                kind = OutOfMemoryError if isinstance(exc, OutOfMemoryError) else VolwarpError
                raise kind(f"{ref.path}: {exc}") from None
    a_s = _matrix(job.align_source, source, job.source.iso, job.source.inside)
    a_t = _matrix(job.align_target, target, job.target.iso, job.target.inside)
    grid = choose_grid(job.grid, Geometry.of(source), Geometry.of(target), a_s, a_t, moved=job.moved,
                       margin=job.margin)
    ensure_fits_in_memory(grid.size * 4 * (5 if job.warp_mode == "static" else 11),
                          f"a morph on a {'x'.join(map(str, grid.shape_xyz))} grid")
    log.info("frame grid %s, spacing %s, origin %s", grid.shape_xyz, list(grid.spacing),
             list(grid.origin))
    uncovered = {}
    on_grid = {}
    for name, vol, mat in (("source", source, a_s), ("target", target, a_t)):
        with timed(f"{name} field onto the frame grid"):
            try:
                on_grid[name], uncovered[name] = grid_field(
                    fields.pop(name), vol.index_to_world_matrix, mat, grid, job.metric)
            except GridError as exc:  # the spec's alignment or grid put it elsewhere
                moved = getattr(job, f"align_{name}")
                key = ("align", name) if moved and not isinstance(job.grid, dict) else ("grid",)
                raise GridError(f"{exc} ({name} {ref_path(job, name)})", key=key) from None
    warp_back = warp_fwd = None
    if job.warp_source_points is not None:
        ps = _apply(a_s, job.warp_source_points)
        pt = _apply(a_t, job.warp_target_points)
        warp_fwd = LandmarkWarp.fit(ps, pt, kind=job.warp_kind, sigma=job.warp_sigma)
        warp_back = LandmarkWarp.fit(pt, ps, kind=job.warp_kind, sigma=job.warp_sigma)
    with timed("warp"):
        morph = Morph(on_grid["source"], on_grid["target"], grid, warp_back=warp_back,
                      warp_fwd=warp_fwd, mode=job.warp_mode)
    prepared = Prepared(morph, grid, a_s, a_t, warp_back, uncovered)
    for name, (va, vb) in (attributes or {}).items():
        sa = resample_to_grid(va.data, va.index_to_world_matrix, a_s, grid, outside="nearest")
        sb = resample_to_grid(vb.data, vb.index_to_world_matrix, a_t, grid, outside="nearest")
        prepared.attributes[name] = (morph.static_source(sa, warp_back), sb)
        prepared.attribute_types[name] = va.data.dtype
    return prepared


def ref_path(job: MorphJob, name: str):
    """The input path of the job's ``name`` shape (``"source"`` or ``"target"``)."""
    return getattr(job, name).path


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]
