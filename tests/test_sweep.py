"""`volwarp sweep`: analytic volumes, direct vs voxelised, CVG algebra, volume templates."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from volwarp_cli.io import write_volume
from volwarp_cli.io.images import write_image
from volwarp_cli.spec.loader import load_schema, parse_spec_text, validate
from volwarp_cli.sweep import cvg, evaluate
from volwarp_cli.sweep.model import fit_grid, parse_sweep_spec
from volwarp_cli.volume import Volume


def disc_image(n=128):
    """A binary disc filling the template square's inscribed circle."""
    c = (np.arange(n) + 0.5) / n - 0.5
    x, y = np.meshgrid(c, c)
    return (np.hypot(x, y) <= 0.5).astype(np.float32)


def make_spec(tmp_path, body: dict, name="spec.yaml"):
    body = {"version": 1, **body}
    path = tmp_path / name
    path.write_text(yaml.safe_dump(body, sort_keys=False))
    doc = parse_spec_text(path.read_text(), str(path), tmp_path)
    validate(doc, load_schema("sweep"))
    return parse_sweep_spec(doc)


def fields_of(spec, method=None, tau=None):
    lo, hi = spec.bounds()
    grid = fit_grid(spec.grid, lo, hi)
    return evaluate(spec, grid, method=method, tau=tau), grid


@pytest.fixture
def disc(tmp_path):
    write_image(tmp_path / "disc.png", disc_image()[:, :, None])
    return "disc.png"


# -- analytic volumes ------------------------------------------------------------------
def test_disc_along_line_is_a_cylinder(tmp_path, disc):
    r, L = 4.0, 20.0
    spec = make_spec(tmp_path, {
        "grid": {"origin": [0, -6, -6], "spacing": 0.5, "shape": [50, 25, 25]},
        "fields": {"opacity": {"image": disc}},
        "trajectory": [{"line": {"from": [2.25, 0.1, -0.05], "to": [2.25 + L, 0.1, -0.05]}}],
        "up": [0, 0, 1], "scale": [2 * r, 2 * r]})
    f, grid = fields_of(spec)
    vol = f["opacity"].sum(dtype=np.float64) * np.prod(grid.spacing)
    assert vol == pytest.approx(np.pi * r * r * L, rel=0.02)
    # the cross-section is a disc of radius r: a voxel 3.5 from the axis is inside, 4.5 outside
    o = f["opacity"]
    iy0 = int(round((0.1 - grid.origin[1]) / 0.5))
    iz0 = int(round((-0.05 - grid.origin[2]) / 0.5))
    assert o[iz0, iy0 + 7, 20] == pytest.approx(1.0) and o[iz0, iy0 + 9, 20] == 0.0


def test_rectangle_about_axis_obeys_pappus(tmp_path):
    # h is a whole number of voxels and the slab's faces lie between voxel centres
    # (an axis-aligned slab's sampled thickness is quantised; the annulus's is not)
    R, w, h = 7.3, 3.1, 5.0
    spec = make_spec(tmp_path, {
        "grid": {"origin": [-9.6, -9.6, -4.125], "spacing": 0.25, "shape": [78, 78, 34]},
        "fields": {"opacity": 1},
        "trajectory": [{"arc": {"center": [0.11, -0.07, 0], "radius": R, "axis": [0, 0, 1]}}],
        "up": [0, 0, 1], "scale": [w, h]})
    f, grid = fields_of(spec)
    vol = np.count_nonzero(f["opacity"] > 0.5) * np.prod(grid.spacing)
    assert vol == pytest.approx(2 * np.pi * R * w * h, rel=0.02)


def test_tilted_arc_pappus_with_direct_evaluation(tmp_path):
    R, w, h = 6.2, 2.9, 3.7
    spec = make_spec(tmp_path, {
        "grid": {"spacing": 0.4},
        "fields": {"opacity": 1},
        "trajectory": [{"arc": {"center": [0, 0, 0], "radius": R, "axis": [1, 1, 2]}}],
        "up": [1, 1, 2], "scale": [w, h], "method": "direct"})
    f, grid = fields_of(spec)
    vol = np.count_nonzero(f["opacity"] > 0.5) * np.prod(grid.spacing)
    assert vol == pytest.approx(2 * np.pi * R * w * h, rel=0.02)


