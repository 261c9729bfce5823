"""Numba kernel of a block's sample statistics, in one pass and without temporaries.

The numpy form (min, max, ``a == iso``, ``a[a < iso].max()``) made four passes
and two full-size temporaries per block, and was the slowest step of a mesh
by blocks after flying edges itself. The loop body has no branch, so that
it vectorises. The comparisons are made in the type numpy would use (the
caller passes ``iso`` already converted to it), so the result is numpy's.
Imported lazily by :class:`.chunked.Stats`.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _row_stats(a, iso, lowest, acc_lo, acc_hi, acc_below):
    """Fold the flat row ``a`` into the running ``(lo, hi, below)``; ``(nan, hit, has_below)``."""
    lo, hi, below = acc_lo, acc_hi, acc_below
    nan = False
    hit = False
    has_below = False
    for n in range(a.size):
        x = a[n]
        nan |= x != x
        lo = min(lo, x)
        hi = max(hi, x)
        hit |= x == iso
        is_below = x < iso
        has_below |= is_below
        below = max(below, x if is_below else lowest)
    return lo, hi, below, nan, hit, has_below


@njit(cache=True, nogil=True)
def block_stats(a, iso, lowest, highest):
    """``(lo, hi, nan, hit, has_below, below_max)`` of a 3-D array (by rows of x).

    ``lo``/``hi`` are meaningless when ``nan``; ``below_max`` (the largest
    sample below ``iso``) only when ``has_below``; ``hit``: some sample
    equals ``iso``. ``lowest``/``highest``: the type's extremes (-inf/inf).
    """
    lo, hi, below = highest, lowest, lowest
    nan = hit = has_below = False
    nz, ny, _ = a.shape
    for k in range(nz):
        for j in range(ny):
            lo, hi, below, n_, h_, b_ = _row_stats(a[k, j], iso, lowest, lo, hi, below)
            nan |= n_
            hit |= h_
            has_below |= b_
    return lo, hi, nan, hit, has_below, below


def stats_of(a: np.ndarray, iso: float | None):
    """:func:`block_stats` of ``a``, with ``iso`` as numpy would compare it with ``a``.

    ``iso`` None: only the range (``hit``/``has_below`` False).
    """
    a = np.asarray(a)
    if a.ndim != 3:
        a = a.reshape((1, 1, -1))
    if a.dtype.kind == "b":
        a = a.view(np.uint8)
    if a.dtype.kind == "f":
        lowest, highest = a.dtype.type(-np.inf), a.dtype.type(np.inf)
    else:
        info = np.iinfo(a.dtype)
        lowest, highest = a.dtype.type(info.min), a.dtype.type(info.max)
    if iso is None:
        lo, hi, nan, _, _, below = block_stats(a, np.float64(np.nan), lowest, highest)
        return lo, hi, nan, False, False, below
    return block_stats(a, np.result_type(a.dtype, iso).type(iso), lowest, highest)
