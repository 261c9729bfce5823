"""Direct evaluation of image-swept volumes by inverse mapping (Winter & Chen §5.2, §5.3).

Instead of scan-converting templates, each voxel centre ``p`` is mapped back
to every template instance whose plane contains it, ``[x, y, u] = rho^-1(p)``:

* ``line`` (direction the tangent or a constant vector): the plane through
  ``a(u)`` with normal ``d`` contains ``p`` at the one ``u`` solving
  ``d . (p - a(u)) = 0`` (linear in ``u``);
* ``arc`` (rotational sweep, direction the tangent, §5.2): every template
  plane contains the axis, so ``p`` lies in the planes at the angles
  ``phi = atan2(q . e2, q . e1)`` and ``phi + pi`` (``q = p - centre``); all
  such angles inside the arc's range are candidates (the second one matters
  when the template crosses the axis);
* ``bezier`` (direction the tangent, §5.3): the candidates are the real roots
  in [0, 1] of ``v . a'(u) = 0`` with ``v = a(u) - p``, a polynomial of degree
  ``2n - 1``. The paper cites Schneider's Bezier root finder; volwarp isolates
  the roots by the derivative chain (the roots of each derivative bracket the
  monotone pieces of the one below) and refines each by safeguarded Newton,
  in a C kernel (:func:`._sweepkernels.real_roots_unit`); numpy's
  companion-matrix eigenvalues (:func:`bezier_candidates_eig`) are the
  reference it is tested against. A root is *trivially rejected* when
  ``|v| > 0.5 sqrt(r_sx(u)^2 + r_sy(u)^2)`` (the template's circumscribed
  circle, Fig. 6).

Departures, for speed and robustness: Bezier voxels farther than the
template's reach from every one of 257 curve samples (plus the largest gap
between samples) are dropped before the root finder (this rejects nothing
the per-root test would keep); and a candidate must put ``p`` in its
template's plane (within 1% of a voxel), which drops the spurious roots at
parameters where ``a'(u)`` vanishes (a Bezier whose end control points
coincide).

For each remaining candidate the frame at ``u`` (the same frames as the
voxeliser: any up function, including the §5.3 ``binormal`` frame, and any
scale function) gives the template coordinates ``x = 0.5 + v'.ex / sx``,
``y = 0.5 + v'.ey / sy`` (``v' = p - a(u)``; the paper's
``|v| sin(theta)`` written as a signed projection); points inside the square
sample the template there, and several instances combine with the field's
CVG operator exactly as in the voxeliser. As there, a template plane where one
segment ends and the next begins (or where a closed trajectory, a full arc,
meets its start) is one instance, the next segment's: the ending segment's
parameters stop 1e-12 short of its end.

Not handled directly (a spec error that says so): polyline segments, and
sweeping directions other than the tangent (or a constant vector on a line),
whose inverse has no closed form here; use ``method: voxelize`` for them.
"""

from __future__ import annotations

import contextlib

import numpy as np

from .. import parallel
from ..box import Box
from ..geometry import Geometry
from ..progress import progress
from ..spec.functions import Function, spec_error
from .cvg import Accumulator
from .templates import sample_template
from .trajectory import Arc, Bezier, Line, Polyline
from .voxelize import check_axis_aligned

CHUNK = 1 << 17


def check_direct(sweep) -> None:
    """Raise a spec error when ``sweep`` has a part direct evaluation cannot invert."""
    for i, (seg, fns) in enumerate(zip(sweep.segments, sweep.functions, strict=True)):
        if isinstance(seg, Polyline):
            raise spec_error(fns.doc, seg.path, "method: direct does not evaluate polyline "
                             "segments; use method: voxelize")
        d = fns.direction
        if isinstance(d, str):
            continue
        if isinstance(seg, Line) and isinstance(d, Function) and d.is_constant:
            continue
        raise spec_error(fns.doc, fns.direction_path,
                         "method: direct needs direction: tangent (or a constant vector on "
                         f"line segments); segment {i} ({seg.kind}) has another; "
                         "use method: voxelize")