def test_linearly_growing_scale_gives_a_frustum(tmp_path, disc):
    r0, r1, L = 1.5, 5.0, 18.0
    spec = make_spec(tmp_path, {
        "grid": {"origin": [-1, -6, -6], "spacing": 0.4, "shape": [52, 31, 31]},
        "fields": {"opacity": {"image": disc}},
        "trajectory": [{"line": {"from": [0.1, 0, 0], "to": [0.1 + L, 0, 0]}}],
        "up": [0, 0, 1],
        "scale": {"keyframes": [[0, [2 * r0, 2 * r0]], [1, [2 * r1, 2 * r1]]]}})
    f, grid = fields_of(spec)
    vol = f["opacity"].sum(dtype=np.float64) * np.prod(grid.spacing)
    assert vol == pytest.approx(np.pi * L * (r0 * r0 + r0 * r1 + r1 * r1) / 3, rel=0.02)


def test_expression_scale_gives_a_cone(tmp_path, disc):
    L = 16.0
    spec = make_spec(tmp_path, {
        "grid": {"spacing": 0.35},
        "fields": {"opacity": {"image": disc}},
        # tilted, so that the base is not a grid plane (whose sampled thickness is quantised)
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [3, 4, float(np.sqrt(L * L - 25))]}}],
        "up": [0, 1, 0], "scale": {"expr": "8 * (1 - u) + 0.0001"}})
    f, grid = fields_of(spec)
    vol = f["opacity"].sum(dtype=np.float64) * np.prod(grid.spacing)
    assert vol == pytest.approx(np.pi * 16 * L / 3, rel=0.02)


# -- direct evaluation vs voxelisation ----------------------------------------------------
def _agree(a, b, frac=0.02):
    diff = np.abs(a - b)
    nonzero = np.count_nonzero((a > 0) | (b > 0))
    assert abs(a.sum() - b.sum()) / a.sum() < 0.01
    assert np.count_nonzero(diff > 0.25) < frac * nonzero


def test_direct_equals_voxelised_for_rotational_sweep(tmp_path, disc):
    spec = make_spec(tmp_path, {
        "grid": {"spacing": 0.3},
        "fields": {"opacity": {"image": disc}, "height": {"image": "ramp.png"}},
        "trajectory": [{"arc": {"center": [0, 0, 0], "radius": 5, "axis": [0, 0, 1],
                                "start": 20, "end": 300}}],
        "up": [0, 0, 1], "scale": [4, 6]})
    f1, _ = fields_of(spec)
    f2, _ = fields_of(spec, method="direct")
    _agree(f1["opacity"], f2["opacity"])
    both = (f1["opacity"] > 0.9) & (f2["opacity"] > 0.9)
    assert np.abs(f1["height"] - f2["height"])[both].max() < 0.05


@pytest.fixture(autouse=True)
def ramp(tmp_path):
    ramp = np.tile(np.linspace(1, 0, 64, dtype=np.float32)[:, None], (1, 64))
    write_image(tmp_path / "ramp.png", (ramp * 65535).astype(np.uint16)[:, :, None])


@pytest.mark.parametrize("up", [[0, 0, 1], "binormal"])
def test_direct_equals_voxelised_for_bezier_sweep(tmp_path, disc, up):
    spec = make_spec(tmp_path, {
        "grid": {"spacing": 0.4},
        "fields": {"opacity": {"image": disc}, "height": {"image": "ramp.png"}},
        "trajectory": [{"bezier": {"points": [[0, 0, 0], [10, 14, 0], [20, -8, 3], [28, 0, 6]]}}],
        "up": up, "scale": {"keyframes": [[0, 3], [1, 5]]}})
    f1, _ = fields_of(spec)
    f2, _ = fields_of(spec, method="direct")
    _agree(f1["opacity"], f2["opacity"])
    both = (f1["opacity"] > 0.9) & (f2["opacity"] > 0.9)
    assert np.abs(f1["height"] - f2["height"])[both].mean() < 0.02


def test_direct_rejects_what_it_cannot_invert(tmp_path, run):
    (tmp_path / "s.yaml").write_text(
        "version: 1\nmethod: direct\nfields: {opacity: 1}\n"
        "trajectory:\n  - polyline: {points: [[0, 0, 0], [5, 0, 0], [5, 5, 0]]}\n")
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o.nrrd")
    assert res.code == 2 and "trajectory[0].polyline" in res.stderr and "voxelize" in res.stderr


def test_tau_with_the_direct_method_is_refused_not_ignored(tmp_path, run):
    """--tau spaces the voxelize method's templates; with --method direct it was taken and
    ignored (outputs for tau 0.15, 2 and 5 byte-identical, exit 0)."""
    (tmp_path / "s.yaml").write_text(
        "version: 1\nfields: {opacity: 1}\n"
        "trajectory:\n  - line: {from: [0, 0, 0], to: [6, 0, 0]}\n")
    for spec_method, given in ((False, ["--method", "direct"]), (True, [])):
        if spec_method:
            (tmp_path / "s.yaml").write_text("method: direct\n" + (tmp_path / "s.yaml").read_text())
        res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o.nrrd", "--tau", "2", *given)
        assert res.code == 2 and "--tau" in res.stderr and "direct" in res.stderr, res.stderr
        assert not (tmp_path / "o.nrrd").exists()
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o.nrrd", "--tau", "2",
              "--method", "voxelize")
    assert res.code == 0, res.stderr


