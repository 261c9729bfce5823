"""The sweep's template frames: the default rotation-minimising frame, and a given up (issue 18)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.errors import SpecError
from volwarp_cli.io.images import write_image
from volwarp_cli.spec.functions import Function, parse_function
from volwarp_cli.spec.loader import load_schema, parse_spec_text, validate
from volwarp_cli.sweep import evaluate
from volwarp_cli.sweep.frames import (
    RotationMinimising,
    SweepFunctions,
    compute_frames,
    prepare_frames,
)
from volwarp_cli.sweep.model import fit_grid, parse_sweep_spec
from volwarp_cli.sweep.trajectory import Arc, Bezier, Line, Polyline

SPECS = sorted((Path(__file__).resolve().parents[1] / "specs").glob("sweep-*.yaml"))


def disc_image(n=128):
    c = (np.arange(n) + 0.5) / n - 0.5
    x, y = np.meshgrid(c, c)
    return (np.hypot(x, y) <= 0.5).astype(np.float32)


@pytest.fixture
def disc(tmp_path):
    write_image(tmp_path / "disc.png", disc_image()[:, :, None])
    return "disc.png"


def make_spec(tmp_path, body: dict, name="spec.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump({"version": 1, **body}, sort_keys=False))
    doc = parse_spec_text(path.read_text(), str(path), tmp_path)
    validate(doc, load_schema("sweep"))
    return parse_sweep_spec(doc)


def fields_of(spec, method=None):
    lo, hi = spec.bounds()
    grid = fit_grid(spec.grid, lo, hi)
    return evaluate(spec, grid, method=method), grid


def default_functions(seg, direction="tangent"):
    """SweepFunctions with the default up, prepared as the parser does."""
    fns = SweepFunctions(direction, RotationMinimising(), parse_function([1, 1], dim=2))
    prepare_frames([seg], [fns])
    return fns


def frames_of(seg, s, fns=None):
    fns = default_functions(seg) if fns is None else fns
    return compute_frames(seg, fns, np.asarray(s, dtype=np.float64), 0)


def assert_orthonormal(fr, tol=1e-12):
    for a in (fr.EX, fr.EY, fr.EZ):
        assert np.abs(np.linalg.norm(a, axis=1) - 1).max() < tol
    for a, b in ((fr.EX, fr.EY), (fr.EY, fr.EZ), (fr.EX, fr.EZ)):
        assert np.abs(np.sum(a * b, axis=1)).max() < tol
    assert np.abs(np.cross(fr.EY, fr.EZ) - fr.EX).max() < tol  # right-handed


def twist_rate(seg, fns, s, h=1e-6):
    """(d ey / ds) . ex: the frame's rotation rate about the direction (0 when minimising)."""
    a = compute_frames(seg, fns, s - h, 0)
    b = compute_frames(seg, fns, s + h, 0)
    mid = compute_frames(seg, fns, s, 0)
    return np.sum((b.EY - a.EY) / (2 * h) * mid.EX, axis=1)


# -- the failure of issue 18: a line along z without up --------------------------------------
@pytest.mark.parametrize("method", ["voxelize", "direct"])
@pytest.mark.parametrize("down", [False, True])
def test_line_along_z_without_up_is_a_cylinder(tmp_path, disc, method, down):
    r, L = 4.0, 20.0
    a, b = [0.1, -0.05, 2.25], [0.1, -0.05, 2.25 + L]
    if down:
        a, b = b, a
    spec = make_spec(tmp_path, {
        "grid": {"origin": [-6, -6, 0], "spacing": 0.5, "shape": [25, 25, 50]},
        "fields": {"opacity": {"image": disc}},
        "trajectory": [{"line": {"from": a, "to": b}}],
        "scale": [2 * r, 2 * r], "method": method})
    f, grid = fields_of(spec)
    vol = f["opacity"].sum(dtype=np.float64) * np.prod(grid.spacing)
    assert vol == pytest.approx(np.pi * r * r * L, rel=0.02)
    # the frame: up is world y (z is the direction), right-handed
    fr = spec.sweeps()[0].frames(0, np.linspace(0, 1, 5))
    assert np.allclose(fr.EY, [0, 1, 0]) and np.allclose(fr.EZ, [0, 0, -1 if down else 1])
    assert np.allclose(fr.EX, [-1 if down else 1, 0, 0])


