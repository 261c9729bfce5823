"""The mesh chain: a volume to its cleaned-up isosurface, and a label map to its labels'.

:func:`surface_mesh` is ``volwarp mesh``'s core: the isosurface at a level
(the middle of the value range unless given), refused or kept empty when the
level is never crossed, then the optional clean-ups in a fixed order
(largest component, smoothing, decimation). :func:`label_indicator` and
:func:`label_meshes` do the same for a segmentation, one label at a time (each
label's indicator at 0.5, closed at the volume's border). Nothing here reads
or writes files.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..errors import VolwarpError
from ..progress import log, timed
from ..volume import Volume
from .mesh import Mesh


@dataclass(frozen=True)
class Cleanup:
    """What is done to a surface after it is extracted, in this order.

    ``largest_component``: keep only the connected piece with the most
    triangles; ``smooth``: windowed-sinc iterations (0: none); ``decimate``:
    the fraction of triangles to remove (0: none).
    """

    largest_component: bool = False
    smooth: int = 0
    decimate: float = 0.0


#: Peak bytes of the mesh chain, over what the process held before it (measured on a
#: 160^3 gyroid, 1.2M triangles; the libraries and compiled kernels already loaded):
#: per voxel (flying edges' per-edge cases), per triangle for the extraction (the mesh
#: as held, about 42 bytes, and its conversion to world coordinates), and per triangle
#: of each clean-up's own work beside it (the largest of those in the chain counts).
CHAIN_BYTES_PER_VOXEL = 4
EXTRACT_BYTES_PER_TRIANGLE = 64
CLEANUP_BYTES_PER_TRIANGLE = {"largest_component": 64, "smooth": 128, "decimate": 208}
#: The side of the ball the chain runs on to load its kernels (see below).
_WARM_SIZE = 8


def crossing_count(data: np.ndarray, level: float, cap: bool = False,
                   inside: str = "above") -> int:
    """How many cell edges the level crosses: the vertex count of the isosurface.

    Flying edges makes one vertex per edge whose samples lie on different
    sides of ``level`` (``>=`` is above); with ``cap`` the layer of outside
    samples around the volume adds one per inside sample (``inside``: above
    or below the level) on its faces. By z slabs over the threads, each
    slab's mask its own (a few MiB).
    """
    below = inside == "below"
    from .. import parallel

    nz = data.shape[0]
    step = max(1, (4 << 20) // max(1, data[0].size))

    def part(z0):
        z1 = min(z0 + step, nz)
        m = data[z0:min(z1 + 1, nz)] >= level
        own = m[:z1 - z0]
        n = (np.count_nonzero(own[:, :, 1:] != own[:, :, :-1])
             + np.count_nonzero(own[:, 1:] != own[:, :-1])
             + np.count_nonzero(m[1:] != m[:-1]))
        if cap:  # an edge to the outside layer from every inside sample on each face
            ins = ~own if below else own
            n += int(np.count_nonzero(ins[:, :, [0, -1]]) + np.count_nonzero(ins[:, [0, -1]]))
            n += int(np.count_nonzero(ins[0])) if z0 == 0 else 0
            n += int(np.count_nonzero(ins[-1])) if z1 == nz else 0
        return n

    if data.size == 0:
        return 0
    return int(sum(parallel.run_blocks(part, range(0, nz, step))))


def chain_bytes(shape, triangles: int, cleanup: Cleanup) -> int:
    """What the mesh chain needs for a volume of ``shape`` and a mesh of ``triangles``."""
    steps = [name for name in CLEANUP_BYTES_PER_TRIANGLE if getattr(cleanup, name)]
    extra = max((CLEANUP_BYTES_PER_TRIANGLE[name] for name in steps), default=0)
    return int(np.prod(shape)) * CHAIN_BYTES_PER_VOXEL + triangles * (
        EXTRACT_BYTES_PER_TRIANGLE + extra)


def _check_chain_memory(data: np.ndarray, iso: float, inside: str, cap: bool,
                        cleanup: Cleanup, name: str) -> None:
    """Refuse a mesh chain that would not fit the memory budget, before it runs.

    The mesh's size comes from :func:`crossing_count` (the exact vertex
    count; a surface has about twice as many triangles, a capped one up to
    2.2 times: 2.25 are counted). Where the budget is tight, the chain first
    runs on a small ball, so that VTK's filters and the compiled kernels it
    uses (over 100 MiB with a clean-up) count in what the process holds
    (:func:`volwarp_cli.memory.ensure_fits_once_loaded`).
    """
    from ..memory import ensure_fits_once_loaded

    def load():
        n = _WARM_SIZE
        z, y, x = np.ogrid[:n, :n, :n]
        r2 = (x - n / 2) ** 2 + (y - n / 2) ** 2 + (z - n / 2) ** 2
        up = inside == "above"
        ball = np.where(r2 < (n / 4) ** 2, 1.0 if up else 0.0, 0.0 if up else 1.0)
        surface_mesh(Volume(ball.astype(np.float32)), 0.5, inside=inside, cap=cap,
                     cleanup=cleanup)

    vertices = crossing_count(data, iso, cap, inside)
    need = chain_bytes(data.shape, (9 * vertices) // 4 + 8, cleanup)
    converted = np.dtype(data.dtype).newbyteorder("=") != data.dtype or data.dtype == np.float16
    if converted or not data.flags.c_contiguous:
        need += data.size * 4
    ensure_fits_once_loaded(need, f"the isosurface of {name} ({vertices} vertices)",
                            load if data.size > _WARM_SIZE ** 3 else None)


def surface_mesh(vol: Volume, iso: float | None = None, *, inside: str = "above",
                 cap: bool = False, allow_empty: bool = False, cleanup: Cleanup = Cleanup(),
                 name: str = "the volume") -> tuple[Mesh, float]:
    """The isosurface of ``vol`` at ``iso`` after ``cleanup``: ``(mesh, iso)``.

    ``iso`` None: the middle of the value range (the level used is returned).
    ``inside``: which side of the level is the shape (``"above"`` or
    ``"below"``), which sets the outward normals; ``cap``: close the surface
    where the shape touches the volume's border. A level outside the data
    range, or never crossed, is a :class:`VolwarpError` naming ``name``
    unless ``allow_empty`` (then an empty mesh, and a warning). NaN and
    infinite samples are refused (:func:`.isosurface.check_finite_range`).
    """
    from .isosurface import check_finite_range, default_iso, isosurface, touches_border

    lo, hi = float(np.min(vol.data)), float(np.max(vol.data))  # NaN if any sample is NaN
    check_finite_range(lo, hi, name)
    if iso is None:
        iso = default_iso(vol.data)
        log.info("iso level not given: using the middle of the value range, %g", iso)
    empty_reason = None
    if not lo <= iso <= hi:
        empty_reason = f"iso level {iso:g} is outside the data range [{lo:g}, {hi:g}] of {name}"
        mesh = Mesh.empty()
    else:
        _check_chain_memory(vol.data, iso, inside, cap, cleanup, name)
        mesh = isosurface(vol, iso, inside=inside, cap=cap)
        if mesh.is_empty:
            empty_reason = f"no surface at level {iso:g} in {name} (the level is never crossed)"
        elif not cap and touches_border(vol.data, iso, inside):
            log.warning("the shape touches the volume's border, where its surface is open "
                        "(use --cap to close it)")
    return finish_surface(mesh, empty_reason, allow_empty, cleanup), iso


def finish_surface(mesh: Mesh, empty_reason: str | None, allow_empty: bool,
                   cleanup: Cleanup) -> Mesh:
    """The surface's last step: refuse an empty one (unless ``allow_empty``), or clean it."""
    if empty_reason:
        if not allow_empty:
            raise VolwarpError(f"{empty_reason}; nothing written (--allow-empty writes an "
                               "empty mesh)")
        log.warning("%s: the mesh is empty", empty_reason)
    return clean(mesh, cleanup)