def _line_candidates(seg: Line, fns, p: np.ndarray) -> np.ndarray:
    d = seg.stop - seg.start if isinstance(fns.direction, str) else fns.direction(np.zeros(1))[0]
    den = float(np.dot(d, seg.stop - seg.start))
    if abs(den) < 1e-12 * np.linalg.norm(d) * seg.length:
        raise spec_error(fns.doc, fns.direction_path, "the sweeping direction is "
                         "perpendicular to the line: the templates all lie in one plane")
    return (((p - seg.start) @ d) / den)[:, None]


def _arc_candidates(seg: Arc, p: np.ndarray) -> np.ndarray:
    q = p - seg.center
    phi = np.arctan2(q @ seg.e2, q @ seg.e1)
    lo, hi = min(seg.t0, seg.t1), max(seg.t0, seg.t1)
    kmin = int(np.floor((lo - np.pi) / np.pi)) - 1
    kmax = int(np.ceil((hi + np.pi) / np.pi)) + 1
    cands = []
    for k in range(kmin, kmax + 1):
        th = phi + k * np.pi
        ok = (th >= lo - 1e-12) & (th <= hi + 1e-12)
        if np.any(ok):
            cands.append(np.where(ok, seg.s_of_angle(th), np.nan))
    if not cands:
        return np.full((len(p), 1), np.nan)
    return np.stack(cands, axis=1)


def bezier_f_coefficients(seg: Bezier, p: np.ndarray) -> np.ndarray:
    """Ascending coefficients of ``f(s) = (p - a(s)) . a'(s)`` for every point, (N, 2n)."""
    c = seg.monomial
    n = c.shape[0] - 1
    scale = max(np.abs(c).max(), 1e-300)
    while n > 1 and np.abs(c[n]).max() < 1e-12 * scale:
        n -= 1
    c = c[:n + 1]
    deg = 2 * n - 1
    fixed = np.zeros(deg + 1)  # a . a'
    for i in range(n + 1):
        for j in range(1, n + 1):
            fixed[i + j - 1] += j * np.dot(c[i], c[j])
    coef = np.zeros((len(p), deg + 1))
    for m in range(n):  # p . a' : coefficient of s^m is (m + 1) p . c_{m+1}
        coef[:, m] = (m + 1) * (p @ c[m + 1])
    coef -= fixed
    return coef


