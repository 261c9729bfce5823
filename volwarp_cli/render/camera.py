"""The orthographic camera of volwarp's renders, and its JSON file (``--camera-to``/``--camera-from``).

Both renderers (the surface rasteriser, :mod:`.surface`, and the volume ray
caster, :mod:`.raycast`) use parallel projection, and one :class:`Camera`
describes either: a camera saved from ``volwarp mesh --render`` can be used for
a ray-cast picture and the other way round. Everything is in world
coordinates, which are LPS millimetres for scans.

The file
--------
A JSON object with VTK's camera terms, so that a pyvista/ParaView user can set
the same camera (``position``, ``focal_point``, ``view_up``,
``parallel_scale``), plus what a picture needs beyond them::

    {
      "volwarp_camera": 1,
      "frame": "LPS",
      "projection": "parallel",
      "position": [x, y, z],                  # eye, on the viewer's side of the focal point
      "focal_point": [x, y, z],               # the world point at the picture's centre
      "view_up": [x, y, z],                   # world direction of the picture's top
      "direction_of_projection": [x, y, z],   # unit vector, focal_point - position
      "view_right": [x, y, z],                # world direction of the picture's right
      "parallel_scale": h,                    # half the picture's height, world units
      "pixels_per_unit": s,                   # image_size[1] / (2 parallel_scale)
      "image_size": [width, height],          # pixels
      "bounds": [xmin, xmax, ymin, ymax, zmin, zmax]   # what the camera was made for
    }

``position``, ``focal_point``, ``view_up``, ``parallel_scale`` and
``image_size`` decide. ``direction_of_projection``, ``view_right`` and
``pixels_per_unit`` are derived from them and are written only so that a
camera read back gives the identical picture bit for bit (a derived number
recomputed may differ in its last bit): each is used where it agrees with the
deciding fields to 1e-9, and recomputed otherwise, so editing ``position`` or
``parallel_scale`` by hand takes effect. ``position`` may be left out when
``direction_of_projection`` is given. ``view_up`` need not be orthogonal to the
direction of projection (it is made so, as VTK's ``OrthogonalizeViewUp``).
``bounds`` (and an optional ``source`` string) are informational: the box of
the mesh or volume the camera was fitted to. A perspective camera
(``view_angle`` without ``parallel_scale``, ``"projection": "perspective"``)
is refused: the renderers project in parallel.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, replace

import numpy as np

from ..errors import SpecError

#: the version written in ``volwarp_camera``
CAMERA_FILE_VERSION = 1
#: largest picture side (as :func:`.surface.parse_size`)
MAX_SIZE = 16384
#: agreement needed for a derived field of the file to be used as written
_AGREE = 1e-9
_MAX_FILE_BYTES = 1 << 20

_KEYS = ("volwarp_camera", "frame", "projection", "parallel_projection", "position",
         "focal_point", "view_up", "direction_of_projection", "view_right", "parallel_scale",
         "pixels_per_unit", "image_size", "bounds", "source", "view_angle", "clipping_range")


class CameraError(SpecError):
    """A camera file that cannot be read or does not describe a parallel camera (exit 2)."""


@dataclass
class Camera:
    """An orthographic camera.

    ``right``, ``up`` and ``back`` are orthonormal world vectors (``back``
    points from the scene towards the viewer, so the direction of projection
    is ``-back``); ``scale`` is output pixels per world unit; ``center`` is the
    world point drawn at the image centre (VTK's focal point); ``size`` is
    (width, height) in pixels. ``bounds`` is the world box (xmin, xmax, ymin,
    ymax, zmin, zmax) the camera was fitted to, when known.
    ``parallel_scale``, when set, is the exact half height of the picture in
    world units (the ray caster's own parameter; ``size[1] / (2 scale)`` up to
    rounding): see :attr:`half_height`.
    """

    center: np.ndarray
    right: np.ndarray
    up: np.ndarray
    back: np.ndarray
    scale: float
    size: tuple[int, int]
    bounds: np.ndarray | None = None
    parallel_scale: float | None = None

    @property
    def half_height(self) -> float:
        """Half the picture's height in world units (VTK's parallel scale)."""
        if self.parallel_scale is not None:
            return float(self.parallel_scale)
        return self.size[1] / (2.0 * float(self.scale))

    @property
    def direction_of_projection(self) -> np.ndarray:
        """The world direction the camera looks along, ``-back``."""
        return -np.asarray(self.back, dtype=np.float64)

    def position(self) -> np.ndarray:
        """An eye point for VTK: on the viewer's side of the focal point, outside the bounds."""
        reach = self.half_height * max(1.0, self.size[0] / self.size[1])
        if self.bounds is not None:
            b = np.asarray(self.bounds, dtype=np.float64).reshape(3, 2)
            reach = max(reach, 0.5 * float(np.linalg.norm(b[:, 1] - b[:, 0])),
                        float(np.linalg.norm(np.asarray(self.center) - 0.5 * (b[:, 0] + b[:, 1]))))
        distance = 2.0 * reach if reach > 0 else 1.0
        return np.asarray(self.center, dtype=np.float64) + distance * np.asarray(self.back)

    def resized(self, size) -> Camera:
        """The same view and world height (parallel scale) in a picture of ``size`` pixels."""
        w, h = _image_size(size, "size", None)
        if (w, h) == tuple(self.size):
            return self
        hh = self.half_height
        return replace(self, size=(w, h), scale=h / (2.0 * hh), parallel_scale=hh)

    def to_dict(self, source: str | None = None) -> dict:
        """The JSON object of the camera file (see the module notes)."""
        def vec(v):
            return [float(x) + 0.0 for x in np.asarray(v, dtype=np.float64)]

        d = {
            "volwarp_camera": CAMERA_FILE_VERSION,
            "frame": "LPS",
            "projection": "parallel",
            "position": vec(self.position()),
            "focal_point": vec(self.center),
            "view_up": vec(self.up),
            "direction_of_projection": vec(self.direction_of_projection),
            "view_right": vec(self.right),
            "parallel_scale": float(self.half_height),
            "pixels_per_unit": float(self.scale),
            "image_size": [int(self.size[0]), int(self.size[1])],
        }
        if self.bounds is not None:
            d["bounds"] = vec(self.bounds)
        if source is not None:
            d["source"] = str(source)
        return d

    @classmethod
    def from_dict(cls, d, *, file: str | None = None) -> Camera:
        """A camera from the JSON object of a camera file; :class:`CameraError` when malformed."""
        def fail(message, key=None):
            raise CameraError(message, file=file, key=key)

        if not isinstance(d, dict):
            fail(f"a camera file holds one JSON object, got {type(d).__name__}")
        unknown = sorted(set(d) - set(_KEYS))
        if unknown:
            fail(f"unknown key(s) {', '.join(map(repr, unknown))} (known: {', '.join(_KEYS)})")
        version = d.get("volwarp_camera", CAMERA_FILE_VERSION)
        if version != CAMERA_FILE_VERSION or isinstance(version, bool):
            fail(f"camera file version {version!r} is not supported (this volwarp reads "
                 f"{CAMERA_FILE_VERSION})", "volwarp_camera")
        frame = d.get("frame", "LPS")
        if not isinstance(frame, str) or frame.strip().lower() not in ("lps",
                                                                       "left-posterior-superior"):
            fail(f"the camera must be in volwarp's world frame, LPS; got {frame!r}", "frame")
        projection = d.get("projection", "parallel")
        if projection not in ("parallel", "orthographic"):
            fail(f"volwarp renders parallel projections only, got {projection!r}", "projection")
        if d.get("parallel_projection", True) is not True:
            fail("volwarp renders parallel projections only (parallel_projection must be true)",
                 "parallel_projection")
        if "parallel_scale" not in d:
            if "view_angle" in d:
                fail("a perspective camera (view_angle) cannot be used: volwarp renders "
                     "parallel projections; give parallel_scale (half the picture's height in "
                     "world units)", "parallel_scale")
            fail("missing (half the picture's height in world units)", "parallel_scale")
        if "view_angle" in d:
            _number(d["view_angle"], "view_angle", file)  # VTK writes it always: checked, unused
        if "clipping_range" in d:
            _vector(d["clipping_range"], "clipping_range", file, 2)
        if "source" in d and not isinstance(d["source"], str):
            fail("must be a string", "source")

        for key in ("focal_point", "view_up", "image_size"):
            if key not in d:
                fail("missing", key)
        focal = _vector(d["focal_point"], "focal_point", file)
        size = _image_size(d["image_size"], "image_size", file)
        ps = _number(d["parallel_scale"], "parallel_scale", file)
        if ps <= 0:
            fail(f"must be positive, got {ps!r}", "parallel_scale")

        given_dop = None
        if "direction_of_projection" in d:
            given_dop = _unit(_vector(d["direction_of_projection"], "direction_of_projection",
                                      file), "direction_of_projection", file)
        if "position" in d:
            position = _vector(d["position"], "position", file)
            offset = focal - position
            length = float(np.linalg.norm(offset))
            if not length > 0:
                fail("position and focal_point are the same point: no direction of projection",
                     "position")
            dop = offset / length
            if given_dop is not None and np.abs(given_dop - dop).max() <= _AGREE:
                dop = given_dop
        elif given_dop is not None:
            dop = given_dop
        else:
            fail("missing (or give direction_of_projection)", "position")

        up = _vector(d["view_up"], "view_up", file)
        length = float(np.linalg.norm(up))
        if not length > 0:
            fail("must not be the zero vector", "view_up")
        if abs(float(up @ dop)) > 1e-12 * length or abs(length - 1.0) > 1e-12:
            up = up - float(up @ dop) * dop  # VTK's OrthogonalizeViewUp
            ortho = float(np.linalg.norm(up))
            if ortho <= 1e-6 * length:
                fail("is parallel to the direction of projection: no picture orientation",
                     "view_up")
            up = up / ortho
        right = np.cross(dop, up)
        right /= np.linalg.norm(right)
        if "view_right" in d:
            given = _vector(d["view_right"], "view_right", file)
            if np.abs(given - right).max() <= _AGREE:
                right = given
        scale = size[1] / (2.0 * ps)
        if "pixels_per_unit" in d:
            given = _number(d["pixels_per_unit"], "pixels_per_unit", file)
            if abs(given - scale) <= _AGREE * scale:
                scale = given
        bounds = None
        if "bounds" in d:
            bounds = _vector(d["bounds"], "bounds", file, 6)
            if np.any(bounds[0::2] > bounds[1::2]):
                fail("must be [xmin, xmax, ymin, ymax, zmin, zmax] with each min <= max",
                     "bounds")
        return cls(center=focal, right=right, up=up, back=-dop, scale=float(scale),
                   size=size, bounds=bounds, parallel_scale=ps)


