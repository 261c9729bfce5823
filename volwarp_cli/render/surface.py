"""Headless shaded pictures of triangle meshes.

A small z-buffer rasteriser (numba) with deferred Blinn-Phong shading,
orthographic projection and 2x2 supersampling for anti-aliasing. It was
chosen over VTK's OpenGL renderer through Mesa's software EGL because it
needs no OpenGL library, no display and no GPU, and gives the same bytes on
every machine; it is also the faster of the two on this kind of machine (the
README's Performance section has the figures, ``benchmarks/bench_mesh.py``
measures them).

Views
-----
The camera looks at the mesh's centre from the direction given by an
azimuth (degrees, in the x-y plane from +x towards +y) and an elevation
(degrees above the x-y plane, towards +z); world +z is up on the screen,
except when looking straight down or up, where the azimuth says which way is
up (the limit of the z-up camera as the elevation reaches +-90).

The world frame is LPS (+x the patient's left, +y posterior, +z superior),
and the patient-named views say what the viewer sees:

=================  ===============  ==========================================
view               looks from       picture
=================  ===============  ==========================================
``patient-left``   +x (0, 0)        the patient's left side; anterior on the
                                    left, superior up
``patient-right``  -x (180, 0)      the right side; anterior on the right
``anterior``       -y (-90, 0)      the face; the patient's left on the right
``posterior``      +y (90, 0)       the back; the patient's left on the left
``superior``       +z (90, 90)      from above the head; anterior up, the
                                    patient's left on the left
``inferior``       -z (-90, -90)    from the feet; anterior up, the patient's
                                    left on the right (radiological)
=================  ===============  ==========================================

The axis names stay: ``"x"`` (from +x, +y to the right: as
``patient-left``), ``"y"`` (from +y, -x to the right: as ``posterior``),
``"z"`` (azimuth -90, elevation 90: from +z, x to the right, y up) and
``"iso"`` (azimuth 45, elevation 35.26: from the (1, 1, 1) diagonal);
``"front"`` (from -y: as ``anterior``), ``"back"`` (as ``posterior``),
``"right"`` (from +x: the patient's *left* side of a scan), ``"left"`` (from
-x), ``"top"`` (as ``"z"``: posterior up) and ``"bottom"`` (as
``inferior``). The volume ray caster (:mod:`.raycast`) uses the same views.

``orientation_labels=True`` writes the anatomical letters of the picture's
edges (:mod:`.orientation`); ``return_camera=True`` also returns the
:class:`~.camera.Camera` used, which :func:`.camera.write_camera` saves and
``camera=`` reuses for an identical framing.

Both sides of a triangle are drawn: the outer side in the mesh's colour,
the inner side (visible through the opening of an open surface) darker.
"""

from __future__ import annotations

import math
import re

import numpy as np

from ..errors import VolwarpError
from ..memory import ensure_fits_in_memory
from ..surface.mesh import Mesh, vertex_normals
from .camera import Camera, sees_any
from .orientation import draw_orientation_labels, screen_letters

__all__ = ["Camera", "NAMED_VIEWS", "fit_camera", "parse_color", "parse_size", "parse_view",
           "render_mesh", "render_turntable", "turntable_views", "view_axes"]

DEFAULT_COLOR = (0.85, 0.80, 0.70)  # bone
DEFAULT_BACKGROUND = (1.0, 1.0, 1.0)
ISO_ELEVATION = math.degrees(math.atan(1 / math.sqrt(2)))
NAMED_VIEWS = {"x": (0.0, 0.0), "y": (90.0, 0.0), "z": (-90.0, 90.0), "iso": (45.0, ISO_ELEVATION),
               # from -y: the face, for LPS scans (y runs to the back of the head)
               "front": (-90.0, 0.0), "back": (90.0, 0.0), "right": (0.0, 0.0),
               "left": (180.0, 0.0), "top": (-90.0, 90.0), "bottom": (-90.0, -90.0),
               # what the viewer sees, in the LPS world frame (see the module notes)
               "patient-left": (0.0, 0.0), "patient-right": (180.0, 0.0),
               "anterior": (-90.0, 0.0), "posterior": (90.0, 0.0),
               "superior": (90.0, 90.0), "inferior": (-90.0, -90.0)}
MAX_SIZE = 16384

