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
``b = r_d x dr_d/du``, ``r_u = r_d x b``. A given up must be neither zero nor
collinear with the direction anywhere: :func:`check_up` (run at parse time by
:func:`prepare_frames`) searches each segment for the places where they come
closest, between samples too, and makes such an up a spec error naming the
key, the ``u`` and the point.

*The default up* (no ``up`` in the spec) is a rotation-minimising frame
(:class:`RotationMinimising`): ``r_u`` is transported along the segment so
that it never turns about the sweeping direction, by the double reflection
method of Wang, Jüttler, Zheng & Liu (2008), "Computation of rotation
minimizing frames", ACM TOG 27(1). It starts perpendicular to the first
direction: world z projected onto the plane normal to it, or world y where
that direction is along z (within the same 1e-6 that makes a given up
collinear). A segment that starts where the previous one ends continues that
one's end frame (turned by the least rotation onto its own first direction,
as at a polyline vertex); a segment that starts elsewhere starts afresh. It
is defined for every trajectory (a line along z included), is continuous
along a composite trajectory, and has no twist: on a planar curve it keeps a
constant angle with the plane. Where world z projected onto the normal plane
*is* that frame (lines not along z, curves in a horizontal plane, or in a
vertical one whose direction is never vertical) the frames are computed
exactly as for an explicit ``up: [0, 0, 1]``, bit for bit the default of
earlier versions. On other trajectories (a helix, a space curve, a circle in
a tilted plane) they differ from it: the projected z twists about the
trajectory and has no value where the direction is vertical, the
rotation-minimising frame does neither. ``up: [0, 0, 1]`` gives the
projected z back.

The double reflection step here reflects with the chord of the curve whose
unit tangent is the sweeping direction (Simpson's rule, ``t0 + 4 tm + t1``,
not the trajectory's own chord), so it works for every direction kind (a
constant or per-u direction, a secondary trajectory) and loses no digits on
short steps; its error is fourth order in the step. A table per segment holds
the frame at parameters no more than one degree of direction apart (polyline
vertices twice: incoming and outgoing); at any other ``s`` one more step from
the nearest table entry below gives it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..spec.functions import Function, parse_function, spec_error
from .trajectory import Polyline, Segment

#: |direction x up| / |up| at or below this is collinear (a given up), or too close to
#: world z for the default frame to start from z
COLLINEAR = 1e-6
#: largest angle between the directions of neighbouring entries of a frame table (radians)
MAX_STEP_ANGLE = np.radians(1.0)
#: the table stops refining an interval shorter than this (in s): a jump of the direction
MIN_STEP = 1e-9
#: upper bound on the entries of one segment's frame table
MAX_TABLE = 1 << 16


@dataclass
class Secondary:
    """A secondary trajectory: one segment per main segment (or one for all)."""

    segments: list[Segment]
    path: tuple

    def for_segment(self, index: int) -> Segment:
        """The secondary segment of main segment ``index`` (the only one, if one for all)."""
        return self.segments[index if len(self.segments) > 1 else 0]


@dataclass
class SweepFunctions:
    """The direction, up and scale functions of one segment (with their spec keys)."""

    direction: object  # "tangent" | Function (3-vector) | Secondary
    up: object  # Function (3-vector) | Secondary | "binormal" | RotationMinimising (default)
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
        """The frames at ``idx`` (an index array or mask into the N frames)."""
        return Frames(*(getattr(self, f)[idx] for f in
                        ("s", "u", "P", "EX", "EY", "EZ", "SX", "SY")))

    @staticmethod
    def concat(parts: list[Frames]) -> Frames:
        """The frames of ``parts`` one after the other."""
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


def _zero_direction_error(seg: Segment, fns: SweepFunctions, u: float):
    path = seg.path if isinstance(fns.direction, str) else fns.direction_path
    return spec_error(fns.doc, path, f"the sweeping direction is zero at u={u:.6g}")


def _unit_rows(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1)[:, None]


def _unit_directions(seg: Segment, fns: SweepFunctions, s: np.ndarray, index: int,
                     left: bool = False) -> np.ndarray:
    """Unit sweeping directions at ``s`` (a zero direction is a spec error)."""
    rd = direction_vectors(seg, fns, s, index, left=left)
    nd = np.linalg.norm(rd, axis=1)
    if np.any(nd < 1e-12):
        raise _zero_direction_error(seg, fns, float(seg.u_of(s)[int(np.argmax(nd < 1e-12))]))
    return rd / nd[:, None]


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles between the rows of two (N, 3) arrays of unit vectors (accurate near 0)."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


