"""Whether a lattice folds its map: the sign of the Jacobian region by region.

A part of the model that passes through another (a fold) is summed where it
lands by the pushforward; a drag that far is rarely what was meant, so the
plan says it. The map's Jacobian at parameter ``a + t`` of each axis is a
tensor product of small filters (the cubic B-spline's weights and their
derivatives at t) over a region's 4^3 control points' positions; a
determinant that changes sign across the map is a fold (one negative
everywhere is a mirror image, not a fold).

Most regions cannot fold, and cost one look at their control points: a
B-spline's derivative along an axis is a convex combination of the control
points' differences along it, so with ``L`` the lattice's spacing the
Jacobian in a region is ``(I + E) diag(L)`` with ``|E[c, a]|`` at most the
region's largest ``|difference of component c along a| / L[a]`` (less L for
c = a); where every row of those bounds sums below 1, ``I + E`` is never
singular there. Only the other regions are sampled, T points per axis (2 to
8, :data:`SAMPLES` in all; past that, every few of them): a fold narrower
than ``1 / T`` of a region can pass unseen.
"""

from __future__ import annotations

import numpy as np

#: the samples taken in all, at most about this many
SAMPLES = 50_000
#: and at most this many per region and axis (1/8 of a region apart), at least 2
MOST_PER_REGION = 8


def _weights(t: float) -> tuple[np.ndarray, np.ndarray]:
    """The cubic B-spline's 4 weights at t in [0, 1), and their derivatives by t."""
    s = 1.0 - t
    value = np.array([s ** 3, 3 * t ** 3 - 6 * t ** 2 + 4, -3 * t ** 3 + 3 * t ** 2 + 3 * t + 1,
                      t ** 3]) / 6.0
    slope = np.array([-s ** 2, 3 * t ** 2 - 4 * t, -3 * t ** 2 + 2 * t + 1, t ** 2]) / 2.0
    return value, slope


def _window_max(a: np.ndarray, widths) -> np.ndarray:
    """The maximum over every window of ``widths`` (z, y, x) of ``a``'s first three axes."""
    for axis, width in enumerate(widths):
        n = a.shape[axis] - width + 1
        out = a.take(range(n), axis=axis)
        for k in range(1, width):
            np.maximum(out, a.take(range(k, k + n), axis=axis), out=out)
        a = out
    return a


def suspect_regions(positions: np.ndarray) -> np.ndarray:
    """The regions ``[Rz, Ry, Rx]`` (bool) the bound of the module notes cannot clear."""
    return _bound(positions)[0]


def _bound(positions: np.ndarray) -> tuple[np.ndarray, float]:
    """``(suspect regions, sign of the spacings' product)``: the sign the cleared ones have.

    One component and axis at a time (a 129^3 lattice's differences are 17 MB each).
    """
    p = np.asarray(positions, dtype=np.float64)
    rows = np.zeros(tuple(n - 3 for n in p.shape[:3]) + (3,))  # [region..., component]
    sign = 1.0
    for axis in range(3):  # (x y z; the array's axis 2 - axis)
        # (any spacing bounds: J = (I + E) diag(L) for any L of one sign, a mirror's too; the
        # mean, not the median, whose first call imports numpy.ma: 8 ms of a small warp)
        spacing = float(np.mean(np.diff(p[..., axis], axis=2 - axis)))
        if not abs(spacing) > 0:
            return np.ones(rows.shape[:3], bool), 1.0
        sign *= np.sign(spacing)
        widths = [4, 4, 4]
        widths[2 - axis] = 3  # (a region's differences along the axis: 3 of its 4 points)
        for component in range(3):
            diff = np.diff(p[..., component], axis=2 - axis)
            if component == axis:
                diff -= spacing
            np.abs(diff, out=diff)
            rows[..., component] += _window_max(diff, widths) / abs(spacing)
    return rows.max(axis=-1) >= 1.0, float(sign)


def jacobian_dets(positions: np.ndarray, regions=None, per_region: int = 2) -> np.ndarray:
    """The Jacobian's determinants at ``per_region`` points per axis of each region given.

    ``positions``: the control points' positions ``[Cz, Cy, Cx, 3]`` (x y z
    last, any linear units); ``regions``: (n, 3) region indices (z, y, x), all
    by default. Returns ``[n, z, y, x]``: point (k, j, i) of a region (a, b,
    c) is parameter ``(c + i / T, b + j / T, a + k / T)`` (x y z), T =
    ``per_region``.
    """
    p = np.asarray(positions, dtype=np.float64)
    if regions is None:
        regions = np.argwhere(np.ones(tuple(n - 3 for n in p.shape[:3]), bool))
    regions = np.asarray(regions, dtype=np.intp).reshape(-1, 3)
    r = np.arange(4)
    local = p[(regions[:, 0, None, None, None] + r[None, :, None, None]),
              (regions[:, 1, None, None, None] + r[None, None, :, None]),
              (regions[:, 2, None, None, None] + r[None, None, None, :])]  # [n, 4, 4, 4, 3]
    value, slope = (np.array(m) for m in zip(*(_weights(k / per_region)
                                               for k in range(per_region)), strict=True))
    j = []  # j[axis][..., component]: d component / d parameter of the axis
    for axis in range(3):
        mx, my, mz = (slope if a == axis else value for a in range(3))
        j.append(np.einsum("zk,yj,xi,nkjic->nzyxc", mz, my, mx, local, optimize=True))
    # (the cofactors on whole arrays: numpy's batched det of 3x3s was half the check's time)
    (a, b, c), (d, e, f), (g, h, i) = [[j[axis][..., k] for k in range(3)] for axis in range(3)]
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)


def fold_count(positions: np.ndarray) -> tuple[int, int]:
    """``(samples on the fold's side, samples)``; ``(0, 0)`` when no region can fold.

    Only the suspect regions are sampled (:func:`suspect_regions`; every few of
    them past about :data:`SAMPLES` points). The others' determinants have the
    sign of the lattice's spacings' product (the bound: positive, or a mirror's
    negative), so where one is left, a sample of the other sign is a fold;
    where every region is suspect, the minority sign is the fold's side (a
    mirror is negative everywhere: no fold, and a fold in a mirror folds back
    into the positive side). A determinant of zero, where a capture's tripled
    end points flatten the map, is neither sign.
    """
    suspect, cleared = _bound(positions)
    if not suspect.any():
        return 0, 0
    chosen = np.argwhere(suspect)
    per_region = int(np.clip(np.floor((SAMPLES / len(chosen)) ** (1 / 3)), 2, MOST_PER_REGION))
    most = max(1, SAMPLES // per_region ** 3)
    chosen = chosen[::-(-len(chosen) // most)]
    det = jacobian_dets(positions, chosen, per_region)
    tiny = 1e-9 * float(np.abs(det).max(initial=0.0))
    positive, negative = int(np.count_nonzero(det > tiny)), int(np.count_nonzero(det < -tiny))
    if not suspect.all():  # (the regions the bound cleared: the sign of the spacings' product)
        return (negative if cleared > 0 else positive), int(det.size)
    return (min(positive, negative) if positive and negative else 0), int(det.size)
