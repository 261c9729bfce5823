"""Anatomical orientation of renders: patient-named views, edge letters, reusable cameras.

The world frame is LPS: +x is the patient's left, +y posterior, +z superior.
"""

from __future__ import annotations

import json

import click
import numpy as np
import pytest
from click.testing import CliRunner

from volwarp_cli.cli.options import core_parser, parse_size
from volwarp_cli.cli.view_options import VIEW_HELP, camera_options, orientation_labels_for
from volwarp_cli.errors import SpecError, VolwarpError
from volwarp_cli.render.camera import (
    Camera,
    CameraError,
    camera_json,
    read_camera,
    write_camera,
)
from volwarp_cli.render.orientation import (
    AXIS_LETTERS,
    direction_letters,
    draw_orientation_labels,
    has_anatomical_frame,
    label_scale,
    screen_letters,
    text_mask,
    view_letters,
)
from volwarp_cli.render.raycast import render_volume
from volwarp_cli.render.surface import (
    NAMED_VIEWS,
    fit_camera,
    parse_view,
    render_mesh,
    render_turntable,
    view_axes,
)
from volwarp_cli.surface.isosurface import isosurface
from volwarp_cli.volume import Volume

# (left, right, top, bottom) letters of every named view
EXPECTED_LETTERS = {
    "patient-left": ("A", "P", "S", "I"),
    "patient-right": ("P", "A", "S", "I"),
    "anterior": ("R", "L", "S", "I"),
    "posterior": ("L", "R", "S", "I"),
    "superior": ("L", "R", "A", "P"),
    "inferior": ("R", "L", "A", "P"),
    "x": ("A", "P", "S", "I"),
    "right": ("A", "P", "S", "I"),   # from +x: the patient's left side
    "left": ("P", "A", "S", "I"),
    "y": ("L", "R", "S", "I"),
    "back": ("L", "R", "S", "I"),
    "front": ("R", "L", "S", "I"),
    "z": ("R", "L", "P", "A"),
    "top": ("R", "L", "P", "A"),
    "bottom": ("R", "L", "A", "P"),
    "iso": ("LA", "RP", "SRA", "ILP"),
}


def letters_tuple(d):
    return d["left"], d["right"], d["top"], d["bottom"]


# -- letters ---------------------------------------------------------------------------

def test_every_named_view_has_its_letters():
    assert set(EXPECTED_LETTERS) == set(NAMED_VIEWS)
    for view, expected in EXPECTED_LETTERS.items():
        assert letters_tuple(view_letters(view)) == expected, view


def test_patient_views_look_from_where_they_say():
    # the direction of projection (viewer into the scene) of each patient view
    looks = {"patient-left": [-1, 0, 0], "patient-right": [1, 0, 0], "anterior": [0, 1, 0],
             "posterior": [0, -1, 0], "superior": [0, 0, -1], "inferior": [0, 0, 1]}
    for view, dop in looks.items():
        right, up, back = view_axes(view)
        np.testing.assert_allclose(-back, dop, atol=1e-12)
        if view not in ("superior", "inferior"):
            np.testing.assert_allclose(up, [0, 0, 1], atol=1e-12)  # superior up
        else:
            np.testing.assert_allclose(up, [0, -1, 0], atol=1e-12)  # anterior up


@pytest.mark.parametrize("view, expected", [
    ((30.0, 0.0), ("AL", "PR", "S", "I")),      # 30 degrees round from patient-left
    ((20.0, 0.0), ("A", "P", "S", "I")),        # within 22.5 degrees: one letter
    ((-60.0, 0.0), ("RA", "LP", "S", "I")),     # between anterior and patient-left
    ((0.0, 30.0), ("A", "P", "SR", "IL")),      # patient-left, from above
    ((0.0, -30.0), ("A", "P", "SL", "IR")),     # patient-left, from below
    ((-90.0, 60.0), ("R", "L", "PS", "AI")),    # anterior, from high above
    ((45.0, 45.0), ("LA", "RP", "SRA", "ILP")),
])
def test_oblique_views(view, expected):
    assert letters_tuple(view_letters(view)) == expected