def test_line_along_z_on_the_command_line(tmp_path, run):
    (tmp_path / "z.yaml").write_text(
        "version: 1\ngrid: {spacing: 0.5}\nfields: {opacity: 1}\n"
        "trajectory:\n  - line: {from: [0, 0, 0], to: [0, 0, 5]}\nscale: [3, 3]\n")
    res = run("sweep", tmp_path / "z.yaml", "-o", tmp_path / "o_{field}.nrrd")
    assert res.code == 0, res.stderr
    assert (tmp_path / "o_opacity.nrrd").exists()


def test_arc_through_vertical_directions_without_up(tmp_path):
    # the ring of fire's circle in the x-z plane: world z is the direction at angles 0 and 180
    # (the template's height, along y, is a whole number of voxels, its faces between
    # voxel centres: an axis-aligned slab's sampled thickness is quantised)
    spec = make_spec(tmp_path, {
        "grid": {"origin": [-8.125, -3.125, -8.125], "spacing": 0.25, "shape": [66, 26, 66]},
        "fields": {"opacity": 1},
        "trajectory": [{"arc": {"center": [0, 0, 0], "radius": 6, "axis": [0, -1, 0]}}],
        "scale": [3, 2]})
    fr = spec.sweeps()[0].frames(0, np.linspace(0, 1, 101))
    assert_orthonormal(fr)
    # a planar curve: the rotation-minimising frame keeps its angle with the plane (here
    # it starts on the plane's normal, world y, and stays there)
    assert np.allclose(fr.EY, [0, 1, 0], atol=1e-12)
    f, grid = fields_of(spec)
    vol = np.count_nonzero(f["opacity"] > 0.5) * np.prod(grid.spacing)
    assert vol == pytest.approx(2 * np.pi * 6 * 3 * 2, rel=0.02)


# -- rotation-minimising ----------------------------------------------------------------------
_TILT = np.linalg.qr(np.array([[1.0, 2, 3], [0, 1, 4], [5, 6, 0]]))[0]  # a rotation


@pytest.mark.parametrize("seg", [
    Arc(center=np.zeros(3), radius=5.0, axis=np.array([1.0, 1.0, 2.0]), start_deg=10,
        end_deg=700),
    Bezier(points=np.array([[0.0, 0, 0], [10, 14, 0], [20, -8, 0], [28, 0, 0]]) @ _TILT.T),
    Polyline(points=np.array([[0.0, 0, 0], [8, 1, 0], [3, 9, 0], [-2, 4, 0]]) @ _TILT.T),
], ids=["tilted-arc", "tilted-bezier", "tilted-polyline"])
def test_planar_curves_have_no_twist(seg):
    pts = seg.sample_points(101)
    normal = np.linalg.svd(pts - pts.mean(axis=0))[2][2]  # the curve's plane
    s = np.unique(np.concatenate([np.linspace(0.0005, 0.9995, 400), seg.breaks()]))
    fns = default_functions(seg)
    for left in (False, True):
        fr = compute_frames(seg, fns, s, 0, left=left)
        assert_orthonormal(fr)
        # a constant angle with the plane: no twist (world z made normal to the direction,
        # the old default, turns from about 20 to 90 degrees here)
        assert np.ptp(np.sum(fr.EY * normal, axis=1)) < 1e-9
    if not isinstance(seg, Polyline):
        assert np.abs(twist_rate(seg, fns, s)).max() < 1e-5


def test_helix_matches_the_analytic_rotation_minimising_frame():
    # the frame depends on the direction only: a line swept along the unit tangent of the
    # helix (a cos t, a sin t, b t) as its direction has the helix's rotation-minimising
    # frame, which turns against the Frenet frame at the rate -torsion * speed
    a, b, turns = 3.0, 1.0, 2.0
    T = 2 * np.pi * turns
    c = np.hypot(a, b)
    tau = b / c ** 2
    direction = parse_function({"expr": [f"-{a} * sin({T} * u)", f"{a} * cos({T} * u)", f"{b}"]},
                               dim=3)
    seg = Line(start=np.zeros(3), stop=np.array([1.0, 0, 0]))
    fns = default_functions(seg, direction)
    s = np.linspace(0, 1, 301)
    fr = compute_frames(seg, fns, s, 0)
    assert_orthonormal(fr)
    t = T * s[:, None]
    normal = np.hstack([-np.cos(t), -np.sin(t), 0 * t])  # Frenet N
    tangent = np.hstack([-a * np.sin(t), a * np.cos(t), b + 0 * t]) / c
    binormal = np.cross(tangent, normal)
    ey0 = fr.EY[0]
    th0 = np.arctan2(ey0 @ binormal[0], ey0 @ normal[0])
    th = th0 - tau * c * t  # the RMF's angle from N
    expect = np.cos(th) * normal + np.sin(th) * binormal
    assert np.abs(fr.EY - expect).max() < 1e-8