# -- subdivision: no holes, no double counting ----------------------------------------------
@pytest.mark.parametrize("segment", [
    {"line": {"from": [0, 0, 0], "to": [12, 3, 1]}},
    {"arc": {"center": [0, 0, 0], "radius": 1.0, "axis": [0, 0, 1], "start": 0, "end": 270}},
    {"bezier": {"points": [[0, 0, 0], [5, 6, 0], [9, -6, 0], [14, 0, 1]]}},
])
def test_sum_within_one_segment_never_double_counts(tmp_path, segment):
    # the arc's template (4 wide) crosses its axis (radius 1): split regions
    spec = make_spec(tmp_path, {
        "grid": {"spacing": 0.25},
        "fields": {"opacity": 0.4},
        "trajectory": [segment], "up": [0, 0, 1], "scale": [4, 2], "combine": "sum"})
    o, _ = fields_of(spec)
    values = set(np.unique(np.round(o["opacity"].astype(np.float64), 5)).tolist())
    if "arc" in segment:  # where the template sweeps back over itself: two instances
        assert values <= {0.0, 0.4, 0.8}
        assert np.count_nonzero(np.isclose(o["opacity"], 0.8)) > 0
    else:
        assert values <= {0.0, 0.4}


def _arc(start, end):
    return {"arc": {"center": [0, 0, 0], "radius": 5, "axis": [0, 0, 1],
                    "start": start, "end": end}}


@pytest.mark.parametrize("method", ["voxelize", "direct"])
@pytest.mark.parametrize("trajectory", [
    [{"line": {"from": [0, 0, 0], "to": [5, 0, 0]}},
     {"line": {"from": [5, 0, 0], "to": [12, 0, 0]}}],
    [_arc(0, 360)],  # a full turn meets its own start
    [_arc(0, 180), _arc(180, 360)],  # two halves: a joint and the loop's closure
], ids=["two-lines", "full-arc", "two-half-arcs"])
def test_a_template_where_segments_join_is_one_instance(tmp_path, method, trajectory):
    # The plane where one segment ends and the next begins (or a closed trajectory
    # meets its start) was met as two instances: "difference" emptied it, "sum"
    # doubled it. Nothing else here overlaps, so every operator must give union's field.
    def opacity(op):
        spec = make_spec(tmp_path, {
            "grid": {"spacing": 0.5, "margin": 1.0}, "fields": {"opacity": 0.4},
            "trajectory": trajectory, "up": [0, 0, 1], "scale": [2, 2], "combine": op},
            name=f"{op}.yaml")
        return fields_of(spec, method=method)[0]["opacity"]

    union = opacity("union")
    assert set(np.unique(np.round(union.astype(np.float64), 5)).tolist()) == {0.0, 0.4}
    for op in ("sum", "difference"):
        np.testing.assert_array_equal(opacity(op), union, err_msg=op)


@pytest.mark.parametrize("method", ["voxelize", "direct"])
def test_a_path_that_turns_back_meets_its_end_planes_twice(tmp_path, method):
    # Out and back under a constant direction: the same frames where the segments meet,
    # but the path crosses the plane back the way it came: two instances there, as
    # everywhere between (a review found lone 0.4 sheets left by "difference").
    def opacity(op):
        spec = make_spec(tmp_path, {
            "grid": {"spacing": 0.5, "margin": 1.0}, "fields": {"opacity": 0.4},
            "trajectory": [{"line": {"from": [0, 0, 0], "to": [5, 0, 0]}},
                           {"line": {"from": [5, 0, 0], "to": [0, 0, 0]}}],
            "direction": [1, 0, 0], "up": [0, 0, 1], "scale": [2, 2], "combine": op},
            name=f"{op}.yaml")
        return fields_of(spec, method=method)[0]["opacity"]

    total = opacity("sum")
    assert set(np.unique(np.round(total.astype(np.float64), 5)).tolist()) == {0.0, 0.8}
    assert not np.any(opacity("difference"))


