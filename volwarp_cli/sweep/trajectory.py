"""Sweeping trajectories a(u): line, arc, n-degree Bezier and polyline segments.

Winter & Chen (2002) §4.1 and §4.2: a *composite trajectory* is a list of
segments ``a_i(u_i)``, each with its own parameter range, joined or not.
Every segment here is evaluated on a normalised parameter ``s`` in [0, 1]
(vectorised: ``s`` is an array), and maps it to the user's ``u`` range
(``[0, 1]`` unless the segment says ``u: [u0, u1]``), which is what the
per-u functions (scale, up, f(u)) see.

* ``line``: ``from`` -> ``to``.
* ``arc``: a circle segment (a rotational sweep, §5.2): ``center``,
  ``radius``, ``axis`` (right-handed: angles increase counter-clockwise seen
  from the tip of ``axis``), ``start`` and ``end`` angles in degrees. Angle 0
  lies along the projection of world x onto the circle's plane (world y when
  the axis is x).
* ``bezier``: an n-degree Bezier curve through its ``points`` (n + 1 control
  points, §5.3).
* ``polyline``: ``points`` joined by straight pieces, parameterised by arc
  length; :meth:`Polyline.breaks` gives the vertex parameters so that the
  voxeliser puts a knot (and a rotational joint) on every vertex.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@dataclass
class Segment:
    """Base class: ``point``/``d1``/``d2`` of the normalised parameter ``s``."""

    u0: float = 0.0
    u1: float = 1.0
    path: tuple = field(default=(), repr=False)  # spec key of the segment

    kind = "segment"

    def u_of(self, s):
        """The user's parameter ``u`` in [u0, u1] at normalised parameters ``s``."""
        return self.u0 + np.asarray(s, dtype=np.float64) * (self.u1 - self.u0)

    def s_of(self, u):
        """The normalised parameter ``s`` of the user's ``u`` (the inverse of :meth:`u_of`)."""
        return (np.asarray(u, dtype=np.float64) - self.u0) / (self.u1 - self.u0)

    def point(self, s: np.ndarray) -> np.ndarray:  # (N, 3)
        """The trajectory point a(s), (N, 3)."""
        raise NotImplementedError

    def d1(self, s: np.ndarray) -> np.ndarray:
        """Derivative d a / d s, (N, 3)."""
        raise NotImplementedError

    def d2(self, s: np.ndarray) -> np.ndarray:
        """Second derivative d2 a / d s2, (N, 3)."""
        raise NotImplementedError

    def breaks(self) -> np.ndarray:
        """Interior parameters where the tangent jumps (polyline vertices)."""
        return np.zeros(0)

    def sample_points(self, n: int = 257) -> np.ndarray:
        """``n`` points at evenly spaced ``s`` from 0 to 1, (n, 3)."""
        return self.point(np.linspace(0.0, 1.0, n))

    def dense_parameters(self, n: int) -> np.ndarray:
        """``n`` evenly spaced ``s`` from 0 to 1 and the :meth:`breaks`, sorted, each once.

        (As ``np.unique``, which imports numpy.ma on its first call: 7 ms of a sweep.)
        """
        s = np.sort(np.concatenate([np.linspace(0.0, 1.0, n), self.breaks()]))
        return s[np.concatenate(([True], s[1:] != s[:-1]))] if s.size else s


@dataclass
class Line(Segment):
    """A straight segment from ``start`` to ``stop``."""

    start: np.ndarray = None
    stop: np.ndarray = None
    kind = "line"

    def point(self, s):
        """``start + s (stop - start)``, (N, 3)."""
        s = np.asarray(s, dtype=np.float64)[:, None]
        return self.start + s * (self.stop - self.start)

    def d1(self, s):
        """``stop - start`` at every ``s``, (N, 3)."""
        return np.broadcast_to(self.stop - self.start, (np.size(s), 3)).copy()

    def d2(self, s):
        """Zero, (N, 3)."""
        return np.zeros((np.size(s), 3))

    @property
    def length(self) -> float:
        """The distance from ``start`` to ``stop``."""
        return float(np.linalg.norm(self.stop - self.start))