def _number(value, key, file) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CameraError(f"must be a number, got {value!r}", file=file, key=key)
    value = float(value)
    if not math.isfinite(value):
        raise CameraError(f"must be a finite number, got {value!r}", file=file, key=key)
    return value


def _vector(value, key, file, n: int = 3) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n:
        raise CameraError(f"must be a list of {n} numbers, got {value!r}", file=file, key=key)
    return np.array([_number(v, key, file) for v in value], dtype=np.float64)


def _unit(v, key, file) -> np.ndarray:
    length = float(np.linalg.norm(v))
    if not length > 0:
        raise CameraError("must not be the zero vector", file=file, key=key)
    return v if abs(length - 1.0) <= 1e-12 else v / length


def _image_size(value, key, file) -> tuple[int, int]:
    if isinstance(value, (list, tuple)) and len(value) == 2 and all(
            isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in value):
        w, h = int(value[0]), int(value[1])
        if 1 <= w <= MAX_SIZE and 1 <= h <= MAX_SIZE:
            return w, h
    raise CameraError(f"must be [width, height], whole numbers of pixels 1..{MAX_SIZE}, got "
                      f"{value!r}", file=file, key=key)


def camera_json(camera: Camera, source: str | None = None) -> bytes:
    """The bytes of ``camera``'s file, one key a line: the same camera, the same bytes."""
    d = camera.to_dict(source)
    lines = [f"  {json.dumps(k)}: {json.dumps(v)}" for k, v in d.items()]
    return ("{\n" + ",\n".join(lines) + "\n}\n").encode("utf-8")


