"""The paper's image-based "min-norm" distance: whole-array shift, increment and min.

Dinh & Carvalho (2004), §0.5: a pass shifts the whole image by one pixel,
adds one distance unit and keeps the per-pixel minimum with the unshifted
image; §0.5.1 combines these passes by *doubling*: with the field known up to
``w/2``, one shift by ``w/2`` with increment ``w/2`` extends it to ``w``, so
shifts by 1, 2, 4, ... complete a horizontal pass across ``w`` pixels in
``ceil(log2 w)`` passes (left and right shifts combined in one pass, as the
paper does with fragment shaders). Horizontal, vertical and depth passes
follow (§0.5.2); inside and outside are computed separately and combined into
a signed field.

Which metric this is
--------------------
After the passes along x the value at a voxel is the distance along its row
to the nearest shape voxel; the passes along y then take
``min_dy (row distance + |dy|)``, and those along z add ``|dz|`` the same way:
the result is the **taxicab (city-block, L1) distance** between voxel centres,
``|dx| + |dy| + |dz|``, exactly (every offset below ``2^k`` is a sum of distinct
powers of two, so the doubling reaches each with its exact cost). It equals
``scipy.ndimage.distance_transform_cdt(..., metric="taxicab")``; the tests check
that equality. The paper's formula (2), ``min_i |p1_i - p2_i|``, does not
describe what its passes compute; volwarp documents the passes' result.
With anisotropic spacing the increment of a shift by ``k`` voxels along an
axis is ``k`` times that axis' spacing: the spacing-weighted L1 distance.

volwarp shifts numpy arrays where the paper shifts textures; a 3-D pass is one
whole-volume shift (the paper needs one render per slice, §0.5.2), so a signed
field takes ``2 * (ceil(log2 nx) + ceil(log2 ny) + ceil(log2 nz))`` passes.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError


def passes_needed(n: int) -> int:
    """Doubling passes to span ``n`` samples along one axis: ``ceil(log2 n)``."""
    return max(int(np.ceil(np.log2(n))), 0) if n > 1 else 0


def shift_min(field: np.ndarray, axis: int, step: int, increment: float,
              scratch: np.ndarray | None = None) -> None:
    """One pass, in place: ``field = min(field, field shifted by ±step + increment)``.

    Both directions along ``axis`` in one pass (the paper's combined left/right
    scan). Values never increase, and every new value is reached by a path of
    real cost, so repeated passes stay upper bounds of the true distance.
    ``scratch`` (a flat array of at least ``field.size`` elements of its type)
    avoids allocating a temporary per pass.
    """
    n = field.shape[axis]
    if step >= n:
        return
    lo = [slice(None)] * field.ndim
    hi = [slice(None)] * field.ndim
    lo[axis] = slice(0, n - step)
    hi[axis] = slice(step, n)
    lo, hi = tuple(lo), tuple(hi)
    inc = field.dtype.type(increment)
    shape = field[lo].shape
    tmp = None if scratch is None else scratch[:int(np.prod(shape))].reshape(shape)
    t = np.add(field[lo], inc, out=tmp)
    np.minimum(field[hi], t, out=field[hi])
    t = np.add(field[hi], inc, out=tmp)
    np.minimum(field[lo], t, out=field[lo])


def doubling_steps(n: int) -> list[int]:
    """The shifts of one axis' doubling passes over ``n`` samples: 1, 2, 4, ... below ``n``."""
    steps = []
    step = 1
    while step < n:
        steps.append(step)
        step *= 2
    return steps


def axis_pass(field: np.ndarray, axis: int, h: float, scratch: np.ndarray | None = None) -> int:
    """All doubling passes along ``axis`` (spacing ``h``), in place; returns their count.

    Each pass only mixes samples along lines of ``axis`` (elementwise along
    them), so on any block that holds whole lines along ``axis`` it makes the
    same float32 operations, in the same order, as on the whole array: the
    passes (:class:`.passes.LineMetricDistance`) call it on blocks, in memory and out of core.
    """
    h = float(h)
    steps = doubling_steps(field.shape[axis])
    for step in steps:
        shift_min(field, axis, step, step * h, scratch)
    return len(steps)