def test_screen_letters_from_camera_vectors():
    # VTK style: view up not orthogonal to the projection is made so first
    assert letters_tuple(screen_letters([0, 0.3, 1], [-1, 0, 0])) == ("A", "P", "S", "I")
    assert letters_tuple(screen_letters([0, 0, 2.0], [0, 5.0, 0])) == ("R", "L", "S", "I")
    assert direction_letters([1, 0, 0]) == "L" and direction_letters([0, -1, 0]) == "A"
    assert direction_letters([0, 0, -3]) == "I"
    assert direction_letters([1, 1, 0]) == "LP" and direction_letters([-1, 0.1, 0]) == "R"
    assert direction_letters([0.2, -1, 0.9]) == "AS"
    with pytest.raises(VolwarpError):
        screen_letters([1, 0, 0], [2, 0, 0])  # view up along the projection
    with pytest.raises(VolwarpError):
        direction_letters([0, 0, 0])


def test_letters_of_many_cameras_are_consistent():
    rng = np.random.default_rng(18)
    opposite = {a: b for pos, neg in AXIS_LETTERS for a, b in ((pos, neg), (neg, pos))}
    for _ in range(500):
        dop = rng.normal(size=3)
        up = rng.normal(size=3)
        d = screen_letters(up, dop)
        for a, b in (("left", "right"), ("top", "bottom")):
            assert d[b] == "".join(opposite[c] for c in d[a])
        dn = dop / np.linalg.norm(dop)
        u = up - (up @ dn) * dn
        u /= np.linalg.norm(u)
        r = np.cross(dn, u)
        for edge, v in (("right", r), ("top", u)):
            text = d[edge]
            assert 1 <= len(text) <= 3
            axes = [next(i for i, p in enumerate(AXIS_LETTERS) if c in p) for c in text]
            assert len(set(axes)) == len(axes)  # no axis twice
            i = int(np.argmax(np.abs(v)))
            assert axes[0] == i and text[0] == AXIS_LETTERS[i][0 if v[i] > 0 else 1]
            if len(text) == 1:  # within 22.5 degrees of that axis (nearest cube direction)
                assert abs(v[i]) >= np.cos(np.radians(35.27)) - 1e-9


def test_parse_view_patient_names_and_old_names():
    assert parse_view("patient-left") == parse_view("x") == parse_view("right") == (0.0, 0.0)
    assert parse_view("Patient_Right") == (180.0, 0.0)
    assert parse_view("anterior") == parse_view("front")
    assert parse_view("posterior") == parse_view("back") == parse_view("y")
    assert parse_view("inferior") == parse_view("bottom")
    assert parse_view("superior") == (90.0, 90.0)
    assert parse_view("top") == parse_view("z") == (-90.0, 90.0)
    assert parse_view("iso")[0] == 45.0
    with pytest.raises(VolwarpError, match="patient-left"):
        parse_view("patient-up")
    for name in ("patient-left", "anterior", "superior", "inferior", "AZIMUTH,ELEVATION"):
        assert name in VIEW_HELP
    # the field at fault is named (a NaN azimuth was called a bad elevation; a review)
    for bad, field in (("nan,0", "azimuth"), ("inf,10", "azimuth"), ("1e308,0", "azimuth"),
                       ("0,nan", "elevation"), ("30,91", "elevation")):
        with pytest.raises(VolwarpError, match=f"view {field} must"):
            parse_view(bad)
    assert parse_view("-720,30") == (-720.0, 30.0)


# -- scenes: a body with a marker on one side ------------------------------------------

N = 40
ORIGIN = (-19.5, -19.5, -19.5)  # voxel centres at world -19.5 .. 19.5 mm


