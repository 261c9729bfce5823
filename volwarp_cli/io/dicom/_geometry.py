"""Stack geometry: slice order, spacing, duplicates, gaps and gantry tilt.

:func:`plan_stack` turns a candidate's frames into a :class:`Plan`: the input
slices in position order, the output grid (origin, direction, spacing), and
what resampling (in-plane shifts for a tilt, interpolation between slices for
an irregular stack) turns the one into the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ...errors import FormatError
from ...geometry import snap_to_samples
from ...progress import log


@dataclass
class Plan:
    frames: list              # input slices in position order (duplicates removed)
    origin: np.ndarray
    direction: np.ndarray     # columns: row cosine, column cosine, stack direction
    spacing: np.ndarray       # (x, y, z)
    n_out: int                # output slices
    shifts: np.ndarray | None = None   # (n_in, 2) in-plane shift [dy, dx] of each input slice
    planes: list | None = None         # per output slice (k, w): (1-w) * in[k] + w * in[k+1]

    @property
    def resampled(self) -> bool:
        return self.shifts is not None or self.planes is not None


def _labels(frames, k) -> str:
    return f"{frames[k].label} and {frames[k + 1].label}"


def plan_stack(frames, where: str, *, irregular: str = "error", duplicates: str = "error",
               keep_shear: bool = False) -> Plan:
    """The output grid of a stack of frames (see the package docstring for the rules)."""
    f0 = frames[0]
    row, col = f0.row, f0.col
    normal = np.cross(row, col)
    normal /= np.linalg.norm(normal)
    sx, sy = f0.pixel_spacing
    frames = sorted(frames, key=lambda f: (f.order, f.frame))  # file order
    pos = np.array([f.position for f in frames], dtype=np.float64)
    d = pos @ normal
    idx = np.argsort(d, kind="stable")
    frames = [frames[i] for i in idx]
    pos, d = pos[idx], d[idx]
    frames, pos, d = _dedupe(frames, pos, d, where, duplicates)
    n = len(frames)
    direction = np.column_stack([row, col, normal])
    if n == 1:
        return Plan(frames, pos[0], direction, np.array([sx, sy, f0.single_spacing]), 1)
    if f0.synthetic:
        return Plan(frames, pos[0], direction, np.array([sx, sy, d[1] - d[0]]), n)
    gaps = np.diff(d)
    nominal = float(np.median(gaps))
    # (0.01 mm, a tenth of the spacing at most: at micro-CT's 0.01 mm it was the whole
    # spacing, and a missing slice passed, the stack placed on an even grid)
    tol = min(max(1e-3 * nominal, 0.01), 0.1 * nominal)
    rel = (d - d[0])[:, None]
    inplane = inplane_offsets(pos, normal)
    extent = float(d[-1] - d[0])
    shear = inplane[-1] / extent      # in-plane movement per mm along the normal
    off = np.linalg.norm(inplane - rel * shear[None, :], axis=1)
    if off.max() > tol:
        k = int(np.argmax(off))
        raise FormatError(f"{where}: slice positions do not lie on a line: {frames[k].label} is "
                          f"{off[k]:.4g} mm off the line through the first and last slice")
    tilted = float(np.linalg.norm(inplane[-1])) > tol
    if not tilted:
        shear = np.zeros(3)
    bad = np.abs(gaps - nominal) > tol
    planes = None
    if bad.any():
        if irregular != "resample":
            raise FormatError(_gap_message(where, frames, gaps, nominal, tol, bad))
        step = float(gaps.min())
        steps = extent / step
        # (the extent a whole number of the smallest gap within the gaps' tolerance is that
        # number: 1/3 mm slices at positions of six decimals, one missing, spanned 6.00001
        # gaps, and the grid had 8 slices 0.286 mm apart, none of them an input slice)
        whole = round(steps)
        n_out = (whole if abs(steps - whole) * step <= tol else int(math.ceil(steps))) + 1
        step = extent / (n_out - 1)
        targets = d[0] + step * np.arange(n_out)
        ks = np.clip(np.searchsorted(d, targets, side="right") - 1, 0, n - 2)
        # (a target a rounding off an input slice is that slice: weighed 1e-15 against the
        # next one, a tilted slice's out-of-field rim, NaN, took a row of the field with it)
        ws = snap_to_samples(np.clip((targets - d[ks]) / (d[ks + 1] - d[ks]), 0.0, 1.0))
        planes = list(zip(ks.tolist(), ws.tolist(), strict=True))
        log.warning("warning: %s: irregular slice spacing (gaps %.4g..%.4g mm): resampled linearly onto "
                    "%d slices %.4g mm apart along the slice normal", where, gaps.min(),
                    gaps.max(), n_out, step)
    else:
        n_out = n
        step = extent / (n - 1)
    shifts = None
    if tilted:
        stack = normal + shear
        angle = math.degrees(math.atan(float(np.linalg.norm(shear))))
        if keep_shear:
            length = float(np.linalg.norm(stack))
            direction = np.column_stack([row, col, stack / length])
            if planes is None:  # exactly ITK's: (last - first) / (n - 1)
                vec = pos[-1] - pos[0]
                return Plan(frames, pos[0], np.column_stack([row, col, vec / np.linalg.norm(vec)]),
                            np.array([sx, sy, np.linalg.norm(vec) / (n - 1)]), n)
            return Plan(frames, pos[0], direction, np.array([sx, sy, step * length]), n_out,
                        planes=planes)
        q = inplane
        # (positions to six decimals put a shift of 3 pixels at 3.0000004: the slice's edge
        # column then lay a hair outside the field and took the fill, exit 0)
        shifts = snap_to_samples(np.column_stack([q @ col / sy, q @ row / sx]))
        log.warning("warning: %s: gantry tilt of %.3g degrees: resampled onto an orthogonal grid "
                    "(keep the sheared geometry with --keep-shear)", where, angle)
    return Plan(frames, pos[0], direction, np.array([sx, sy, step]), n_out, shifts=shifts,
                planes=planes)


def inplane_offsets(pos: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Each position's offset from the first, within the slice plane: 0 unless tilted.

    ``pos`` (n, 3) positions, ``normal`` the unit slice normal.
    """
    step = pos - pos[0]
    return step - (step @ normal)[:, None] * normal[None, :]


