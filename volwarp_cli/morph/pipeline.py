"""From the inputs to a ready :class:`~.interpolate.Morph`: fields, alignment, grid, warp.

Every distance field is computed once (on its input's grid); frames only
interpolate. :func:`prepare_on` runs the steps of :mod:`.fields` where a
:class:`~.fields.Steps` says (in memory, or by blocks on an engine);
:func:`prepare` is the in-memory case for loaded volumes. Nothing here reads
or writes files of its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import Geometry
from ..memory import ensure_fits_in_memory
from ..progress import log, timed
from ..volume import Volume
from .align import linear_scale
from .fields import (
    Steps,
    alignment_matrices,
    attribute_values,
    onto_grid,
    shape_field,
    shape_rule,
)
from .grid import GridError, choose_grid
from .interpolate import Morph
from .landmarks import LandmarkWarp
from .spec import MorphJob


@dataclass
class Prepared:
    """A morph ready for its frames (:func:`prepare_on`).

    Both fields on the frame grid, the alignment matrices, the landmark warp back,
    the voxels of each field's grid its input did not cover (in memory: they
    were filled), and each attribute's source and target on the grid.
    """

    morph: Morph
    grid: Geometry
    source_matrix: np.ndarray
    target_matrix: np.ndarray
    warp_back: LandmarkWarp | None
    uncovered: dict
    attributes: dict = field(default_factory=dict)  # name -> (source on grid, target on grid)
    attribute_types: dict = field(default_factory=dict)  # name -> its source's type
    rules: dict = field(default_factory=dict)  # "source"/"target" -> its shape's rule


def prepare(job: MorphJob, source: Volume, target: Volume,
            attributes: dict[str, tuple[Volume, Volume]] | None = None) -> Prepared:
    """Compute both fields, align them, pick the grid, fit the warp: in memory."""

    def check(grid, matrices):
        ensure_fits_in_memory(grid.size * 4 * (5 if job.warp_mode == "static" else 11),
                              f"a morph on a {'x'.join(map(str, grid.shape_xyz))} grid")

    return prepare_on(job, {"source": (source.header, source.data),
                            "target": (target.header, target.data)},
                      {name: ((a.header, a.data), (b.header, b.data))
                       for name, (a, b) in (attributes or {}).items()}, Steps(), check=check)


def prepare_on(job: MorphJob, inputs: dict, attributes: dict, steps: Steps, *,
               check=None) -> Prepared:
    """The morph's fields and attributes on the frame grid, each step where ``steps`` runs it.

    ``inputs``: ``{"source": (header, samples), "target": ...}`` (a
    :class:`~volwarp_cli.volume.Header` for the geometry, sliceable samples);
    ``attributes``: name -> ``((header, samples), (header, samples))``. ``check(grid, matrices)``:
    called once the frame grid is known, before any field (a refusal there
    costs no work but the alignment's). In memory (``steps.whole``) the
    voxels no input covers are filled and a landmark warp applied; by blocks
    the caller refuses both first. Each shape follows the label rule
    (:func:`.fields.shape_rule`) and a label-map attribute is refused
    (:func:`.fields.attribute_values`), before any work.
    """
    rules = {name: shape_rule(job, name, *inputs[name]) for name in ("source", "target")}
    for name, pair in attributes.items():
        for side, (header, samples) in zip(("source", "target"), pair, strict=True):
            attribute_values(job, name, side, header, samples)
    matrices = alignment_matrices(job, inputs, steps, rules)
    grid = choose_grid(job.grid, Geometry.of(inputs["source"][0]),
                       Geometry.of(inputs["target"][0]), matrices["source"],
                       matrices["target"], moved=job.moved, margin=job.margin)
    if check is not None:
        check(grid, matrices)
    log.info("frame grid %s, spacing %s, origin %s", grid.shape_xyz, list(grid.spacing),
             list(grid.origin))
    on_grid, uncovered = {}, {}
    for name in ("source", "target"):
        header, samples = inputs[name]
        mat = matrices[name]
        values = onto_grid(shape_field(job, name, header, samples, steps, rules[name]), header,
                           mat, grid, steps, name, outside="nan", scale=linear_scale(mat))
        uncovered[name] = 0
        if steps.whole:
            uncovered[name] = _fill_uncovered(values, grid, job, name)
        on_grid[name] = values
    warp_back = warp_fwd = None
    if job.warp_source_points is not None:
        ps = _apply(matrices["source"], job.warp_source_points)
        pt = _apply(matrices["target"], job.warp_target_points)
        warp_fwd = LandmarkWarp.fit(ps, pt, kind=job.warp_kind, sigma=job.warp_sigma)
        warp_back = LandmarkWarp.fit(pt, ps, kind=job.warp_kind, sigma=job.warp_sigma)
    with timed("warp"):
        morph = Morph(on_grid["source"], on_grid["target"], grid, warp_back=warp_back,
                      warp_fwd=warp_fwd, mode=job.warp_mode)
    prepared = Prepared(morph, grid, matrices["source"], matrices["target"], warp_back,
                        uncovered, rules=rules)
    for name, pair in attributes.items():
        sa, sb = (onto_grid(samples, header, matrices[side], grid, steps,
                            f"attribute {name} ({side})", outside="nearest")
                  for side, (header, samples) in zip(("source", "target"), pair, strict=True))
        prepared.attributes[name] = (morph.static_source(sa, warp_back), sb)
        prepared.attribute_types[name] = np.dtype(pair[0][1].dtype)
    return prepared


def _fill_uncovered(values: np.ndarray, grid: Geometry, job: MorphJob, name: str) -> int:
    """Fill the frame voxels the input's grid does not cover (NaN); how many there were.

    The paper's shift-and-increment propagation across the whole field
    (:func:`volwarp_cli.distance.update.fill_uncovered`); a grid the input
    does not reach at all is the spec's error.
    """
    from ..distance.update import fill_uncovered

    unknown = np.isnan(values)
    count = int(unknown.sum())
    if not count:
        return 0
    if count == values.size:
        moved = getattr(job, f"align_{name}")
        key = ("align", name) if moved and not isinstance(job.grid, dict) else ("grid",)
        raise GridError("the frame grid does not overlap an input's grid at all "
                        f"({name} {ref_path(job, name)})", key=key)
    fill_uncovered(values, unknown, grid.spacing_zyx,
                   metric="minnorm" if job.metric in ("minnorm", "taxicab") else "euclidean")
    return count


def ref_path(job: MorphJob, name: str):
    """The input path of the job's ``name`` shape (``"source"`` or ``"target"``)."""
    return getattr(job, name).path


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]
