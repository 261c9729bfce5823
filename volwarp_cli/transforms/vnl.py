"""ITK's 3x3 matrix inverse, bit for bit: what its images map world points to indices with.

ITK (5.4: SimpleITK 2.x, ANTs) inverts an image's index-to-world matrix
``direction @ diag(spacing)`` with ``vnl_matrix_inverse``: the pseudo-inverse
``V diag(1/w) U^T`` of LINPACK's ``dsvdc`` (VXL's v3p netlib translation).
Its result differs from the exact inverse by a few ULPs, and a point that
lies on an edge of a transform's grid in exact arithmetic (a B-spline placed
as ANTs places it has the fixed image's first voxels at grid index 1, the
edge of its valid region) is inside or outside by those ULPs. The same
operations in the same order give the same doubles (IEEE arithmetic, no
fused multiply-add: ITK's x86-64 builds have none).
"""

from __future__ import annotations

import math

import numpy as np


def _sign(a: float, b: float) -> float:
    """f2c's ``d_sign``: ``|a|`` with the sign of ``b`` (``b >= 0``: positive)."""
    x = a if a >= 0 else -a
    return x if b >= 0 else -x


def _nrm2(v: list) -> float:
    """The reference BLAS ``dnrm2`` (scaled sum of squares)."""
    if len(v) == 1:
        return abs(v[0])
    scale, ssq = 0.0, 1.0
    for xi in v:
        if xi != 0.0:
            a = abs(xi)
            if scale < a:
                r = scale / a
                ssq = ssq * (r * r) + 1.0
                scale = a
            else:
                r = a / scale
                ssq += r * r
    return scale * math.sqrt(ssq)


def _dot(a: list, b: list) -> float:
    t = 0.0
    for x, y in zip(a, b, strict=True):
        t += x * y
    return t


def _rotg(da: float, db: float) -> tuple[float, float, float, float]:
    """BLAS ``drotg``: ``(r, z, c, s)``."""
    roe = da if abs(da) > abs(db) else db
    scale = abs(da) + abs(db)
    if scale == 0.0:
        return 0.0, 0.0, 1.0, 0.0
    a, b = da / scale, db / scale
    r = scale * math.sqrt(a * a + b * b)
    r = _sign(1.0, roe) * r
    c, s = da / r, db / r
    z = 1.0
    if abs(da) > abs(db):
        z = s
    if abs(db) >= abs(da) and c != 0.0:
        z = 1.0 / c
    return r, z, c, s


def _rot(x: list, y: list, c: float, s: float) -> None:
    for i in range(len(x)):
        t = c * x[i] + s * y[i]
        y[i] = c * y[i] - s * x[i]
        x[i] = t


