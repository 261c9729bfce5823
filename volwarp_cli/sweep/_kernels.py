"""numba kernels of the sweep voxeliser (see :mod:`.voxelize` for the method).

Imported lazily: numba costs about 0.3 s to import and the kernels are cached
on disk (``cache=True``; set ``NUMBA_CACHE_DIR`` when the package is read-only).

Plain ``nogil`` kernels over a range of z slices or of polynomials: the
callers run ranges over volwarp's threads (:func:`~volwarp_cli.parallel.run_blocks`),
a block task runs one range in its own thread. Every slice and polynomial is
computed on its own, so the result does not depend on the split. (They were
``prange`` kernels with serial twins: those compiled several times slower,
and numba's workqueue layer aborts when two threads run ``prange`` at once.)
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

UNION, INTERSECTION, DIFFERENCE, BLEND, SUM, FIRST = range(6)
BLEND_FLOOR = 1e-6


@njit(cache=True, inline="always")
def _bilinear(tex, off, h, w, n, x, y, sl):
    cx = x * w - 0.5
    cy = (1.0 - y) * h - 0.5
    if cx < 0.0:
        cx = 0.0
    elif cx > w - 1:
        cx = w - 1.0
    if cy < 0.0:
        cy = 0.0
    elif cy > h - 1:
        cy = h - 1.0
    x0 = int(cx)
    y0 = int(cy)
    fx = cx - x0
    fy = cy - y0
    x1 = x0 + 1 if x0 + 1 < w else x0
    y1 = y0 + 1 if y0 + 1 < h else y0
    z0 = 0
    fz = 0.0
    if n > 1:
        cz = sl
        if cz < 0.0:
            cz = 0.0
        elif cz > n - 1:
            cz = n - 1.0
        z0 = int(cz)
        fz = cz - z0
    base = off + z0 * h * w
    v = ((tex[base + y0 * w + x0] * (1 - fx) + tex[base + y0 * w + x1] * fx) * (1 - fy)
         + (tex[base + y1 * w + x0] * (1 - fx) + tex[base + y1 * w + x1] * fx) * fy)
    if fz > 0.0:
        base = base + h * w
        v2 = ((tex[base + y0 * w + x0] * (1 - fx) + tex[base + y0 * w + x1] * fx) * (1 - fy)
              + (tex[base + y1 * w + x0] * (1 - fx) + tex[base + y1 * w + x1] * fx) * fy)
        v = v * (1 - fz) + v2 * fz
    return v


@njit(cache=True, inline="always")
def _half_line(c, g, strict, positive, lo, hi):
    """Clip [lo, hi] (index units) to where c + g*i >= 0 (positive) or <= 0, widened by 1."""
    if positive:
        c = -c
        g = -g
    # want c + g*i <= 0
    if g > 1e-300:
        r = -c / g
        if r + 1.0 < hi:
            hi = r + 1.0
    elif g < -1e-300:
        r = -c / g
        if r - 1.0 > lo:
            lo = r - 1.0
    else:
        if c > 0.0 or (strict and c >= 0.0):
            hi = lo - 1.0
    return lo, hi


@njit(cache=True, nogil=True)
def sweep_voxelize(P, EX, EY, EZ, SX, SY, SL, sub_a, sub_b, closed, boxes, origin, spacing,
                   tex, off, th, tw, tn, ops, opac, tol, acc, wsum, covered, zlo, zhi,
                   oz, oy, ox):
    """Voxelise the sub-segments into the accumulators, z slices ``[zlo, zhi)``.

    Indices (``boxes``, ``zlo``, ``zhi``, the loops) are the whole grid's, so a
    voxel's world point is computed from its grid index alone; the arrays
    ``acc``, ``wsum`` and ``covered`` hold the block whose first voxel is
    ``(oz, oy, ox)`` (all 0 for the whole grid).
    """
    F = ops.shape[0]
    S = sub_a.shape[0]
    has_blend = False
    for f in range(F):
        if ops[f] == BLEND:
            has_blend = True
    for zz in range(zhi - zlo):
        z = zlo + zz
        zl = z - oz
        vals = np.empty(F)
        wz = origin[2] + spacing[2] * z
        for s in range(S):
            if z < boxes[s, 4] or z > boxes[s, 5]:
                continue
            a = sub_a[s]
            b = sub_b[s]
            # segment ends: accept points within tol of the end planes (rounding at seams)
            last = (closed[s] & 2) != 0
            ta = tol if (closed[s] & 1) != 0 else 0.0
            tb = tol if last else 0.0
            for y in range(boxes[s, 2], boxes[s, 3] + 1):
                yl = y - oy
                wy = origin[1] + spacing[1] * y
                # plane distances as functions of the x index: c + g * i
                dax = origin[0] - P[a, 0]
                day = wy - P[a, 1]
                daz = wz - P[a, 2]
                dbx = origin[0] - P[b, 0]
                dby = wy - P[b, 1]
                dbz = wz - P[b, 2]
                cA = dax * EZ[a, 0] + day * EZ[a, 1] + daz * EZ[a, 2]
                gA = spacing[0] * EZ[a, 0]
                cB = dbx * EZ[b, 0] + dby * EZ[b, 1] + dbz * EZ[b, 2]
                gB = spacing[0] * EZ[b, 0]
                # local template coordinates on A and B, also linear in i
                cxa = 0.5 + (dax * EX[a, 0] + day * EX[a, 1] + daz * EX[a, 2]) / SX[a]
                gxa = spacing[0] * EX[a, 0] / SX[a]
                cya = 0.5 + (dax * EY[a, 0] + day * EY[a, 1] + daz * EY[a, 2]) / SY[a]
                gya = spacing[0] * EY[a, 0] / SY[a]
                cxb = 0.5 + (dbx * EX[b, 0] + dby * EX[b, 1] + dbz * EX[b, 2]) / SX[b]
                gxb = spacing[0] * EX[b, 0] / SX[b]
                cyb = 0.5 + (dbx * EY[b, 0] + dby * EY[b, 1] + dbz * EY[b, 2]) / SY[b]
                gyb = spacing[0] * EY[b, 0] / SY[b]
                for region in range(2):
                    lo = float(boxes[s, 0])
                    hi = float(boxes[s, 1])
                    if region == 0:  # sA >= 0 > sB
                        lo, hi = _half_line(cA + ta, gA, False, True, lo, hi)
                        lo, hi = _half_line(cB - tb, gB, not last, False, lo, hi)
                    else:  # sA <= 0 < sB
                        lo, hi = _half_line(cA - ta, gA, False, False, lo, hi)
                        lo, hi = _half_line(cB + tb, gB, not last, True, lo, hi)
                    if hi < lo:
                        continue
                    i0 = int(math.ceil(lo))
                    i1 = int(math.floor(hi))
                    if i0 < boxes[s, 0]:
                        i0 = boxes[s, 0]
                    if i1 > boxes[s, 1]:
                        i1 = boxes[s, 1]
                    for x in range(i0, i1 + 1):
                        sA = cA + gA * x
                        sB = cB + gB * x
                        if region == 0:
                            if not (sA >= -ta and (sB < 0.0 or (last and sB <= tb))):
                                continue
                        else:
                            if not (sA <= ta and sB > -tb):
                                continue
                        den = sA - sB
                        if den == 0.0:
                            continue
                        t = sA / den
                        xa = cxa + gxa * x
                        ya = cya + gya * x
                        xb = cxb + gxb * x
                        yb = cyb + gyb * x
                        xt = (1.0 - t) * xa + t * xb
                        yt = (1.0 - t) * ya + t * yb
                        if xt < 0.0 or xt > 1.0 or yt < 0.0 or yt > 1.0:
                            continue
                        for f in range(F):
                            va = _bilinear(tex, off[f], th[f], tw[f], tn[f], xa, ya, SL[a, f])
                            vb = _bilinear(tex, off[f], th[f], tw[f], tn[f], xb, yb, SL[b, f])
                            vals[f] = (1.0 - t) * va + t * vb
                        w = 1.0
                        if opac >= 0:
                            w = vals[opac]
                            if w < 0.0:
                                w = 0.0
                            w += BLEND_FLOOR
                        xl = x - ox
                        cov = covered[zl, yl, xl] != 0
                        for f in range(F):
                            v = vals[f]
                            op = ops[f]
                            if op == BLEND:
                                acc[f, zl, yl, xl] += w * v
                            elif not cov:
                                acc[f, zl, yl, xl] = v
                            elif op == UNION:
                                if v > acc[f, zl, yl, xl]:
                                    acc[f, zl, yl, xl] = v
                            elif op == INTERSECTION:
                                if v < acc[f, zl, yl, xl]:
                                    acc[f, zl, yl, xl] = v
                            elif op == DIFFERENCE:
                                d = acc[f, zl, yl, xl] - v
                                acc[f, zl, yl, xl] = d if d > 0.0 else 0.0
                            elif op == SUM:
                                d = acc[f, zl, yl, xl] + v
                                if d > 1.0:
                                    d = 1.0
                                elif d < 0.0:
                                    d = 0.0
                                acc[f, zl, yl, xl] = d
                        if has_blend:
                            wsum[zl, yl, xl] += w
                        covered[zl, yl, xl] = 1



@njit(cache=True)
def _horner(c, deg, x):
    v = c[deg]
    for j in range(deg - 1, -1, -1):
        v = v * x + c[j]
    return v


@njit(cache=True, nogil=True)
def real_roots_unit(coef, out):
    """Real roots in [0, 1] of many polynomials (ascending ``coef[N, D + 1]``).

    Root isolation by the derivative chain: the roots of the k-th derivative
    split [0, 1] into intervals on which the (k - 1)-th derivative is monotone,
    so each holds at most one of its roots, found by safeguarded Newton
    (bisection whenever a step leaves the bracket). ``out[N, D]`` receives
    the roots in increasing order, NaN-padded.
    """
    n, m = coef.shape
    D = m - 1
    for v in range(n):
        c = np.empty(m)
        dc = np.empty(m)
        crit = np.empty(m + 1)
        roots = np.empty(m + 1)
        ncrit = 0
        for k in range(D - 1, -1, -1):
            deg = D - k
            # coefficients of the k-th derivative (degree deg) and of its derivative
            for j in range(deg + 1):
                f = 1.0
                for q in range(j + 1, j + k + 1):
                    f *= q
                c[j] = coef[v, j + k] * f
            for j in range(deg):
                dc[j] = c[j + 1] * (j + 1)
            nroots = 0
            a = 0.0
            fa = _horner(c, deg, a)
            for it in range(ncrit + 1):
                b = crit[it] if it < ncrit else 1.0
                fb = _horner(c, deg, b)
                if fa == 0.0:
                    if nroots == 0 or a - roots[nroots - 1] > 1e-13:
                        roots[nroots] = a
                        nroots += 1
                elif fa * fb < 0.0:
                    lo = a
                    hi = b
                    flo = fa
                    x = 0.5 * (lo + hi)
                    for _ in range(100):
                        fx = _horner(c, deg, x)
                        if fx == 0.0:
                            break
                        if (fx < 0.0) == (flo < 0.0):
                            lo = x
                            flo = fx
                        else:
                            hi = x
                        d = _horner(dc, deg - 1, x) if deg > 0 else 0.0
                        nx = x - fx / d if d != 0.0 else 0.5 * (lo + hi)
                        if not (nx > lo and nx < hi):
                            nx = 0.5 * (lo + hi)
                        if abs(nx - x) <= 1e-15 * (1.0 + abs(x)) or hi - lo <= 1e-15:
                            x = nx
                            break
                        x = nx
                    roots[nroots] = x
                    nroots += 1
                a = b
                fa = fb
            if fa == 0.0 and (nroots == 0 or a - roots[nroots - 1] > 1e-13):
                roots[nroots] = a
                nroots += 1
            for j in range(nroots):
                crit[j] = roots[j]
            ncrit = nroots
        for j in range(D):
            out[v, j] = crit[j] if j < ncrit else np.nan