def test_random_curves_give_continuous_orthonormal_minimising_frames():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=40, deadline=None)
    @given(st.sampled_from(["bezier", "polyline"]), st.integers(2, 6), st.integers(0, 2**32 - 1))
    def check(kind, n, seed):
        rng = np.random.default_rng(seed)
        pts = rng.normal(scale=10, size=(n + 1, 3))
        if kind == "polyline":
            steps = np.diff(pts, axis=0)
            steps /= np.linalg.norm(steps, axis=1)[:, None]
            if np.any(np.sum(steps[1:] * steps[:-1], axis=1) < -0.99):
                return  # turns (nearly) back on itself at a vertex: no least rotation
            seg = Polyline(points=pts)
        else:
            seg = Bezier(points=pts)
        fns = default_functions(seg)
        s = np.unique(np.concatenate([np.linspace(0, 1, 2001), seg.breaks()]))
        fr = compute_frames(seg, fns, s, 0)
        assert_orthonormal(fr, 1e-10)
        # continuity, and no twist: the up moves no more than the direction turns
        # (a rotation-minimising frame's up changes by -(up . t') t, |.| <= |t'|)
        turn = np.arctan2(np.linalg.norm(np.cross(fr.EZ[:-1], fr.EZ[1:]), axis=1),
                          np.sum(fr.EZ[:-1] * fr.EZ[1:], axis=1))
        move = np.linalg.norm(np.diff(fr.EY, axis=0), axis=1)
        assert np.all(move <= 1.001 * turn + 1e-7)
        # the same frames from another batch of queries, and from the left side of a
        # vertex as at the end of the piece before it
        one = compute_frames(seg, fns, s[::97].copy(), 0)
        assert np.abs(one.EY - fr.EY[::97]).max() < 1e-12
        if seg.breaks().size:
            b = seg.breaks()
            left = compute_frames(seg, fns, b, 0, left=True)
            before = compute_frames(seg, fns, b - 1e-7, 0)
            assert np.abs(left.EY - before.EY).max() < 1e-6

    check()


def test_joined_segments_continue_the_frame():
    # a space curve then a line starting where it ends: the frame does not jump there
    bez = Bezier(points=np.array([[0.0, 0, 0], [5, 6, 1], [10, -4, 5], [14, 2, 9]]))
    end = bez.point(np.array([1.0]))[0]
    line = Line(start=end, stop=end + 6 * bez.d1(np.array([1.0]))[0]
                / np.linalg.norm(bez.d1(np.array([1.0]))[0]))
    fns = [SweepFunctions("tangent", RotationMinimising(), parse_function([1, 1], dim=2))
           for _ in range(2)]
    prepare_frames([bez, line], fns)
    a = compute_frames(bez, fns[0], np.array([1.0]), 0, left=True)
    b = compute_frames(line, fns[1], np.array([0.0, 0.5, 1.0]), 1)
    assert np.abs(a.EY[0] - b.EY[0]).max() < 1e-12
    assert np.abs(b.EY - b.EY[0]).max() < 1e-12  # constant along the line
    # the z-projected up would have turned: the bezier's end frame is not world z's
    z = np.array([0.0, 0, 1]) - b.EZ[0][2] * b.EZ[0]
    assert np.linalg.norm(z / np.linalg.norm(z) - b.EY[0]) > 1e-3


def test_corner_between_segments_turns_least():
    # two lines meeting at a right angle in a vertical plane: the up turns with the direction
    l1 = Line(start=np.zeros(3), stop=np.array([5.0, 0, 0]))
    l2 = Line(start=np.array([5.0, 0, 0]), stop=np.array([5.0, 0, 5]))
    fns = [SweepFunctions("tangent", RotationMinimising(), parse_function([1, 1], dim=2))
           for _ in range(2)]
    prepare_frames([l1, l2], fns)
    a = compute_frames(l1, fns[0], np.array([0.5]), 0)
    b = compute_frames(l2, fns[1], np.array([0.5]), 1)
    assert np.allclose(a.EY, [0, 0, 1]) and np.allclose(b.EY, [-1, 0, 0])
    assert np.allclose(a.EX, b.EX)  # the turn is about the template's x axis