def transport(r: np.ndarray, t0: np.ndarray, tm: np.ndarray, t1: np.ndarray,
              h: np.ndarray) -> np.ndarray:
    """One double reflection step (Wang et al. 2008) of the frame vectors ``r``.

    ``r`` (unit, perpendicular to the unit direction ``t0``) goes to the unit
    vector perpendicular to ``t1`` that a rotation-minimising frame reaches
    over a step of ``h`` in ``s``; ``tm`` is the direction half way. The first
    reflection is in the plane normal to ``t0 + 4 tm + t1`` (Simpson's rule
    for the chord of the curve whose unit tangent is the direction), the
    second one sends the reflected ``t0`` onto ``t1``. A step of at most
    :data:`MIN_STEP` (a polyline vertex, a jump of the direction) is the least
    rotation from ``t0`` to ``t1`` (chord ``t0 + t1``); a direction that turns
    back on itself there (``t1 = -t0``) turns ``r``'s template half a turn about
    ``r``. All arguments are (N, 3) arrays, ``h`` (N,).
    """
    v1 = t0 + 4.0 * tm + t1
    corner = np.asarray(h) <= MIN_STEP
    if np.any(corner):
        v1 = np.where(corner[:, None], t0 + t1, v1)
    c1 = np.sum(v1 * v1, axis=1)
    back = c1 < 1e-20
    if np.any(back):
        v1 = np.where(back[:, None], np.cross(r, t0), v1)
        c1 = np.sum(v1 * v1, axis=1)
    rl = r - (2.0 * np.sum(v1 * r, axis=1) / c1)[:, None] * v1
    tl = t0 - (2.0 * np.sum(v1 * t0, axis=1) / c1)[:, None] * v1
    v2 = t1 - tl
    c2 = np.sum(v2 * v2, axis=1)
    ok = c2 > 1e-30
    k = np.where(ok, 2.0 * np.sum(v2 * rl, axis=1) / np.where(ok, c2, 1.0), 0.0)
    r1 = rl - k[:, None] * v2
    r1 -= np.sum(r1 * t1, axis=1)[:, None] * t1  # rounding: keep it in the normal plane
    return _unit_rows(r1)


def _transport_table(r0: np.ndarray, T: np.ndarray, TM: np.ndarray, H: np.ndarray) -> np.ndarray:
    """:func:`transport` from entry to entry of a table, ``R[0] = r0``.

    A scalar loop: the steps depend on each other, and numpy's per-call overhead
    would dominate.
    """
    R = np.empty_like(T)
    R[0] = r0
    r = [float(v) for v in r0]
    tl_ = T.tolist()
    tm_ = TM.tolist()
    for k, h in enumerate(H.tolist()):
        t0, t1, tm = tl_[k], tl_[k + 1], tm_[k]
        if h <= MIN_STEP:
            v = [t0[0] + t1[0], t0[1] + t1[1], t0[2] + t1[2]]
        else:
            v = [t0[0] + 4.0 * tm[0] + t1[0], t0[1] + 4.0 * tm[1] + t1[1],
                 t0[2] + 4.0 * tm[2] + t1[2]]
        c1 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        if c1 < 1e-20:  # turns back: half a turn about r
            v = [r[1] * t0[2] - r[2] * t0[1], r[2] * t0[0] - r[0] * t0[2],
                 r[0] * t0[1] - r[1] * t0[0]]
            c1 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        a = 2.0 * (v[0] * r[0] + v[1] * r[1] + v[2] * r[2]) / c1
        b = 2.0 * (v[0] * t0[0] + v[1] * t0[1] + v[2] * t0[2]) / c1
        rl = [r[0] - a * v[0], r[1] - a * v[1], r[2] - a * v[2]]
        w = [t1[0] - t0[0] + b * v[0], t1[1] - t0[1] + b * v[1], t1[2] - t0[2] + b * v[2]]
        c2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
        a = 2.0 * (w[0] * rl[0] + w[1] * rl[1] + w[2] * rl[2]) / c2 if c2 > 1e-30 else 0.0
        r = [rl[0] - a * w[0], rl[1] - a * w[1], rl[2] - a * w[2]]
        d = r[0] * t1[0] + r[1] * t1[1] + r[2] * t1[2]
        r = [r[0] - d * t1[0], r[1] - d * t1[1], r[2] - d * t1[2]]
        n = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]) ** 0.5
        r = [r[0] / n, r[1] / n, r[2] / n]
        R[k + 1] = r
    return R