def body_and_marker(marker_at=(14.0, 0.0, 0.0), r_marker=4.0):
    """Fields of a ball (radius 10) at the world origin and a marker ball at ``marker_at``."""
    z, y, x = (np.indices((N, N, N)).astype(np.float32) + np.float32(ORIGIN[0]))
    body = 10.0 - np.sqrt(x ** 2 + y ** 2 + z ** 2)
    mx, my, mz = marker_at
    marker = r_marker - np.sqrt((x - mx) ** 2 + (y - my) ** 2 + (z - mz) ** 2)
    return body, marker


def marker_mesh(marker_at=(14.0, 0.0, 0.0)):
    body, marker = body_and_marker(marker_at)
    field = np.maximum(body, marker)
    mesh = isosurface(Volume(field, origin=ORIGIN), 0.0)
    centroid = mesh.vertices[mesh.faces].mean(axis=1)
    near = np.linalg.norm(centroid - np.asarray(marker_at), axis=1) < 4.5
    colors = np.where(near[:, None], [1.0, 0.0, 0.0], [0.6, 0.6, 0.6])
    return mesh, colors


def red_pixels(image):
    im = image.astype(int)
    return (im[:, :, 0] > 120) & (im[:, :, 1] < 0.5 * im[:, :, 0]) & (im[:, :, 2] < 0.5 * im[:, :, 0])


def marker_volume(marker_at=(14.0, 0.0, 0.0)):
    body, marker = body_and_marker(marker_at)
    ob = np.clip(body + 0.5, 0, 1)
    om = np.clip(marker + 0.5, 0, 1)
    opacity = np.maximum(ob, om).astype(np.float32)
    red = np.ones_like(opacity)
    grey = np.where(om > 0, 0.0, 0.6).astype(np.float32)
    return opacity, [red, grey, grey]


def test_patient_left_mesh_view_shows_the_marker_centred():
    mesh, colors = marker_mesh()
    w, h = 120, 100
    left = render_mesh(mesh, view="patient-left", size=(w, h), face_colors=colors)
    red = red_pixels(left)
    assert red.sum() > 200  # a disc of radius 4 mm, seen face on
    ys, xs = np.nonzero(red)
    assert abs(xs.mean() - (w - 1) / 2) < 2 and abs(ys.mean() - (h - 1) / 2) < 2
    right = render_mesh(mesh, view="patient-right", size=(w, h), face_colors=colors)
    assert red_pixels(right).sum() == 0  # hidden behind the body
    assert red_pixels(render_mesh(mesh, view="anterior", size=(w, h),
                                  face_colors=colors)).sum() > 0  # a side view: at the edge


def test_a_marker_front_left_is_on_the_left_from_patient_left():
    # anterior-left (+x, -y): from the patient's left the face is on the picture's left
    mesh, colors = marker_mesh((9.0, -9.0, 0.0))
    w = 120
    xs = np.nonzero(red_pixels(render_mesh(mesh, view="patient-left", size=(w, 100),
                                           face_colors=colors)))[1]
    assert xs.size and xs.mean() < w / 2
    # and from the front the patient's left is on the picture's right
    xs = np.nonzero(red_pixels(render_mesh(mesh, view="anterior", size=(w, 100),
                                           face_colors=colors)))[1]
    assert xs.size and xs.mean() > w / 2


def test_patient_left_ray_cast_shows_the_marker_centred():
    opacity, colour = marker_volume()
    w, h = 64, 64
    kw = dict(colour=colour, spacing=(1, 1, 1), origin=ORIGIN, size=(w, h), shading=False)
    left = render_volume(opacity, view="patient-left", **kw)
    red = red_pixels(left)
    assert red.sum() > 30
    ys, xs = np.nonzero(red)
    assert abs(xs.mean() - (w - 1) / 2) < 1.5 and abs(ys.mean() - (h - 1) / 2) < 1.5
    assert red_pixels(render_volume(opacity, view="patient-right", **kw)).sum() == 0


