"""Whether a lattice folds its map: the sign of the Jacobian across the lattice.

A part of the model that passes through another (a fold) is summed where it
lands by the pushforward; a drag that far is rarely what was meant, so the
plan says it. The map's Jacobian at parameter ``a + t`` of each axis is a
tensor product of small filters (the cubic B-spline's weights and their
derivatives at t) over the control points' positions, evaluated here at T
points per region and axis; a determinant that changes sign across the map
is a fold (one negative everywhere is a mirror image, not a fold).

Most lattices cannot fold, and cost one pass over their control points: a
B-spline's derivative along an axis is a convex combination of the control
points' differences along it, so with ``L`` the lattice's spacing the
Jacobian is ``L (I + E)`` with ``|E[c, a]|`` at most the largest
``|difference of offset c along a| / L[a]``; where every row of those bounds
sums below 1, ``I + E`` is never singular. Sampled: a fold narrower than
``1 / T`` of a region can pass unseen.
"""

from __future__ import annotations

import numpy as np

#: the samples on the lattice's axes, in all, at most about this many
SAMPLES = 50_000
#: and at most this many per region and axis (1/8 of a region apart)
MOST_PER_REGION = 8


def _weights(t: float) -> tuple[np.ndarray, np.ndarray]:
    """The cubic B-spline's 4 weights at t in [0, 1), and their derivatives by t."""
    s = 1.0 - t
    value = np.array([s ** 3, 3 * t ** 3 - 6 * t ** 2 + 4, -3 * t ** 3 + 3 * t ** 2 + 3 * t + 1,
                      t ** 3]) / 6.0
    slope = np.array([-s ** 2, 3 * t ** 2 - 4 * t, -3 * t ** 2 + 2 * t + 1, t ** 2]) / 2.0
    return value, slope


def _axis_matrices(controls: int, per_region: int) -> tuple[np.ndarray, np.ndarray]:
    """(values, slopes): (regions * per_region, controls) matrices of one axis's samples."""
    regions = controls - 3
    value = np.zeros((regions * per_region, controls))
    slope = np.zeros_like(value)
    for k in range(per_region):
        v, d = _weights(k / per_region)
        for a in range(regions):
            value[a * per_region + k, a:a + 4] = v
            slope[a * per_region + k, a:a + 4] = d
    return value, slope


def cannot_fold(positions: np.ndarray) -> bool:
    """Whether the bound of the module notes rules a fold out (one pass, no sampling)."""
    p = np.asarray(positions, dtype=np.float64)
    bound = np.zeros((3, 3))  # [component, axis]
    for axis in range(3):  # (array axes z y x: x y z is 2 - axis)
        diff = np.diff(p, axis=2 - axis)
        spacing = np.abs(np.median(diff[..., axis]))
        if not spacing > 0:
            return False
        change = np.abs(diff).max(axis=(0, 1, 2)) / spacing  # per component
        change[axis] = np.abs(diff[..., axis] - spacing).max() / spacing
        bound[:, axis] = change
    return bool(bound.sum(axis=1).max() < 1.0)


def jacobian_dets(positions: np.ndarray, per_region: int) -> np.ndarray:
    """The map's Jacobian determinants at ``per_region`` points of each region and axis.

    ``positions``: the control points' positions ``[Cz, Cy, Cx, 3]`` (x y z
    last, any linear units). Sample ``a * per_region + k`` of an axis is
    parameter ``a + k / per_region``; the result is ``[z, y, x]``.
    """
    p = np.asarray(positions, dtype=np.float64)
    mats = [_axis_matrices(n, per_region) for n in p.shape[2::-1]]  # x y z
    columns = []
    for axis in range(3):
        mx, my, mz = (mats[a][1 if a == axis else 0] for a in range(3))
        columns.append(np.einsum("zk,yj,xi,kjic->zyxc", mz, my, mx, p, optimize=True))
    return np.linalg.det(np.stack(columns, axis=-1))


def fold_count(positions: np.ndarray) -> tuple[int, int]:
    """``(samples on the fold's side, samples)``; ``(0, 0)`` when the map cannot fold.

    The fold's side is the minority sign (a mirror with a fold folds back
    into the positive side), 0 when one sign has no sample (a determinant of
    zero, where a capture's tripled end points flatten the map, is neither);
    at most about :data:`SAMPLES` samples.
    """
    if cannot_fold(positions):
        return 0, 0
    regions = max(np.asarray(positions).shape[:3]) - 3
    per_region = int(max(1, min(MOST_PER_REGION, round(SAMPLES ** (1 / 3) / max(regions, 1)))))
    det = jacobian_dets(positions, per_region)
    # (a zero is neither side: a capture's tripled end points flatten the map there)
    tiny = 1e-9 * float(np.abs(det).max(initial=0.0))
    positive, negative = int(np.count_nonzero(det > tiny)), int(np.count_nonzero(det < -tiny))
    return (min(positive, negative) if positive and negative else 0), int(det.size)