def test_split_region_has_no_holes(tmp_path):
    # template 6 wide on an arc of radius 1: the inner part sweeps across the axis;
    # a full turn of it covers a solid disc of radius 1 + 3 (the hole would be at the centre)
    spec = make_spec(tmp_path, {
        "grid": {"origin": [-5, -5, -0.5], "spacing": 0.25, "shape": [41, 41, 5]},
        "fields": {"opacity": 1},
        "trajectory": [{"arc": {"center": [0, 0, 0], "radius": 1.0, "axis": [0, 0, 1]}}],
        "up": [0, 0, 1], "scale": [6, 1.5]})
    o = fields_of(spec)[0]["opacity"][2]
    y, x = np.mgrid[-5:5.01:0.25, -5:5.01:0.25]
    r = np.hypot(x, y)
    assert np.all(o[r < 3.9] == 1.0) and np.all(o[r > 4.1] == 0.0)


def test_polyline_corner_is_closed_by_a_joint(tmp_path):
    spec = make_spec(tmp_path, {
        "grid": {"origin": [-4, -4, -1], "spacing": 0.25, "shape": [57, 57, 9]},
        "fields": {"opacity": 1},
        "trajectory": [{"polyline": {"points": [[0, 0, 0], [8, 0, 0], [8, 8, 0]]}}],
        "up": [0, 0, 1], "scale": [4, 1]})
    o = fields_of(spec)[0]["opacity"][4]
    # the outer corner square [8, 10] x [-2, 0] is swept by the turning template
    # up to the quarter disc of radius 2 about the vertex
    j, i = np.mgrid[0:57, 0:57]
    x, y = -4 + 0.25 * i, -4 + 0.25 * j
    corner = (x > 8) & (y < 0) & (np.hypot(x - 8, y) < 1.9)
    assert np.all(o[corner] == 1.0)


# -- CVG operators ----------------------------------------------------------------------------
@pytest.fixture
def two_sweeps(tmp_path, disc):
    body = {"grid": {"origin": [-8, -8, -4], "spacing": 0.5, "shape": [33, 33, 17]},
            "fields": {"opacity": {"image": disc}, "red": {"image": "ramp.png"}},
            "up": [0, 0, 1], "scale": [6, 6]}
    a = make_spec(tmp_path, {**body, "trajectory": [{"line": {"from": [-7, 0, 0], "to": [7, 0, 0]}}]},
                  "a.yaml")
    b = make_spec(tmp_path, {**body, "trajectory": [{"line": {"from": [0, -7, 0], "to": [0, 7, 0]}}],
                             "up": [1, 0, 1]}, "b.yaml")
    return fields_of(a)[0], fields_of(b)[0]


def test_cvg_algebra_on_overlapping_sweeps(two_sweeps):
    fa, fb = two_sweeps
    a, b = fa["opacity"], fb["opacity"]
    assert np.any((a > 0.5) & (b > 0.5))  # they overlap
    assert np.array_equal(cvg.union(a, b), np.maximum(a, b))
    assert np.array_equal(cvg.union(a, b), cvg.union(b, a))
    assert np.array_equal(cvg.intersection(a, b), cvg.intersection(b, a))
    assert np.array_equal(cvg.intersection(a, b), np.minimum(a, b))
    assert not np.any(cvg.difference(a, a))
    assert np.all(cvg.difference(a, b) <= a) and np.all(cvg.difference(a, b) >= 0)
    assert np.allclose(cvg.blend(a, a, a, a), a)
    assert np.allclose(cvg.blend(fa["red"], fb["red"], a, b), cvg.blend(fb["red"], fa["red"], b, a))
    s = cvg.sum_clamped(a, b)
    assert s.max() <= 1 and np.allclose(s, np.minimum(a + b, 1))
    # union/intersection absorb: a u (a n b) = a
    assert np.array_equal(cvg.union(a, cvg.intersection(a, b)), a)
    # blend is the opacity-weighted mean: where only a is present it is a's value
    only_a = (a > 0.5) & (b == 0)
    assert np.allclose(cvg.blend(fa["red"], fb["red"], a, b)[only_a], fa["red"][only_a], atol=1e-4)


def test_scene_operator_tree(tmp_path, disc):
    line = {"fields": {"opacity": {"image": disc}}, "up": [0, 0, 1], "scale": [6, 6],
            "trajectory": [{"line": {"from": [-7, 0, 0], "to": [7, 0, 0]}}]}
    cross = {**line, "trajectory": [{"line": {"from": [0, -7, 0], "to": [0, 7, 0]}}]}
    grid = {"origin": [-8, -8, -4], "spacing": 0.5, "shape": [33, 33, 17]}

    def scene(op, first, second):
        return fields_of(make_spec(tmp_path, {"grid": grid, "scene": {
            "op": op, "of": [{"sweep": first}, {"sweep": second}]}}))[0]["opacity"]

    a = fields_of(make_spec(tmp_path, {"grid": grid, **line}))[0]["opacity"]
    b = fields_of(make_spec(tmp_path, {"grid": grid, **cross}))[0]["opacity"]
    assert np.array_equal(scene("union", line, cross), np.maximum(a, b))
    assert np.array_equal(scene("union", line, cross), scene("union", cross, line))
    assert np.array_equal(scene("intersection", line, cross), np.minimum(a, b))
    assert not np.any(scene("difference", line, line))
    assert np.allclose(scene("difference", line, cross), np.maximum(a - b, 0))