def test_ray_cast_applies_the_direction_matrix():
    # the same world scene stored with x reversed (direction diag(-1, 1, 1)): the views are
    # world views, so patient-left still shows the marker
    opacity, colour = marker_volume()
    flip = np.diag([-1.0, 1.0, 1.0])
    origin = (-ORIGIN[0], ORIGIN[1], ORIGIN[2])
    kw = dict(spacing=(1, 1, 1), size=(64, 64), shading=False)
    ref = render_volume(opacity, colour=colour, origin=ORIGIN, view="patient-left", **kw)
    img = render_volume(opacity[:, :, ::-1], colour=[c[:, :, ::-1] for c in colour],
                        origin=origin, direction=flip, view="patient-left", **kw)
    assert red_pixels(img).sum() == pytest.approx(red_pixels(ref).sum(), rel=0.05)
    assert np.abs(img.astype(int) - ref.astype(int)).mean() < 1.0
    # without the direction matrix the marker is on the far side
    wrong = render_volume(opacity[:, :, ::-1], colour=[c[:, :, ::-1] for c in colour],
                          view="patient-left", **kw)
    assert red_pixels(wrong).sum() == 0
    with pytest.raises(VolwarpError, match="orthonormal"):
        render_volume(opacity, direction=[[1, 0.5, 0], [0, 1, 0], [0, 0, 1]], **kw)


# -- labels drawn ----------------------------------------------------------------------

