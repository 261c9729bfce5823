"""The sweep's C kernels (volwarp_cli/sweep/_sweepkernels.c): the Bezier root finder against
known roots and numpy's, the voxeliser against an analytic sweep, their argument checks, and
no numba on the sweep command's path."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from volwarp_cli.sweep import _sweepkernels as K
from volwarp_cli.sweep.cvg import OP_CODES


def roots_of(coef) -> np.ndarray:
    """real_roots_unit of one polynomial (ascending coefficients), NaN padding dropped."""
    coef = np.ascontiguousarray(np.atleast_2d(coef), dtype=np.float64)
    out = np.full((coef.shape[0], coef.shape[1] - 1), -7.0)
    K.real_roots_unit(coef, out)
    assert not np.any(out == -7.0)  # every slot written
    return out


def from_roots(roots, lead=1.0) -> np.ndarray:
    """Ascending coefficients of lead * prod (x - r)."""
    return np.polynomial.polynomial.polyfromroots(roots) * lead


# -- the root finder --------------------------------------------------------------------
# roots and products of dyadic numbers: the coefficients and Horner's values are exact, so a
# double root evaluates to an exact zero where the derivative chain finds it
@pytest.mark.parametrize("roots, expected", [
    ([0.5], [0.5]),
    ([0.0], [0.0]),
    ([1.0], [1.0]),
    ([1.5], []),
    ([-0.25], []),
    ([0.25, 0.75], [0.25, 0.75]),
    ([0.0, 1.0], [0.0, 1.0]),
    ([0.5, 0.5], [0.5]),  # a double root, once
    ([0.0, 0.0], [0.0]),
    ([1.0, 1.0], [1.0]),
    ([0.125, 0.5, 0.875], [0.125, 0.5, 0.875]),
    ([0.0, 0.5, 1.0], [0.0, 0.5, 1.0]),
    ([-2.0, 0.375, 3.0], [0.375]),
    ([0.5, 0.5, 0.5], [0.5]),  # a triple root
    ([0.125, 0.375, 0.625, 0.875], [0.125, 0.375, 0.625, 0.875]),
    ([0.25, 0.25, 0.75, 0.75], [0.25, 0.75]),
    ([0.0, 0.0, 1.0, 1.0, 0.5], [0.0, 0.5, 1.0]),
    ([0.0625, 0.25, 0.5, 0.75, 0.9375], [0.0625, 0.25, 0.5, 0.75, 0.9375]),
    ([-1.0, 0.25, 0.5, 2.0, 0.75], [0.25, 0.5, 0.75]),
])
def test_known_roots(roots, expected):
    for lead in (1.0, -4.0, 2.0 ** -12, 2.0 ** 16):  # (exact scalings)
        got = roots_of(from_roots(roots, lead))[0]
        found = got[np.isfinite(got)]
        assert got.shape == (len(roots),)
        assert np.all(np.isnan(got[len(found):]))  # NaN-padded at the end
        assert found.size == len(expected), (lead, got)
        np.testing.assert_allclose(found, expected, atol=1e-12, rtol=0)
        assert np.all(np.diff(found) > 0)


@pytest.mark.parametrize("roots, simple", [
    ([0.3, 0.3, 0.7], [0.7]),
    ([0.2, 0.2, 0.9, -1.0], [0.9]),
    ([0.1, 0.45, 0.45, 0.8, 3.0], [0.1, 0.8]),
])
def test_inexact_double_roots(roots, simple):
    """A double root whose value rounds off zero may be missed (a grazing root: nothing in
    [0, 1] changes sign there) or found, never elsewhere; the simple roots are all found."""
    for lead in (1.0, -3.0, 1e-4, 2e5):
        got = roots_of(from_roots(roots, lead))[0]
        found = got[np.isfinite(got)]
        for r in simple:
            assert np.min(np.abs(found - r)) < 1e-9, (lead, got)
        true = np.array([r for r in roots if 0 <= r <= 1])
        assert np.all(np.min(np.abs(found[:, None] - true[None, :]), axis=1) < 1e-6), got


def test_near_double_roots_are_both_found():
    for gap in (1e-3, 1e-5, 1e-6):
        for x0 in (0.3, 0.5, 0.8):
            got = roots_of(from_roots([x0, x0 + gap, 2.5]))[0]
            np.testing.assert_allclose(got[:2], [x0, x0 + gap], atol=1e-9 + gap * 1e-3)
            assert np.isnan(got[2])


def test_polynomials_without_roots_in_the_interval():
    got = roots_of([[1.0, 0.0, 1.0], [2.0, -1.0, 0.0], [-5.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    assert np.all(np.isnan(got))


def test_degree_zero():
    out = roots_of([[3.0], [0.5]])
    assert out.shape == (2, 0)


@pytest.mark.parametrize("degree", [1, 2, 3, 4, 5])
def test_random_polynomials_match_numpy_roots(degree):
    """Where numpy.roots' real roots in [0, 1] are well separated (and clear of the ends),
    the C kernel finds the same ones."""
    rng = np.random.default_rng(degree)
    coef = rng.normal(size=(3000, degree + 1))
    got = roots_of(coef)
    compared = 0
    for c, g in zip(coef, got, strict=True):
        r = np.roots(c[::-1])
        if np.any((np.abs(r.imag) < 1e-4 * (1 + np.abs(r))) & (r.imag != 0)):
            continue  # a pair near the real axis: ill-conditioned
        real = np.sort(r.real[r.imag == 0])
        if real.size > 1 and np.min(np.diff(real)) < 1e-4:
            continue
        if np.any(np.minimum(np.abs(real), np.abs(real - 1)) < 1e-6):
            continue
        want = real[(real >= 0) & (real <= 1)]
        found = g[np.isfinite(g)]
        assert found.size == want.size, (c, found, want)
        np.testing.assert_allclose(found, want, atol=1e-8, rtol=0)
        compared += 1
    assert compared > 2000


# -- the voxeliser ------------------------------------------------------------------------
def straight_sweep():
    """A hand-made sweep along x: two templates at x = 0.2 and 10.2 (one sub-segment, the
    whole segment), template square 4.2 x 4.2 in y and z about the axis; field 0 a constant
    0.7, field 1 a 2-slice stack of constants 0 and 1 whose slice coordinate goes 0 -> 1 (so
    its value is t). Grid: spacing 1, voxel centres at half-integers from -1.5 (x) and -3.5
    (y, z): no centre lies on the swept box's faces."""
    args = dict(
        P=np.array([[0.2, 0.0, 0.0], [10.2, 0.0, 0.0]]),
        EX=np.array([[0.0, 1.0, 0.0]] * 2), EY=np.array([[0.0, 0.0, 1.0]] * 2),
        EZ=np.array([[1.0, 0.0, 0.0]] * 2), SX=np.full(2, 4.2), SY=np.full(2, 4.2),
        SL=np.array([[0.0, 0.0], [0.0, 1.0]]),
        sub_a=np.array([0], np.int64), sub_b=np.array([1], np.int64),
        closed=np.array([3], np.uint8), boxes=np.array([[0, 13, 0, 7, 0, 7]], np.int64),
        origin=np.array([-1.5, -3.5, -3.5]), spacing=np.ones(3),
        tex=np.array([0.7, 0.0, 1.0], np.float32), off=np.array([0, 1], np.int64),
        th=np.ones(2, np.int64), tw=np.ones(2, np.int64), tn=np.array([1, 2], np.int64),
        ops=np.array([OP_CODES["union"], OP_CODES["blend"]], np.int64), opac=0, tol=1e-6,
        acc=np.zeros((2, 8, 8, 14), np.float32), wsum=np.zeros((8, 8, 14), np.float32),
        covered=np.zeros((8, 8, 14), np.uint8), zlo=0, zhi=8, oz=0, oy=0, ox=0)
    return args


