"""Which operation computes a distance field: a band of blocks, or passes over whole lines.

The euclidean field within ``--max-distance`` (or to a sub-voxel surface) is
local: :class:`.band.BandedDistance` computes any block from itself grown by
a halo. The exact field of the whole, and the line metrics, are not: they
run in passes (:mod:`.passes`). Either is an operation of
:mod:`volwarp_cli.execute`, run in memory or by blocks as the budget says.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError
from .band import BandedDistance
from .field import check_method
from .passes import ExactDistance, LineMetricDistance, mask_source


def field_operation(source, grid, rule, *, metric: str, surface: str,
                    max_distance: float | None = None, unsigned: bool = False, target=None,
                    name: str | None = None):
    """The operation computing ``rule``'s field of ``source`` on ``grid``.

    ``rule``: a :class:`.labels.ShapeRule`; ``surface``: ``"voxel"`` or
    ``"subvoxel"``, as :func:`.scan.field_surface` resolved it; ``target``:
    the output (:class:`~volwarp_cli.execute.Target`). A sheared ``grid`` is
    refused (the message starts with ``name``, the input, when given): every pass measures along an index
    axis by its spacing, a world distance only where the axes meet at right
    angles (a z axis leaning half a voxel per plane put 3.5 mm errors in a
    10 mm ball's field); so is one whose direction's columns are not unit
    vectors (the spacing is not the world step then).
    """
    check_axes(grid, name)
    check_method(metric, surface)
    if metric == "euclidean" and (max_distance is not None or surface == "subvoxel"):
        return BandedDistance(source, grid, rule, surface=surface, max_distance=max_distance,
                              unsigned=unsigned, target=target)
    masks = mask_source(source, rule)
    if metric == "euclidean":
        return ExactDistance(masks, grid, target=target, unsigned=unsigned)
    return LineMetricDistance(masks, grid, metric=metric, target=target, unsigned=unsigned,
                              max_distance=max_distance)


def check_axes(grid, name: str | None = None) -> None:
    """Refuse a grid along whose axes the spacing is not the world step (:func:`field_operation`).

    ``name``: the input, which the message starts with when given.
    """
    if not grid.right_angled:
        raise VolwarpError(f"{name + ': ' if name else ''}its grid is sheared (its axes are not at right angles), "
                           "and a distance field's passes measure along the axes: resample it "
                           "onto a grid with right angles first (volwarp apply --reference), "
                           "or read a tilted DICOM series without --keep-shear")
    if not grid.orthonormal:
        lengths = ", ".join(f"{v:.6g}" for v in np.linalg.norm(grid.direction_array, axis=0))
        raise VolwarpError(f"{name + ': ' if name else ''}its direction's columns are not unit "
                           f"vectors (lengths {lengths}, as a MetaImage's TransformMatrix may "
                           "have them), so its spacing is not the world step a distance "
                           "field's passes measure by: convert it to .nrrd first (the lengths "
                           "become its spacing)")


def field_memory(shape_zyx, dtype, *, metric: str = "euclidean", surface: str = "auto",
                 max_distance: float | None = None) -> int:
    """The bytes the in-memory field of a grid of ``shape_zyx`` and ``dtype`` holds at its peak.

    Its operation's own count (:meth:`~volwarp_cli.execute.Operation.memory`
    of the whole, the field included), before any sample is read; under
    ``surface="auto"`` the euclidean field's larger of the voxel and
    sub-voxel ways (which one, the samples say); ``max_distance``: a band's.
    """
    from ..geometry import Geometry
    from .labels import ShapeRule

    source = np.broadcast_to(np.zeros((), dtype), tuple(int(n) for n in shape_zyx))
    grid = Geometry(source.shape, (1.0, 1.0, 1.0))
    rule = ShapeRule("intensity", "given", iso=0.5)
    surfaces = ["voxel", "subvoxel"] if metric == "euclidean" and surface == "auto" else [
        "voxel" if surface == "auto" else surface]
    return max(field_operation(source, grid, rule, metric=metric, surface=s,
                               max_distance=max_distance).memory(grid.box) for s in surfaces)