def arc_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (e1, e2, n) for a circle about ``axis``; e1 is angle 0."""
    n = _unit(np.asarray(axis, dtype=np.float64))
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _unit(ref - np.dot(ref, n) * n)
    e2 = np.cross(n, e1)
    return e1, e2, n


@dataclass
class Arc(Segment):
    """A circle segment about ``axis`` through ``center``, from ``start_deg`` to ``end_deg``."""

    center: np.ndarray = None
    radius: float = 1.0
    axis: np.ndarray = None
    start_deg: float = 0.0
    end_deg: float = 360.0
    kind = "arc"

    def __post_init__(self):
        self.e1, self.e2, self.n = arc_basis(self.axis)
        self.t0 = math.radians(self.start_deg)
        self.t1 = math.radians(self.end_deg)

    def angle(self, s):
        """The angle (radians) at normalised parameters ``s``."""
        return self.t0 + np.asarray(s, dtype=np.float64) * (self.t1 - self.t0)

    def s_of_angle(self, theta):
        """The normalised parameter ``s`` of angle ``theta`` (radians)."""
        return (theta - self.t0) / (self.t1 - self.t0)

    def point(self, s):
        """The circle's points at ``s``, (N, 3)."""
        th = self.angle(s)[:, None]
        return self.center + self.radius * (np.cos(th) * self.e1 + np.sin(th) * self.e2)

    def d1(self, s):
        """Derivative d a / d s, (N, 3)."""
        th = self.angle(s)[:, None]
        k = self.radius * (self.t1 - self.t0)
        return k * (-np.sin(th) * self.e1 + np.cos(th) * self.e2)

    def d2(self, s):
        """Second derivative d2 a / d s2, (N, 3)."""
        th = self.angle(s)[:, None]
        k = self.radius * (self.t1 - self.t0) ** 2
        return -k * (np.cos(th) * self.e1 + np.sin(th) * self.e2)


@dataclass
class Bezier(Segment):
    """An n-degree Bezier curve of ``n + 1`` control points."""

    points: np.ndarray = None  # (n + 1, 3) control points
    kind = "bezier"

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64)
        self.monomial = bezier_to_monomial(self.points)  # (n + 1, 3), a(s) = sum c_k s^k

    @property
    def degree(self) -> int:
        """The degree n (control points less one)."""
        return self.points.shape[0] - 1

    def point(self, s):
        """The curve's points at ``s`` (de Casteljau), (N, 3)."""
        return _de_casteljau(self.points, np.asarray(s, dtype=np.float64))

    def d1(self, s):
        """Derivative d a / d s, (N, 3) (zero for degree 0)."""
        n = self.degree
        if n < 1:
            return np.zeros((np.size(s), 3))
        return n * _de_casteljau(np.diff(self.points, axis=0), np.asarray(s, dtype=np.float64))

    def d2(self, s):
        """Second derivative d2 a / d s2, (N, 3) (zero below degree 2)."""
        n = self.degree
        if n < 2:
            return np.zeros((np.size(s), 3))
        return n * (n - 1) * _de_casteljau(np.diff(self.points, n=2, axis=0),
                                           np.asarray(s, dtype=np.float64))


def _de_casteljau(ctrl: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Evaluate a Bezier curve with control points ``ctrl`` at all ``s`` (stable)."""
    s = s[:, None]
    pts = np.broadcast_to(ctrl, (s.shape[0],) + ctrl.shape).copy()
    for r in range(ctrl.shape[0] - 1, 0, -1):
        pts = pts[:, :r] * (1.0 - s[:, :, None]) + pts[:, 1:r + 1] * s[:, :, None]
    return pts[:, 0]


def bezier_to_monomial(ctrl: np.ndarray) -> np.ndarray:
    """Coefficients ``c_k`` (k = 0..n) with ``a(s) = sum_k c_k s^k`` for control points ``ctrl``."""
    n = ctrl.shape[0] - 1
    coef = np.zeros_like(ctrl, dtype=np.float64)
    for k in range(n + 1):
        acc = np.zeros(ctrl.shape[1])
        for i in range(k + 1):
            acc += (-1) ** (k - i) * math.comb(k, i) * ctrl[i]
        coef[k] = math.comb(n, k) * acc
    return coef


@dataclass
class Polyline(Segment):
    """Points joined by straight pieces, parameterised by arc length."""

    points: np.ndarray = None  # (m, 3), m >= 2
    kind = "polyline"

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64)
        lengths = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.total = float(lengths.sum())
        self.cum = np.concatenate([[0.0], np.cumsum(lengths)]) / self.total

    def _piece(self, s):
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
        idx = np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.cum) - 2)
        return s, idx

    def point(self, s):
        """The points at arc-length parameters ``s``, (N, 3)."""
        s, idx = self._piece(s)
        a, b = self.points[idx], self.points[idx + 1]
        w = ((s - self.cum[idx]) / (self.cum[idx + 1] - self.cum[idx]))[:, None]
        return a + w * (b - a)

    def d1(self, s):
        """The right-hand derivative d a / d s (left-hand at s = 1), (N, 3)."""
        s, idx = self._piece(s)
        return (self.points[idx + 1] - self.points[idx]) / (self.cum[idx + 1] - self.cum[idx])[:, None]

    def d1_left(self, s):
        """The left-hand derivative d a / d s (right-hand at s = 0), (N, 3).

        At a vertex, that of the piece ending there.
        """
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
        idx = np.clip(np.searchsorted(self.cum, s, side="left") - 1, 0, len(self.cum) - 2)
        return (self.points[idx + 1] - self.points[idx]) / (self.cum[idx + 1] - self.cum[idx])[:, None]

    def d2(self, s):
        """Zero on every piece, (N, 3)."""
        return np.zeros((np.size(s), 3))

    def breaks(self):
        """The parameters of the interior vertices, where the tangent jumps."""
        return self.cum[1:-1].copy()