# -- the default where z worked: exactly the old frames ------------------------------------------
@pytest.mark.parametrize("trajectory", [
    [{"line": {"from": [0, 0, 0], "to": [10, 1, 0]}}],
    [{"line": {"from": [0, 0, 0], "to": [1, 2, 10]}}],
    [{"arc": {"center": [0, 0, 0], "radius": 6, "axis": [0, 0, 1], "start": 20, "end": 300}}],
    [{"arc": {"center": [0, 0, 0], "radius": 6, "axis": [0, 1, 0], "start": 100, "end": 170}}],
    [{"bezier": {"points": [[0, 0, 0], [10, 14, 0], [20, -8, 0], [28, 0, 0]]}}],
    [{"bezier": {"points": [[0, 0, 0], [10, 0, 3], [20, 0, -4], [28, 0, 1]]}}],
    [{"polyline": {"points": [[0, 0, 0], [8, 0, 0], [8, 8, 0], [14, 3, 0]]}}],
    [{"line": {"from": [-5, -6, 0], "to": [0, -6, 0]}},
     {"arc": {"center": [0, 0, 0], "radius": 6, "axis": [0, 0, 1], "start": -90, "end": 90}}],
])
def test_default_equals_up_z_where_that_is_rotation_minimising(tmp_path, trajectory):
    body = {"fields": {"opacity": 1}, "trajectory": trajectory, "scale": [3, 2]}
    default = make_spec(tmp_path, body, "a.yaml").sweeps()[0]
    given = make_spec(tmp_path, {**body, "up": [0, 0, 1]}, "b.yaml").sweeps()[0]
    for i, seg in enumerate(default.segments):
        assert isinstance(default.functions[i].up, Function)  # the old code path, exactly
        s = np.unique(np.concatenate([np.linspace(0, 1, 333), seg.breaks()]))
        for left in (False, True):
            a = compute_frames(seg, default.functions[i], s, i, left=left)
            b = compute_frames(seg, given.functions[i], s, i, left=left)
            for f in ("EX", "EY", "EZ"):
                assert np.array_equal(getattr(a, f), getattr(b, f))


def test_default_differs_from_up_z_on_a_space_curve(tmp_path):
    body = {"fields": {"opacity": 1}, "scale": [3, 2],
            "trajectory": [{"bezier": {"points": [[0, 0, 0], [10, 14, 0], [20, -8, 3],
                                                  [28, 0, 6]]}}]}
    default = make_spec(tmp_path, body, "a.yaml").sweeps()[0]
    given = make_spec(tmp_path, {**body, "up": [0, 0, 1]}, "b.yaml").sweeps()[0]
    assert isinstance(default.functions[0].up, RotationMinimising)
    s = np.linspace(0, 1, 50)
    a, b = default.frames(0, s), given.frames(0, s)
    assert np.allclose(a.EY[0], b.EY[0], atol=1e-12)  # it starts from world z
    assert np.abs(a.EY - b.EY).max() > 1e-3  # and then does not twist as world z does


# -- a given up ----------------------------------------------------------------------------------
def _frames_by_formula(seg, up, s):
    """The given-up frame: ez the unit tangent, ey the up made normal to it."""
    d = seg.d1(s)
    ez = d / np.linalg.norm(d, axis=1)[:, None]
    ey = up - np.sum(up * ez, axis=1)[:, None] * ez
    ey /= np.linalg.norm(ey, axis=1)[:, None]
    return np.cross(ey, ez), ey, ez


@pytest.mark.parametrize("spec", SPECS, ids=[s.stem for s in SPECS])
def test_given_up_keeps_the_example_frames(tmp_path, spec):
    body = yaml.safe_load(spec.read_text())
    sweeps = [body] if "scene" not in body else []
    if "scene" in body:
        stack = [body["scene"]]
        while stack:
            node = stack.pop()
            if "sweep" in node:
                sweeps.append(node["sweep"])
            else:
                stack.extend(node["of"])
    for k, sw in enumerate(sweeps):
        up = sw.get("up")
        if up is None or not isinstance(up, (list, dict)):
            continue
        one = {"fields": {"opacity": 1}, **{key: sw[key] for key in
                                            ("trajectory", "up", "scale", "direction") if key in sw}}
        if sw.get("direction", "tangent") != "tangent":
            continue
        parsed = make_spec(tmp_path, one, f"s{k}.yaml").sweeps()[0]
        for i, seg in enumerate(parsed.segments):
            s = np.linspace(0.001, 0.999, 200)
            fr = parsed.frames(i, s)
            upv = parsed.functions[i].up(seg.u_of(s))
            ex, ey, ez = _frames_by_formula(seg, upv, s)
            assert np.abs(fr.EY - ey).max() < 1e-12 and np.abs(fr.EX - ex).max() < 1e-12