def test_self_intersection_combines_with_the_chosen_operator(tmp_path):
    base = {"grid": {"origin": [-6, -6, -2], "spacing": 0.5, "shape": [25, 25, 9]},
            "fields": {"opacity": 0.5},
            "trajectory": [{"line": {"from": [-5, 0, 0], "to": [5, 0, 0]}},
                           {"line": {"from": [0, -5, 0], "to": [0, 5, 0]}}],
            "up": [0, 0, 1], "scale": [2, 2]}
    union = fields_of(make_spec(tmp_path, {**base, "combine": "union"}))[0]["opacity"]
    total = fields_of(make_spec(tmp_path, {**base, "combine": "sum"}))[0]["opacity"]
    diff = fields_of(make_spec(tmp_path, {**base, "combine": "difference"}))[0]["opacity"]
    centre = (4, 12, 12)
    assert union[centre] == 0.5 and total[centre] == 1.0 and diff[centre] == 0.0
    assert set(np.unique(union)) == {0.0, 0.5}
    arm = (4, 12, 3)
    assert union[arm] == total[arm] == diff[arm] == 0.5


# -- volume templates -------------------------------------------------------------------------
@pytest.mark.parametrize("path_expr, f", [("9 * u", lambda u: 9 * u),
                                          ("9 * u * u", lambda u: 9 * u * u)])
def test_volume_template_slice_follows_path_function(tmp_path, path_expr, f):
    stack = np.repeat(np.arange(10, dtype=np.float32)[:, None, None], 8, axis=1)
    stack = np.repeat(stack, 8, axis=2)  # slice k is the constant image k
    write_volume(Volume(stack), tmp_path / "stack.nrrd")
    x0, L = 0.25, 20.0
    spec = make_spec(tmp_path, {
        "grid": {"origin": [0, -2, -2], "spacing": 0.5, "shape": [42, 9, 9]},
        "fields": {"opacity": 1, "flame": {"frames": "stack.nrrd", "path": {"expr": path_expr}}},
        "trajectory": [{"line": {"from": [x0, 0, 0], "to": [x0 + L, 0, 0]}}],
        "up": [0, 0, 1], "scale": [2, 2]})
    fl = fields_of(spec)[0]["flame"][4, 4]
    xs = 0.5 * np.arange(42)
    inside = (xs >= x0) & (xs <= x0 + L)
    u = (xs[inside] - x0) / L
    assert np.allclose(fl[inside], f(u), atol=0.05)
    assert np.all(np.diff(fl[inside]) >= -1e-6)  # increases along the path


def test_image_sequence_template_by_glob(tmp_path):
    for k in range(5):
        write_image(tmp_path / f"f_{k}.tif", np.full((4, 4, 1), float(k), dtype=np.float32))
    spec = make_spec(tmp_path, {
        "grid": {"origin": [0, -2, -2], "spacing": 0.5, "shape": [21, 9, 9]},
        "fields": {"v": {"frames": "f_*.tif"}},
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [10, 0, 0]}}],
        "up": [0, 0, 1], "scale": [2, 2]})
    v = fields_of(spec)[0]["v"][4, 4]
    assert np.allclose(v, 4 * np.arange(21) / 20, atol=1e-4)  # default f: first to last frame


def test_template_orientation(tmp_path):
    # a template whose top-left quadrant is 1: with up +z and direction +x,
    # template x runs along +y (ex = ey x ez = z x x), template y along +z: seen
    # from ahead of the sweep, looking back at it, the picture is not mirrored
    img = np.zeros((8, 8, 1), dtype=np.float32)
    img[:4, :4] = 1
    write_image(tmp_path / "q.tif", img)
    spec = make_spec(tmp_path, {
        "grid": {"origin": [0, -2, -2], "spacing": 0.5, "shape": [5, 9, 9]},
        "fields": {"v": {"image": "q.tif"}},
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [2, 0, 0]}}],
        "up": [0, 0, 1], "scale": [4, 4]})
    v = fields_of(spec)[0]["v"][:, :, 2]  # [z, y]
    assert v[7, 1] == 1.0 and v[1, 7] == 0.0 and v[7, 7] == 0.0 and v[1, 1] == 0.0


