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

Every ray has the same direction, so every ray crosses the volume's z planes
in the same order: :func:`render_volume_slabs` marches the rays slab after
slab of z planes (a volume read by slabs, e.g. written by blocks), carrying
each pixel's state across, and makes the same picture bit for bit;
:func:`render_volume` is its one slab of the whole volume.

The camera looks at the centre of the volume's box from the view's azimuth
``az`` (in the x-y plane from +x towards +y: 0 looks from +x along -x, 90
from +y along -y, -90 from -y along +y) and elevation ``el`` (above the x-y
plane, towards +z), with world z up, and frames the box's bounding sphere:
the same views as the surface renders (:func:`.surface.view_axes`), including
the patient-named ones (``patient-left`` looks from +x, the patient's left
in the LPS world frame).

The volume is sampled in its own (index x spacing) frame. ``origin`` and
``direction`` (orthonormal) place it in the world: the view and a given
camera are world directions, turned into the volume's frame, so that
``patient-left`` shows the patient's left whatever the scan's axis order.
Left out, the volume's axes are taken as the world's (a sweep's grid).
A saved camera (:mod:`.camera`) replaces the view and the framing, and
``orientation_labels`` writes the picture's anatomical letters
(:mod:`.orientation`).
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError
from .camera import Camera, bounds_of, sees_any
from .orientation import draw_orientation_labels, screen_letters
from .surface import view_axes

BLOCK = 8
#: Largest picture (pixels) the ray caster makes.
MAX_PIXELS = 1 << 26


def camera(view) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit (forward, right, up) vectors for ``view`` (as :func:`.surface.parse_view` reads it).

    The same camera directions as the surface renders: a sweep's picture and a
    mesh's picture of the same view show the same side.
    """
    right, up, back = view_axes(view)
    return -back, right, up


def render_volume(opacity: np.ndarray, *, colour: list[np.ndarray] | None = None,
                  geometry: np.ndarray | None = None, spacing=(1.0, 1.0, 1.0),
                  view="iso", size=(512, 512), background=(0.0, 0.0, 0.0),
                  step: float = 0.5, shading: bool = True, zoom: float = 1.0,
                  origin=None, direction=None, camera: Camera | None = None,
                  orientation_labels: bool = False, return_camera: bool = False):
    """Ray-cast ``opacity[z, y, x]`` (values in [0, 1]) into an ``(H, W, 3)`` uint8 image.

    Parameters
    ----------
    opacity : (nz, ny, nx) array
        Opacity per voxel length; values are clipped to [0, 1].
    colour : list of three (nz, ny, nx) arrays, optional
        Red, green, blue in [0, 1]; white when omitted.
    geometry : (nz, ny, nx) array, optional
        Field whose gradient gives the shading normals (default: opacity).
    spacing : (x, y, z) voxel size; view : a view name or (azimuth, elevation)
    degrees; size : (width, height) pixels; step : sample distance in voxels;
    zoom : magnification of the default framing (the box's bounding sphere).
    origin : (x, y, z), optional
        World position of the first voxel's centre (default 0): where a camera
        is (its focal point is a world point).
    direction : (3, 3) array, optional
        Columns: the world directions of the index axes (a Volume's
        ``direction``; orthonormal). Default: the identity.
    camera : Camera, optional
        A saved camera (:func:`.camera.read_camera`): replaces ``view``,
        ``size`` and ``zoom``.
    orientation_labels : bool
        Write the anatomical letters of the picture's edges.
    return_camera : bool
        Return ``(image, camera)``: the camera used, for :func:`.camera.write_camera`.

    The whole volume is :func:`render_volume_slabs`'s one slab (the same march).

    References
    ----------
    Winter & Chen, "Image-swept volumes", §5.1; Levoy, "Display of surfaces
    from volume data", 1988.
    """
    if np.ndim(opacity) != 3:
        raise VolwarpError(f"opacity must be a 3-D array, got shape {np.shape(opacity)}")
    shape = tuple(int(n) for n in np.shape(opacity))
    if colour is not None and (len(colour) != 3
                               or any(np.shape(c) != shape for c in colour)):
        raise VolwarpError("colour must be three arrays shaped like the opacity")
    fields = {"opacity": opacity, "geometry": geometry}
    if colour is not None:
        fields.update(zip(("red", "green", "blue"), colour, strict=True))

    def read_slab(z0, z1, names):
        return [fields[n][z0:z1] for n in names]

    return _render(read_slab, shape, colour is not None, geometry is not None, None,
                   spacing=spacing, view=view, size=size, background=background, step=step,
                   shading=shading, zoom=zoom, origin=origin, direction=direction, camera=camera,
                   orientation_labels=orientation_labels, return_camera=return_camera)


#: bytes a voxel of a slab takes (clipped opacity, colours, geometry, its gradient, and the
#: slab as read, up to 8 bytes a sample of 5 fields)
SLAB_BYTES_PER_VOXEL = 4 * 8 + 5 * 8


def slab_depth(shape, budget: int) -> int:
    """How many cells along z a slab of :func:`render_volume_slabs` takes within ``budget`` bytes.

    At least 4 (a slab holds its cells' planes, and the gradient's one more on each side).
    """
    nz, ny, nx = shape
    per_plane = max(1, ny * nx * SLAB_BYTES_PER_VOXEL)
    return int(max(4, min(max(nz - 1, 1), budget // per_plane - 3)))


def render_volume_slabs(read_slab, shape, *, colour: bool = False, geometry: bool = False,
                        slab: int | None = None, spacing=(1.0, 1.0, 1.0), view="iso",
                        size=(512, 512), background=(0.0, 0.0, 0.0), step: float = 0.5,
                        shading: bool = True, zoom: float = 1.0, origin=None, direction=None,
                        camera: Camera | None = None, orientation_labels: bool = False,
                        return_camera: bool = False):
    """:func:`render_volume` of a volume read by slabs of z planes: the same picture, bit for bit.

    Every ray has the same direction, so all rays cross the z planes in the same
    order: the rays are marched slab after slab, in that order, each pixel's
    state (its sample position, colour sums and opacity) carried across; each
    sample is taken by the slab holding its cell's first plane, with the whole
    volume's empty-block map (made by a first pass over the opacity, by slabs
    of whole 8-plane blocks).

    Parameters
    ----------
    read_slab : callable
        ``read_slab(z0, z1, names)``: the planes ``z0 .. z1 - 1`` of each field
        named (``"opacity"``, ``"red"``, ``"green"``, ``"blue"``, ``"geometry"``),
        arrays ``(z1 - z0, ny, nx)`` in the order of ``names``.
    shape : (nz, ny, nx)
        The volume's shape.
    colour, geometry : bool
        Whether the volume has red/green/blue and geometry fields (read by
        ``read_slab``): as :func:`render_volume`'s ``colour`` and ``geometry``.
    slab : int, optional
        Cells along z per slab (at least 1; a slab holds one more plane, and
        with shading one more on each side). Default: from the memory budget
        (:func:`slab_depth`).
    Others
        As :func:`render_volume`'s.
    """
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise VolwarpError(f"the volume's shape must be 3 positive sizes, got {shape}")
    if slab is not None and int(slab) < 1:
        raise VolwarpError(f"a slab takes 1 cell along z at least, got {slab}")
    if slab is None:
        from ..memory import memory_limit

        slab = slab_depth(shape, memory_limit() // 2)
    return _render(read_slab, shape, bool(colour), bool(geometry), int(slab),
                   spacing=spacing, view=view, size=size, background=background, step=step,
                   shading=shading, zoom=zoom, origin=origin, direction=direction, camera=camera,
                   orientation_labels=orientation_labels, return_camera=return_camera)


def _render(read_slab, shape, has_colour, has_geometry, slab, *, spacing, view, size, background,
            step, shading, zoom, origin, direction, camera, orientation_labels, return_camera):
    """The ray caster, by slabs of ``slab`` cells along z (None: one slab of the whole)."""
    from ..memory import ensure_fits_in_memory
    from ._raycast_kernels import block_max_slab, finish, gradient_slab, march_slab

    if step <= 0:
        raise VolwarpError("step must be positive")
    spacing = np.asarray(spacing, dtype=np.float64)
    nz, ny, nx = shape
    ext = spacing * (np.array([nx, ny, nz]) - 1)
    centre = 0.5 * ext  # box of voxel centres in the volume's own frame, min corner at 0
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    if direction is not None:
        direction = np.asarray(direction, dtype=np.float64)
        if direction.shape != (3, 3) or not np.allclose(direction.T @ direction, np.eye(3),
                                                       atol=1e-6):
            raise VolwarpError("the ray caster needs an orthonormal 3x3 direction matrix (a "
                               "sheared volume must be resampled first)")

    def to_frame(v):  # a world direction in the volume's frame
        return np.asarray(v, dtype=np.float64) if direction is None else direction.T @ v

    def to_world(v):
        return np.asarray(v, dtype=np.float64) if direction is None else direction @ v

    if camera is None:
        right_w, up_w, back_w = view_axes(view)
        w, h = (int(v) for v in size)
        radius = 0.5 * float(np.linalg.norm(ext)) + float(spacing.max())
        half_h = radius / zoom
    else:
        right_w, up_w, back_w = (np.asarray(v, dtype=np.float64)
                                 for v in (camera.right, camera.up, camera.back))
        w, h = camera.size
        half_h = camera.half_height
        box = np.array([[a, b, c] for a in (0.0, ext[0]) for b in (0.0, ext[1])
                        for c in (0.0, ext[2])])
        if not sees_any(camera, np.array([to_world(q) for q in box]) + origin):
            from ..progress import log

            log.warning("the volume lies outside the camera's picture: the render is empty")
        wanted = to_frame(np.asarray(camera.center, dtype=np.float64) - origin)
        # the focal point of a camera made for this volume, back in its frame, differs from
        # the box centre by rounding: use the centre itself (the same rays, the same picture)
        if np.abs(wanted - centre).max() <= 1e-9 * (1.0 + float(np.abs(ext).max())):
            radius = 0.5 * float(np.linalg.norm(ext)) + float(spacing.max())
        else:
            centre = wanted
            radius = float(np.linalg.norm(box - centre, axis=1).max()) + float(spacing.max())
    if w < 1 or h < 1 or w * h > MAX_PIXELS:
        raise VolwarpError(f"image size must be at least 1x1 and at most {MAX_PIXELS} pixels, "
                           f"got {w}x{h}")
    ncell = max(nz - 1, 1)  # the samples' cells along z, by their first plane (z0)
    whole = slab is None or slab >= ncell
    depth = ncell if whole else slab
    halo = 1 if shading else 0
    held = min(nz, depth + 1 + 2 * halo)  # planes a slab holds
    # clipped opacity, its gradient (3 floats) and the geometry copy; the pixels' state
    ensure_fits_in_memory((nz if whole else held) * ny * nx * 4 * 5 + w * h * 8 * 6,
                          "volume render")
    names = ["opacity"] + (["red", "green", "blue"] if has_colour else []) \
        + (["geometry"] if has_geometry and shading else [])
    # one colour for every sample: white, or a single voxel's
    const_col = not has_colour or nz * ny * nx == 1
    ones = np.ones((1, 1, 1), dtype=np.float32)
    no_grad = np.zeros((1, 1, 1, 3), dtype=np.float32)

    def prepared(z0, z1, which):
        arrays = dict(zip(which, read_slab(z0, z1, which), strict=True))
        for n, a in arrays.items():
            if np.shape(a) != (z1 - z0, ny, nx):
                raise VolwarpError(f"the {n} field's planes {z0}..{z1 - 1} are shaped "
                                   f"{np.shape(a)}, not {(z1 - z0, ny, nx)}")
        op = np.ascontiguousarray(np.clip(np.nan_to_num(arrays["opacity"]), 0.0, 1.0),
                                  dtype=np.float32)
        # no copy for float32 fields (the kernel clips to [0, 1] and treats NaN as 0)
        col = tuple(np.ascontiguousarray(arrays[c], dtype=np.float32) if c in arrays else ones
                    for c in ("red", "green", "blue"))
        if const_col and has_colour:
            col = tuple(c.reshape(1, 1, 1) for c in col)
        return op, col, arrays.get("geometry")

    bz = (nz + BLOCK - 1) // BLOCK
    right, up = to_frame(right_w), to_frame(up_w)
    fwd = -to_frame(back_w)
    half_w = half_h * w / h
    pix = 2.0 * half_h / h
    # lighting over the viewer's shoulder
    light = -fwd + 0.35 * right + 0.45 * up
    light /= np.linalg.norm(light)
    halfway = light - fwd
    halfway /= np.linalg.norm(halfway)
    hstep = float(step) * float(spacing.min())
    state = np.zeros((h, w, 5), dtype=np.float64)
    # every ray crosses the planes in one order: that of fwd's z step (any, when it is 0)
    slabs = [(c0, min(c0 + depth, ncell)) for c0 in range(0, ncell, depth)]
    if fwd[2] / spacing[2] < 0:
        slabs.reverse()
    if whole:
        op, col, geo = prepared(0, nz, names)
        bmax = block_max_slab(op, BLOCK, 0, nz, 0, bz)
        pre = (0, op, col, geo)
    else:  # the whole volume's empty-block map, by slabs of whole blocks (and one plane more)
        per = max(1, depth // BLOCK)
        bmax = np.concatenate([
            block_max_slab(prepared(k * BLOCK, min((k1 * BLOCK) + 1, nz), ["opacity"])[0],
                           BLOCK, k * BLOCK, nz, k, k1)
            for k in range(0, bz, per) for k1 in [min(k + per, bz)]])
        pre = None
    for i, (zs, ze) in enumerate(slabs):
        if pre is None:
            g0, g1 = max(zs - halo, 0), min(ze + 1 + halo, nz)
            op, col, geo = prepared(g0, g1, names)
        else:
            g0, op, col, geo = pre
        if shading:
            geo = op if geo is None else np.ascontiguousarray(np.nan_to_num(geo),
                                                              dtype=np.float32)
            grad = gradient_slab(geo, g0, nz)
        else:
            grad = no_grad
        del geo
        march_slab(op, col[0], col[1], col[2], const_col, grad, g0, nz, ny, nx, zs, ze,
                   i == 0, bmax, BLOCK, spacing, centre, fwd, right, up, half_w, half_h, pix,
                   radius, hstep, float(step), light, halfway, bool(shading), state)
        del op, col, grad
    pre = None
    img = np.zeros((h, w, 3), dtype=np.float32)
    finish(state, np.asarray(background, dtype=np.float32), img)
    out = np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8)
    if orientation_labels:
        bg = np.clip(np.asarray(background, dtype=np.float64), 0.0, 1.0) * 255.0
        draw_orientation_labels(out, screen_letters(up_w, -back_w), background=bg)
    if not return_camera:
        return out
    if camera is None:
        corners = np.array([[a, b, c] for a in (0.0, ext[0]) for b in (0.0, ext[1])
                            for c in (0.0, ext[2])])
        world = np.array([to_world(p) for p in corners]) + origin
        camera = Camera(center=origin + to_world(centre), right=right_w, up=up_w, back=back_w,
                        scale=h / (2.0 * half_h), size=(w, h), bounds=bounds_of(world),
                        parallel_scale=half_h)
    return out, camera