def test_up_collinear_between_samples_is_a_spec_error(tmp_path, run):
    # an S-curve in the x-z plane: its direction is vertical at s = 1/2 - sqrt(3)/6, between
    # any samples; up [0, 0, 1] is collinear there
    text = ("version: 1\ngrid: {spacing: 0.5}\nfields: {opacity: 1}\ntrajectory:\n"
            "  - bezier: {points: [[0, 0, 0], [6, 0, 4], [-6, 0, 8], [0, 0, 12]]}\n"
            "up: [0, 0, 1]\nscale: [3, 3]\n")
    (tmp_path / "bad.yaml").write_text(text)
    for method in ("voxelize", "direct"):
        res = run("sweep", tmp_path / "bad.yaml", "-o", tmp_path / "o_{field}.nrrd",
                  "--method", method)
        assert res.code == 2, res.stderr
        assert "bad.yaml:6: up" in res.stderr and "collinear" in res.stderr
        s0 = 0.5 - np.sqrt(3) / 6
        assert f"u={s0:.6g}" in res.stderr and "point [1.73205, 0.0, 2.5359]" in res.stderr
        assert res.stderr.count("\n") == 1
        assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.yaml"]


@pytest.mark.parametrize("up, words, point", [
    ({"expr": ["0", "0", "u - 0.3"]}, "is zero", "[3.0, 0.0, 0.0]"),
    ({"expr": ["1", "0", "0.3 - u"]}, "collinear", "[3.0, 0.0, 0.0]"),
    ({"keyframes": [[0, [0, 1, 1]], [0.7, [1, 0, 0]], [1, [0, 1, 0]]]}, "collinear",
     "[7.0, 0.0, 0.0]"),
    ({"trajectory": [{"line": {"from": [3, 0, 0], "to": [13, 0, 0]}}]}, "collinear",
     "[0.0, 0.0, 0.0]"),
])
def test_other_bad_ups(tmp_path, up, words, point):
    with pytest.raises(SpecError, match=words) as exc:
        make_spec(tmp_path, {"fields": {"opacity": 1}, "up": up,
                             "trajectory": [{"line": {"from": [0, 0, 0], "to": [10, 0, 0]}}]})
    assert f"(point {point})" in str(exc.value)


def test_up_given_per_segment_and_default_elsewhere(tmp_path):
    spec = make_spec(tmp_path, {
        "fields": {"opacity": 1}, "scale": [2, 2],
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [5, 0, 0], "up": [0, 1, 1]}},
                       {"line": {"from": [5, 0, 0], "to": [5, 0, 5]}}]})
    sw = spec.sweeps()[0]
    a = sw.frames(0, np.array([1.0]))
    b = sw.frames(1, np.array([0.0, 1.0]))
    assert np.allclose(a.EY, np.array([0, 1, 1]) / np.sqrt(2))
    # the second (vertical) line continues the first one's end frame, turned by the least
    # rotation from x to z: a quarter turn about -y, which keeps the y components
    assert np.allclose(b.EY, np.array([-1, 1, 0]) / np.sqrt(2))
    assert np.allclose(b.EX, np.array([1, 1, 0]) / np.sqrt(2))


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*[st.integers(-6, 6)] * 3), min_size=2, max_size=9, unique=True),
       st.integers(2, 40))
def test_dense_parameters_are_numpys_unique_of_the_samples_and_breaks(vertices, n):
    """Evenly spaced parameters and a polyline's vertices (some on a sample: equal steps),
    sorted, each once: np.unique's answer (which the sweep no longer calls)."""
    seg = Polyline(points=np.array(vertices, dtype=np.float64))
    want = np.unique(np.concatenate([np.linspace(0.0, 1.0, n), seg.breaks()]))
    got = seg.dense_parameters(n)
    assert got.dtype == want.dtype and np.array_equal(got, want)
