"""The morph's frames: each frame's volume, attributes, surface and picture from a prepared morph.

After Dinh & Carvalho 2004, section 0.3.

:func:`morph_frames` walks the job's times over a
:class:`~.pipeline.Prepared` morph and yields one :class:`Frame` per time:
the interpolated signed distance field (or the 0..1 occupancy, or that
occupancy mapped to the source's value range), every attribute blended at
the same time, and, when asked, the frame's zero-level surface and its
render, all frames seen by one fixed camera. Nothing here reads or writes
files: ``volwarp morph`` writes what it gets.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from ..errors import VolwarpError
from ..progress import progress
from ..samples import cast_samples
from ..volume import Volume
from .interpolate import density, occupancy_to_range
from .pipeline import Prepared
from .spec import MorphJob


@dataclass(frozen=True)
class RenderSettings:
    """How the frames' surfaces are rendered.

    A view (a name or (azimuth, elevation)) and a (width, height) in pixels; one
    camera, fitted to both shapes, for every frame, or ``camera`` (a
    :class:`volwarp_cli.render.camera.Camera`, e.g. one read back to compare with
    another run); ``orientation_labels``: the anatomical letters at the edges.
    """

    view: object = "iso"
    size: tuple[int, int] = (800, 600)
    camera: object = None
    orientation_labels: bool = False


@dataclass
class Frame:
    """One frame of a morph.

    ``volume``: the frame's field (float32 SDF, negative inside) or occupancy,
    with the frame's key/values (``volwarp_morph_t``); ``attributes``: name ->
    the attribute at ``t`` in its output type; ``mesh``: the zero-level surface
    (when meshes or renders were asked for); ``image``: its ``(H, W, 3)`` render,
    ``camera`` the camera of every frame's render.
    The arrays may be reused by the next frame: use (write) a frame before
    asking for the next.
    """

    index: int
    t: float
    volume: Volume
    attributes: dict[str, Volume] = field(default_factory=dict)
    mesh: object = None
    image: np.ndarray | None = None
    camera: object = None


def shape_box(prep: Prepared) -> np.ndarray:
    """World corners ``(8, 3)`` of the box holding source and target shapes on the frame grid.

    For one fixed camera.
    """
    inside = (prep.morph.source < 0) | (prep.morph.target < 0)
    return box_corners([inside.any(axis=a) for a in ((1, 2), (0, 2), (0, 1))], prep.grid)


def box_corners(occupied_zyx, grid) -> np.ndarray:
    """World corners ``(8, 3)`` of the index box spanned by per-axis occupancy.

    ``occupied_zyx``: three boolean arrays, along z, y and x, true where a
    plane holds a voxel inside either shape (the shapes' projections).
    """
    idx = [np.flatnonzero(a) for a in occupied_zyx]  # z, y, x
    if not all(len(i) for i in idx):
        raise VolwarpError("neither shape has any voxel inside on the frame grid")
    lo = np.array([idx[2][0], idx[1][0], idx[0][0]], dtype=np.float64)
    hi = np.array([idx[2][-1], idx[1][-1], idx[0][-1]], dtype=np.float64)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                        for c in (lo[2], hi[2])])
    m = grid.index_to_world_matrix
    return corners @ m[:3, :3].T + m[:3, 3]


@dataclass(frozen=True)
class FrameValues:
    """What a frame's field becomes in its volume: the SDF, an occupancy, or source values.

    Elementwise (a block of the field gives the block of the frame), so the
    in-memory frames and the frames by blocks share it. ``range_lo, range_hi``:
    the source's value range, for a density ``range: source``.
    """

    output: str = "sdf"
    width: float = 1.0
    range_source: bool = False
    range_lo: float = 0.0
    range_hi: float = 1.0
    iso: float = 0.0
    inside: str = "above"
    dtype: str = "float32"

    @staticmethod
    def of(job: MorphJob, grid, source_dtype, value_range=None) -> FrameValues:
        """The values of ``job``'s frames on ``grid``; ``value_range``: the source's (lo, hi)."""
        ranged = job.output == "density" and job.density_range == "source"
        lo, hi = value_range if ranged else (0.0, 1.0)
        return FrameValues(job.output, float(job.density_width or min(grid.spacing)), ranged,
                           float(lo), float(hi), float(job.source.iso), job.source.inside,
                           np.dtype(source_dtype).name)

    def __call__(self, sdf: np.ndarray) -> np.ndarray:
        """The frame's samples from its field ``sdf`` (``sdf`` itself for an SDF output)."""
        if self.output != "density":
            return sdf
        data = density(sdf, self.width)
        if self.range_source:
            data = occupancy_to_range(data, self.range_lo, self.iso, self.range_hi,
                                      self.inside, self.dtype)
        return data


def morph_frames(job: MorphJob, prep: Prepared, source: Volume,
                 attributes: dict[str, tuple[Volume, Volume]] | None = None, *,
                 meta: dict | None = None, meshes: bool = False,
                 render: RenderSettings | None = None) -> Iterator[Frame]:
    """The frames of ``job`` at its times, in order (a progress bar counts them).

    Parameters
    ----------
    job : MorphJob
        Times, output kind (``sdf`` or ``density``, its width and range) and
        attributes.
    prep : Prepared
        :func:`.pipeline.prepare` of ``job`` with ``source``, the target and
        ``attributes``.
    source : Volume
        The source shape's volume (its value range and type for a density
        ``range: source``).
    attributes : dict, optional
        The attributes' (source, target) volumes, by name (the default output
        type of each is its source's).
    meta : dict, optional
        Key/values every frame carries (provenance); each frame adds
        ``volwarp_morph_t``.
    meshes : bool
        Make each frame's surface (:attr:`Frame.mesh`).
    render : RenderSettings, optional
        Render each frame's surface (:attr:`Frame.image`).
    """
    grid = prep.grid
    meta = dict(meta or {})
    types = {a.name: a.dtype or np.dtype(attributes[a.name][0].data.dtype).name
             for a in job.attributes}
    value_range = None
    if job.output == "density" and job.density_range == "source":
        value_range = float(np.nanmin(source.data)), float(np.nanmax(source.data))
    values = FrameValues.of(job, grid, source.data.dtype, value_range)
    camera = None if render is None else render.camera
    with progress(len(job.times), "morph frames") as bar:
        buf = np.empty(grid.shape, np.float32)
        for i, t in enumerate(job.times):
            sdf = prep.morph.field(t, out=buf)
            data = values(sdf)
            frame_meta = dict(meta, volwarp_morph_t=f"{t:.9g}")
            frame = Frame(i, t, grid.volume(data, meta=frame_meta))
            for a in job.attributes:
                va, vb = prep.attributes[a.name]
                blended = cast_samples(prep.morph.attribute(t, va, vb), types[a.name],
                                       what=f"attribute {a.name} at t = {t:g}")
                frame.attributes[a.name] = grid.volume(blended, meta=dict(frame_meta))
            if meshes or render is not None:
                from ..surface.isosurface import isosurface

                frame.mesh = isosurface(grid.volume(sdf), 0.0, inside="below")
                if render is not None:
                    from ..render.surface import fit_camera, render_mesh

                    if camera is None:
                        camera = fit_camera(shape_box(prep), render.view, render.size)
                    frame.image = render_mesh(frame.mesh, camera=camera,
                                              orientation_labels=render.orientation_labels)
                    frame.camera = camera
            yield frame
            bar.advance()
