"""Image-swept volumes (Winter & Chen 2002): templates swept along trajectories into fields.

``trajectory`` (segments a(u)), ``frames`` (direction, up, scale -> template
frames), ``templates`` (images and image stacks on [0, 1]^2), ``voxelize``
(adaptive subdivision, §4.2), ``direct`` (inverse mapping, §5.2-5.3),
``cvg`` (real-domain operators, §4.3), ``model`` (the spec as objects).
:func:`evaluate` runs a whole spec (one sweep or a scene tree) on a grid.
"""

from __future__ import annotations

import numpy as np

from ..progress import timed


def evaluate_sweep(sweep, grid, method: str = "voxelize", tau: float | None = None,
                   default_tau: float | None = None) -> dict:
    """Fields of one sweep on ``grid`` (an axis-aligned :class:`~volwarp_cli.geometry.Geometry`).

    ``tau`` (e.g. from the command line) wins over the sweep's own ``tau``,
    which wins over ``default_tau`` (the spec's top-level one), which defaults
    to half the smallest voxel side.
    """
    if method == "direct":
        from .direct import direct_sweep
        return direct_sweep(sweep, grid)
    from .voxelize import voxelize_sweep
    for t in (tau, sweep.tau, default_tau, 0.5 * float(np.min(grid.spacing))):
        if t is not None:
            break
    return voxelize_sweep(sweep, grid, float(t))


def evaluate(spec, grid, method: str | None = None, tau: float | None = None) -> dict:
    """All output fields of a :class:`~.model.SweepSpec` on ``grid``, ``{name: [z, y, x]}``.

    ``grid``: an axis-aligned :class:`~volwarp_cli.geometry.Geometry` (identity
    direction), e.g. :func:`.model.fit_grid`'s.
    """
    from .cvg import combine_objects
    from .model import SceneNode

    method = method or spec.method or "voxelize"

    def run(node):
        if isinstance(node, SceneNode):
            objects = [run(c) for c in node.children]
            with timed("sweep: combine scene"):
                return combine_objects(node.ops, objects, grid.shape)
        return evaluate_sweep(node, grid, method, tau, spec.tau)

    return run(spec.root)