def write_camera(camera: Camera, path: str | os.PathLike, *, source: str | None = None) -> None:
    """Write ``camera`` to ``path`` as JSON, atomically (see the module notes)."""
    from ..io.atomic import write_bytes_atomic

    write_bytes_atomic(path, camera_json(camera, source))


def read_camera(path: str | os.PathLike) -> Camera:
    """The camera in the JSON file ``path``; :class:`CameraError` (exit 2) naming what is wrong."""
    where = str(path)
    try:
        with open(path, "rb") as fh:
            raw = fh.read(_MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise CameraError(f"cannot read camera file ({exc.strerror or exc})", file=where) from None
    if len(raw) > _MAX_FILE_BYTES:
        raise CameraError("too large for a camera file (over 1 MiB)", file=where)
    try:
        text = raw.decode("utf-8-sig")  # (a byte-order mark, as the YAML specs take it)
    except UnicodeDecodeError:
        raise CameraError("not a camera file (not UTF-8 text)", file=where) from None
    try:
        d = json.loads(text, object_pairs_hook=_distinct_keys)
    except json.JSONDecodeError as exc:
        raise CameraError(f"not valid JSON: {exc.msg} (column {exc.colno})", file=where,
                          line=exc.lineno) from None
    except _RepeatedKey as exc:
        raise CameraError(f"the key {exc.args[0]!r} is given twice (which one is meant?)",
                          file=where) from None
    return Camera.from_dict(d, file=where)


class _RepeatedKey(ValueError):
    """A JSON object with a key twice (json keeps the last without a word)."""


def _distinct_keys(pairs) -> dict:
    """A JSON object's dict; :class:`_RepeatedKey` for a key given twice, as the specs refuse."""
    out = {}
    for key, value in pairs:
        if key in out:
            raise _RepeatedKey(key)
        out[key] = value
    return out


def bounds_of(points) -> np.ndarray | None:
    """(xmin, xmax, ymin, ymax, zmin, zmax) of world ``points`` (N, 3); None when empty."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return None
    lo, hi = p.min(axis=0), p.max(axis=0)
    return np.stack([lo, hi], axis=1).ravel()


def sees_any(camera: Camera, points) -> bool:
    """Whether the bounding box of ``points`` reaches into the camera's picture."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return True
    lo, hi = p.min(axis=0), p.max(axis=0)
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                        for c in (lo[2], hi[2])]) - np.asarray(camera.center)
    px, py = corners @ np.asarray(camera.right), corners @ np.asarray(camera.up)
    hw = camera.half_height * camera.size[0] / camera.size[1]
    hh = camera.half_height
    return bool(px.max() >= -hw and px.min() <= hw and py.max() >= -hh and py.min() <= hh)