NAMED_COLORS = {
    "white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0), "gray": (0.5, 0.5, 0.5),
    "grey": (0.5, 0.5, 0.5), "lightgray": (0.83, 0.83, 0.83), "lightgrey": (0.83, 0.83, 0.83),
    "darkgray": (0.25, 0.25, 0.25), "darkgrey": (0.25, 0.25, 0.25),
    "red": (0.85, 0.15, 0.15), "green": (0.2, 0.65, 0.25), "blue": (0.2, 0.35, 0.85),
    "yellow": (0.95, 0.85, 0.2), "orange": (0.95, 0.55, 0.15), "purple": (0.55, 0.3, 0.7),
    "cyan": (0.2, 0.75, 0.85), "magenta": (0.8, 0.25, 0.7), "pink": (0.95, 0.6, 0.7),
    "brown": (0.55, 0.35, 0.2), "tan": (0.82, 0.71, 0.55), "gold": (0.9, 0.75, 0.3),
    "bone": DEFAULT_COLOR, "ivory": (1.0, 1.0, 0.94), "skin": (0.94, 0.75, 0.65),
    "steelblue": (0.27, 0.51, 0.71), "navy": (0.1, 0.12, 0.35), "silver": (0.75, 0.75, 0.75),
}

_HEX = re.compile(r"^#?([0-9a-fA-F]{3}|[0-9a-fA-F]{6})$")


def parse_color(value) -> tuple[float, float, float]:
    """An RGB triple in [0, 1] from a name, ``#rrggbb``/``#rgb``, ``r,g,b`` or a sequence.

    ``r,g,b`` values are read as 0..1 when all are at most 1, else as 0..255.
    """
    if value is None:
        raise VolwarpError("no colour given")
    if isinstance(value, str):
        text = value.strip().lower()
        if text in NAMED_COLORS:
            return NAMED_COLORS[text]
        m = _HEX.match(text)
        if m and (text.startswith("#") or len(text) in (3, 6)) and "," not in text:
            digits = m.group(1)
            if len(digits) == 3:
                digits = "".join(c * 2 for c in digits)
            return tuple(int(digits[i:i + 2], 16) / 255.0 for i in (0, 2, 4))
        parts = [p for p in re.split(r"[,\s]+", text) if p]
        try:
            values = [float(p) for p in parts]
        except ValueError:
            values = []
        if len(values) != 3:
            known = ", ".join(sorted(NAMED_COLORS))
            raise VolwarpError(f"unknown colour {value!r}: give #rrggbb, r,g,b or a name ({known})")
    else:
        try:
            values = [float(v) for v in value]
        except (TypeError, ValueError):
            raise VolwarpError(f"a colour is 3 numbers, got {value!r}") from None
        if len(values) != 3:
            raise VolwarpError(f"a colour is 3 numbers, got {value!r}")
    if not all(math.isfinite(v) and v >= 0 for v in values):
        raise VolwarpError(f"colour values must be non-negative numbers, got {value!r}")
    if max(values) > 1.0:
        if max(values) > 255:
            raise VolwarpError(f"colour values must be 0..1 or 0..255, got {value!r}")
        values = [v / 255.0 for v in values]
    return (values[0], values[1], values[2])


def parse_view(value) -> tuple[float, float]:
    """(azimuth, elevation) in degrees from a view name, ``"az,el"`` or a pair.

    Names: ``patient-left``, ``patient-right``, ``anterior``, ``posterior``,
    ``superior``, ``inferior`` (also with ``_``), ``iso``, ``x``, ``y``, ``z``,
    ``front``, ``back``, ``left``, ``right``, ``top``, ``bottom`` (see the
    module notes).
    """
    names = ", ".join(NAMED_VIEWS)
    if isinstance(value, str):
        text = value.strip().lower().replace("_", "-")
        if text in NAMED_VIEWS:
            return NAMED_VIEWS[text]
        parts = [p for p in re.split(r"[,\s]+", text) if p]
        try:
            az, el = (float(p) for p in parts)
        except ValueError:
            raise VolwarpError(f"unknown view {value!r}: give {names} or "
                               "AZIMUTH,ELEVATION in degrees") from None
    else:
        try:
            az, el = (float(v) for v in value)
        except (TypeError, ValueError):
            raise VolwarpError(f"a view is one of {names} or (azimuth, "
                               f"elevation), got {value!r}") from None
    if not math.isfinite(az) or abs(az) > 1e6:
        raise VolwarpError(f"view azimuth must be a finite number of degrees (within "
                           f"+-1e6), got {value!r}")
    if not math.isfinite(el) or not -90.0 <= el <= 90.0:
        raise VolwarpError(f"view elevation must be within -90..90 degrees, got {value!r}")
    return az, el