# -- sweeping functions ------------------------------------------------------------------------
def test_secondary_trajectories_for_direction_and_up(tmp_path, disc):
    # a_d(u) = a(u) + (1, 0, 0) and a_u(u) = a(u) + (0, 0, 1) give the tangent and [0, 0, 1]
    # of a line along x: the same sweep as the defaults
    base = {"grid": {"origin": [-1, -4, -4], "spacing": 0.5, "shape": [27, 17, 17]},
            "fields": {"opacity": {"image": disc}, "height": {"image": "ramp.png"}},
            "trajectory": [{"line": {"from": [0, 0, 0], "to": [11, 0, 0]}}], "scale": [6, 6]}
    ref = fields_of(make_spec(tmp_path, {**base, "up": [0, 0, 1]}))[0]
    sec = fields_of(make_spec(tmp_path, {
        **base,
        "direction": {"trajectory": [{"line": {"from": [1, 0, 0], "to": [12, 0, 0]}}]},
        "up": {"trajectory": [{"line": {"from": [0, 0, 1], "to": [11, 0, 1]}}]}}))[0]
    for name in ref:
        assert np.allclose(ref[name], sec[name], atol=1e-5)


def test_secondary_direction_tilts_the_templates(tmp_path):
    # direction (1, 0, 1) along a line on x: the planes are tilted 45 degrees, so a slab of
    # opacity appears whose faces are planes x + z = const
    spec = make_spec(tmp_path, {
        "grid": {"origin": [-6, -3, -6], "spacing": 0.25, "shape": [73, 25, 49]},
        "fields": {"opacity": 1},
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [6, 0, 0]}}],
        "direction": {"trajectory": [{"line": {"from": [1, 0, 1], "to": [7, 0, 1]}}]},
        "up": [0, 1, 0], "scale": [4, 2]})
    o = fields_of(spec)[0]["opacity"]
    k, j, i = np.nonzero(o)
    x, z = -6 + 0.25 * i, -6 + 0.25 * k
    s = (x + z) / np.sqrt(2)  # distance along the direction
    assert s.min() >= -0.01 and s.max() <= 6 / np.sqrt(2) + 0.01


def test_per_segment_overrides(tmp_path):
    spec = make_spec(tmp_path, {
        "grid": {"origin": [-2, -3, -3], "spacing": 0.5, "shape": [29, 13, 13]},
        "fields": {"opacity": 1},
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [6, 0, 0]}},
                       {"line": {"from": [6, 0, 0], "to": [12, 0, 0], "scale": [2, 2]}}],
        "up": [0, 0, 1], "scale": [4, 4]})
    o = fields_of(spec)[0]["opacity"]
    area = np.count_nonzero(o, axis=(0, 1))  # per x slice
    assert area[10] > 2 * area[22] > 0  # [4, 4] before x = 6, [2, 2] after


def test_arc_beyond_a_full_turn_is_two_instances(tmp_path):
    spec = make_spec(tmp_path, {
        "grid": {"spacing": 0.4},
        "fields": {"opacity": 0.3},
        "trajectory": [{"arc": {"center": [0, 0, 0], "radius": 5, "axis": [0, 0, 1],
                                "start": 0, "end": 450}}],
        "up": [0, 0, 1], "scale": [2, 2], "combine": "sum"})
    for method in ("voxelize", "direct"):
        o = fields_of(spec, method=method)[0]["opacity"]
        v = np.round(o[o > 0].astype(np.float64), 4)
        # the first quarter (0..90 degrees) is swept twice
        frac2 = np.count_nonzero(v == 0.6) / v.size
        assert set(np.unique(v)) <= {0.3, 0.6} and 0.22 < frac2 < 0.28  # 90 of 360 degrees


def test_first_operator_keeps_the_first_instance(tmp_path):
    body = {"grid": {"origin": [-6, -6, -2], "spacing": 0.5, "shape": [25, 25, 9]},
            "fields": {"opacity": 1, "tag": {"frames": "tags.nrrd"}},
            "trajectory": [{"line": {"from": [-5, 0, 0], "to": [5, 0, 0]}},
                           {"line": {"from": [0, -5, 0], "to": [0, 5, 0]}}],
            "up": [0, 0, 1], "scale": [2, 2], "combine": {"tag": "first"}}
    write_volume(Volume(np.full((2, 2, 2), 7.0, dtype=np.float32)), tmp_path / "tags.nrrd")
    tag = fields_of(make_spec(tmp_path, body))[0]["tag"]
    assert tag[4, 12, 12] == 7.0