def start_up(t0: np.ndarray) -> np.ndarray:
    """The default frame's first up: world z (world y if ``t0`` is along z) made normal to ``t0``."""
    t0 = np.asarray(t0, dtype=np.float64)
    ref = np.array([0.0, 0.0, 1.0])
    if np.linalg.norm(np.cross(t0, ref)) <= COLLINEAR:
        ref = np.array([0.0, 1.0, 0.0])
    r = ref - np.dot(ref, t0) * t0
    return r / np.linalg.norm(r)


@dataclass
class RotationMinimising:
    """The default up of one segment: a rotation-minimising frame (see the module doc).

    ``start`` is the up at ``s = 0`` (unit, normal to the first direction;
    ``None``: :func:`start_up`). :meth:`build` fills the table ``s`` (polyline
    vertices twice, incoming then outgoing), ``T`` (unit directions) and ``R``
    (the frame's up); calling the object gives the up at any ``s``.
    """

    start: np.ndarray | None = None
    s: np.ndarray | None = None
    T: np.ndarray | None = None
    R: np.ndarray | None = None

    def build(self, seg: Segment, fns: SweepFunctions, index: int) -> RotationMinimising:
        """Fill the table: its entries no more than :data:`MAX_STEP_ANGLE` of direction apart."""
        edges = np.concatenate([[0.0], seg.breaks(), [1.0]])
        n_pieces = len(edges) - 1
        n0 = max(3, 33 // n_pieces)
        w = np.linspace(0.0, 1.0, n0)
        s = (edges[:-1, None] + (edges[1:] - edges[:-1])[:, None] * w).ravel()
        t = _unit_directions(seg, fns, s, index)
        ends = np.arange(1, n_pieces) * n0 - 1  # a piece's end at a vertex: incoming direction
        if ends.size:
            t[ends] = _unit_directions(seg, fns, s[ends], index, left=True)
        while True:
            mid = 0.5 * (s[:-1] + s[1:])
            tm = _unit_directions(seg, fns, mid, index)
            turn = _angle(t[:-1], tm) + _angle(tm, t[1:])
            split = (turn > MAX_STEP_ANGLE) & (np.diff(s) > MIN_STEP)
            if not np.any(split) or s.size + int(split.sum()) > MAX_TABLE:
                break
            order = np.argsort(np.concatenate([s, mid[split]]), kind="stable")
            s = np.concatenate([s, mid[split]])[order]
            t = np.concatenate([t, tm[split]])[order]
        # (at a vertex the step has no length: the least rotation, whatever tm says)
        r0 = start_up(t[0]) if self.start is None else np.asarray(self.start, dtype=np.float64)
        self.s, self.T, self.R = s, t, _transport_table(r0, t, tm, np.diff(s))
        return self

    def matches_world_z(self, tol: float = 1e-9) -> bool:
        """True when world z made normal to the direction is this frame at every table entry."""
        z = np.array([0.0, 0.0, 1.0])
        if np.any(np.linalg.norm(np.cross(self.T, z), axis=1) <= COLLINEAR):
            return False
        proj = _unit_rows(z - (self.T @ z)[:, None] * self.T)
        return bool(np.abs(proj - self.R).max() <= tol)

    def __call__(self, seg: Segment, fns: SweepFunctions, s: np.ndarray, ez: np.ndarray,
                 index: int, left: bool = False) -> np.ndarray:
        """The up (unit, normal to ``ez``) at parameters ``s`` with unit directions ``ez``."""
        if self.R is None:
            self.build(seg, fns, index)
        k = np.searchsorted(self.s, s, side="left" if left else "right") - 1
        k = np.clip(k, 0, len(self.s) - 1)
        h = s - self.s[k]
        tm = ez.copy()
        far = h > MIN_STEP
        if np.any(far):
            tm[far] = _unit_directions(seg, fns, 0.5 * (s[far] + self.s[k[far]]), index)
        return transport(self.R[k], self.T[k], tm, ez, h)


def _fmt(v) -> list:
    return [float(f"{x:.6g}") + 0.0 for x in np.asarray(v, dtype=np.float64)]


def _up_error(seg: Segment, fns: SweepFunctions, index: int, s: float, ez, zero: bool):
    u = float(seg.u_of(np.array([s]))[0])
    point = seg.point(np.array([s]))[0]
    what = "is zero" if zero else "is collinear with the sweeping direction"
    return spec_error(fns.doc, fns.up_path,
                      f"the up vector {what} at u={u:.6g} (point {_fmt(point)}) of {seg.kind} "
                      f"segment {index} (direction {_fmt(np.round(ez, 6))}); choose another up")


def _closeness(seg, fns, s, index, scale, left=False):
    """``|ez x up| / |up|`` (0 where up is zero) and ``|ez x up| / scale`` at ``s``.

    Also the unit directions and ``|up|``.
    """
    s = np.asarray(s, dtype=np.float64)
    ez = _unit_directions(seg, fns, s, index, left=left)
    if isinstance(fns.up, Secondary):
        up = fns.up.for_segment(index).point(s) - seg.point(s)
    else:
        up = fns.up(seg.u_of(s))
    nu = np.linalg.norm(up, axis=1)
    cross = np.linalg.norm(np.cross(ez, up), axis=1)
    rel = np.where(nu < 1e-300, 0.0, cross / np.maximum(nu, 1e-300))
    return rel, cross / scale, ez, nu


def check_up(seg: Segment, fns: SweepFunctions, index: int, samples: int = 1025) -> None:
    """A spec error if a given up is zero or collinear with the direction anywhere on ``seg``.

    Collinear is ``|ez x up| <= 1e-6 |up|`` (as in :func:`compute_frames`), zero
    is ``|up|`` at most 1e-9 of its largest sampled length. Both closeness
    measures (``|ez x up|`` relative to ``|up|`` and to that largest length)
    are sampled densely, both sides of every polyline vertex, and minimised
    from every local minimum of the samples, so a direction that swings
    through the up, or an up through zero, between two samples is found too.
    """
    breaks = seg.breaks()
    s = seg.dense_parameters(samples)
    rel, _, _, nu = _closeness(seg, fns, s, index, 1.0)
    scale = max(float(nu.max()), 1e-300)
    zero = 1e-9 * scale

    def fail(x, left=False):
        x = np.atleast_1d(np.asarray(x, dtype=np.float64))
        r, _, e, n = _closeness(seg, fns, x, index, scale, left)
        bad = np.flatnonzero((n <= zero) | (r <= COLLINEAR))
        if bad.size:
            k = int(bad[0])
            raise _up_error(seg, fns, index, float(x[k]), e[k], n[k] <= zero)

    if breaks.size:
        fail(breaks, left=True)
    fail(s)
    absolute = rel * nu / scale
    for values, which in ((rel, 0), (absolute, 1)):
        lo = np.concatenate([[np.inf], values[:-1]])
        hi = np.concatenate([values[1:], [np.inf]])
        cand = np.flatnonzero((values <= lo) & (values <= hi) & ((values < lo) | (values < hi))
                              & (values < 0.1))
        for k in cand[np.argsort(values[cand])][:16]:
            a, b = s[max(k - 1, 0)], s[min(k + 1, len(s) - 1)]
            fail(_minimum(lambda x, w=which: _closeness(seg, fns, x, index, scale)[w], a, b))


def _minimum(f, a: float, b: float, iterations: int = 26) -> float:
    """Where the vectorised ``f`` is smallest on [a, b] (a local minimum).

    Nine samples a round, keeping the two intervals about the smallest: a quarter
    of the bracket.
    """
    x = np.array([a])
    j = 0
    for _ in range(iterations):
        x = np.linspace(a, b, 9)
        j = int(np.argmin(f(x)))
        a, b = x[max(j - 1, 0)], x[min(j + 1, 8)]
        if b - a <= 1e-15:
            break
    return float(x[j])


def _joined(a: Segment, b: Segment, scale: float) -> bool:
    return bool(np.linalg.norm(a.point(np.array([1.0]))[0] - b.point(np.array([0.0]))[0])
                <= 1e-9 * scale)


def prepare_frames(segments: list[Segment], functions: list[SweepFunctions]) -> None:
    """Check given ups and set up the default frames of one sweep (at parse time).

    A given up (a vector, a function, a secondary trajectory) is searched for a
    place where it is zero or collinear with the direction (:func:`check_up`).
    A default up (:class:`RotationMinimising`) gets its table; a segment that
    starts where the previous one ends starts from that one's end frame. Where
    the table equals world z made normal to the direction, the up becomes the
    constant ``[0, 0, 1]``: exactly the frames of ``up: [0, 0, 1]``.
    """
    pts = np.concatenate([seg.sample_points(9) for seg in segments])
    scale = max(float(np.ptp(pts, axis=0).max()), 1e-12)
    for i, (seg, fns) in enumerate(zip(segments, functions, strict=True)):
        if isinstance(fns.up, RotationMinimising):
            rmf = fns.up
            if rmf.start is None and i > 0 and _joined(segments[i - 1], seg, scale):
                end = compute_frames(segments[i - 1], functions[i - 1], np.array([1.0]), i - 1,
                                     left=True)
                t0 = _unit_directions(seg, fns, np.array([0.0]), i)
                rmf.start = transport(end.EY, end.EZ, t0, t0, np.zeros(1))[0]
            rmf.build(seg, fns, i)
            if rmf.matches_world_z():
                fns.up = parse_function([0, 0, 1], fns.up_path, fns.doc, dim=3, name="up")
        elif not isinstance(fns.up, str):
            check_up(seg, fns, i)
    check_sweeps_volume(segments, functions)


def check_sweeps_volume(segments: list[Segment], functions: list[SweepFunctions],
                        samples: int = 257) -> None:
    """A spec error if every segment of a sweep keeps its templates in one plane: no volume.

    A given direction perpendicular to a straight path (``direction: [0, 0, 1]``
    along a line in x) moves the template within its own plane: the swept set
    is flat, and every voxel of the output was 0, exit 0. Flat is: a constant
    direction, and the template centres within :data:`COLLINEAR` of the
    segment's size off the first template's plane at ``samples`` parameters
    and the polyline vertices (all of the path: lines, arcs, Beziers of lower
    degree). One flat segment among others that sweep is no slip: an in-plane
    leg of a staircase adds nothing, as a polyline's in-plane leg does. A
    direction that varies (keyframes, an expression, a secondary trajectory)
    may turn between any two samples (a nod, a wobble): not refused here, an
    all-zero output of it is said when the run ends.
    """
    flat = [i for i, (seg, fns) in enumerate(zip(segments, functions, strict=True))
            if isinstance(fns.direction, Function) and fns.direction.is_constant
            and _in_one_plane(seg, fns, i, samples)]
    if not flat or len(flat) < len(segments):
        return
    index = flat[0]
    seg, fns = segments[index], functions[index]
    normal = compute_frames(seg, fns, np.zeros(1), index).EZ[0]
    raise spec_error(fns.doc, fns.direction_path,
                     f"{seg.kind} segment {index} moves its template within the template's "
                     f"own plane (normal {_fmt(np.round(normal, 6))} all along it)"
                     + (", as every other segment does" if len(segments) > 1 else "")
                     + ": it sweeps no volume, every voxel would be 0; give a direction "
                     "across the path, or leave direction out (the path's tangent)")


def _in_one_plane(seg: Segment, fns: SweepFunctions, index: int, samples: int) -> bool:
    """Whether every template of ``seg`` lies in the plane of its first one."""
    fr = compute_frames(seg, fns, seg.dense_parameters(samples), index)
    size = max(float(np.ptp(fr.P, axis=0).max()), float(fr.SX.max()), float(fr.SY.max()))
    return float(np.abs((fr.P - fr.P[0]) @ fr.EZ[0]).max()) <= COLLINEAR * size


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
        raise _zero_direction_error(seg, fns, float(u[int(np.argmax(nd < 1e-12))]))
    ez = rd / nd[:, None]
    if isinstance(fns.up, RotationMinimising):  # the default: rotation-minimising
        up = fns.up(seg, fns, s, ez, index, left)
    elif isinstance(fns.up, str):  # binormal frame, §5.3
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
    bad = cross <= COLLINEAR * np.maximum(nu, 1e-300)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise _up_error(seg, fns, index, float(s[i]), ez[i], nu[i] < 1e-300)
    ey = up - np.sum(up * ez, axis=1)[:, None] * ez
    ey /= np.linalg.norm(ey, axis=1)[:, None]
    ex = np.cross(ey, ez)
    sc = fns.scale(u)
    if np.any(sc <= 0):
        i = int(np.argmax(np.any(sc <= 0, axis=1)))
        raise spec_error(fns.doc, fns.scale.path,
                         f"scale must be positive, got {sc[i].tolist()} at u={u[i]:.6g}")
    return Frames(s, u, P, ex, ey, ez, sc[:, 0].copy(), sc[:, 1].copy())
