"""Landmark warps through scipy's RBFInterpolator: the same warps as the old dense solver.

``_old_fit``/``_old_displacement`` are the solver of ``morph/landmarks.py`` as it was
before it moved onto :class:`scipy.interpolate.RBFInterpolator` (kept verbatim, less
the argument checks): the reference the new one must reproduce.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.morph.landmarks import LandmarkWarp


# -- the old solver (reference) ----------------------------------------------------------
def _old_phi(r, kind, sigma):
    if kind == "thin-plate":
        return r
    return np.exp(-(r * r) / (2.0 * sigma * sigma))


def _old_fit(source, target, kind="thin-plate", sigma=None):
    p = np.asarray(source, dtype=np.float64)
    q = np.asarray(target, dtype=np.float64)
    n = len(p)
    dist = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    poly = np.hstack([np.ones((n, 1)), p])
    if n < 4 or np.linalg.matrix_rank(poly - poly.mean(axis=0) * [0, 1, 1, 1]) < 4:
        poly = poly[:, :1]  # translation only
    m = poly.shape[1]
    k = _old_phi(dist, kind, sigma)
    system = np.zeros((n + m, n + m))
    system[:n, :n] = k
    system[:n, n:] = poly
    system[n:, :n] = poly.T
    rhs = np.zeros((n + m, 3))
    rhs[:n] = q - p
    sol = np.linalg.solve(system, rhs)
    affine = np.zeros((4, 3))
    affine[:m] = sol[n:]
    return p, sol[:n], affine, kind, sigma


def _old_displacement(fitted, points):
    centers, weights, affine, kind, sigma = fitted
    x = np.asarray(points, dtype=np.float64)
    shape = x.shape
    x = x.reshape(-1, 3)
    out = np.empty_like(x)
    chunk = max(1, 2_000_000 // max(len(centers), 1))
    for s in range(0, len(x), chunk):
        xs = x[s:s + chunk]
        r = np.sqrt(((xs[:, None, :] - centers[None, :, :]) ** 2).sum(-1))
        out[s:s + chunk] = _old_phi(r, kind, sigma) @ weights + affine[0] + xs @ affine[1:]
    return out.reshape(shape)


def _rel(a, b):
    """Largest difference relative to the largest displacement."""
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def _tolerance(p, kind, sigma):
    """1e-12, or more for an ill-conditioned system (two solvers of one system differ by
    about machine epsilon times its condition number): the kernel matrix bordered by the
    affine part, the system both solve, each block scaled to unit size (a condition that
    does not depend on the coordinates' units). Its condition can exceed the kernel's
    alone: four landmarks near a plane differed by 1.4e-12 where the kernel's (16)
    allowed 1e-12, the bordered system's being 7e4."""
    r = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=-1)
    if len(p) < 2:
        return 1e-12
    k = _old_phi(r, kind, sigma)
    poly = np.hstack([np.ones((len(p), 1)), p])
    if len(p) < 4 or np.linalg.matrix_rank(poly - poly.mean(axis=0) * [0, 1, 1, 1]) < 4:
        poly = poly[:, :1]  # (as _old_fit)
    m = poly.shape[1]
    poly = poly / np.abs(poly).max(axis=0)
    system = np.block([[k / np.abs(k).max(), poly], [poly.T, np.zeros((m, m))]])
    cond = max(np.linalg.cond(k), np.linalg.cond(system))
    return max(1e-12, 1e-15 * cond)


# -- the new solver equals the old ---------------------------------------------------------
KINDS = [("thin-plate", None), ("gaussian", 4.0), ("gaussian", 15.0)]


@pytest.mark.parametrize("kind,sigma", KINDS)
@pytest.mark.parametrize("n", [1, 2, 3, 4, 7, 20, 60])
def test_matches_the_old_solver(kind, sigma, n):
    rng = np.random.default_rng(100 + n)
    p = rng.uniform(-20, 30, (n, 3))
    q = p + rng.normal(0, 3, (n, 3))
    x = rng.uniform(-30, 40, (2000, 3))
    new = LandmarkWarp.fit(p, q, kind=kind, sigma=sigma)
    old = _old_fit(p, q, kind, sigma)
    tol = _tolerance(p, kind, sigma)
    assert _rel(new.displacement(x), _old_displacement(old, x)) < tol
    assert _rel(new(x), x + _old_displacement(old, x)) < tol


