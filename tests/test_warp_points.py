"""`volwarp warp --points-in/--points-to, --mesh-in/--mesh-to`: points moved by the forward map."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

ANG = np.deg2rad(20)
DIRECTION = np.array([[np.cos(ANG), -np.sin(ANG), 0], [np.sin(ANG), np.cos(ANG), 0], [0, 0, 1]])


def ball_volume(n=30):
    z, y, x = np.mgrid[:n, :n, :n].astype(float)
    c = (n - 1) / 2
    r = np.sqrt((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2)
    data = (200.0 / (1.0 + np.exp((r - 8.0) / 1.2))).astype(np.float32)  # smooth ball
    return Volume(data, spacing=(1.0, 1.1, 1.3), origin=(-4.0, 2.0, 7.0), direction=DIRECTION)


@pytest.fixture
def setup(tmp_path):
    vol = ball_volume()
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    a = [float(v) for v in vol.index_to_world([14.5, 14.5, 22.0])]
    b = [float(v) for v in vol.index_to_world([6.0, 14.5, 14.5])]
    ta = [a[0], a[1] + 1.0, a[2] + 4.0]
    tb = [b[0] - 2.0, b[1], b[2]]
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 9}\nsteps:\n  - drag:\n"
                    f"      - {{from: {a}, to: {ta}}}\n      - {{from: {b}, to: {tb}}}\n")
    return vol, src, spec, np.array([a, b]), np.array([ta, tb])


def test_handle_points_land_on_their_targets(run, setup, tmp_path):
    vol, src, spec, froms, tos = setup
    pin = tmp_path / "p.csv"
    rows = ["x,y,z,t,label,comment"] + [f"{float(p[0])!r},{float(p[1])!r},{float(p[2])!r},0,{n + 1},h{n}"
                                        for n, p in enumerate(froms)]
    pin.write_text("\n".join(rows) + "\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--points-in", pin,
              "--points-to", tmp_path / "q.csv", "-v")
    assert res.code == 0, res.stderr
    misses = [float(m) for m in re.findall(r"missed its target by ([0-9.e+-]+) mm", res.stderr)]
    assert len(misses) == 2
    lines = (tmp_path / "q.csv").read_text().splitlines()
    assert lines[0] == "x,y,z,t,label,comment"
    got = np.array([[float(v) for v in ln.split(",")[:3]] for ln in lines[1:]])
    assert [ln.split(",")[3:] for ln in lines[1:]] == [["0", "1", "h0"], ["0", "2", "h1"]]
    err = np.linalg.norm(got - tos, axis=1)
    assert np.all(err <= np.array(misses) + 1e-6), (err, misses)
    assert np.all(np.linalg.norm(got - froms, axis=1) > 1.5)  # they did move


def test_markups_keep_their_coordinate_system(run, setup, tmp_path):
    vol, src, spec, froms, tos = setup
    doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                      "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
           "markups": [{"type": "Fiducial", "coordinateSystem": "RAS",
                        "controlPoints": [{"id": "1", "label": "F-1",
                                           "position": [-froms[0][0], -froms[0][1],
                                                        froms[0][2]]}]},
                       {"type": "Fiducial", "coordinateSystem": "LPS",
                        "controlPoints": [{"id": "2", "label": "F-2",
                                           "position": list(froms[1])}]}]}
    pin = tmp_path / "p.mrk.json"
    pin.write_text(json.dumps(doc))
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--points-in", pin,
              "--points-to", tmp_path / "q.mrk.json")
    assert res.code == 0, res.stderr
    out = json.loads((tmp_path / "q.mrk.json").read_text())
    assert out["markups"][0]["coordinateSystem"] == "RAS"
    assert out["markups"][0]["controlPoints"][0]["label"] == "F-1"
    p0 = np.array(out["markups"][0]["controlPoints"][0]["position"]) * [-1, -1, 1]
    p1 = np.array(out["markups"][1]["controlPoints"][0]["position"])
    assert np.linalg.norm(p0 - tos[0]) < 0.5 and np.linalg.norm(p1 - tos[1]) < 0.5


def test_a_markups_point_without_a_position_is_not_counted_outside(run, setup, tmp_path):
    """A point not placed (Slicer's positionStatus undefined) stays so, and is neither
    moved nor among the points outside the support."""
    vol, src, spec, froms, tos = setup
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "controlPoints": [
        {"id": "1", "label": "a", "position": list(froms[0])},
        {"id": "2", "label": "b", "position": [0.0, 0.0, 0.0], "positionStatus": "undefined"},
        {"id": "3", "label": "c", "position": [1000.0, 1000.0, 1000.0]}]}]}
    pin = tmp_path / "p.mrk.json"
    pin.write_text(json.dumps(doc))
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--points-in", pin,
              "--points-to", tmp_path / "q.mrk.json", "--json")
    assert res.code == 0, res.stderr
    assert "1 of 2 points lie outside the lattice's support" in res.stderr
    assert json.loads(res.stdout)["points"]["outside"] == 1
    a, b, c = json.loads((tmp_path / "q.mrk.json").read_text())["markups"][0]["controlPoints"]
    assert np.linalg.norm(np.array(a["position"]) - tos[0]) < 0.5
    assert b["positionStatus"] == "undefined"
    assert c["position"] == [1000.0, 1000.0, 1000.0]


def test_points_outside_the_support_are_reported_and_left(run, setup, tmp_path):
    vol, src, spec, froms, _ = setup
    far = [1000.0, 1000.0, 1000.0]
    pin = tmp_path / "p.csv"
    pin.write_text(f"label,X,Y,Z\na,{far[0]},{far[1]},{far[2]}\nb,{float(froms[0][0])!r},"
                   f"{float(froms[0][1])!r},{float(froms[0][2])!r}\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--points-in", pin,
              "--points-to", tmp_path / "q.csv", "--json")
    assert res.code == 0, res.stderr
    assert "1 of 2 points lie outside the lattice's support" in res.stderr
    rows = (tmp_path / "q.csv").read_text().splitlines()
    assert rows[1] == "a,1000.0,1000.0,1000.0"
    doc = json.loads(res.stdout)  # the warning on stderr, the one document on stdout
    assert doc["points"] == {"path": str(tmp_path / "q.csv"), "count": 2, "outside": 1}
    assert len(doc["handles"]) == 2


def test_mesh_lies_on_the_warped_isosurface(run, setup, tmp_path):
    from scipy.spatial import cKDTree
    from skimage.measure import marching_cubes

    from volwarp_cli.surface.mesh import Mesh
    from volwarp_cli.surface.mesh_io import read_mesh, write_mesh

    vol, src, spec, _, _ = setup
    level = 100.0

    def iso(v):
        verts, faces, _, _ = marching_cubes(v.data.astype(np.float64), level)
        return Mesh(v.index_to_world(verts[:, ::-1]), faces[:, ::-1])

    write_mesh(iso(vol).with_normals(), tmp_path / "m.ply")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--mesh-in",
              tmp_path / "m.ply", "--mesh-to", tmp_path / "m2.ply", "--json")
    assert res.code == 0, res.stderr
    moved = read_mesh(tmp_path / "m2.ply")
    assert json.loads(res.stdout)["mesh"] == {"path": str(tmp_path / "m2.ply"),
                                              "count": len(moved.vertices), "outside": 0}
    assert moved.normals is not None and moved.n_faces == iso(vol).n_faces
    target = iso(read_volume(tmp_path / "o.nrrd"))
    # densify the reference surface (edge midpoints and centroids) for point-to-surface distances
    tv, tf = target.vertices, target.faces
    ref = np.concatenate([tv, tv[tf].mean(1), (tv[tf[:, 0]] + tv[tf[:, 1]]) / 2,
                          (tv[tf[:, 1]] + tv[tf[:, 2]]) / 2, (tv[tf[:, 2]] + tv[tf[:, 0]]) / 2])
    d, _ = cKDTree(ref).query(moved.vertices)
    voxel = float(np.min(vol.spacing))
    assert d.mean() <= 0.25 * voxel and d.max() <= 1.0 * voxel, (d.mean(), d.max())
    # a non-trivial warp: the unwarped mesh is off
    d0, _ = cKDTree(ref).query(read_mesh(tmp_path / "m.ply").vertices)
    assert d0.max() > 2.0


@pytest.mark.parametrize("content,ext", [("a,b,c\n1,2,3\n", ".csv"),
                                         ("x,y,z\n1,2,oops\n", ".csv"),
                                         ("{\"markups\": 3}", ".mrk.json")])
def test_bad_points_file(run, setup, tmp_path, content, ext):
    _, src, spec, _, _ = setup
    pin = tmp_path / f"p{ext}"
    pin.write_text(content)
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--points-in", pin,
              "--points-to", tmp_path / f"q{ext}", "--displacement-to", tmp_path / "d.nrrd")
    assert res.code == 1
    assert len(res.stderr.strip().splitlines()) == 1 and str(pin) in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["in.nrrd", "w.yaml", pin.name])


def test_bad_mesh_and_usage_errors(run, setup, tmp_path):
    _, src, spec, _, _ = setup
    bad = tmp_path / "m.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--mesh-in", bad,
              "--mesh-to", tmp_path / "m2.ply")
    assert res.code == 1 and len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o.nrrd").exists() and not (tmp_path / "m2.ply").exists()
    for args in (["--mesh-in", bad, "--mesh-to", tmp_path / "m2.xyz"],
                 ["--mesh-in", bad],
                 ["--points-in", bad, "--points-to", tmp_path / "q.csv"]):
        res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", *args)
        assert res.code == 2, (args, res.stderr)
        assert not (tmp_path / "o.nrrd").exists()


def test_a_mirroring_lattice_keeps_the_exported_meshs_faces_outward(run, tmp_path):
    """Every control point moved to its mirror image across x = c: the B-spline map is the
    mirror (an affine lattice reproduces an affine map), which turned a moved mesh inside
    out (its volume negative, every normal inward). The faces are turned back."""
    from volwarp_cli.bspline.lattice import Lattice
    from volwarp_cli.surface.isosurface import isosurface
    from volwarp_cli.surface.mesh_io import read_mesh, write_mesh

    z, y, x = np.mgrid[:20, :22, :24]
    vol = Volume((((x - 9) ** 2 + (y - 11) ** 2 + (z - 10) ** 2) < 25).astype(np.float32))
    write_volume(vol, tmp_path / "in.nrrd")
    mesh = isosurface(vol, 0.5)
    write_mesh(mesh, tmp_path / "m.ply")
    uni = Lattice.create(vol.shape_xyz, (5, 5, 5), 1).uniform_positions()
    moves = [f"      - {{index: [{i}, {j}, {k}], by: [{2 * (11.5 - uni[k, j, i, 0]):.6f}, 0, 0]}}"
             for k in range(5) for j in range(5) for i in range(5)]
    (tmp_path / "mirror.yaml").write_text(
        "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\nsteps:\n  - move:\n"
        + "\n".join(moves) + "\n")
    res = run("warp", tmp_path / "in.nrrd", "--spec", tmp_path / "mirror.yaml", "-o",
              tmp_path / "o.nrrd", "--mesh-in", tmp_path / "m.ply", "--mesh-to",
              tmp_path / "m2.ply", "--values", "intensity")
    assert res.code == 0, res.stderr
    out = read_mesh(tmp_path / "m2.ply")
    assert np.allclose(out.vertices[:, 0], 23.0 - mesh.vertices[:, 0], atol=1e-3)  # mirrored
    assert np.array_equal(out.faces, mesh.faces[:, ::-1])
    v = out.vertices[out.faces]
    assert np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() > 0
    centre = out.vertices.mean(axis=0)
    assert (np.einsum("ij,ij->i", out.normals, out.vertices - centre) > 0).mean() > 0.99


@pytest.mark.parametrize("name, text", [
    ("none.csv", "x,y,z,label\n"),
    ("none.mrk.json", json.dumps({"markups": [{"type": "Fiducial", "coordinateSystem": "LPS",
                                               "controlPoints": []}]}))])
def test_a_points_file_of_no_point_is_written_as_empty(run, setup, tmp_path, name, text):
    """(an internal error after the warp had run: the outside count reshaped no row)"""
    vol, src, spec, _, _ = setup
    pin, out = tmp_path / name, tmp_path / ("q_" + name)
    pin.write_text(text)
    res = run("warp", src, "--spec", spec, "--points-in", pin, "--points-to", out)
    assert res.code == 0, res.stderr
    if name.endswith(".csv"):
        assert out.read_text().splitlines() == ["x,y,z,label"]
    else:
        assert json.loads(out.read_text())["markups"][0]["controlPoints"] == []


def test_a_points_file_naming_a_coordinate_twice_is_refused(run, setup, tmp_path):
    """``x,y,z,x``: the first x was moved and the second passed through unchanged (exit 0)."""
    vol, src, spec, froms, _ = setup
    pin = tmp_path / "p.csv"
    p = froms[0]
    pin.write_text(f"x,y,z,X\n{p[0]!r},{p[1]!r},{p[2]!r},{p[0] + 1!r}\n")
    res = run("warp", src, "--spec", spec, "--points-in", pin, "--points-to", tmp_path / "q.csv")
    assert res.code == 1
    assert "names column 'x' 2 times" in res.stderr
    assert not (tmp_path / "q.csv").exists()



def test_a_large_points_file_is_held_to_the_memory_limit(tmp_path):
    """A points file is read whole, with its rows kept to be written back: a 2M-point CSV
    took ``apply`` to 912 MiB under --memory-limit 100M, charged nothing (a hunt). It is
    charged before it is read: refused at once, nothing written, where it cannot fit; run
    under a limit it fits, its peak below that limit."""
    from peaks import volwarp_peak

    rng = np.random.default_rng(2)
    pts = tmp_path / "p.csv"
    np.savetxt(pts, rng.uniform(-100, 100, (200_000, 3)), fmt="%.3f", delimiter=",",
               header="x,y,z", comments="")
    tfm = tmp_path / "t.tfm"
    tfm.write_text("#Insight Transform File V1.0\n#Transform 0\n"
                   "Transform: TranslationTransform_double_3_3\nParameters: 1 2 3\n"
                   "FixedParameters:\n")
    for limit, fits in (("60M", False), ("200M", True)):
        out = tmp_path / f"q{limit}.csv"
        code, err, peak = volwarp_peak("apply", "-t", tfm, "--points-in", pts, "--points-to",
                                       out, "--memory-limit", limit)
        if fits:
            assert code == 0, err
            moved = np.loadtxt(out, delimiter=",", skiprows=1)
            np.testing.assert_allclose(moved, np.loadtxt(pts, delimiter=",", skiprows=1)
                                       - [1, 2, 3], atol=1e-9)
            assert peak < 200 << 20, peak
        else:
            assert code == 1 and "its points, read with their rows, needs" in err, err
            assert not out.exists() and peak < 60 << 20, peak
