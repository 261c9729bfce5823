"""A finished warp's deformation exports, written beside its output.

``volwarp warp`` can also write what its final lattice does, for other tools
(see :mod:`.export` for the maths and the formats): the resampling
displacement field on the output grid (``--displacement-to``), the forward
field (``--forward-field-to``) and det dF/dx (``--jacobian-to``) on the
input grid, the ITK transform (``--transform-to``), and moved points and
meshes (``--points-in``/``--points-to``, ``--mesh-in``/``--mesh-to``).
:func:`write_exports` writes the requested ones (each file atomic on its
own) and returns their figures.

By blocks (``warp --chunked``, :class:`FieldBlocks`): the small exports
(transform, points, meshes) depend on the final lattice only and are made
as in memory; the volume-sized fields are computed and written slab by slab
of z planes (their values are per voxel: the same float32 values as in
memory, and the same figures, the slabs' counts added and their extremes
combined) into block outputs (:mod:`volwarp_cli.io.blockwrite`), so that
no whole field is held. A field is then an uncompressed NRRD, the bytes of
the in-memory one (a NIfTI field or a compressed one, ``--compress``, cannot
be placed by slabs: :func:`block_export_problem` says so before any work),
the Jacobian any format written by blocks (uncompressed NRRD, MetaImage,
raw, OME-Zarr).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..io import write_volume
from ..progress import log, timed
from ..volume import Header


@dataclass(frozen=True)
class ExportRequests:
    """The exports asked for: output paths, and the points and meshes to move.

    ``points``: ``(PointsFile, output path)``; ``mesh``: ``(Mesh, its source
    path, output path)``. False when nothing is asked for. ``compress``,
    ``byte_order``, ``ome_zarr_version``: the command's writer options, for
    the fields and the Jacobian as for its output (gzip NRRD, zlib
    MetaImage; a ``.nii.gz`` is gzip either way).
    """

    displacement: str | None = None
    forward: str | None = None
    jacobian: str | None = None
    transform: str | None = None
    points: tuple | None = None
    mesh: tuple | None = None
    compress: bool = False
    byte_order: str = "little"
    ome_zarr_version: str = "0.5"

    def __bool__(self) -> bool:
        return any(getattr(self, f.name) is not None for f in fields(self)
                   if f.name not in WRITER_OPTIONS)

    @property
    def writes_volumes(self) -> bool:
        """Whether a field or the Jacobian is asked for (what the writer options reach)."""
        return any(p is not None for p in (self.displacement, self.forward, self.jacobian))


#: the writer options an :class:`ExportRequests` carries (not exports)
WRITER_OPTIONS = ("compress", "byte_order", "ome_zarr_version")


#: the most field samples (bytes) a slab of the displacement field holds by blocks
SLAB_BYTES = 16 << 20


@dataclass(frozen=True)
class FieldBlocks:
    """How :func:`write_exports` writes the volume-sized fields by slabs.

    ``memory``: the bytes a slab of the displacement field may take (its
    depth is chosen from it, and :data:`SLAB_BYTES` at most, unless ``depth``
    is given: output z planes per slab). The forward field and the Jacobian go by the slabs of
    :meth:`.export.ForwardMap.slab_depth` (about 131 000 voxels each, the
    in-memory export's own slabs); ``threads`` for the inversion (None: the CPUs).
    """

    memory: int
    depth: int | None = None
    threads: int | None = None

    def displacement_depth(self, plane_voxels: int) -> int:
        """The output z planes of a slab of the displacement field, planes of ``plane_voxels``."""
        # a slab's field (12 bytes a voxel), status (1), the fold mask (1) and the
        # slab being placed (12, at most one more): about 40 bytes a voxel
        if self.depth is not None:
            return max(1, int(self.depth))
        # no more than SLAB_BYTES of field a slab: a larger one saves nothing
        most = min(int(self.memory) // 40, SLAB_BYTES // 12)
        return max(1, most // max(1, int(plane_voxels)))


#: Bytes a whole field export holds per voxel in memory, measured (peak RSS less the
#: command's without it, 200^3 voxels): the displacement 46 (3 float32 components, a
#: status byte, the inversion's and the writer's copies), the forward field 27, the
#: Jacobian 12.6; rounded up
WHOLE_FIELD_BYTES = {"displacement": 48, "forward": 28, "jacobian": 14}


def whole_fields_bytes(requests: ExportRequests, warp) -> int:
    """What the volume-sized exports hold in memory at their peak, written whole (0: none asked).

    They are made one after the other: the largest counts. The displacement
    is on the output grid, the forward field and the Jacobian on the input's.
    """
    from .prepare import _output_window

    cap = warp.cap
    nx, ny, nz = cap.grid.input_shape
    sizes = []
    if requests.displacement is not None:
        window, _ = _output_window(cap, warp.scene, warp.options.crop)
        out = int(np.prod([w.stop - w.start for w in window]))
        sizes.append(out * WHOLE_FIELD_BYTES["displacement"])
    for name in ("forward", "jacobian"):
        if getattr(requests, name) is not None:
            sizes.append(nx * ny * nz * WHOLE_FIELD_BYTES[name])
    return max(sizes, default=0)


def refuse_export_byte_order(requests: ExportRequests) -> None:
    """A NIfTI export with ``--byte-order big``: the usage error ``-o x.nii`` gets, before any work.

    (Found when the Jacobian was written, after the warp's work, in a first
    version; a NIfTI field was written little-endian without a word.)
    """
    from ..io import check_byte_order, volume_format

    for name, path in (("--displacement-to", requests.displacement),
                       ("--forward-field-to", requests.forward),
                       ("--jacobian-to", requests.jacobian)):
        if path is not None:
            check_byte_order(path, volume_format(path), requests.byte_order, name)


def say_unused_field_options(requests: ExportRequests, path: str) -> None:
    """Say the writer options a field's file has no use for, as an output's are said."""
    from ..io import say_unused_writer_options, volume_format

    say_unused_writer_options(path, volume_format(path), requests.compress,
                              requests.ome_zarr_version)


def block_export_problem(requests: ExportRequests) -> str | None:
    """Why ``requests`` cannot be written by blocks (a sentence naming the option), or None.

    The fields are written by blocks as uncompressed NRRD only (not NIfTI, not
    with ``--compress``), the Jacobian in a format written by blocks
    (:func:`~volwarp_cli.io.blockwrite.check_block_format`).
    """
    from ..errors import VolwarpError
    from ..io.blockwrite import check_block_format
    from .export import field_format

    for name, path in (("--displacement-to", requests.displacement),
                       ("--forward-field-to", requests.forward)):
        if path is not None and field_format(path) != "nrrd":
            return (f"{name} {path}: a NIfTI field cannot be written by blocks; write .nrrd "
                    "(by blocks it is written uncompressed)")
        if path is not None and requests.compress:
            return (f"{name} {path}: a compressed field cannot be written by blocks; drop "
                    "--compress (by blocks a field is an uncompressed .nrrd)")
    if requests.jacobian is not None:
        try:
            check_block_format(requests.jacobian, requests.compress)
        except VolwarpError as exc:
            return f"--jacobian-to {exc}"
    return None


def _place_slabs(out, slabs, counts=None) -> None:
    """Write ``(z0, planes, ...)`` slabs (in order of z, covering the grid) into ``out``.

    ``out``'s blocks span whole planes (any z edges: a store's grid may start
    at the far end); a slab is cut or joined to its blocks, at most one slab
    more held. ``counts``: each slab's third item is added into it (a dict).
    """
    from ..box import Box

    nz, ny, nx = out.geometry.shape
    edges = sorted({(b.lo[0], b.hi[0]) for b in out.blocks()})
    if any((b.lo[1:], b.hi[1:]) != ((0, 0), (ny, nx)) for b in out.blocks()):
        raise ValueError("slabs are placed into blocks of whole planes")  # pragma: no cover
    it = iter(slabs)
    buf, start = None, 0  # buf: planes [start, start + len(buf))
    for b0, b1 in edges:
        while buf is None or start + len(buf) < b1:
            item = next(it)
            z0, planes = item[0], item[1]
            if counts is not None:
                for k, v in item[2].items():
                    counts[k] = counts.get(k, 0) + v
            if buf is None or not len(buf):
                buf, start = planes, z0
            else:
                buf = np.concatenate([buf, planes])
        out.write(Box((b0, 0, 0), (b1, ny, nx)), buf[b0 - start:b1 - start])
        buf, start = buf[b1 - start:], b1


def write_exports(requests: ExportRequests, warp, *, meta: dict, mesh_meta: dict,
                  blocks: FieldBlocks | None = None) -> dict:
    """Write the exports of ``warp`` and return their figures, keyed as ``warp --json`` has them.

    ``warp`` is a planned :class:`.run.IntensityWarp`, whose final lattice they
    describe. The figures: ``jacobian`` {path, min, max, below_0, below_0_1},
    ``displacement`` {path, voxels, folded, no_preimage}, ``points`` / ``mesh``
    {path, count, outside}.

    ``meta``: the key/values (provenance) of the field, Jacobian and transform
    files; ``mesh_meta``: the moved mesh's comments.

    ``blocks``: write the fields by slabs (:class:`FieldBlocks`; check the paths
    with :func:`block_export_problem` first). ``warp`` then needs no volume computed:
    its capture, scene and frames (a warp made with ``WarpOptions(blocks=True)``).
    The same values and figures as in memory.
    """
    from ..labelmap import without_label_keys
    from .export import (
        ForwardMap,
        field_format,
        field_stats_ok,
        jacobian_stats,
        report_outside,
        write_field,
        write_points,
        write_tfm,
    )
    from .prepare import _output_window

    cap, scene = warp.cap, warp.scene
    stats = {}
    fmap = ForwardMap(cap.grid, warp.final_lattice, cap.geometry)
    g = cap.geometry
    nx, ny, nz = cap.grid.input_shape
    in_grid = Header((nz, ny, nx), np.float32, spacing=g.spacing, origin=g.origin,
                     direction=g.direction, space=g.space)
    if requests.displacement is not None:
        path = requests.displacement
        say_unused_field_options(requests, path)
        window, origin = _output_window(cap, scene, warp.options.crop)
        shape = tuple(w.stop - w.start for w in window)
        out_grid = Header(shape, np.float32, spacing=g.spacing, origin=origin,
                          direction=g.direction, space=g.space)
        shift = np.array([window[2].start, window[1].start, window[0].start]) - np.array(scene.pad)
        if blocks is None:
            with timed(f"invert the map on {shape[2]}x{shape[1]}x{shape[0]} voxels"):
                field, counts = fmap.resampling_field(shape[::-1], shift)
        else:
            from ..io.blockwrite import committed
            from .export import field_block_output

            depth = blocks.displacement_depth(shape[1] * shape[2])
            counts = {}
            with timed(f"invert the map on {shape[2]}x{shape[1]}x{shape[0]} voxels and write "
                       f"{path}, by slabs of {depth} planes"), \
                    committed(field_block_output(path, out_grid, meta, "resampling",
                                                 depth, requests.byte_order)) as out:
                _place_slabs(out, fmap.resampling_field_slabs(shape[::-1], shift, depth,
                                                              threads=blocks.threads),
                             counts)
        log.info("%s: %s", path, field_stats_ok(counts))
        if counts["folded"]:
            log.warning("%s: the map folds: %d voxels have no single inverse (NaN)", path,
                        counts["folded"])
        nan = counts["folded"] + counts["no_inverse"]
        if nan and field_format(path) != "nrrd":
            # (SimpleITK's reader gives a NIfTI's NaN vectors as 0: no move, where there is
            # no inverse; a review measured the resampled scan 7.07 off against 2.99 with
            # the .nrrd field)
            log.warning("warning: %s: %d voxels have no inverse (NaN vectors), which ITK's "
                        "NIfTI reader takes for 0, no move: write .nrrd to keep them NaN",
                        path, nan)
        if blocks is None:
            with timed(f"write {path}"):
                write_field(field, out_grid, path, meta, "resampling",
                            compress=requests.compress, byte_order=requests.byte_order)
            del field
        stats["displacement"] = {"path": str(path), "voxels": counts["voxels"],
                                 "folded": counts["folded"],
                                 "no_preimage": counts["no_inverse"]}
    if requests.forward is not None:
        path = requests.forward
        say_unused_field_options(requests, path)
        if blocks is None:
            with timed(f"write {path}"):
                write_field(fmap.forward_field(), in_grid, path, meta, "forward",
                            compress=requests.compress, byte_order=requests.byte_order)
        else:
            from ..io.blockwrite import committed
            from .export import field_block_output

            with timed(f"write {path}, by slabs"), \
                    committed(field_block_output(path, in_grid, meta, "forward",
                                                 fmap.slab_depth(), requests.byte_order)) as out:
                _place_slabs(out, fmap.forward_field_slabs())
    if requests.jacobian is not None:
        path = requests.jacobian
        # (the input's keys but what says they are labels: a label map's Jacobian is none)
        jmeta = {**without_label_keys(g.meta), **meta, "volwarp_field": "jacobian"}
        if blocks is None:
            det = fmap.jacobian()
            st = jacobian_stats(det)
        else:
            st = _jacobian_by_slabs(fmap, in_grid, path, jmeta, requests)
        log.info("%s: det dF/dx min %.4g, max %.4g; %.3g%% of voxels below 0, %.3g%% below 0.1",
                 path, st["min"], st["max"], 100 * st["below_0"], 100 * st["below_0.1"])
        stats["jacobian"] = {"path": str(path), "min": st["min"], "max": st["max"],
                             "below_0": st["below_0"], "below_0_1": st["below_0.1"]}
        if blocks is None:
            with timed(f"write {path}"):
                write_volume(in_grid.with_data(det, meta=jmeta), path,
                             compress=requests.compress, byte_order=requests.byte_order,
                             ome_zarr_version=requests.ome_zarr_version)
            del det
    if requests.transform is not None:
        path = requests.transform
        with timed(f"write {path}"):
            write_tfm(fmap, path, meta)
    if requests.points is not None:
        pf, path = requests.points
        moved, inside = fmap.map_world(pf.points)
        outside = report_outside(pf.path, inside, fmap, pf.points)
        with timed(f"write {path}"):
            write_points(pf, moved, path)
        stats["points"] = {"path": str(path), "count": len(inside), "outside": outside}
    if requests.mesh is not None:
        from ..surface.mesh import map_orientation
        from ..surface.mesh import moved as moved_mesh
        from ..surface.mesh_io import write_mesh

        mesh, src, path = requests.mesh
        points, inside = fmap.map_world(mesh.vertices)
        outside = report_outside(src, inside, fmap)
        sign = map_orientation(lambda p: fmap.map_world(p)[0], mesh.vertices[inside])
        out = moved_mesh(mesh, points, sign, src)
        with timed(f"write {path}"):
            write_mesh(out, path, comments={**mesh_meta, "volwarp_field": "forward"})
        stats["mesh"] = {"path": str(path), "count": len(inside), "outside": outside}
    return stats


def _jacobian_by_slabs(fmap, in_grid: Header, path: str, jmeta: dict,
                       requests: ExportRequests) -> dict:
    """Write det dF/dx to ``path`` slab by slab; its :func:`.export.jacobian_stats`.

    The figures of the whole map, reduced exactly: the extremes combined, the
    counts below 0 and 0.1 added, then divided by the voxels.
    """
    from ..io.blockwrite import committed, open_block_output

    nz, ny, nx = in_grid.shape
    acc = {"min": np.inf, "max": -np.inf, "neg": 0, "low": 0, "n": 0}

    def slabs():
        for z0, det in fmap.jacobian_slabs():
            d = det.astype(np.float64, copy=False)
            acc["min"] = min(acc["min"], float(d.min()))
            acc["max"] = max(acc["max"], float(d.max()))
            acc["neg"] += int(np.count_nonzero(d < 0))
            acc["low"] += int(np.count_nonzero(d < 0.1))
            acc["n"] += d.size
            yield z0, det

    # (the header of the in-memory file: in_grid.with_data(det, meta=jmeta))
    out = open_block_output(path, in_grid.replace(meta=jmeta), dtype=np.float32,
                            chunks_zyx=(fmap.slab_depth(), ny, nx),
                            version=requests.ome_zarr_version, byte_order=requests.byte_order)
    with timed(f"write {path}, by slabs"), committed(out):
        _place_slabs(out, slabs())
    return {"min": acc["min"], "max": acc["max"], "below_0": float(acc["neg"] / acc["n"]),
            "below_0.1": float(acc["low"] / acc["n"])}
