"""The sweep's one evaluation, on any block of the output grid: the whole grid is one block.

A sweep has no input volume (:func:`~volwarp_cli.regions.sweep_input`): every
output voxel is computed from its own world point and the swept model alone,
so a block of the output is a pure function of its :class:`~volwarp_cli.box.Box`
and the model, and the blocks need no overlap. Each path has its block form:

* ``voxelize`` (:func:`.voxelize.voxelize_block`): the subdivision into
  templates depends on the sweep and ``tau`` only (the default ``tau``, half
  the smallest voxel side, is the whole grid's), so it is made once
  (:func:`prepare_sweep`, a :class:`~.voxelize.VoxelPlan` per sweep) and
  handed to every block; the kernel then runs the sub-segments' voxel boxes
  clamped to the block, with indices (hence world points) of the whole grid;
* ``direct`` (:func:`.direct.direct_block`): the inverse mapping of each voxel
  of the block, from the same world point, candidates met in the same order;
* the CVG operators, within a sweep (the kernels' per-voxel accumulation, the
  blend's division by its weight sum) and between the sweeps of a ``scene``
  (:func:`.cvg.combine_objects`), are voxelwise: a block combines the blocks.

Nothing of the sweep is global over the output (no normalisation, no
bounding box of the result): nothing is refused for being blocked. What the
in-memory sweep refuses, a block refuses with the same error: a grid whose
direction is not the identity (the sweep's samplers place voxel ``(i, j, k)``
at ``origin + spacing * (i, j, k)``, :func:`.voxelize.check_axis_aligned`),
and for ``method: direct``, polyline segments and directions it cannot invert
(:func:`.direct.check_direct`).

Block tasks call the kernels in their own thread (C kernels that release
the GIL, :mod:`._sweepkernels`): a Dask scheduler runs tasks in threads of
its own, and the parallelism is across blocks.

Nothing here imports dask: the executor (:mod:`volwarp_cli.execute`) runs the blocks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..box import Box
from ..errors import BadUsage, VolwarpError
from ..geometry import Geometry
from .cvg import combine_objects
from .direct import check_direct, direct_block
from .model import SceneNode, Sweep, SweepSpec
from .voxelize import TooManyTemplates, VoxelPlan, check_axis_aligned, plan_voxelize, voxelize_block

METHODS = ("voxelize", "direct")


@dataclass
class SweepPlan:
    """What every block of one sweep run shares: the model, the method, the subdivisions.

    ``root``: the sweep or scene tree; ``names``: the output fields in order;
    ``voxel_plans``: a :class:`~.voxelize.VoxelPlan` per sweep (voxelize only), by
    the sweep's position in :meth:`~.model.SceneNode.sweeps` order.
    """

    root: Sweep | SceneNode
    method: str
    names: list[str]
    geometry: Geometry
    voxel_plans: list[VoxelPlan] = field(default_factory=list)


def _sweeps(root) -> list[Sweep]:
    return root.sweeps() if isinstance(root, SceneNode) else [root]


def _sweep_tau(sweep: Sweep, grid: Geometry, tau, default_tau) -> float:
    """The voxelising step, chosen as :func:`volwarp_cli.sweep.evaluate_sweep` chooses it."""
    for t in (tau, sweep.tau, default_tau, 0.5 * float(np.min(grid.spacing))):
        if t is not None:
            return float(t)
    raise AssertionError("unreachable")  # pragma: no cover


def prepare_sweep(model, geometry: Geometry, *, method: str | None = None,
                  tau: float | None = None) -> SweepPlan:
    """Check ``model`` on ``geometry`` and make what its blocks share (:class:`SweepPlan`).

    Parameters
    ----------
    model : SweepSpec, Sweep or SceneNode
        The parsed spec (its ``method`` and ``tau`` are the defaults), or one
        sweep or scene of it (a :class:`SweepPlan` is returned as it is).
    geometry : Geometry
        The whole output grid (axis-aligned, as the sweep's samplers take it).
    method : {"voxelize", "direct"}, optional
        As :func:`volwarp_cli.sweep.evaluate`'s: default the spec's, else voxelize.
    tau : float, optional
        As :func:`volwarp_cli.sweep.evaluate`'s (wins over the sweep's and the spec's).

    Raises
    ------
    VolwarpError
        For a grid with a non-identity direction; a SpecError for what
        ``method: direct`` cannot invert (as the in-memory sweep raises them).
    """
    if isinstance(model, SweepPlan):
        return model
    default_tau = None
    if isinstance(model, SweepSpec):
        method = method or model.method
        default_tau = model.tau
        root = model.root
    elif isinstance(model, (Sweep, SceneNode)):
        root = model
    else:
        raise TypeError(f"a sweep model is a SweepSpec, Sweep or SceneNode, got "
                        f"{type(model).__name__}")
    method = method or "voxelize"
    if method not in METHODS:
        raise VolwarpError(f"unknown sweep method {method!r} (known: {', '.join(METHODS)})")
    if method == "direct" and tau is not None:  # (it was taken and ignored)
        raise BadUsage("--tau spaces the templates the voxelize method places; the direct "
                       "method inverts the mapping at every voxel and has none")
    sweeps = _sweeps(root)
    if method == "direct" and (default_tau is not None or any(sw.tau is not None
                                                              for sw in sweeps)):
        message = ("tau spaces the templates the voxelize method places; the direct method "
                   "inverts the mapping at every voxel and has none (leave tau out, or use "
                   "the voxelize method)")
        doc = getattr(model, "doc", None)
        if doc is not None and default_tau is not None:  # (the spec's key and line)
            from ..spec.functions import spec_error

            raise spec_error(doc, ("tau",), message)
        raise BadUsage(f"the spec's {message}")
    check_axis_aligned(geometry)
    if isinstance(root, SceneNode):
        names = root.field_names()
    else:
        names = list(root.templates)
    plans = []
    for sw in sweeps:
        if method == "direct":
            check_direct(sw)
        else:
            try:
                plans.append(plan_voxelize(sw, _sweep_tau(sw, geometry, tau, default_tau)))
            except TooManyTemplates as exc:
                raise _too_many(exc, sw, getattr(model, "doc", None), tau, default_tau) from None
    return SweepPlan(root, method, names, geometry, plans)


def _too_many(exc: TooManyTemplates, sweep: Sweep, doc, tau, default_tau) -> VolwarpError:
    """``exc`` at what asked for it: ``--tau``, the spec's ``tau`` or a field's ``path`` key.

    (A tau of 1e-300 was an exit 1 that named no key.) With the default tau
    (half the grid's spacing) it stays as it is: the trajectory is too long for the grid.
    """
    from ..spec.functions import spec_error

    if exc.cause == "path":
        name = list(sweep.templates)[exc.template]
        return spec_error(doc, sweep.key + ("fields", name, "path"), str(exc))
    if tau is not None:
        return BadUsage(f"--tau: {exc}")
    if sweep.tau is not None:
        return spec_error(doc, sweep.key + ("tau",), str(exc))
    if default_tau is not None:
        return spec_error(doc, ("tau",), str(exc))
    return exc


def block_fields(plan: SweepPlan, box: Box, *, threads: int = 1) -> dict[str, np.ndarray]:
    """``{field: float32 [z, y, x]}`` of the sweep tree on the voxels ``box``.

    The one evaluation of a sweep: the whole grid is the box
    ``plan.geometry.box`` (:func:`volwarp_cli.sweep.evaluate`), a block any
    box inside it, with the whole's values bit for bit. ``threads``: 1 in a
    block task (the calling thread only), more for the whole grid's run.
    """
    index = {id(sw): i for i, sw in enumerate(_sweeps(plan.root))}

    def run(node):
        if isinstance(node, SceneNode):
            return combine_objects(node.ops, [run(c) for c in node.children], box.shape)
        if plan.method == "direct":
            return direct_block(node, plan.geometry, box, threads=threads)
        return voxelize_block(plan.voxel_plans[index[id(node)]], plan.geometry, box,
                              threads=threads)

    return run(plan.root)


def sweep_block(model, geometry: Geometry, box: Box, *, method: str | None = None,
                tau: float | None = None, plan: SweepPlan | None = None) -> np.ndarray:
    """The output samples of ``box``, exactly as the whole sweep computes them.

    Parameters
    ----------
    model : SweepSpec, Sweep or SceneNode
        What :func:`prepare_sweep` takes.
    geometry : Geometry
        The whole output grid (not the block's: voxel indices, hence world
        points, are the whole grid's).
    box : Box
        The block, array order (z, y, x), inside ``geometry.box``.
    method, tau : optional
        As :func:`prepare_sweep`'s.
    plan : SweepPlan, optional
        :func:`prepare_sweep`'s result for the same model, geometry, method and
        tau: pass it when computing many blocks (else the subdivision is made
        again for this block, with the same result).

    Returns
    -------
    numpy.ndarray
        float32 ``[F, z, y, x]``: the fields in :attr:`SweepPlan.names` order
        (``model.field_names()``), each ``evaluate(...)[name][box.slices]``.
    """
    if plan is None:
        plan = prepare_sweep(model, geometry, method=method, tau=tau)
    elif plan.geometry != geometry:
        raise VolwarpError("the sweep plan was made for another grid")
    if not geometry.box.contains(box):
        raise VolwarpError(f"block {box} lies outside the sweep's grid of shape {geometry.shape}")
    fields = block_fields(plan, box)
    out = np.empty((len(plan.names),) + box.shape, dtype=np.float32)
    for f, name in enumerate(plan.names):
        out[f] = fields[name]
    return out


def field_names(model) -> list[str]:
    """The output fields of ``model`` (a SweepSpec, Sweep, SceneNode or SweepPlan), in order.

    The order of the first axis of :func:`sweep_block`'s arrays.
    """
    if isinstance(model, SweepPlan):
        return list(model.names)
    if isinstance(model, (SweepSpec, SceneNode)):
        return model.field_names()
    return list(model.templates)