def clean(mesh: Mesh, cleanup: Cleanup) -> Mesh:
    """``mesh`` after ``cleanup`` (largest component, smoothing, decimation, in order)."""
    from . import ops

    if cleanup.largest_component and not mesh.is_empty:
        with timed("largest component"):
            mesh = ops.largest_component(mesh)
    if cleanup.smooth:
        with timed(f"smooth ({cleanup.smooth} iterations)"):
            mesh = ops.smooth(mesh, cleanup.smooth)
    if cleanup.decimate:
        with timed(f"decimate ({cleanup.decimate:g})"):
            mesh = ops.decimate(mesh, cleanup.decimate)
    return mesh


def check_label_map(vol: Volume, name: str, what: str) -> None:
    """Refuse a volume that is not a label map (integer samples) for ``what``."""
    if np.dtype(vol.dtype).kind not in "iu":
        raise VolwarpError(f"{name}: {what} needs a label map (integer samples), got {vol.dtype}")


def label_indicator(vol: Volume, label: int, *, name: str = "the volume",
                    what: str = "--label") -> Volume:
    """The indicator of ``label`` in the label map ``vol`` (1 inside, 0 elsewhere).

    Float32, the same geometry; its surface is the isosurface at 0.5.
    """
    check_label_map(vol, name, what)
    ind = vol.data == label
    if not ind.any():
        raise VolwarpError(f"{name}: label {label} does not occur in the volume")
    return vol.with_data(ind.astype(np.float32))


def labels_of(vol: Volume, *, name: str = "the volume", what: str = "--labels") -> list[int]:
    """The label map's labels other than 0, ascending (none: a :class:`VolwarpError`)."""
    check_label_map(vol, name, what)
    values = [int(v) for v in np.unique(vol.data) if v != 0]
    if not values:
        raise VolwarpError(f"{name}: no label other than 0 in the volume")
    return values


def label_surface(vol: Volume, label: int, *, allow_empty: bool = False,
                  cleanup: Cleanup = Cleanup(), name: str = "the volume",
                  what: str = "--label") -> Mesh:
    """The closed surface of ``label`` (its indicator at 0.5, capped at the border)."""
    ind = label_indicator(vol, label, name=name, what=what)
    mesh, _ = surface_mesh(ind, 0.5, inside="above", cap=True, allow_empty=allow_empty,
                           cleanup=cleanup, name=f"{name} label {label}")
    return mesh


def label_meshes(vol: Volume, *, allow_empty: bool = False, cleanup: Cleanup = Cleanup(),
                 name: str = "the volume") -> Iterator[tuple[int, Mesh]]:
    """``(label, surface)`` for every label of ``vol`` other than 0, ascending."""
    values = labels_of(vol, name=name)
    log.info("%d labels: %s", len(values), " ".join(map(str, values[:20])))
    for label in values:
        yield label, label_surface(vol, label, allow_empty=allow_empty, cleanup=cleanup,
                                   name=name, what="--labels")