def test_bezier_with_a_vanishing_end_derivative(tmp_path, disc):
    # the first two control points coincide: a'(0) = 0, the tangent is the chord's limit
    spec = make_spec(tmp_path, {
        "grid": {"spacing": 0.4},
        "fields": {"opacity": {"image": disc}},
        "trajectory": [{"bezier": {"points": [[0, 0, 0], [0, 0, 0], [10, 8, 0], [16, 0, 2]]}}],
        "up": [0, 0, 1], "scale": [3, 3]})
    _agree(fields_of(spec)[0]["opacity"], fields_of(spec, method="direct")[0]["opacity"])


def test_multipage_tiff_volume_template(tmp_path):
    import tifffile

    stack = (np.arange(4, dtype=np.uint8)[:, None, None] * 10 + np.zeros((4, 6, 6), np.uint8))
    tifffile.imwrite(tmp_path / "stack.tif", stack, photometric="minisblack")
    spec = make_spec(tmp_path, {
        "grid": {"origin": [0, -2, -2], "spacing": 0.5, "shape": [13, 9, 9]},
        "fields": {"v": {"frames": "stack.tif", "path": {"keyframes": [[0, 3], [1, 0]]}}},
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [6, 0, 0]}}],
        "up": [0, 0, 1], "scale": [2, 2]})
    v = fields_of(spec)[0]["v"][4, 4]
    # frames 3 -> 0, scaled as the same frames as image files are (255 -> 1.0)
    assert np.allclose(v, (30 - 30 * np.arange(13) / 12) / 255, atol=1e-5)


def test_one_stack_three_ways_is_one_template(tmp_path):
    """The same frames as PNG files, as one uint8 TIFF stack and as one uint16 NRRD give the
    same field: the stack's samples were kept raw (255 where the PNGs gave 1.0: a "volume"
    255 times too large, and --dtype uint8 clipped everything)."""
    import tifffile

    frames = np.zeros((3, 8, 8), np.uint8)
    frames[:, 2:6, 2:6] = [[[40]], [[255]], [[128]]]
    for k, frame in enumerate(frames):
        write_image(tmp_path / f"p_{k}.png", frame[:, :, None])
    tifffile.imwrite(tmp_path / "stack.tif", frames, photometric="minisblack")
    write_volume(Volume(frames.astype(np.uint16) * 257), tmp_path / "stack.nrrd")
    got = []
    for frames_spec in ("p_*.png", "stack.tif", "stack.nrrd"):
        spec = make_spec(tmp_path, {
            "grid": {"origin": [0, -2, -2], "spacing": 0.5, "shape": [13, 9, 9]},
            "fields": {"v": {"frames": frames_spec}},
            "trajectory": [{"line": {"from": [0, 0, 0], "to": [6, 0, 0]}}],
            "up": [0, 0, 1], "scale": [2, 2]})
        got.append(fields_of(spec)[0]["v"])
    assert 0.99 < got[0].max() <= 1.0
    np.testing.assert_allclose(got[1], got[0], atol=1e-6)
    np.testing.assert_allclose(got[2], got[0], atol=1e-6)


def test_a_frame_glob_is_in_natural_order(tmp_path):
    """f_1 ... f_12 unpadded: the glob's frames were in string order (f_1, f_10, f_11, f_12,
    f_2, ...), so the second frame was f_10 and the stack played out of order."""
    for k in range(1, 13):
        write_image(tmp_path / f"f_{k}.tif", np.full((4, 4, 1), float(k), dtype=np.float32))
    spec = make_spec(tmp_path, {
        "grid": {"origin": [0, -2, -2], "spacing": 0.5, "shape": [23, 9, 9]},
        "fields": {"v": {"frames": "f_*.tif"}},
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [11, 0, 0]}}],
        "up": [0, 0, 1], "scale": [2, 2]})
    v = fields_of(spec)[0]["v"][4, 4]
    assert np.allclose(v, 1 + np.arange(23) / 2, atol=1e-4)  # frame k+1 at x = k


def test_natural_order_takes_decimals_and_breaks_ties_by_name():
    """t_0.25 before t_0.5 (digit runs alone put it after: 25 > 5, where plain sorting had
    them right); f_01 and f_1, equal numbers, by name, never by the folder's listing."""
    import random

    from volwarp_cli.sweep.templates import natural_order

    want = ["f_01.png", "f_1.png", "f_2.png", "f_10.png", "t_0.0.png", "t_0.25.png",
            "t_0.5.png", "t_0.75.png", "t_1.0.png", "t_10.png"]
    for seed in range(5):
        names = want[:]
        random.Random(seed).shuffle(names)
        assert sorted(names, key=natural_order) == want