def call(args: dict):
    K.sweep_voxelize(*args.values())


def test_straight_sweep_is_the_analytic_box():
    a = straight_sweep()
    call(a)
    z, y, x = np.meshgrid(np.arange(8) - 3.5, np.arange(8) - 3.5, np.arange(14) - 1.5,
                          indexing="ij")
    inside = (x >= 0.2) & (x <= 10.2) & (np.abs(y) <= 2.1) & (np.abs(z) <= 2.1)
    assert inside.sum() == 10 * 4 * 4
    np.testing.assert_array_equal(a["covered"], inside)
    assert np.all(a["acc"][0][inside] == np.float32(0.7)) and np.all(a["acc"][0][~inside] == 0)
    # blend: the value weighed by the opacity (plus the floor), the weights summed
    w = 0.7 + 1e-6
    t = (x - 0.2) / 10.0
    np.testing.assert_allclose(a["acc"][1][inside], (w * t)[inside], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(a["wsum"][inside], w, rtol=1e-6)
    assert np.all(a["acc"][1][~inside] == 0) and np.all(a["wsum"][~inside] == 0)


def test_a_box_empty_in_x_is_skipped_whatever_its_y_range():
    """A sub-segment whose box holds no voxel (x range empty) is not scanned row by row:
    with 2**40 rows it returned at once (the review's hang), and wrote nothing."""
    a = straight_sweep()
    a["boxes"] = np.array([[5, 4, 0, 1 << 40, 0, 7]], np.int64)
    call(a)
    assert not a["covered"].any() and not a["acc"].any() and not a["wsum"].any()


def turning_pair(ops, rng):
    """Two templates through the origin, the second turned 40 degrees about z: the square
    (4 x 3, centred on the axis) sweeps two opposite wedges, the ordinary one (sA >= 0 > sB)
    and the split one (sA <= 0 < sB). One field per operator, random templates of a few
    sizes and slices, random accumulators and coverage; voxel centres off the axis."""
    c, s = np.cos(np.radians(40)), np.sin(np.radians(40))
    F = len(ops)
    shapes = [(1, 3, 4), (2, 4, 3), (3, 2, 2), (1, 1, 1), (4, 5, 6), (2, 1, 3)][:F]
    images = [rng.uniform(0.05, 1, sh).astype(np.float32) for sh in shapes]
    sizes = [im.size for im in images]
    shape = (16, 22, 22)
    return dict(
        P=np.zeros((2, 3)), EX=np.array([[0.0, 1.0, 0.0], [-s, c, 0.0]]),
        EY=np.array([[0.0, 0.0, 1.0]] * 2), EZ=np.array([[1.0, 0.0, 0.0], [c, s, 0.0]]),
        SX=np.full(2, 4.0), SY=np.full(2, 3.0), SL=rng.uniform(-0.5, 4, (2, F)),
        sub_a=np.array([0], np.int64), sub_b=np.array([1], np.int64),
        closed=np.array([3], np.uint8), boxes=np.array([[0, 21, 0, 21, 0, 15]], np.int64),
        origin=np.array([-2.625, -2.625, -1.875]), spacing=np.full(3, 0.25),
        tex=np.concatenate([im.ravel() for im in images]),
        off=np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64),
        th=np.array([sh[1] for sh in shapes], np.int64),
        tw=np.array([sh[2] for sh in shapes], np.int64),
        tn=np.array([sh[0] for sh in shapes], np.int64),
        ops=np.array([OP_CODES[o] for o in ops], np.int64), opac=0, tol=1e-6,
        acc=rng.uniform(-0.5, 1.5, (F,) + shape).astype(np.float32),
        wsum=rng.uniform(0, 2, shape).astype(np.float32),
        covered=(rng.random(shape) < 0.5).astype(np.uint8),
        zlo=0, zhi=shape[0], oz=0, oy=0, ox=0), images


