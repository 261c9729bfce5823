"""Emission-absorption volume ray casting of spatial objects (Winter & Chen §5.1, Levoy 1988).

A spatial object is an opacity field plus attribute fields (colour, and a
``geometry`` field whose gradient gives the shading normal). Every pixel
casts one parallel (orthographic) ray through the volume's box; samples are
taken every ``step`` voxels with trilinear interpolation and composited front
to back,

    C += (1 - A) * alpha * shade * colour,    A += (1 - A) * alpha,

with the opacity corrected for the step length, ``alpha = 1 - (1 - o)^(step)``
(an opacity is "per voxel length"), until ``A`` exceeds 0.995 (early ray
termination). ``shade = ka + kd |n . l| + ks (n . h)^p`` with ``n`` the
normalised central-difference gradient of the geometry field (or of the
opacity), a light over the viewer's shoulder, and ``shade = 1`` where the
gradient vanishes. Empty 8^3 blocks are skipped whole.

The camera looks at the centre of the volume's box from azimuth ``az``
(about the world z axis; 0 looks along +y, 90 along -x) and elevation ``el``
(above the xy plane), with world z up, and frames the box's bounding sphere.
The volume is rendered in its own (index x spacing) frame: its direction
matrix, if any, is not applied.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError

BLOCK = 8
#: Largest picture (pixels) the ray caster makes.
MAX_PIXELS = 1 << 26


def camera(view) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit (forward, right, up) vectors for ``view`` (as :func:`.surface.parse_view` reads it).

    The same camera directions as the surface renders: a sweep's picture and a
    mesh's picture of the same view show the same side.
    """
    from .surface import view_axes

    right, up, back = view_axes(view)
    return -back, right, up


def render_volume(opacity: np.ndarray, *, colour: list[np.ndarray] | None = None,
                  geometry: np.ndarray | None = None, spacing=(1.0, 1.0, 1.0),
                  view="iso", size=(512, 512), background=(0.0, 0.0, 0.0),
                  step: float = 0.5, shading: bool = True, zoom: float = 1.0) -> np.ndarray:
    """Ray-cast ``opacity[z, y, x]`` (values in [0, 1]) into an ``(H, W, 3)`` uint8 image.

    Parameters
    ----------
    opacity : (nz, ny, nx) array
        Opacity per voxel length; values are clipped to [0, 1].
    colour : list of three (nz, ny, nx) arrays, optional
        Red, green, blue in [0, 1]; white when omitted.
    geometry : (nz, ny, nx) array, optional
        Field whose gradient gives the shading normals (default: opacity).
    spacing : (x, y, z) voxel size; view : (azimuth, elevation) degrees;
    size : (width, height) pixels; step : sample distance in voxels.

    References
    ----------
    Winter & Chen, "Image-swept volumes", §5.1; Levoy, "Display of surfaces
    from volume data", 1988.
    """
    from ..io.common import ensure_fits_in_memory
    from ._raycast_kernels import block_max, gradient, march

    if np.ndim(opacity) != 3:
        raise VolwarpError(f"opacity must be a 3-D array, got shape {np.shape(opacity)}")
    # clipped opacity, its gradient (3 floats) and the geometry copy
    ensure_fits_in_memory(int(np.size(opacity)) * 4 * 5, "volume render")
    op = np.ascontiguousarray(np.clip(np.nan_to_num(opacity), 0.0, 1.0), dtype=np.float32)
    w, h = (int(v) for v in size)
    if w < 1 or h < 1 or w * h > MAX_PIXELS:
        raise VolwarpError(f"image size must be at least 1x1 and at most {MAX_PIXELS} pixels, "
                           f"got {w}x{h}")
    if step <= 0:
        raise VolwarpError("step must be positive")
    nz, ny, nx = op.shape
    if colour is None:
        col = tuple(np.ones((1, 1, 1), dtype=np.float32) for _ in range(3))
    else:
        if len(colour) != 3 or any(np.shape(c) != op.shape for c in colour):
            raise VolwarpError("colour must be three arrays shaped like the opacity")
        # no copy for float32 fields (the kernel clips to [0, 1] and treats NaN as 0)
        col = tuple(np.ascontiguousarray(c, dtype=np.float32) for c in colour)
    geo = op if geometry is None else np.ascontiguousarray(np.nan_to_num(geometry),
                                                           dtype=np.float32)
    grad = gradient(geo) if shading else np.zeros((1, 1, 1, 3), dtype=np.float32)
    bmax = block_max(op, BLOCK)
    spacing = np.asarray(spacing, dtype=np.float64)
    fwd, right, up = camera(view)
    ext = spacing * (np.array([nx, ny, nz]) - 1)
    centre = 0.5 * ext  # box of voxel centres in the volume's own frame, min corner at 0
    radius = 0.5 * float(np.linalg.norm(ext)) + float(spacing.max())
    half_h = radius / zoom
    half_w = half_h * w / h
    pix = 2.0 * half_h / h
    # lighting over the viewer's shoulder
    light = -fwd + 0.35 * right + 0.45 * up
    light /= np.linalg.norm(light)
    halfway = light - fwd
    halfway /= np.linalg.norm(halfway)
    img = np.zeros((h, w, 3), dtype=np.float32)
    hstep = float(step) * float(spacing.min())
    march(op, col[0], col[1], col[2], grad, bmax, BLOCK, spacing, centre, fwd, right, up, half_w, half_h, pix,
          radius, hstep, float(step), light, halfway, np.asarray(background, dtype=np.float32),
          bool(shading), img)
    return np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