def test_cvg_operator_algebra_on_random_fields():
    from hypothesis import given, settings
    from hypothesis import strategies as st
    from hypothesis.extra.numpy import arrays

    unit = arrays(np.float32, 16, elements=st.floats(0, 1, width=32))

    @settings(max_examples=60, deadline=None)
    @given(unit, unit, unit)
    def check(a, b, c):
        assert np.array_equal(cvg.union(a, b), cvg.union(b, a))
        assert np.array_equal(cvg.union(cvg.union(a, b), c), cvg.union(a, cvg.union(b, c)))
        assert np.array_equal(cvg.intersection(a, cvg.union(a, b)), a)
        assert not np.any(cvg.difference(a, a))
        assert np.all(cvg.difference(a, b) <= a)
        assert np.allclose(cvg.sum_clamped(a, b), cvg.sum_clamped(b, a))
        m = cvg.blend(a, b, c, c)
        assert np.all(m >= np.minimum(a, b) - 1e-6) and np.all(m <= np.maximum(a, b) + 1e-6)
        assert np.array_equal(cvg.first(a, b), a)

    check()


@pytest.mark.parametrize("method", ["voxelize", "direct"])
def test_anisotropic_grid(tmp_path, method):
    R, w, h = 6.2, 2.9, 3.7
    spec = make_spec(tmp_path, {
        "grid": {"spacing": [0.35, 0.45, 0.3]},
        "fields": {"opacity": 1},
        "trajectory": [{"arc": {"center": [0, 0, 0], "radius": R, "axis": [1, 2, 2]}}],
        "up": [1, 2, 2], "scale": [w, h], "method": method})
    f, grid = fields_of(spec)
    assert np.allclose(grid.spacing, [0.35, 0.45, 0.3])
    vol = np.count_nonzero(f["opacity"] > 0.5) * np.prod(grid.spacing)
    assert vol == pytest.approx(2 * np.pi * R * w * h, rel=0.02)


def test_rgba_template_channels_are_not_premultiplied(tmp_path):
    from volwarp_cli.io.images import read_image

    img = np.zeros((4, 4, 4), dtype=np.float32)
    img[..., 0] = 1.0
    img[..., 3] = 0.25
    write_image(tmp_path / "rgba.png", img)
    got = read_image(tmp_path / "rgba.png")
    assert np.allclose(got[..., 0], 1.0) and np.allclose(got[..., 3], 64 / 255)


def test_root_finder_matches_companion_eigenvalues():
    from volwarp_cli.sweep.direct import _bezier_candidates, bezier_candidates_eig
    from volwarp_cli.sweep.trajectory import Bezier

    rng = np.random.default_rng(5)
    for n in (2, 3, 5):
        seg = Bezier(points=rng.normal(scale=10, size=(n + 1, 3)))
        p = rng.normal(scale=10, size=(4000, 3))
        a = np.sort(_bezier_candidates(seg, p), axis=1)
        b = np.sort(bezier_candidates_eig(seg, p), axis=1)
        same = np.isfinite(a).sum(1) == np.isfinite(b).sum(1)
        assert same.mean() > 0.999  # (a root grazing 0 or 1 may be counted differently)
        assert np.nanmax(np.abs(a[same] - b[same])) < 1e-6
        # every root found is a root: the point lies in the template plane there
        s = a[np.isfinite(a)]
        assert s.size > 100


def test_a_path_along_its_template_plane_goes_on_at_a_joint(tmp_path):
    # Two arcs meeting where the path runs within the template's plane (a constant
    # direction along x, the tangent along y there): one instance, as the single arc
    # (a review found a sheet left by "difference" when such joints were not joined).
    def opacity(trajectory, op):
        spec = make_spec(tmp_path, {
            "grid": {"origin": [-1, -7, -2], "spacing": 0.5, "shape": [15, 29, 9]},
            "fields": {"opacity": 0.4}, "trajectory": trajectory, "direction": [1, 0, 0],
            "up": [0, 0, 1], "scale": [2, 2], "combine": op}, name=f"{op}{len(trajectory)}.yaml")
        return fields_of(spec)[0]["opacity"]  # (direct: no constant direction on arcs)

    arc = {"center": [0, 0, 0], "radius": 5, "axis": [0, 0, 1]}
    one = [{"arc": {**arc, "start": -90, "end": 90}}]
    two = [{"arc": {**arc, "start": -90, "end": 0}}, {"arc": {**arc, "start": 0, "end": 90}}]
    for op in ("sum", "difference"):
        np.testing.assert_array_equal(opacity(two, op), opacity(one, op), err_msg=op)