def parse_size(value) -> tuple[int, int]:
    """(width, height) from ``"WxH"`` or a pair, each 1..16384."""
    if isinstance(value, str):
        m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", value)
        if not m:
            raise VolwarpError(f"image size must be WIDTHxHEIGHT (e.g. 800x600), got {value!r}")
        w, h = int(m.group(1)), int(m.group(2))
    else:
        try:
            w, h = (int(v) for v in value)
        except (TypeError, ValueError):
            raise VolwarpError(f"image size is (width, height), got {value!r}") from None
    if not (1 <= w <= MAX_SIZE and 1 <= h <= MAX_SIZE):
        raise VolwarpError(f"image size must be 1..{MAX_SIZE} pixels each way, got {w}x{h}")
    return w, h


def view_axes(view) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, back) unit vectors of a view (see the module notes)."""
    az, el = parse_view(view)
    a, e = math.radians(az), math.radians(el)
    back = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])
    if abs(math.cos(e)) < 1e-6:
        # straight down or up: the limit of the z-up camera as the elevation
        # reaches +-90 (so "z" = (-90, 90) has x to the right and y up)
        sign = -1.0 if el > 0 else 1.0
        up_hint = sign * np.array([math.cos(a), math.sin(a), 0.0])
    else:
        up_hint = np.array([0.0, 0.0, 1.0])
    right = np.cross(-back, up_hint)
    right /= np.linalg.norm(right)
    up = np.cross(right, -back)
    return right, up, back


def fit_camera(vertices: np.ndarray, view="iso", size=(800, 600), *, margin: float = 0.05,
               fit: str = "tight") -> Camera:
    """A camera that shows all ``vertices`` with ``margin`` (fraction of the image) around.

    ``fit="tight"`` fits the projected extent of this view; ``fit="sphere"``
    fits the bounding sphere around the bounding box centre, so every view
    direction gets the same scale (turntables).
    """
    width, height = parse_size(size)
    right, up, back = view_axes(view)
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    usable_w = max(width * (1 - 2 * margin), 1.0)
    usable_h = max(height * (1 - 2 * margin), 1.0)
    if len(v) == 0:
        return Camera(np.zeros(3), right, up, back, 1.0, (width, height))
    lo, hi = v.min(axis=0), v.max(axis=0)
    if fit == "sphere":
        center = 0.5 * (lo + hi)
        radius = float(np.sqrt(((v - center) ** 2).sum(axis=1).max()))
        extent_w = extent_h = 2 * radius
    elif fit == "tight":
        px = v @ right
        py = v @ up
        center_2d = (0.5 * (px.min() + px.max()), 0.5 * (py.min() + py.max()))
        extent_w = px.max() - px.min()
        extent_h = py.max() - py.min()
        depth = v @ back
        center = right * center_2d[0] + up * center_2d[1] + back * 0.5 * (depth.min() + depth.max())
    else:
        raise VolwarpError(f"fit must be tight or sphere, got {fit!r}")
    scales = []
    if extent_w > 0:
        scales.append(usable_w / extent_w)
    if extent_h > 0:
        scales.append(usable_h / extent_h)
    scale = min(scales) if scales else 1.0
    return Camera(np.asarray(center, dtype=np.float64), right, up, back, float(scale),
                  (width, height), bounds=np.stack([lo, hi], axis=1).ravel())


def _render_kernel():
    import numba

    @numba.njit(cache=True, nogil=True)
    def draw(vertices, world_normals, faces, center, axes, scale, ss, shading, face_colors,
             back_shade, background, out):
        """Project, z-buffer the triangles at ``ss`` x the output size, shade, average down.

        ``axes`` rows are the camera's right, up and back (towards the viewer)
        unit vectors; ``scale`` is output pixels per world unit. ``shading`` =
        (key xyz, fill xyz, half xyz, ambient, key diffuse, fill diffuse,
        specular, shininess) in the camera frame; ``face_colors`` one RGB row
        per triangle (its back side drawn ``back_shade`` times as bright).
        """
        height, width = out.shape[0], out.shape[1]
        big_h = height * ss
        big_w = width * ss
        n_vert = vertices.shape[0]
        sx = np.empty(n_vert)
        sy = np.empty(n_vert)
        sz = np.empty(n_vert)
        normals = np.empty((n_vert, 3), dtype=np.float32)
        s = scale * ss
        for q in range(n_vert):
            px = vertices[q, 0] - center[0]
            py = vertices[q, 1] - center[1]
            pz = vertices[q, 2] - center[2]
            sx[q] = (px * axes[0, 0] + py * axes[0, 1] + pz * axes[0, 2]) * s + 0.5 * big_w
            sy[q] = 0.5 * big_h - (px * axes[1, 0] + py * axes[1, 1] + pz * axes[1, 2]) * s
            sz[q] = px * axes[2, 0] + py * axes[2, 1] + pz * axes[2, 2]
            for k in range(3):
                normals[q, k] = (world_normals[q, 0] * axes[k, 0]
                                 + world_normals[q, 1] * axes[k, 1]
                                 + world_normals[q, 2] * axes[k, 2])
        zbuf = np.full((big_h, big_w), -np.inf, dtype=np.float32)
        nbuf = np.zeros((big_h, big_w, 3), dtype=np.float32)
        front = np.zeros((big_h, big_w), dtype=np.bool_)
        fid = np.zeros((big_h, big_w), dtype=np.int32)
        for t in range(faces.shape[0]):
            a = faces[t, 0]
            b = faces[t, 1]
            c = faces[t, 2]
            x0, y0, z0 = sx[a], sy[a], sz[a]
            x1, y1, z1 = sx[b], sy[b], sz[b]
            x2, y2, z2 = sx[c], sy[c], sz[c]
            area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
            if area == 0.0 or not (area == area):
                continue
            # pixel (i, j) has its centre at (j + 0.5, i + 0.5)
            jmin = max(int(math.ceil(min(x0, x1, x2) - 0.5)), 0)
            jmax = min(int(math.floor(max(x0, x1, x2) - 0.5)), big_w - 1)
            imin = max(int(math.ceil(min(y0, y1, y2) - 0.5)), 0)
            imax = min(int(math.floor(max(y0, y1, y2) - 0.5)), big_h - 1)
            if jmin > jmax or imin > imax:
                continue
            inv = 1.0 / area
            # edge functions w_k = (A_k x + B_k y + C_k) / area
            a0 = (y1 - y2) * inv
            b0 = (x2 - x1) * inv
            c0 = (x1 * y2 - x2 * y1) * inv
            a1 = (y2 - y0) * inv
            b1 = (x0 - x2) * inv
            c1 = (x2 * y0 - x0 * y2) * inv
            # screen y runs down, so a triangle wound counter-clockwise as seen
            # by the viewer has a negative area here: its outer side faces us
            is_front = area < 0.0
            for i in range(imin, imax + 1):
                py = i + 0.5
                r0 = b0 * py + c0
                r1 = b1 * py + c1
                for j in range(jmin, jmax + 1):
                    px = j + 0.5
                    w0 = a0 * px + r0
                    if w0 < 0.0:
                        continue
                    w1 = a1 * px + r1
                    if w1 < 0.0:
                        continue
                    w2 = 1.0 - w0 - w1
                    if w2 < 0.0:
                        continue
                    z = w0 * z0 + w1 * z1 + w2 * z2
                    if z > zbuf[i, j]:
                        zbuf[i, j] = z
                        for k in range(3):
                            nbuf[i, j, k] = (w0 * normals[a, k] + w1 * normals[b, k]
                                             + w2 * normals[c, k])
                        front[i, j] = is_front
                        fid[i, j] = t
        # Blinn-Phong per sample, averaged over the ss x ss samples of a pixel
        inv_n = 1.0 / (ss * ss)
        for i in range(height):
            for j in range(width):
                acc0 = 0.0
                acc1 = 0.0
                acc2 = 0.0
                for u in range(ss):
                    for v in range(ss):
                        y = i * ss + u
                        x = j * ss + v
                        if zbuf[y, x] == -np.inf:
                            acc0 += background[0]
                            acc1 += background[1]
                            acc2 += background[2]
                            continue
                        nx = nbuf[y, x, 0]
                        ny = nbuf[y, x, 1]
                        nz = nbuf[y, x, 2]
                        length = math.sqrt(nx * nx + ny * ny + nz * nz)
                        if length > 0.0:
                            nx /= length
                            ny /= length
                            nz /= length
                        shade = 1.0
                        if not front[y, x]:
                            # seen from behind (inside an open surface): light that side
                            nx, ny, nz = -nx, -ny, -nz
                            shade = back_shade
                        dk = max(nx * shading[0] + ny * shading[1] + nz * shading[2], 0.0)
                        df = max(nx * shading[3] + ny * shading[4] + nz * shading[5], 0.0)
                        dh = max(nx * shading[6] + ny * shading[7] + nz * shading[8], 0.0)
                        light = shading[9] + shading[10] * dk + shading[11] * df
                        spec = shading[12] * dh ** shading[13]
                        f = fid[y, x]
                        acc0 += min(shade * face_colors[f, 0] * light + spec, 1.0)
                        acc1 += min(shade * face_colors[f, 1] * light + spec, 1.0)
                        acc2 += min(shade * face_colors[f, 2] * light + spec, 1.0)
                out[i, j, 0] = np.uint8(min(max(acc0 * inv_n, 0.0), 1.0) * 255.0 + 0.5)
                out[i, j, 1] = np.uint8(min(max(acc1 * inv_n, 0.0), 1.0) * 255.0 + 0.5)
                out[i, j, 2] = np.uint8(min(max(acc2 * inv_n, 0.0), 1.0) * 255.0 + 0.5)

    return draw


_KERNELS: dict = {}


def _shading_table() -> np.ndarray:
    """Lights in the camera frame (x right, y up, z towards the viewer)."""
    key = np.array([-0.45, 0.55, 1.0])
    key /= np.linalg.norm(key)
    fill = np.array([0.6, -0.25, 1.0])
    fill /= np.linalg.norm(fill)
    half = key + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half)
    ambient, key_diffuse, fill_diffuse, specular, shininess = 0.16, 0.72, 0.28, 0.22, 40.0
    return np.concatenate([key, fill, half,
                           [ambient, key_diffuse, fill_diffuse, specular, shininess]])


#: the inner side of an open surface is drawn in this fraction of the colour
BACK_SIDE_SHADE = 0.55


def render_mesh(mesh: Mesh, *, view="iso", size=(800, 600), color=None, background=None,
                camera: Camera | None = None, supersample: int = 2,
                face_colors=None, orientation_labels: bool = False,
                return_camera: bool = False):
    """Render ``mesh`` shaded, headless: an ``(H, W, 3)`` uint8 picture.

    Parameters
    ----------
    mesh : Mesh
        World-coordinate triangles; vertex normals are computed when absent.
    view : str or (float, float)
        A view name (``"patient-left"``, ``"anterior"``, ``"iso"``, ``"x"``, ...;
        see the module notes) or (azimuth, elevation) in degrees.
    size : (int, int) or str
        (width, height) in pixels, or ``"WxH"``.
    color, background : str or (r, g, b), optional
        Surface and background colours (names, ``#rrggbb``, 0..1 triples).
    camera : Camera, optional
        Overrides ``view`` and ``size``: one from :func:`fit_camera`, or a
        saved one (:func:`.camera.read_camera`), for pictures framed alike. A
        warning says so when the mesh lies wholly outside its picture.
    supersample : int
        Samples per pixel along each axis (anti-aliasing), 1..4.
    face_colors : (F, 3) array, optional
        One colour per triangle (0..1 floats, or uint8), instead of ``color``:
        parts of a model in their own colours, drawn in one picture.
    orientation_labels : bool
        Write the anatomical letters (L/R, A/P, S/I of the LPS world frame) at
        the picture's edges (:mod:`.orientation`).
    return_camera : bool
        Return ``(image, camera)``: the camera used (fitted or given), for
        :func:`.camera.write_camera`.

    Returns
    -------
    (H, W, 3) uint8, or (image, Camera) with ``return_camera``
        Write the image with :func:`volwarp_cli.io.images.write_image`.
    """
    color = DEFAULT_COLOR if color is None else parse_color(color)
    background = DEFAULT_BACKGROUND if background is None else parse_color(background)
    if camera is None:
        camera = fit_camera(mesh.vertices, view, size)
    elif not mesh.is_empty and not sees_any(camera, mesh.vertices):
        from ..progress import log

        log.warning("the mesh lies outside the camera's picture: the render is empty")
    width, height = camera.size
    ss = int(supersample)
    if not 1 <= ss <= 4:
        raise VolwarpError(f"supersample must be 1..4, got {supersample}")
    while ss > 1 and width * height * ss * ss > 64_000_000:
        ss -= 1
    ensure_fits_in_memory(width * height * ss * ss * 21 + width * height * 3,
                          f"a {width}x{height} render")
    n_faces = len(mesh.faces)
    if face_colors is None:
        face_colors = np.empty((n_faces, 3))
        face_colors[:] = color
    else:
        face_colors = np.asarray(face_colors)
        if face_colors.shape != (n_faces, 3):
            raise VolwarpError(f"face_colors must be one RGB row per triangle ({n_faces}, 3), "
                               f"got {face_colors.shape}")
        scale = 1.0 / 255.0 if face_colors.dtype == np.uint8 else 1.0
        face_colors = np.clip(face_colors.astype(np.float64) * scale, 0.0, 1.0)
    out = np.empty((height, width, 3), dtype=np.uint8)
    if mesh.is_empty:
        out[...] = np.rint(np.asarray(background) * 255.0).astype(np.uint8)
    else:
        normals = mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices,
                                                                              mesh.faces)
        axes = np.stack([camera.right, camera.up, camera.back]).astype(np.float64)
        if "draw" not in _KERNELS:
            _KERNELS["draw"] = _render_kernel()
        _KERNELS["draw"](mesh.vertices, np.ascontiguousarray(normals, dtype=np.float32),
                         mesh.faces, np.asarray(camera.center, dtype=np.float64), axes,
                         float(camera.scale), ss, _shading_table(),
                         np.ascontiguousarray(face_colors, dtype=np.float64), BACK_SIDE_SHADE,
                         np.asarray(background, dtype=np.float64), out)
    if orientation_labels:
        draw_orientation_labels(out, screen_letters(camera.up, -np.asarray(camera.back)),
                                background=np.asarray(background) * 255.0)
    return (out, camera) if return_camera else out


def turntable_views(n: int, view="iso") -> list[tuple[float, float]]:
    """``n`` (azimuth, elevation) pairs around the vertical axis, starting at ``view``."""
    if n < 1:
        raise VolwarpError(f"a turntable needs at least 1 view, got {n}")
    az, el = parse_view(view)
    return [(az + 360.0 * k / n, el) for k in range(n)]


def turntable_cameras(camera: Camera, n: int) -> list[Camera]:
    """``n`` copies of ``camera`` turned about the vertical (world z) axis through its focal point.

    Copy k is turned by 360 k / n degrees (frame 0 is ``camera`` itself).
    """
    from dataclasses import replace

    if n < 1:
        raise VolwarpError(f"a turntable needs at least 1 view, got {n}")
    cams = [camera]
    for k in range(1, n):
        a = math.radians(360.0 * k / n)
        c, s = math.cos(a), math.sin(a)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        cams.append(replace(camera, right=rot @ camera.right, up=rot @ camera.up,
                            back=rot @ camera.back))
    return cams


def render_turntable(mesh: Mesh, n: int, *, view="iso", size=(800, 600), color=None,
                     background=None, camera: Camera | None = None,
                     orientation_labels: bool = False, return_cameras: bool = False):
    """``n`` renders around the vertical (z) axis, all at the same scale.

    Without ``camera`` each frame fits the mesh's bounding sphere from its
    view; with one (a saved camera) frame 0 is that camera and the others
    turn it about the vertical axis through its focal point
    (:func:`turntable_cameras`). ``orientation_labels`` as in
    :func:`render_mesh`; ``return_cameras`` returns ``(images, cameras)``.
    """
    if camera is None:
        cams = [fit_camera(mesh.vertices, v, size, fit="sphere") for v in turntable_views(n, view)]
    else:
        cams = turntable_cameras(camera, n)
    images = [render_mesh(mesh, color=color, background=background, camera=cam,
                          orientation_labels=orientation_labels) for cam in cams]
    return (images, cams) if return_cameras else images