@pytest.mark.parametrize("kind,sigma", KINDS)
def test_coplanar_landmarks_fall_back_to_a_translation_as_before(kind, sigma):
    rng = np.random.default_rng(3)
    p = np.column_stack([rng.uniform(0, 20, (8, 2)), np.full(8, 5.0)])  # all in z = 5
    q = p + rng.normal(0, 2, (8, 3))
    x = rng.uniform(-5, 25, (500, 3))
    new = LandmarkWarp.fit(p, q, kind=kind, sigma=sigma)
    assert _rel(new.displacement(x), _old_displacement(_old_fit(p, q, kind, sigma), x)) < 1e-12
    assert np.abs(new(p) - q).max() < 1e-9


def test_matches_the_old_solver_on_random_sets():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=40, deadline=None)
    @given(st.integers(1, 30), st.integers(0, 2**32 - 1), st.sampled_from(KINDS))
    def check(n, seed, ks):
        kind, sigma = ks
        rng = np.random.default_rng(seed)
        p = rng.uniform(-50, 50, (n, 3))
        if n > 1 and np.min(np.linalg.norm(p[:, None] - p[None], axis=-1)
                            + 1e9 * np.eye(n)) < 1.0:
            return  # nearly coincident landmarks: both systems are ill-conditioned
        q = p + rng.normal(0, 5, (n, 3))
        x = rng.uniform(-60, 60, (300, 3))
        new = LandmarkWarp.fit(p, q, kind=kind, sigma=sigma)
        old = _old_displacement(_old_fit(p, q, kind, sigma), x)
        assert _rel(new.displacement(x), old) < _tolerance(p, kind, sigma)

    check()


# -- interpolation and polynomial reproduction ----------------------------------------------
@pytest.mark.parametrize("kind,sigma", KINDS)
@pytest.mark.parametrize("n", [1, 2, 3, 5, 12, 50])
def test_reproduces_the_landmarks(kind, sigma, n):
    rng = np.random.default_rng(n)
    p = rng.uniform(0, 40, (n, 3))
    q = p + rng.normal(0, 3, (n, 3))
    w = LandmarkWarp.fit(p, q, kind=kind, sigma=sigma)
    assert np.abs(w(p) - q).max() < 1e-10 * max(1.0, np.abs(q).max())


def test_thin_plate_reproduces_an_affine_map_exactly():
    rng = np.random.default_rng(11)
    p = rng.uniform(-10, 10, (25, 3))
    a = np.array([[1.1, 0.2, -0.1], [-0.3, 0.9, 0.05], [0.1, 0.15, 1.3]])
    t = np.array([4.0, -2.0, 0.5])
    q = p @ a.T + t
    w = LandmarkWarp.fit(p, q)
    x = rng.uniform(-30, 30, (400, 3))
    np.testing.assert_allclose(w(x), x @ a.T + t, rtol=0, atol=1e-11)


def test_fewer_than_four_landmarks_translate():
    p = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    q = p + [[1.0, 2, 3], [1, 2, 3], [1, 2, 3]]
    w = LandmarkWarp.fit(p, q)
    x = np.array([[5.0, 5, 5], [-20, 3, 40]])
    np.testing.assert_allclose(w.displacement(x), [[1, 2, 3], [1, 2, 3]], atol=1e-12)


def test_shapes_and_errors():
    w = LandmarkWarp.fit([[0, 0, 0], [1, 0, 0]], [[0, 0, 1], [1, 0, 1]])
    assert w.displacement(np.zeros((4, 5, 3))).shape == (4, 5, 3)
    assert w.displacement(np.zeros((0, 3))).shape == (0, 3)
    assert w(np.zeros(3)).shape == (3,)
    with pytest.raises(VolwarpError, match="differ in length"):
        LandmarkWarp.fit(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(VolwarpError, match="sigma"):
        LandmarkWarp.fit(np.eye(3), np.eye(3), kind="gaussian")
    with pytest.raises(VolwarpError, match="coincide"):
        LandmarkWarp.fit([[0, 0, 0], [0, 0, 0]], [[1, 0, 0], [2, 0, 0]])
    with pytest.raises(VolwarpError, match="unknown warp kind"):
        LandmarkWarp.fit(np.eye(3), np.eye(3), kind="cubic")
    with pytest.raises(VolwarpError, match="at least one pair"):
        LandmarkWarp.fit(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(VolwarpError, match="finite"):
        LandmarkWarp.fit([[0, 0, np.nan]], [[0, 0, 0]])
    with pytest.raises(VolwarpError, match=r"\(x, y, z\)"):
        LandmarkWarp.fit([[0, 0]], [[0, 0]])


def test_singular_system_is_a_volwarp_error():
    # a huge gaussian sigma on nearby points makes the kernel matrix numerically singular
    p = np.array([[0.0, 0, 0], [5e-8, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    with pytest.raises(VolwarpError, match="the landmark system is singular"):
        LandmarkWarp.fit(p, p + 1.0, kind="gaussian", sigma=1e9)