def _dedupe(frames, pos, d, where, duplicates):
    if len(frames) < 2:
        return frames, pos, d
    gaps = np.diff(d)
    positive = gaps[gaps > 1e-6]
    dup_tol = min(0.01, 0.1 * float(np.median(positive))) if len(positive) else 0.01
    same = gaps <= dup_tol
    if not same.any():
        return frames, pos, d
    if duplicates not in ("first", "last"):
        k = int(np.argmax(same))
        count = int(same.sum())
        raise FormatError(f"{where}: {count + 1 if count == 1 else count} images share slice "
                          f"positions, e.g. {_labels(frames, k)} both at {d[k]:.4g} mm along the "
                          "slice normal (keep one with --duplicates first|last)")
    keep = []
    k = 0
    while k < len(frames):
        j = k
        while j + 1 < len(frames) and d[j + 1] - d[j] <= dup_tol:
            j += 1
        # by file order, not by position: duplicates a few micrometres apart sort by position
        group = sorted(range(k, j + 1), key=lambda i: (frames[i].order, frames[i].frame))
        keep.append(group[0] if duplicates == "first" else group[-1])
        k = j + 1
    log.info("%s: %d duplicate image(s) dropped (--duplicates %s)", where,
             len(frames) - len(keep), duplicates)
    return [frames[i] for i in keep], pos[keep], d[keep]


def _gap_message(where, frames, gaps, nominal, tol, bad) -> str:
    ks = np.flatnonzero(bad)
    k = int(ks[0])
    g = float(gaps[k])
    more = f" (and {len(ks) - 1} more irregular gap(s))" if len(ks) > 1 else ""
    m = round(g / nominal)
    if m >= 2 and abs(g - m * nominal) <= tol * m:
        return (f"{where}: missing slice(s): the gap between {_labels(frames, k)} (slices {k} "
                f"and {k + 1} in position order) is {g:.4g} mm, {m} times the spacing "
                f"{nominal:.4g} mm ({m - 1} slice(s) missing){more}; read anyway with "
                "--irregular resample")
    return (f"{where}: irregular slice spacing: the gap between {_labels(frames, k)} (slices {k} "
            f"and {k + 1} in position order) is {g:.4g} mm, elsewhere {nominal:.4g} mm{more}; "
            "read anyway with --irregular resample")


def resample(plan: Plan, data: np.ndarray, labels: bool = False) -> np.ndarray:
    """Apply the plan's tilt shifts and slice interpolation to ``data`` (input slices).

    A voxel is interpolated from samples of the field only, or is the fill (the
    input's minimum): the shifts mark what lies outside the field NaN, the
    interpolation between slices carries the NaN on, and only then does it become
    the fill, so that no voxel at the field's rim blends the fill with data.

    ``labels``: ``data`` is a label map: each voxel takes its nearest sample
    (between two slices, the nearer; half way, the lower), in ``data``'s type,
    so no id is invented (linear weights blended ids 7 and 55 into 27.5).
    """
    from scipy import ndimage

    if labels:
        return _resample_nearest(plan, data)
    fill = None
    if plan.shifts is not None:
        fill = float(data.min())
        out = np.empty(data.shape, dtype=np.float32)
        for k in range(data.shape[0]):
            ndimage.shift(data[k].astype(np.float32, copy=False), plan.shifts[k], output=out[k],
                          order=1, mode="constant", cval=np.nan, prefilter=False)
        data = out
    if plan.planes is not None:
        out = np.empty((plan.n_out,) + data.shape[1:], dtype=np.float32)
        for m, (k, w) in enumerate(plan.planes):
            if w == 0:
                out[m] = data[k]
            elif w == 1:
                out[m] = data[k + 1]
            else:
                np.multiply(data[k], 1.0 - w, out=out[m], casting="unsafe")
                out[m] += np.float32(w) * data[k + 1]
        data = out
    if data.dtype != np.float32:
        data = data.astype(np.float32)
    if fill is not None:
        for plane in data:  # (a slice at a time: no mask of the whole volume)
            np.copyto(plane, np.float32(fill), where=np.isnan(plane))
    return data


def _resample_nearest(plan: Plan, data: np.ndarray) -> np.ndarray:
    from scipy import ndimage

    if plan.shifts is not None:
        fill = data.min()
        out = np.empty_like(data)
        for k in range(data.shape[0]):
            ndimage.shift(data[k], plan.shifts[k], output=out[k], order=0, mode="constant",
                          cval=fill, prefilter=False)
        data = out
    if plan.planes is not None:
        out = np.empty((plan.n_out,) + data.shape[1:], dtype=data.dtype)
        for m, (k, w) in enumerate(plan.planes):
            out[m] = data[k] if w <= 0.5 else data[k + 1]
        data = out
    return data