def label_boxes(w, h, letters):
    """Where draw_orientation_labels puts each label: {edge: (y, x, mask)}."""
    k = label_scale(w, h)
    margin = max(2, 2 * k)
    out = {}
    for edge, text in letters.items():
        m = text_mask(text, k)
        mh, mw = m.shape
        y, x = {"left": ((h - mh) // 2, margin), "right": ((h - mh) // 2, w - margin - mw),
                "top": (margin, (w - mw) // 2), "bottom": (h - margin - mh, (w - mw) // 2)}[edge]
        out[edge] = (y, x, m)
    return out


@pytest.mark.parametrize("view", ["patient-left", "superior", "iso"])
def test_mesh_labels_are_the_view_letters_at_the_edges(view):
    mesh, colors = marker_mesh()
    w, h = 200, 160
    plain = render_mesh(mesh, view=view, size=(w, h), face_colors=colors)
    img = render_mesh(mesh, view=view, size=(w, h), face_colors=colors, orientation_labels=True)
    letters = view_letters(view)
    changed = np.any(img != plain, axis=2)
    allowed = np.zeros_like(changed)
    k = label_scale(w, h)
    halo = max(1, k // 2)
    for y, x, m in label_boxes(w, h, letters).values():
        # the letter in dark ink on the white background, exactly the glyph
        patch = img[y:y + m.shape[0], x:x + m.shape[1]]
        assert np.all(patch[m] == 20)
        allowed[y - halo:y + m.shape[0] + halo, x - halo:x + m.shape[1] + halo] = True
        assert changed[y:y + m.shape[0], x:x + m.shape[1]].any()
    assert not np.any(changed & ~allowed)  # nothing else touched


def test_ray_cast_labels_light_on_dark():
    opacity, colour = marker_volume()
    w, h = 96, 96
    img = render_volume(opacity, colour=colour, origin=ORIGIN, view="anterior", size=(w, h),
                        shading=False, orientation_labels=True)
    for edge, (y, x, m) in label_boxes(w, h, view_letters("anterior")).items():
        assert np.all(img[y:y + m.shape[0], x:x + m.shape[1]][m] == 240), edge


def test_tiny_pictures_get_no_labels():
    im = np.zeros((12, 12, 3), np.uint8)
    assert np.all(draw_orientation_labels(im, view_letters("iso")) == 0)
    with pytest.raises(VolwarpError):
        draw_orientation_labels(np.zeros((40, 40), np.uint8), view_letters("x"))


def test_default_renders_unchanged_by_the_new_keywords():
    mesh, colors = marker_mesh()
    a = render_mesh(mesh, view="iso", size=(80, 60))
    b, cam = render_mesh(mesh, view="iso", size=(80, 60), orientation_labels=False,
                         return_camera=True)
    assert np.array_equal(a, b) and isinstance(cam, Camera)
    opacity, colour = marker_volume()
    a = render_volume(opacity, size=(40, 30))
    b, cam = render_volume(opacity, size=(40, 30), return_camera=True)
    assert np.array_equal(a, b) and cam.size == (40, 30)


# -- cameras ---------------------------------------------------------------------------

def png_bytes(tmp_path, name, image):
    from volwarp_cli.io.images import write_image

    path = tmp_path / name
    write_image(path, image)
    return path.read_bytes()


def test_saved_mesh_camera_gives_the_identical_picture(tmp_path):
    mesh, colors = marker_mesh()
    first, cam = render_mesh(mesh, view=(33.0, 21.0), size=(150, 110), face_colors=colors,
                             orientation_labels=True, return_camera=True)
    write_camera(cam, tmp_path / "cam.json")
    again = read_camera(tmp_path / "cam.json")
    second, used = render_mesh(mesh, camera=again, face_colors=colors, orientation_labels=True,
                               return_camera=True)
    assert np.array_equal(first, second)
    assert png_bytes(tmp_path, "a.png", first) == png_bytes(tmp_path, "b.png", second)
    # and the camera file itself round-trips byte for byte
    assert camera_json(used) == (tmp_path / "cam.json").read_bytes()
    d = json.loads((tmp_path / "cam.json").read_text())
    assert d["frame"] == "LPS" and d["projection"] == "parallel"
    assert d["image_size"] == [150, 110]
    np.testing.assert_allclose(d["parallel_scale"], 110 / (2 * cam.scale))
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    np.testing.assert_allclose(d["bounds"], np.stack([lo, hi], axis=1).ravel())
    dop = np.subtract(d["focal_point"], d["position"])
    np.testing.assert_allclose(dop / np.linalg.norm(dop), d["direction_of_projection"],
                               atol=1e-12)


def test_saved_ray_cast_camera_gives_the_identical_picture(tmp_path):
    opacity, colour = marker_volume()
    first, cam = render_volume(opacity, colour=colour, origin=ORIGIN, view="patient-left",
                               size=(48, 40), orientation_labels=True, return_camera=True)
    np.testing.assert_allclose(cam.center, [0, 0, 0], atol=1e-12)  # the box centre, in world
    write_camera(cam, tmp_path / "vol.json")
    second = render_volume(opacity, colour=colour, origin=ORIGIN,
                           camera=read_camera(tmp_path / "vol.json"), orientation_labels=True)
    assert np.array_equal(first, second)
    assert png_bytes(tmp_path, "a.png", first) == png_bytes(tmp_path, "b.png", second)


def test_camera_reused_on_a_moved_object_keeps_the_world_framing(tmp_path):
    """Before/after: the same camera on a larger (padded) volume of the same scene draws the
    scene where it was; the padded volume's own fit would frame it differently."""
    opacity, colour = marker_volume()
    _, cam = render_volume(opacity, colour=colour, origin=ORIGIN, view="patient-left",
                           size=(64, 64), shading=False, return_camera=True)
    write_camera(cam, tmp_path / "before.json")
    pad = ((0, 0), (20, 0), (0, 0))  # 20 more voxels on the -y (anterior) side
    after = np.pad(opacity, pad)
    after_col = [np.pad(c, pad) for c in colour]
    moved_origin = (ORIGIN[0], ORIGIN[1] - 20, ORIGIN[2])
    kw = dict(colour=after_col, origin=moved_origin, shading=False)
    reused = render_volume(after, camera=read_camera(tmp_path / "before.json"), **kw)
    ref = render_volume(opacity, colour=colour, origin=ORIGIN, view="patient-left",
                        size=(64, 64), shading=False)
    a, b = np.argwhere(red_pixels(ref)).mean(axis=0), np.argwhere(red_pixels(reused)).mean(axis=0)
    assert np.abs(a - b).max() < 0.5 and abs(int(red_pixels(ref).sum())
                                              - int(red_pixels(reused).sum())) <= 4
    own = render_volume(after, view="patient-left", size=(64, 64), **kw)
    assert red_pixels(own).sum() < 0.8 * red_pixels(ref).sum()  # framed to the bigger box
    assert np.abs(np.argwhere(red_pixels(own)).mean(axis=0) - a).max() > 3
    # a mesh camera works for the mesh of the moved object too: shifted by the move, in pixels
    mesh, colors = marker_mesh()
    _, mcam = render_mesh(mesh, view="anterior", size=(100, 80), return_camera=True)
    from volwarp_cli.surface.mesh import Mesh

    moved = Mesh(mesh.vertices + np.float32([-5.0, 0.0, 2.0]), mesh.faces)  # right, up
    a = np.argwhere(red_pixels(render_mesh(mesh, camera=mcam, face_colors=colors)))
    b = np.argwhere(red_pixels(render_mesh(moved, camera=mcam, face_colors=colors)))
    # from the front, the patient's right (-x) is the picture's left; superior is up
    np.testing.assert_allclose(b.mean(axis=0) - a.mean(axis=0),
                               [-2.0 * mcam.scale, -5.0 * mcam.scale], atol=0.5)


def test_pyvista_draws_the_same_picture_from_the_camera_file(tmp_path):
    """The file's VTK terms mean what VTK means by them: pyvista (OpenGL through Mesa's
    EGL) set from position, focal_point, view_up and parallel_scale draws the silhouette
    volwarp's rasteriser draws."""
    pv = pytest.importorskip("pyvista")
    mesh, _ = marker_mesh((9.0, -9.0, 4.0))
    ours, cam = render_mesh(mesh, view=(30.0, 20.0), size=(160, 120), return_camera=True)
    write_camera(cam, tmp_path / "cam.json")
    d = json.loads((tmp_path / "cam.json").read_text())
    faces = np.hstack([np.full((len(mesh.faces), 1), 3), mesh.faces]).ravel()
    plotter = pv.Plotter(off_screen=True, window_size=d["image_size"])
    try:
        plotter.add_mesh(pv.PolyData(np.asarray(mesh.vertices, np.float64), faces),
                         color="white")
        plotter.set_background("black")
        c = plotter.camera
        c.parallel_projection = True
        c.position, c.focal_point, c.up = d["position"], d["focal_point"], d["view_up"]
        c.parallel_scale = d["parallel_scale"]
        plotter.reset_camera_clipping_range()
        theirs = plotter.screenshot(return_img=True)
    finally:
        plotter.close()
    a = np.abs(ours.astype(int) - 255).max(axis=2) > 8
    b = theirs.max(axis=2) > 8
    assert (a & b).sum() / (a | b).sum() > 0.98


def test_turntable_from_a_camera_starts_at_it():
    mesh, colors = marker_mesh()
    cam = fit_camera(mesh.vertices, "anterior", (80, 60))
    frames, cams = render_turntable(mesh, 4, camera=cam, orientation_labels=True,
                                    return_cameras=True)
    assert np.array_equal(frames[0], render_mesh(mesh, camera=cam, orientation_labels=True))
    # a quarter turn about z from anterior (azimuth -90) is azimuth 0: patient-left
    np.testing.assert_allclose(cams[1].back, view_axes("patient-left")[2], atol=1e-12)
    assert letters_tuple(screen_letters(cams[1].up, -cams[1].back)) == EXPECTED_LETTERS["x"]


def test_resized_camera_keeps_the_world_height():
    mesh, _ = marker_mesh()
    cam = fit_camera(mesh.vertices, "iso", (100, 80))
    big = cam.resized((200, 160))
    assert big.size == (200, 160) and big.half_height == pytest.approx(cam.half_height)
    assert big.scale == pytest.approx(2 * cam.scale)
    assert cam.resized((100, 80)) is cam


GOOD = {"position": [100.0, 0.0, 0.0], "focal_point": [0.0, 0.0, 0.0],
        "view_up": [0.0, 0.0, 1.0], "parallel_scale": 20.0, "image_size": [64, 48]}


def test_a_hand_written_vtk_style_camera(tmp_path):
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(dict(GOOD, view_angle=30.0, clipping_range=[1.0, 300.0],
                                    parallel_projection=True, view_up=[0.5, 0.0, 3.0])))
    cam = read_camera(path)
    np.testing.assert_allclose(cam.back, [1, 0, 0])
    np.testing.assert_allclose(cam.up, [0, 0, 1], atol=1e-12)  # orthogonalised
    np.testing.assert_allclose(cam.right, [0, 1, 0], atol=1e-12)
    assert cam.size == (64, 48) and cam.scale == pytest.approx(48 / 40)
    # it looks from +x: the same picture as the patient-left view at that framing
    assert letters_tuple(screen_letters(cam.up, -cam.back)) == EXPECTED_LETTERS["patient-left"]


@pytest.mark.parametrize("payload, key, message", [
    ("{", None, "not valid JSON"),
    ("[1, 2]", None, "one JSON object"),
    (dict(GOOD, focal_pont=[0, 0, 0]), None, "unknown key"),
    ({k: v for k, v in GOOD.items() if k != "focal_point"}, "focal_point", "missing"),
    ({k: v for k, v in GOOD.items() if k != "parallel_scale"}, "parallel_scale", "missing"),
    (dict({k: v for k, v in GOOD.items() if k != "parallel_scale"}, view_angle=30.0),
     "parallel_scale", "perspective"),
    (dict(GOOD, projection="perspective"), "projection", "parallel"),
    (dict(GOOD, parallel_projection=False), "parallel_projection", "parallel"),
    (dict(GOOD, parallel_scale=-1.0), "parallel_scale", "positive"),
    (dict(GOOD, parallel_scale="big"), "parallel_scale", "number"),
    (dict(GOOD, image_size=[0, 10]), "image_size", "width, height"),
    (dict(GOOD, image_size=[64.5, 48]), "image_size", "whole numbers"),
    (dict(GOOD, view_up=[1.0, 0.0, 0.0]), "view_up", "parallel to the direction"),
    (dict(GOOD, view_up=[0, 0]), "view_up", "list of 3 numbers"),
    (dict(GOOD, position=[0.0, 0.0, 0.0]), "position", "same point"),
    ({k: v for k, v in GOOD.items() if k != "position"}, "position", "missing"),
    ('{"position": [NaN, 0, 0], "focal_point": [0, 0, 0], "view_up": [0, 0, 1], '
     '"parallel_scale": 1, "image_size": [8, 8]}', "position", "finite"),
    (dict(GOOD, frame="RAS"), "frame", "LPS"),
    (dict(GOOD, volwarp_camera=2), "volwarp_camera", "version"),
    (dict(GOOD, bounds=[1, 0, 0, 1, 0, 1]), "bounds", "min <= max"),
])
def test_malformed_camera_files_are_clear_errors(tmp_path, payload, key, message):
    path = tmp_path / "bad.json"
    path.write_text(payload if isinstance(payload, str) else json.dumps(payload))
    with pytest.raises(CameraError, match=message) as info:
        read_camera(path)
    err = info.value
    assert isinstance(err, SpecError)  # exit 2 on the command line
    assert str(err).startswith(str(path)) and err.key == key


def test_missing_and_binary_camera_files(tmp_path):
    with pytest.raises(CameraError, match="cannot read camera file"):
        read_camera(tmp_path / "none.json")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(CameraError, match="UTF-8"):
        read_camera(tmp_path / "bin.json")


# -- the click decorator ---------------------------------------------------------------

@click.command()
@click.option("--view", default="iso")
@click.option("--size", default="64x48", callback=core_parser(parse_size))
@camera_options
def _render_cmd(view, size, camera_from, camera_to, orientation_labels):
    out = {"labels": orientation_labels, "camera_to": camera_to}
    if camera_from is not None:
        out["size"] = list(camera_from.size)
        out["half_height"] = camera_from.half_height
    click.echo(json.dumps(out))


def invoke(*args):
    return CliRunner().invoke(_render_cmd, [str(a) for a in args])


def test_camera_options_pass_typed_values(tmp_path):
    res = invoke()
    assert res.exit_code == 0, res.output
    assert json.loads(res.output) == {"labels": None, "camera_to": None}
    assert json.loads(invoke("--orientation-labels").output)["labels"] is True
    assert json.loads(invoke("--no-orientation-labels").output)["labels"] is False
    (tmp_path / "cam.json").write_text(json.dumps(GOOD))
    out = json.loads(invoke("--camera-from", tmp_path / "cam.json",
                            "--camera-to", tmp_path / "out.json").output)
    assert out["size"] == [64, 48] and out["half_height"] == 20.0
    assert out["camera_to"] == str(tmp_path / "out.json")
    # --size given: the camera's world height in the new picture size
    out = json.loads(invoke("--camera-from", tmp_path / "cam.json", "--size", "128x96").output)
    assert out["size"] == [128, 96] and out["half_height"] == 20.0


@click.command()
@click.option("--render-size", "render_size", default="64x48", callback=core_parser(parse_size))
@camera_options
def _sweep_like_cmd(render_size, camera_from, camera_to, orientation_labels):
    click.echo(json.dumps(list(camera_from.size) if camera_from else None))


def test_camera_options_resize_with_render_size(tmp_path):
    (tmp_path / "cam.json").write_text(json.dumps(GOOD))
    res = CliRunner().invoke(_sweep_like_cmd, ["--camera-from", str(tmp_path / "cam.json")])
    assert json.loads(res.output) == [64, 48]
    res = CliRunner().invoke(_sweep_like_cmd, ["--camera-from", str(tmp_path / "cam.json"),
                                               "--render-size", "32x32"])
    assert json.loads(res.output) == [32, 32]


def test_camera_options_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(dict(GOOD, image_size="64x48")))
    res = invoke("--camera-from", bad)
    assert res.exit_code == 2
    assert "--camera-from" in res.output and "image_size" in res.output and str(bad) in res.output
    res = invoke("--camera-from", tmp_path / "missing.json")
    assert res.exit_code == 2 and "cannot read camera file" in res.output
    (tmp_path / "cam.json").write_text(json.dumps(GOOD))
    res = invoke("--camera-from", tmp_path / "cam.json", "--view", "anterior")
    assert res.exit_code == 2 and "exclude each other" in res.output
    res = invoke("--camera-to", tmp_path / "no-folder" / "cam.json")
    assert isinstance(res.exception, VolwarpError) and "does not exist" in str(res.exception)


def test_orientation_labels_default():
    scan = Volume(np.zeros((2, 2, 2)), space="RAS")
    lps_file = Volume(np.zeros((2, 2, 2)), space="left-posterior-superior")
    no_frame = Volume(np.zeros((2, 2, 2)))  # TIFF, raw, a sweep's volume
    scanner = Volume(np.zeros((2, 2, 2)), space="scanner-xyz")
    assert has_anatomical_frame(scan) and has_anatomical_frame(lps_file)
    assert not has_anatomical_frame(no_frame) and not has_anatomical_frame(scanner)
    assert orientation_labels_for(None, scan) is True
    assert orientation_labels_for(None, scan, no_frame) is False
    assert orientation_labels_for(None) is False
    assert orientation_labels_for(True, no_frame) is True
    assert orientation_labels_for(False, scan) is False
