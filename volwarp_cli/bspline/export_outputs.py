"""A finished warp's deformation exports, written beside its output.

``volwarp warp`` can also write what its final lattice does, for other tools
(see :mod:`.export` for the maths and the formats): the resampling
displacement field on the output grid (``--displacement-to``), the forward
field (``--forward-field-to``) and det dF/dx (``--jacobian-to``) on the
input grid, the ITK transform (``--transform-to``), and moved points and
meshes (``--points-in``/``--points-to``, ``--mesh-in``/``--mesh-to``).
:func:`write_exports` writes the requested ones (each file atomic on its
own) and returns their figures.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..io import write_volume
from ..progress import log, timed
from ..volume import Volume


@dataclass(frozen=True)
class ExportRequests:
    """The exports asked for: output paths, and the points and meshes to move.

    ``points``: ``(PointsFile, output path)``; ``mesh``: ``(Mesh, its source
    path, output path)``. False when nothing is asked for.
    """

    displacement: str | None = None
    forward: str | None = None
    jacobian: str | None = None
    transform: str | None = None
    points: tuple | None = None
    mesh: tuple | None = None

    def __bool__(self) -> bool:
        return any(getattr(self, f.name) is not None for f in fields(self))


def write_exports(requests: ExportRequests, warp, *, meta: dict, mesh_meta: dict) -> dict:
    """Write the exports of ``warp`` and return their figures, keyed as ``warp --json`` has them.

    ``warp`` is a rendered :class:`.run.IntensityWarp`, whose final lattice they
    describe. The figures: ``jacobian`` {path, min, max, below_0, below_0_1},
    ``displacement`` {path, voxels, folded, no_preimage}, ``points`` / ``mesh``
    {path, count, outside}.

    ``meta``: the key/values (provenance) of the field, Jacobian and transform
    files; ``mesh_meta``: the moved mesh's comments.
    """
    from .export import (
        ForwardMap,
        field_stats_ok,
        jacobian_stats,
        report_outside,
        write_field,
        write_points,
        write_tfm,
    )
    from .warp import _output_window

    cap, scene = warp.cap, warp.scene
    stats = {}
    fmap = ForwardMap(cap.grid, warp.final_lattice, cap.geometry)
    g = cap.geometry
    nx, ny, nz = cap.grid.input_shape
    in_grid = Volume(np.zeros((nz, ny, nx), np.uint8), spacing=g.spacing, origin=g.origin,
                     direction=g.direction, space=g.space)
    if requests.displacement is not None:
        path = requests.displacement
        window, origin = _output_window(cap, scene, warp.options.crop)
        shape = tuple(w.stop - w.start for w in window)
        out_grid = Volume(np.zeros(shape, np.uint8), spacing=g.spacing, origin=origin,
                          direction=g.direction, space=g.space)
        shift = np.array([window[2].start, window[1].start, window[0].start]) - np.array(scene.pad)
        with timed(f"invert the map on {shape[2]}x{shape[1]}x{shape[0]} voxels"):
            field, counts = fmap.resampling_field(shape[::-1], shift)
        log.info("%s: %s", path, field_stats_ok(counts))
        if counts["folded"]:
            log.warning("%s: the map folds: %d voxels have no single inverse (NaN)", path,
                        counts["folded"])
        with timed(f"write {path}"):
            write_field(field, out_grid, path, meta, "resampling")
        stats["displacement"] = {"path": str(path), "voxels": counts["voxels"],
                                 "folded": counts["folded"],
                                 "no_preimage": counts["no_inverse"]}
        del field
    if requests.forward is not None:
        path = requests.forward
        with timed(f"write {path}"):
            write_field(fmap.forward_field(), in_grid, path, meta, "forward")
    if requests.jacobian is not None:
        path = requests.jacobian
        det = fmap.jacobian()
        st = jacobian_stats(det)
        log.info("%s: det dF/dx min %.4g, max %.4g; %.3g%% of voxels below 0, %.3g%% below 0.1",
                 path, st["min"], st["max"], 100 * st["below_0"], 100 * st["below_0.1"])
        stats["jacobian"] = {"path": str(path), "min": st["min"], "max": st["max"],
                             "below_0": st["below_0"], "below_0_1": st["below_0.1"]}
        jmeta = {**dict(g.meta), **meta, "volwarp_field": "jacobian"}
        with timed(f"write {path}"):
            write_volume(in_grid.with_data(det, meta=jmeta), path)
    if requests.transform is not None:
        path = requests.transform
        with timed(f"write {path}"):
            write_tfm(fmap, path, meta)
    if requests.points is not None:
        pf, path = requests.points
        moved, inside = fmap.map_world(pf.points)
        outside = report_outside(pf.path, inside, fmap)
        with timed(f"write {path}"):
            write_points(pf, moved, path)
        stats["points"] = {"path": str(path), "count": len(inside), "outside": outside}
    if requests.mesh is not None:
        from ..surface.mesh import Mesh
        from ..surface.mesh_io import write_mesh

        mesh, src, path = requests.mesh
        moved, inside = fmap.map_world(mesh.vertices)
        outside = report_outside(src, inside, fmap)
        out = Mesh(moved, mesh.faces).with_normals()
        with timed(f"write {path}"):
            write_mesh(out, path, comments={**mesh_meta, "volwarp_field": "forward"})
        stats["mesh"] = {"path": str(path), "count": len(inside), "outside": outside}
    return stats