def polynomial_roots(coef: np.ndarray) -> np.ndarray:
    """Complex roots of many polynomials at once (ascending ``coef``, (N, D+1)) -> (N, D)."""
    d = coef.shape[1] - 1
    lead = coef[:, -1]
    if d == 1:
        return (-coef[:, 0] / lead)[:, None].astype(np.complex128)
    comp = np.zeros((coef.shape[0], d, d))
    comp[:, np.arange(1, d), np.arange(d - 1)] = 1.0
    comp[:, :, -1] = -coef[:, :-1] / lead[:, None]
    workers = min(parallel.threads(), 8, max(1, len(comp) // 4096))
    if workers == 1:
        return np.linalg.eigvals(comp)
    # numpy's batched eigvals releases the GIL: split the batch over threads
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(workers) as pool:
        return np.concatenate(list(pool.map(np.linalg.eigvals, np.array_split(comp, workers))))


def _bezier_candidates(seg: Bezier, p: np.ndarray, serial: bool = False) -> np.ndarray:
    """Real roots in [0, 1] of ``(p - a(s)) . a'(s)`` per point, NaN-padded (N, 2n - 1).

    ``serial``: in the calling thread only (a block task in a thread of its own).
    """
    from ._sweepkernels import real_roots_unit

    coef = np.ascontiguousarray(bezier_f_coefficients(seg, p))
    roots = np.empty((coef.shape[0], coef.shape[1] - 1))
    parallel.run_ranges(lambda a, b: real_roots_unit(coef[a:b], roots[a:b]), len(coef),
                        1 if serial else None)
    return roots


def bezier_candidates_eig(seg: Bezier, p: np.ndarray) -> np.ndarray:
    """The same roots from the companion matrices' eigenvalues (reference, slower)."""
    coef = bezier_f_coefficients(seg, p)
    roots = polynomial_roots(coef)
    scale = np.abs(roots).max(axis=1, keepdims=True) + 1.0
    real = np.abs(roots.imag) <= 1e-6 * scale
    s = np.where(real, roots.real, np.nan)
    deriv = coef[:, 1:] * np.arange(1, coef.shape[1])
    for _ in range(2):  # Newton polishing
        f = _polyval(coef, s)
        df = _polyval(deriv, s)
        step = np.where(np.abs(df) > 1e-300, f / np.where(df == 0, 1, df), 0.0)
        s = s - step
    ok = (s >= -1e-9) & (s <= 1 + 1e-9)
    return np.where(ok, np.clip(s, 0.0, 1.0), np.nan)


def _polyval(coef, s):
    out = np.zeros_like(s)
    for k in range(coef.shape[1] - 1, -1, -1):
        out = out * s + coef[:, k:k + 1]
    return out


def _segment_box(sweep, index: int, grid: Geometry):
    fr = sweep.frames(index, np.linspace(0.0, 1.0, 513))
    c = fr.corners().reshape(-1, 3)
    origin, spacing = grid.origin_array, grid.spacing_array
    lo = np.floor((c.min(axis=0) - origin) / spacing).astype(int) - 1
    hi = np.ceil((c.max(axis=0) - origin) / spacing).astype(int) + 1
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, np.array(grid.shape_xyz) - 1)
    return lo, hi


def _near_curve(sweep, index: int, samples: int = 257, workers: int = -1):
    """A test that keeps the points that may lie within a template's reach of the curve.

    A conservative pre-filter ahead of the root finder (a departure for speed;
    it rejects nothing the paper's per-root test would keep): a point farther
    than ``R + h`` from every one of ``samples`` curve points, with ``R`` the
    largest template half-diagonal and ``h`` the largest gap between samples,
    is farther than ``R`` from the whole curve.
    """
    from scipy.spatial import cKDTree

    fr = sweep.frames(index, np.linspace(0.0, 1.0, samples))
    gap = float(np.linalg.norm(np.diff(fr.P, axis=0), axis=1).max())
    reach = float(0.5 * np.hypot(fr.SX, fr.SY).max()) * 1.01 + gap
    tree = cKDTree(fr.P)

    def keep(p):
        d, _ = tree.query(p, k=1, distance_upper_bound=reach, workers=workers)
        return np.isfinite(d)
    return keep


def direct_block(sweep, grid: Geometry, box: Box, *, threads: int = 1) -> dict[str, np.ndarray]:
    """The fields of ``sweep`` on the voxels ``box`` of ``grid`` by inverse mapping.

    The one evaluation, for the whole grid as for a block: every voxel is
    mapped back from its own world point (computed from its grid index), its
    candidates met in the same order (segment, then root), so any box gives
    the whole grid's values bit for bit. ``threads``: 1 runs the serial root
    finder in the calling thread (safe in any thread: a block task); more use
    volwarp's threads (the whole grid's run, with a progress bar).
    """
    check_axis_aligned(grid)
    check_direct(sweep)
    return _evaluate_box(sweep, grid, box, serial=threads <= 1)


def _evaluate_box(sweep, grid: Geometry, out: Box, serial: bool) -> dict[str, np.ndarray]:
    """Inverse mapping of the voxels ``out`` of ``grid`` (fields of ``out``'s shape)."""
    names = list(sweep.templates)
    templates = [sweep.templates[n] for n in names]
    bz, by, bx = out.shape
    oz, oy, ox = out.lo
    accum = Accumulator(names, sweep.ops, out.size)
    olo = np.array(out.xyz()[0])
    ohi = np.array(out.xyz()[1]) - 1
    boxes = []
    for i in range(len(sweep.segments)):
        lo, hi = _segment_box(sweep, i, grid)
        boxes.append((np.maximum(lo, olo), np.minimum(hi, ohi)))
    plane_tol = 0.01 * float(np.min(grid.spacing))
    # a segment whose last template is the next one's first leaves that plane to
    # the next (Sweep.joined_ends): its parameters stop short of 1
    s_top = [1.0 - 1e-12 if join else 1.0 + 1e-12 for join in sweep.joined_ends()]
    origin, spacing = grid.origin_array, grid.spacing_array
    total = sum(int(np.prod(np.maximum(hi - lo + 1, 0))) for lo, hi in boxes)
    bar_ctx = contextlib.nullcontext(None) if serial else \
        progress(max(total // CHUNK, 1), "sweep (direct)")
    with bar_ctx as bar:
        for i, seg in enumerate(sweep.segments):
            lo, hi = boxes[i]
            if np.any(hi < lo):
                continue
            fns = sweep.functions[i]
            box = tuple(int(v) for v in (hi - lo + 1)[::-1])  # (z, y, x) sizes
            n_box = box[0] * box[1] * box[2]
            near = (_near_curve(sweep, i, workers=1 if serial else -1)
                    if isinstance(seg, Bezier) else None)
            for start in range(0, n_box, CHUNK):
                kk, jj, ii = np.unravel_index(np.arange(start, min(start + CHUNK, n_box)), box)
                kk, jj, ii = kk + lo[2], jj + lo[1], ii + lo[0]
                idx = ((kk - oz) * by + (jj - oy)) * bx + (ii - ox)
                p = origin + np.stack([ii, jj, kk], axis=1) * spacing
                if near is not None:
                    keep = near(p)
                    idx, p = idx[keep], p[keep]
                    if idx.size == 0:
                        if bar is not None:
                            bar.advance()
                        continue
                if isinstance(seg, Line):
                    cand = _line_candidates(seg, fns, p)
                elif isinstance(seg, Arc):
                    cand = _arc_candidates(seg, p)
                else:
                    cand = _bezier_candidates(seg, p, serial)
                for j in range(cand.shape[1]):
                    s = cand[:, j]
                    ok = np.isfinite(s) & (s >= -1e-12) & (s <= s_top[i])
                    if not np.any(ok):
                        continue
                    sel = np.flatnonzero(ok)
                    s_sel = np.clip(s[sel], 0.0, 1.0)
                    psel = p[sel]
                    if isinstance(seg, Bezier):  # trivial rejection, §5.3
                        sc = fns.scale(seg.u_of(s_sel))
                        v = seg.point(s_sel) - psel
                        keep = np.linalg.norm(v, axis=1) <= 0.5 * np.hypot(sc[:, 0], sc[:, 1])
                        sel, s_sel, psel = sel[keep], s_sel[keep], psel[keep]
                        if sel.size == 0:
                            continue
                    fr = sweep.frames(i, s_sel)
                    vv = psel - fr.P
                    x = 0.5 + np.sum(vv * fr.EX, axis=1) / fr.SX
                    y = 0.5 + np.sum(vv * fr.EY, axis=1) / fr.SY
                    # p must lie in the template's plane: this drops the spurious roots
                    # where a'(u) vanishes (f(u) = 0 there for every p)
                    off_plane = np.abs(np.sum(vv * fr.EZ, axis=1))
                    inside = ((x >= 0) & (x <= 1) & (y >= 0) & (y <= 1)
                              & (off_plane <= plane_tol))
                    if not np.any(inside):
                        continue
                    sel, s_sel, x, y = sel[inside], s_sel[inside], x[inside], y[inside]
                    vals = np.empty((len(names), sel.size), dtype=np.float64)
                    for f, t in enumerate(templates):
                        sl = t.slice_coords(seg, s_sel) if t.n_slices > 1 else None
                        vals[f] = sample_template(t.data, x, y, sl)
                    accum.add(idx[sel], vals)
                if bar is not None:
                    bar.advance()
    fields = accum.result()
    return {n: fields[n].reshape(bz, by, bx) for n in names}