def signed_pass_count(shape) -> int:
    """The passes :func:`minnorm_signed` makes on a grid of ``shape`` (outside and inside)."""
    return 2 * sum(len(doubling_steps(int(n))) for n in shape)


def propagate(field: np.ndarray, spacing_zyx, axes=(2, 1, 0)) -> int:
    """Doubling shift-increment-min passes along ``axes`` (x, y, z), in place.

    Returns the number of passes made. On a field that is 0 on the sites and
    +inf elsewhere, the result is the spacing-weighted taxicab distance to the
    nearest site; on any field, ``min over q (field(q) + L1(p, q))``.
    """
    count = 0
    scratch = np.empty(field.size, field.dtype)
    for axis in axes:
        count += axis_pass(field, axis, float(spacing_zyx[axis]), scratch)
    return count


# -- chessboard (L-infinity) by per-axis line passes -------------------------------------


def chessboard_axis_pass(field: np.ndarray, axis: int) -> None:
    """One L-infinity line pass along ``axis``, in place: ``g(i) = min_j max(|i - j|, f(j))``.

    ``field``: float32, 0 on the sites, +inf elsewhere (or the result of
    passes along other axes). After passes along x, y and z in turn it is the
    chessboard distance ``min over sites max(|dx|, |dy|, |dz|)`` in voxel
    steps, what ``scipy.ndimage.distance_transform_cdt(metric="chessboard")``
    gives (``tests/test_distance_metrics_chunked.py`` checks the equality).
    Values must be integers (or inf), exact in float32. A serial numba kernel
    (``nogil``), for block tasks, linear in the line's length (Meijster et al.
    2000's chessboard lower envelope); it only reads and writes lines of ``axis``.
    """
    if field.dtype != np.float32:
        raise VolwarpError(f"the chessboard pass needs a float32 field, got {field.dtype}")
    from ._line_kernels import chessboard_lines

    chessboard_lines(np.moveaxis(field, axis, -1))




def taxicab_axis_pass(field: np.ndarray, axis: int) -> None:
    """One taxicab line pass along ``axis``, in place: ``g(i) = min_j |i - j| + f(j)``.

    In voxel steps (the caller scales by the isotropic spacing); after passes
    along x, y and z, scipy's taxicab ``distance_transform_cdt``. The values
    the doubling passes of :func:`axis_pass` give with unit spacing (integer
    sums, exact in float32), in one forward and one backward sweep of each
    line: linear where the doubling passes are ``n log n``.
    """
    if field.dtype != np.float32:
        raise VolwarpError(f"the taxicab pass needs a float32 field, got {field.dtype}")
    from ._line_kernels import taxicab_lines

    taxicab_lines(np.moveaxis(field, axis, -1))


def line_metric_pass(metric: str, field: np.ndarray, axis: int, h: float,
                     scratch: np.ndarray | None = None) -> int:
    """One axis of the per-line passes of ``metric`` (minnorm, taxicab, chessboard), in place.

    ``minnorm``: :func:`axis_pass` with spacing ``h`` (the paper's doubling
    passes); ``taxicab``: :func:`taxicab_axis_pass` (integer voxel steps; the
    caller scales by the spacing); ``chessboard``: :func:`chessboard_axis_pass`.
    Returns the doubling passes made.
    """
    if metric == "chessboard":
        chessboard_axis_pass(field, axis)
        return 0
    if metric == "taxicab":
        taxicab_axis_pass(field, axis)
        return 0
    return axis_pass(field, axis, h, scratch)


def minnorm_signed(mask: np.ndarray, spacing_zyx=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, int]:
    """Signed min-norm (taxicab) field between voxel centres: negative inside.

    Outside voxels get their distance to the nearest inside voxel, inside
    voxels minus their distance to the nearest outside voxel, so the result
    equals ``cdt(~mask) - cdt(mask)`` with ``distance_transform_cdt(metric='taxicab')``
    for unit spacing. Returns the field and the total number of passes.
    """
    from .passes import MaskSource, field_in_memory

    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 3:
        raise VolwarpError(f"min-norm distance needs a 3-D mask, got shape {mask.shape}")
    field = field_in_memory(MaskSource(mask, 0.5, "above", check=False), spacing_zyx,
                            metric="minnorm")
    return field, signed_pass_count(mask.shape)
