"""Sweeping functions and the template frames they define (Winter & Chen §4.1, §5.3).

At every ``u`` the sweep places the template square in the plane through
``a(u)`` whose normal is the sweeping direction ``r_d(u)``, rotated about it
by the up-vector ``r_u(u)`` and scaled by ``r_s(u)`` (the world width and
height of the template square; the paper's default [1, 1] becomes the spec's
``scale``). The local frame is

* ``ez = r_d / |r_d|`` (template normal),
* ``ey = (r_u - (r_u . ez) ez) / |...|`` (template "up", image rows go down it),
* ``ex = ey x ez`` (template "right"; (ex, ey, ez) is right-handed),

and the template point (x, y) in [0, 1]^2 lies at
``a(u) + sx (x - 0.5) ex + sy (y - 0.5) ey``.

``r_d`` is the tangent ``da/du`` (default), a constant or per-u vector, or
``a_d(u) - a(u)`` for a secondary trajectory ``a_d``; ``r_u`` is a constant or
per-u vector, ``a_u(u) - a(u)``, or ``binormal``: the paper's §5.3 frame,
``b = r_d x dr_d/du``, ``r_u = r_d x b``. Up and direction must not be
collinear anywhere (a spec error naming the key and the ``u``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..spec.functions import Function, spec_error
from .trajectory import Polyline, Segment


@dataclass
class Secondary:
    """A secondary trajectory: one segment per main segment (or one for all)."""

    segments: list[Segment]
    path: tuple

    def for_segment(self, index: int) -> Segment:
        return self.segments[index if len(self.segments) > 1 else 0]


@dataclass
class SweepFunctions:
    """The direction, up and scale functions of one segment (with their spec keys)."""

    direction: object  # "tangent" | Function (3-vector) | Secondary
    up: object  # Function (3-vector) | Secondary | "binormal"
    scale: Function  # 2-vector
    direction_path: tuple = ("direction",)
    up_path: tuple = ("up",)
    doc: object = None


@dataclass
class Frames:
    """Template frames at parameters ``s`` (all arrays, length N)."""

    s: np.ndarray
    u: np.ndarray
    P: np.ndarray  # (N, 3) a(u)
    EX: np.ndarray
    EY: np.ndarray
    EZ: np.ndarray
    SX: np.ndarray  # (N,)
    SY: np.ndarray

    def corners(self) -> np.ndarray:
        """(N, 5, 3): the template's four corners and its centre in world space."""
        hx = (0.5 * self.SX)[:, None] * self.EX
        hy = (0.5 * self.SY)[:, None] * self.EY
        P = self.P
        return np.stack([P - hx - hy, P + hx - hy, P + hx + hy, P - hx + hy, P], axis=1)

    def take(self, idx) -> Frames:
        return Frames(*(getattr(self, f)[idx] for f in
                        ("s", "u", "P", "EX", "EY", "EZ", "SX", "SY")))

    @staticmethod
    def concat(parts: list[Frames]) -> Frames:
        return Frames(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                        ("s", "u", "P", "EX", "EY", "EZ", "SX", "SY")))


def _tangent(seg: Segment, s: np.ndarray, left: bool) -> np.ndarray:
    if left and isinstance(seg, Polyline):
        d = seg.d1_left(s)
    else:
        d = seg.d1(s)
    n = np.linalg.norm(d, axis=1)
    scale = max(float(np.ptp(seg.sample_points(9), axis=0).max()), 1e-12)
    bad = n < 1e-9 * scale
    if np.any(bad):
        # a vanishing derivative (e.g. a Bezier whose first two control points
        # coincide): the tangent's limit is the direction of a small chord.
        h = 1e-4
        sb = s[bad]
        chord = seg.point(np.clip(sb + h, 0, 1)) - seg.point(np.clip(sb - h, 0, 1))
        d = d.copy()
        d[bad] = chord
    return d


def direction_vectors(seg: Segment, fns: SweepFunctions, s: np.ndarray, index: int,
                      P: np.ndarray | None = None, left: bool = False) -> np.ndarray:
    """r_d at normalised parameters ``s`` of segment number ``index`` (not normalised)."""
    u = seg.u_of(s)
    d = fns.direction
    if isinstance(d, str):
        return _tangent(seg, s, left)
    if isinstance(d, Secondary):
        P = seg.point(s) if P is None else P
        return d.for_segment(index).point(s) - P
    return d(u)


def _direction_derivative(seg, fns, s, index, left):
    if isinstance(fns.direction, str) and not isinstance(seg, Polyline):
        return seg.d2(s)
    h = 1e-5
    lo = np.clip(s - h, 0.0, 1.0)
    hi = np.clip(s + h, 0.0, 1.0)
    dl = direction_vectors(seg, fns, lo, index, left=left)
    dh = direction_vectors(seg, fns, hi, index, left=left)
    return (dh - dl) / (hi - lo)[:, None]


def compute_frames(seg: Segment, fns: SweepFunctions, s: np.ndarray, index: int,
                   left: bool = False) -> Frames:
    """Template frames of segment ``seg`` (number ``index``) at normalised ``s``.

    ``left`` uses the left-hand tangent at polyline vertices.
    """
    s = np.asarray(s, dtype=np.float64)
    u = seg.u_of(s)
    P = seg.point(s)
    rd = direction_vectors(seg, fns, s, index, P, left)
    nd = np.linalg.norm(rd, axis=1)
    if np.any(nd < 1e-12):
        i = int(np.argmax(nd < 1e-12))
        path = seg.path if isinstance(fns.direction, str) else fns.direction_path
        raise spec_error(fns.doc, path, f"the sweeping direction is zero at u={u[i]:.6g}")
    ez = rd / nd[:, None]
    if isinstance(fns.up, str):  # binormal frame, §5.3
        drd = _direction_derivative(seg, fns, s, index, left)
        b = np.cross(rd, drd)
        nb = np.linalg.norm(b, axis=1)
        if np.any(nb < 1e-9 * np.maximum(nd, 1e-300) ** 2):
            i = int(np.argmax(nb < 1e-9 * nd ** 2))
            raise spec_error(fns.doc, fns.up_path,
                             f"up: binormal is undefined at u={u[i]:.6g} of {seg.kind} segment "
                             f"{index} (the trajectory is straight there); give an up vector")
        up = np.cross(rd, b)
    elif isinstance(fns.up, Secondary):
        up = fns.up.for_segment(index).point(s) - P
    else:
        up = fns.up(u)
    nu = np.linalg.norm(up, axis=1)
    cross = np.linalg.norm(np.cross(ez, up), axis=1)
    bad = cross <= 1e-6 * np.maximum(nu, 1e-300)
    if np.any(bad):
        i = int(np.argmax(bad))
        what = "is zero" if nu[i] < 1e-300 else "is collinear with the sweeping direction"
        raise spec_error(fns.doc, fns.up_path,
                         f"the up vector {what} at u={u[i]:.6g} of {seg.kind} segment {index} "
                         f"(direction {np.round(ez[i], 6).tolist()}); choose another up")
    ey = up - np.sum(up * ez, axis=1)[:, None] * ez
    ey /= np.linalg.norm(ey, axis=1)[:, None]
    ex = np.cross(ey, ez)
    sc = fns.scale(u)
    if np.any(sc <= 0):
        i = int(np.argmax(np.any(sc <= 0, axis=1)))
        raise spec_error(fns.doc, fns.scale.path,
                         f"scale must be positive, got {sc[i].tolist()} at u={u[i]:.6g}")
    return Frames(s, u, P, ex, ey, ez, sc[:, 0].copy(), sc[:, 1].copy())