def _svdc(m: np.ndarray):
    """LINPACK ``dsvdc`` with job 21 on square ``m``: ``(s, U, V)`` (columns as lists)."""
    n = p = m.shape[0]
    x = [[float(m[i, j]) for i in range(n)] for j in range(p)]  # x[j][i]: column j
    s, e = [0.0] * (p + 1), [0.0] * p
    u = [[0.0] * n for _ in range(p)]
    v = [[0.0] * p for _ in range(p)]
    work = [0.0] * n
    nct, nrt = min(n - 1, p), max(0, min(p - 2, n))
    for l in range(max(nct, nrt)):  # noqa: E741 (LINPACK's names, 0-based)
        if l < nct:
            s[l] = _nrm2(x[l][l:])
            if s[l] != 0.0:
                if x[l][l] != 0.0:
                    s[l] = _sign(s[l], x[l][l])
                d = 1.0 / s[l]
                x[l][l:] = [d * t for t in x[l][l:]]
                x[l][l] = 1.0 + x[l][l]
            s[l] = -s[l]
        for j in range(l + 1, p):
            if l < nct and s[l] != 0.0:
                t = -_dot(x[l][l:], x[j][l:]) / x[l][l]
                if t != 0.0:
                    for i in range(l, n):
                        x[j][i] += t * x[l][i]
            e[j] = x[j][l]
        if l < nct:
            for i in range(l, n):
                u[l][i] = x[l][i]
        if l < nrt:
            e[l] = _nrm2(e[l + 1:])
            if e[l] != 0.0:
                if e[l + 1] != 0.0:
                    e[l] = _sign(e[l], e[l + 1])
                d = 1.0 / e[l]
                e[l + 1:] = [d * t for t in e[l + 1:]]
                e[l + 1] = 1.0 + e[l + 1]
            e[l] = -e[l]
            if l + 1 < n and e[l] != 0.0:
                for i in range(l + 1, n):
                    work[i] = 0.0
                for j in range(l + 1, p):
                    if e[j] != 0.0:
                        for i in range(l + 1, n):
                            work[i] += e[j] * x[j][i]
                for j in range(l + 1, p):
                    d = -e[j] / e[l + 1]
                    if d != 0.0:
                        for i in range(l + 1, n):
                            x[j][i] += d * work[i]
            for i in range(l + 1, p):
                v[l][i] = e[i]
    m_ = min(p, n + 1)
    if nct < p:
        s[nct] = x[nct][nct]
    if n < m_:
        s[m_ - 1] = 0.0
    if nrt + 1 < m_:
        e[nrt] = x[m_ - 1][nrt]
    e[m_ - 1] = 0.0
    ncu = min(n, p)
    for j in range(nct, ncu):
        u[j] = [0.0] * n
        u[j][j] = 1.0
    for l in range(nct - 1, -1, -1):  # noqa: E741
        if s[l] != 0.0:
            for j in range(l + 1, ncu):
                t = -_dot(u[l][l:], u[j][l:]) / u[l][l]
                if t != 0.0:
                    for i in range(l, n):
                        u[j][i] += t * u[l][i]
            for i in range(l, n):
                u[l][i] = -1.0 * u[l][i]
            u[l][l] = 1.0 + u[l][l]
            for i in range(l):
                u[l][i] = 0.0
        else:
            u[l] = [0.0] * n
            u[l][l] = 1.0
    for l in range(p - 1, -1, -1):  # noqa: E741
        if l < nrt and e[l] != 0.0:
            for j in range(l + 1, p):
                t = -_dot(v[l][l + 1:], v[j][l + 1:]) / v[l][l + 1]
                if t != 0.0:
                    for i in range(l + 1, p):
                        v[j][i] += t * v[l][i]
        v[l] = [0.0] * p
        v[l][l] = 1.0
    # (the iterations: LINPACK's 1-based indices kept, the arrays read at k - 1)
    mm, it, m1 = m_, 0, m_
    while m1 != 0:
        if it >= 1000:
            raise ArithmeticError("dsvdc did not converge")
        ll = 1
        for ll in range(1, m1 + 1):
            lq = m1 - ll
            if lq == 0:
                break
            test = abs(s[lq - 1]) + abs(s[lq])
            if test + abs(e[lq - 1]) == test:
                e[lq - 1] = 0.0
                break
        if lq == m1 - 1:
            kase = 4
        else:
            ls = lq
            for lls in range(lq + 1, m1 + 2):
                ls = m1 - lls + lq + 1
                if ls == lq:
                    break
                test = 0.0
                if ls != m1:
                    test += abs(e[ls - 1])
                if ls != lq + 1:
                    test += abs(e[ls - 2])
                if test + abs(s[ls - 1]) == test:
                    s[ls - 1] = 0.0
                    break
            if ls == lq:
                kase = 3
            elif ls == m1:
                kase = 1
            else:
                kase = 2
                lq = ls
        lq += 1
        if kase == 1:
            f = e[m1 - 2]
            e[m1 - 2] = 0.0
            for k in range(m1 - 1, lq - 1, -1):
                s[k - 1], f, cs, sn = _rotg(s[k - 1], f)
                if k != lq:
                    f = -sn * e[k - 2]
                    e[k - 2] = cs * e[k - 2]
                _rot(v[k - 1], v[m1 - 1], cs, sn)
        elif kase == 2:
            f = e[lq - 2]
            e[lq - 2] = 0.0
            for k in range(lq, m1 + 1):
                s[k - 1], f, cs, sn = _rotg(s[k - 1], f)
                f = -sn * e[k - 1]
                e[k - 1] = cs * e[k - 1]
                _rot(u[k - 1], u[lq - 2], cs, sn)
        elif kase == 3:
            scale = abs(s[m1 - 1])
            for t in (abs(s[m1 - 2]), abs(e[m1 - 2]), abs(s[lq - 1]), abs(e[lq - 1])):
                scale = scale if scale >= t else t
            sm, smm1 = s[m1 - 1] / scale, s[m1 - 2] / scale
            emm1, sl, el = e[m1 - 2] / scale, s[lq - 1] / scale, e[lq - 1] / scale
            b = ((smm1 + sm) * (smm1 - sm) + emm1 * emm1) / 2.0
            c = sm * emm1
            c = c * c
            shift = 0.0
            if not (b == 0.0 and c == 0.0):
                shift = math.sqrt(b * b + c)
                if b < 0.0:
                    shift = -shift
                shift = c / (b + shift)
            f = (sl + sm) * (sl - sm) + shift
            g = sl * el
            for k in range(lq, m1):
                f, g, cs, sn = _rotg(f, g)
                if k != lq:
                    e[k - 2] = f
                f = cs * s[k - 1] + sn * e[k - 1]
                e[k - 1] = cs * e[k - 1] - sn * s[k - 1]
                g = sn * s[k]
                s[k] = cs * s[k]
                _rot(v[k - 1], v[k], cs, sn)
                f, g, cs, sn = _rotg(f, g)
                s[k - 1] = f
                f = cs * e[k - 1] + sn * s[k]
                s[k] = -sn * e[k - 1] + cs * s[k]
                g = sn * e[k]
                e[k] = cs * e[k]
                if k < n:
                    _rot(u[k - 1], u[k], cs, sn)
            e[m1 - 2] = f
            it += 1
        else:
            if s[lq - 1] < 0.0:
                s[lq - 1] = -s[lq - 1]
                v[lq - 1] = [-1.0 * t for t in v[lq - 1]]
            while lq != mm and s[lq - 1] < s[lq]:
                s[lq - 1], s[lq] = s[lq], s[lq - 1]
                if lq < p:
                    v[lq - 1], v[lq] = v[lq], v[lq - 1]
                if lq < n:
                    u[lq - 1], u[lq] = u[lq], u[lq - 1]
                lq += 1
            it = 0
            m1 -= 1
    return s[:p], u, v


def itk_inverse(m) -> np.ndarray:
    """ITK's ``Matrix::GetInverse`` of a non-singular square ``m`` (5.4: ``vnl_matrix_inverse``)."""
    m = np.asarray(m, dtype=np.float64)
    n = m.shape[0]
    s, u, v = _svdc(m)
    winv = [1.0 / abs(w) if abs(w) > 0.0 else 0.0 for w in s]
    # V * W^-1 (a full matrix of zeros off the diagonal), then * U^T: vnl's sums in order
    vw = [[0.0] * n for _ in range(n)]
    for i in range(n):
        for k in range(n):
            t = 0.0
            for j in range(n):
                t += v[j][i] * (winv[j] if j == k else 0.0)
            vw[i][k] = t
    out = np.empty((n, n))
    for i in range(n):
        for k in range(n):
            t = 0.0
            for j in range(n):
                t += vw[i][j] * u[j][k]
            out[i, k] = t
    return out
