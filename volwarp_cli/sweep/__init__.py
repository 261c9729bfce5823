"""Image-swept volumes (Winter & Chen 2002): templates swept along trajectories into fields.

``trajectory`` (segments a(u)), ``frames`` (direction, up, scale -> template
frames), ``templates`` (images and image stacks on [0, 1]^2), ``voxelize``
(adaptive subdivision, §4.2), ``direct`` (inverse mapping, §5.2-5.3),
``cvg`` (real-domain operators, §4.3), ``model`` (the spec as objects),
``_sweepkernels`` (the voxeliser's and the Bezier root finder's loops, in C).
:func:`evaluate` runs a whole spec (one sweep or a scene tree) on a grid.
"""

from __future__ import annotations


def evaluate(spec, grid, method: str | None = None, tau: float | None = None) -> dict:
    """All output fields of a :class:`~.model.SweepSpec` on ``grid``, ``{name: [z, y, x]}``.

    ``grid``: an axis-aligned :class:`~volwarp_cli.geometry.Geometry` (identity
    direction), e.g. :func:`.model.fit_grid`'s. The whole grid as one block
    of :func:`.chunked.block_fields` on volwarp's threads: the same
    evaluation as any block of it (``volwarp sweep`` runs it through the
    executor, :class:`.run.SweepOperation`).
    """
    from .. import parallel
    from .chunked import block_fields, prepare_sweep

    plan = prepare_sweep(spec, grid, method=method, tau=tau)
    return block_fields(plan, grid.box, threads=parallel.threads())