def expected(a, images):
    """numpy's evaluation of the voxeliser's rule for one sub-segment (the same formulas, in
    the kernel's order) and of the operators: (acc, wsum, covered, region-1 voxels)."""
    from volwarp_cli.sweep.templates import sample_template

    o, h, tol = a["origin"], a["spacing"], a["tol"]
    nz, ny, nx = a["covered"].shape
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    wz, wy = o[2] + h[2] * z, o[1] + h[1] * y

    def linear(k, E, S=None):  # c + g * x, as the kernel makes it per row
        P = a["P"][k]
        c = (o[0] - P[0]) * E[k, 0] + (wy - P[1]) * E[k, 1] + (wz - P[2]) * E[k, 2]
        if S is None:
            return c + h[0] * E[k, 0] * x
        return (0.5 + c / S[k]) + (h[0] * E[k, 0] / S[k]) * x

    sA, sB = linear(0, a["EZ"]), linear(1, a["EZ"])
    xa, ya = linear(0, a["EX"], a["SX"]), linear(0, a["EY"], a["SY"])
    xb, yb = linear(1, a["EX"], a["SX"]), linear(1, a["EY"], a["SY"])
    with np.errstate(all="ignore"):
        t = sA / (sA - sB)
    xt, yt = (1 - t) * xa + t * xb, (1 - t) * ya + t * yb
    square = (sA != sB) & ~((xt < 0) | (xt > 1) | (yt < 0) | (yt > 1))
    region0 = (sA >= -tol) & (sB <= tol) & square  # (the segment's last sub-segment)
    region1 = (sA <= tol) & (sB > -tol) & square
    assert not np.any(region0 & region1)
    hit = region0 | region1
    vals = [(1 - t) * sample_template(im, xa, ya, a["SL"][0, f])
            + t * sample_template(im, xb, yb, a["SL"][1, f]) for f, im in enumerate(images)]
    w = np.maximum(vals[a["opac"]], 0.0) + 1e-6
    acc, cov = a["acc"].astype(np.float64), a["covered"] != 0
    rules = {"union": np.maximum, "intersection": np.minimum,
             "difference": lambda p, v: np.maximum(p - v, 0.0),
             "sum": lambda p, v: np.clip(p + v, 0.0, 1.0), "first": lambda p, v: p}
    codes = {v: k for k, v in OP_CODES.items()}
    for f, v in enumerate(vals):
        op = codes[int(a["ops"][f])]
        new = acc[f] + w * v if op == "blend" else np.where(cov, rules[op](acc[f], v), v)
        acc[f] = np.where(hit, new, acc[f])
    wsum = np.where(hit, a["wsum"] + w, a["wsum"])
    return acc.astype(np.float32), wsum.astype(np.float32), cov | hit, region1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_both_regions_and_every_operator_follow_the_rule(seed):
    rng = np.random.default_rng(seed)
    ops = ["union", "intersection", "difference", "blend", "sum", "first"]
    ops = [ops[(seed + k) % 6] for k in range(6)]  # (field 0, the opacity, changes)
    a, images = turning_pair(ops, rng)
    acc, wsum, covered, region1 = expected(a, images)
    assert region1.sum() > 100 and (covered & ~a["covered"].astype(bool)).sum() > 100
    call(a)
    np.testing.assert_array_equal(a["covered"], covered)
    np.testing.assert_allclose(a["acc"], acc, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(a["wsum"], wsum, rtol=1e-6, atol=1e-7)


def test_a_block_and_a_split_give_the_whole():
    """z slices in ranges, on threads, and a block of the grid: the whole's values, bit for bit."""
    from concurrent.futures import ThreadPoolExecutor

    whole = straight_sweep()
    call(whole)
    split = straight_sweep()

    def part(r):
        call({**split, "zlo": r[0], "zhi": r[1]})

    with ThreadPoolExecutor(3) as pool:
        list(pool.map(part, [(0, 3), (3, 5), (5, 8)]))
    for k in ("acc", "wsum", "covered"):
        assert split[k].tobytes() == whole[k].tobytes()
    # the block z 2..6, y 1..7, x 3..13 (the boxes clamped to it, as voxelize.py does)
    block = {**straight_sweep(), "acc": np.zeros((2, 4, 6, 10), np.float32),
             "wsum": np.zeros((4, 6, 10), np.float32), "covered": np.zeros((4, 6, 10), np.uint8),
             "boxes": np.array([[3, 12, 1, 6, 2, 5]], np.int64), "zlo": 2, "zhi": 6, "oz": 2,
             "oy": 1, "ox": 3}
    call(block)
    sl = (slice(2, 6), slice(1, 7), slice(3, 13))
    assert block["acc"].tobytes() == whole["acc"][(slice(None), *sl)].tobytes()
    assert block["covered"].tobytes() == whole["covered"][sl].tobytes()


@pytest.mark.parametrize("change, error", [
    ({"acc": np.zeros((2, 8, 8, 14), np.float64)}, TypeError),  # a wrong type
    ({"covered": np.zeros((8, 8, 14), np.int64)}, TypeError),
    ({"closed": np.array([3], np.int64)}, TypeError),
    ({"tex": np.array([0.7, 0.0, 1.0], np.float64)}, TypeError),
    ({"P": np.zeros((2, 3), np.float32)}, TypeError),
    ({"SL": np.zeros((2, 3))}, ValueError),  # a wrong size
    ({"covered": np.zeros((8, 8, 13), np.uint8)}, ValueError),
    ({"boxes": np.zeros((1, 5), np.int64)}, ValueError),
    ({"tex": np.array([0.7, 0.0], np.float32)}, ValueError),  # field 1's stack beyond tex
    ({"off": np.array([0, 2], np.int64)}, ValueError),
    ({"tn": np.array([1, 0], np.int64)}, ValueError),
    ({"sub_b": np.array([2], np.int64)}, ValueError),  # a template that does not exist
    ({"sub_a": np.array([-1], np.int64)}, ValueError),
    # a voxel outside the block
    ({"boxes": np.array([[0, 14, 0, 7, 0, 7]], np.int64)}, ValueError),
    ({"boxes": np.array([[-1, 13, 0, 7, 0, 7]], np.int64)}, ValueError),
    ({"zhi": 9}, ValueError),
    ({"zlo": -1}, ValueError),
    ({"ops": np.array([0, 9], np.int64)}, ValueError),
    ({"opac": 2}, ValueError),
    # field 1 blends: wsum is the block's
    ({"wsum": np.zeros((1, 1, 1), np.float32)}, ValueError),
    ({"acc": np.zeros((2, 8, 8, 28), np.float32)[..., ::2]}, ValueError),  # not contiguous
])
def test_the_voxeliser_refuses_wrong_buffers_and_writes_nothing(change, error):
    a = straight_sweep()
    a.update(change)
    with pytest.raises(error):
        call(a)
    for k in ("acc", "wsum", "covered"):
        assert not np.any(a[k])


@pytest.mark.parametrize("coef, out, error", [
    (np.zeros((4, 3), np.float32), np.zeros((4, 2)), TypeError),  # a wrong type
    (np.zeros((4, 3)), np.zeros((4, 2), np.float32), TypeError),
    (np.zeros((4, 3), np.int64), np.zeros((4, 2)), TypeError),
    (np.zeros((4, 3), ">f8"), np.zeros((4, 2)), TypeError),  # not the machine's byte order
    (np.zeros((4, 3)), np.zeros((4, 3)), ValueError),  # a wrong size
    (np.zeros((4, 3)), np.zeros((5, 2)), ValueError),
    (np.zeros((4, 3)), np.zeros(8), ValueError),
    (np.zeros((4, 0)), np.zeros((4, 0)), ValueError),
    (np.zeros((4, 6))[:, ::2], np.zeros((4, 2)), ValueError),  # not contiguous
])
def test_the_root_finder_refuses_wrong_buffers(coef, out, error):
    with pytest.raises(error):
        K.real_roots_unit(coef, out)
    assert not np.any(out)


def test_nan_frames_read_nothing_outside_the_template():
    """A zero template scale (NaN template coordinates): values, and no stray reads."""
    a = straight_sweep()
    a["SX"] = np.zeros(2)
    call(a)
    assert np.all(np.isfinite(a["acc"]))


# -- the command ------------------------------------------------------------------------------
def test_the_sweep_command_imports_no_numba(tmp_path):
    """`volwarp sweep`, voxelised (in memory and by blocks) and direct (the Bezier root
    finder), loads no numba: its kernels are C (numba's start-up was most of a small sweep)."""
    (tmp_path / "s.yaml").write_text(textwrap.dedent("""\
        version: 1
        grid: {spacing: 0.5}
        fields:
          opacity: {value: 0.8}
          red: 0.25
        trajectory:
          - bezier: {points: [[0, 0, 0], [3, 4, 0], [6, -2, 1], [8, 0, 2]]}
        up: [0, 0, 1]
        scale: [3, 3]
        """))
    code = textwrap.dedent("""
        import sys
        from volwarp_cli.cli.main import main
        for name, extra in (("v", []), ("d", ["--method", "direct"]),
                            ("c", ["--chunked", "--block", "8", "--threads", "2"])):
            assert main(["sweep", "s.yaml", "-o", name + "_{field}.nrrd", *extra]) == 0, name
        assert "numba" not in sys.modules, "numba imported"
    """)
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert len(list(tmp_path.glob("*_opacity.nrrd"))) == 3
