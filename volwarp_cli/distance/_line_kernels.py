"""Per-line kernels of the voxel-step metrics (serial numba ``nogil``, any strides).

Imported when a chessboard or taxicab pass runs (:mod:`.minnorm`): each
turns every line along the last axis of an (a, b, n) float32 array of
integers or +inf into its one-dimensional distance transform, in place.
"""

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def chessboard_lines(f):
    # f: (a, b, n) float32 of integers or +inf, any strides. Each line becomes
    # g(u) = min_i max(|u - i|, f(i)): Meijster, Roerdink & Hesselink (2000)'s
    # lower envelope with the chessboard Sep, in int64 (+inf as a sentinel)
    a, b, n = f.shape
    big = np.int64(1) << 40
    g = np.empty(n, np.int64)
    s = np.empty(n, np.int64)
    t = np.empty(n, np.int64)
    for i0 in range(a):
        for j0 in range(b):
            finite = False
            for k in range(n):
                v = f[i0, j0, k]
                if v < np.inf:
                    g[k] = np.int64(v)
                    finite = True
                else:
                    g[k] = big
            if not finite:
                continue
            q = 0
            s[0] = 0
            t[0] = 0
            for u in range(1, n):
                while q >= 0 and (max(abs(t[q] - s[q]), g[s[q]])
                                  > max(abs(t[q] - u), g[u])):
                    q -= 1
                if q < 0:
                    q = 0
                    s[0] = u
                else:
                    i = s[q]
                    if g[i] <= g[u]:
                        sep = max(i + g[u], (i + u) // 2)
                    else:
                        sep = min(u - g[i], (i + u) // 2)
                    w = 1 + sep
                    if w < n:
                        q += 1
                        s[q] = u
                        t[q] = w
            for u in range(n - 1, -1, -1):
                d = max(abs(u - s[q]), g[s[q]])
                f[i0, j0, u] = np.float32(d) if d < big else np.float32(np.inf)
                if u == t[q]:
                    q -= 1


@nb.njit(cache=True, nogil=True)
def taxicab_lines(f):
    # f: (a, b, n) float32 of integers or +inf, any strides. Each line becomes
    # g(u) = min_i |u - i| + f(i): one sweep each way (a chamfer along the line;
    # integer sums, exact in float32)
    a, b, n = f.shape
    for i0 in range(a):
        for j0 in range(b):
            for k in range(1, n):
                v = f[i0, j0, k - 1] + np.float32(1)
                if v < f[i0, j0, k]:
                    f[i0, j0, k] = v
            for k in range(n - 2, -1, -1):
                v = f[i0, j0, k + 1] + np.float32(1)
                if v < f[i0, j0, k]:
                    f[i0, j0, k] = v
