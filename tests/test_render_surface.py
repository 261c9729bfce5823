"""Headless surface renders: sizes, silhouettes against projected areas, view conventions."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.render.surface import (
    fit_camera,
    parse_color,
    parse_size,
    parse_view,
    render_mesh,
    render_turntable,
    view_axes,
)
from volwarp_cli.surface.isosurface import isosurface
from volwarp_cli.surface.mesh import Mesh
from volwarp_cli.volume import Volume


def silhouette(image: np.ndarray, background=(255, 255, 255)) -> np.ndarray:
    """Pixels that differ visibly from the background colour."""
    diff = np.abs(image.astype(int) - np.asarray(background)[None, None, :]).max(axis=2)
    return diff > 8


@pytest.fixture(scope="module")
def sphere() -> tuple[Mesh, float, np.ndarray]:
    r = 10.0
    z, y, x = np.indices((26, 26, 26)).astype(np.float32)
    f = r - np.sqrt((x - 12.5) ** 2 + (y - 12.5) ** 2 + (z - 12.5) ** 2)
    vol = Volume(f, spacing=(1.0, 1.0, 1.0), origin=(100.0, -50.0, 20.0))
    return isosurface(vol, 0.0), r, np.array([112.5, -37.5, 32.5])


def box_mesh(size=(12.0, 6.0, 4.0)) -> Mesh:
    """A closed box of the given (x, y, z) size from the isosurface of a padded block."""
    sx, sy, sz = size
    h = 0.5
    data = np.zeros((int(sz / h) + 4, int(sy / h) + 4, int(sx / h) + 4), dtype=np.float32)
    data[2:-2, 2:-2, 2:-2] = 1.0
    # the 0.5 level between 0 and 1 lies half a sample out: sizes are exact
    return isosurface(Volume(data, spacing=(h, h, h)), 0.5)


def test_size_and_sphere_silhouette_area(sphere):
    mesh, r, _ = sphere
    for size in [(320, 240), (200, 300)]:
        for view in ["iso", "x", (10, -60)]:
            image = render_mesh(mesh, view=view, size=size)
            assert image.shape == (size[1], size[0], 3) and image.dtype == np.uint8
            cam = fit_camera(mesh.vertices, view, size)
            expected = np.pi * (r * cam.scale) ** 2
            assert silhouette(image).sum() == pytest.approx(expected, rel=0.10)


@pytest.mark.parametrize("view", ["x", "y", "z", "iso", (30.0, 20.0)])
def test_box_silhouette_matches_projected_area(view):
    size = np.array([12.0, 6.0, 4.0])
    mesh = box_mesh(tuple(size))
    extent = mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)
    np.testing.assert_allclose(extent, size, atol=1e-6)
    image = render_mesh(mesh, view=view, size=(400, 300))
    cam = fit_camera(mesh.vertices, view, (400, 300))
    d = np.abs(cam.back)
    # orthographic shadow of a box: each face pair contributes |d . n| times its area
    projected = size[1] * size[2] * d[0] + size[0] * size[2] * d[1] + size[0] * size[1] * d[2]
    expected = projected * cam.scale**2
    assert silhouette(image).sum() == pytest.approx(expected, rel=0.10)


def test_two_views_differ_and_are_deterministic():
    mesh = box_mesh((12.0, 6.0, 4.0))
    a = render_mesh(mesh, view="x", size=(160, 120))
    b = render_mesh(mesh, view="y", size=(160, 120))
    assert np.abs(a.astype(int) - b.astype(int)).mean() > 10
    assert silhouette(a).sum() != silhouette(b).sum()
    again = render_mesh(mesh, view="x", size=(160, 120))
    assert np.array_equal(a, again)


def test_view_conventions_put_axes_where_documented():
    # a small ball at +x and +z of a big one: where does it show?
    z, y, x = np.indices((30, 30, 40)).astype(np.float32)
    f = np.maximum(6 - np.sqrt((x - 12) ** 2 + (y - 15) ** 2 + (z - 12) ** 2),
                   3 - np.sqrt((x - 30) ** 2 + (y - 15) ** 2 + (z - 20) ** 2))
    mesh = isosurface(Volume(f), 0.0)

    def centroid(image):
        rows, cols = np.nonzero(silhouette(image))
        return cols.mean(), rows.mean()

    w, h = 400, 300
    # "z": from above, x to the right: the small ball (x = 30) pulls the centroid right
    col, _ = centroid(render_mesh(mesh, view="z", size=(w, h)))
    cam = fit_camera(mesh.vertices, "z", (w, h))
    big_col = w / 2 + (np.array([12, 15, 12]) - cam.center) @ cam.right * cam.scale
    assert col > big_col
    # "y": from +y, z up: the small ball is higher, so the top rows hold it
    image = render_mesh(mesh, view="y", size=(w, h))
    rows = np.nonzero(silhouette(image).any(axis=1))[0]
    top_cols = np.nonzero(silhouette(image)[rows[0] + 2])[0]
    cam = fit_camera(mesh.vertices, "y", (w, h))
    small_col = w / 2 + (np.array([30, 15, 20]) - cam.center) @ cam.right * cam.scale
    assert abs(top_cols.mean() - small_col) < 3
    # and from +y, +x is on the left
    assert small_col < w / 2


def test_view_axes_are_orthonormal_and_named_views():
    for view in ["x", "y", "z", "iso", (123.0, -90.0), (10.0, 90.0), (-45.0, 12.0)]:
        r, u, b = view_axes(view)
        m = np.stack([r, u, b])
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-12)
        # right-handed: right x up = back (towards the viewer)
        np.testing.assert_allclose(np.cross(r, u), b, atol=1e-12)
    np.testing.assert_allclose(view_axes("z")[0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(view_axes("z")[1], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(view_axes("x")[2], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(view_axes("iso")[2], np.ones(3) / np.sqrt(3), atol=1e-12)


def test_colors_background_and_empty_mesh(sphere):
    mesh, _, _ = sphere
    image = render_mesh(mesh, view="x", size=(100, 80), color="#ff0000", background="black")
    assert tuple(image[0, 0]) == (0, 0, 0)
    inside = silhouette(image, background=(0, 0, 0))
    assert image[inside][:, 0].mean() > 3 * image[inside][:, 1].mean()
    empty = render_mesh(Mesh.empty(), size=(30, 20), background=(0.2, 0.4, 0.6))
    assert empty.shape == (20, 30, 3)
    assert np.all(empty == np.array([51, 102, 153], dtype=np.uint8))


def test_face_colors_paint_each_triangle(sphere):
    mesh, _, centre = sphere
    # uniform face colours give exactly the single-colour picture
    plain = render_mesh(mesh, view="y", size=(90, 70), color="#3080c0")
    rows = np.tile(np.array([[0x30, 0x80, 0xC0]], np.uint8), (len(mesh.faces), 1))
    assert np.array_equal(render_mesh(mesh, view="y", size=(90, 70), face_colors=rows), plain)
    # the +x half red, the -x half blue: seen along y (x to the right) they split left/right
    cx = mesh.vertices[mesh.faces].mean(axis=1)[:, 0]
    colors = np.where((cx > centre[0])[:, None], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    image = render_mesh(mesh, view="y", size=(90, 70), face_colors=colors,
                        background="black").astype(int)
    from scipy import ndimage as ndi

    inside = ndi.binary_erosion(silhouette(image.astype(np.uint8), background=(0, 0, 0)))
    cols = np.nonzero(inside.any(axis=0))[0]
    mid = (cols[0] + cols[-1]) // 2
    left, right = inside.copy(), inside.copy()
    left[:, mid - 3:] = False
    right[:, :mid + 4] = False
    sides = {"left": image[left], "right": image[right]}
    red = "right" if view_axes("y")[0][0] > 0 else "left"
    blue = "left" if red == "right" else "right"
    assert (sides[red][:, 0] > sides[red][:, 2] + 30).all()
    assert (sides[blue][:, 2] > sides[blue][:, 0] + 30).all()
    with pytest.raises(VolwarpError, match="one RGB row per triangle"):
        render_mesh(mesh, size=(20, 20), face_colors=colors[:-1])


def test_open_surface_inside_is_drawn_darker():
    # half a sphere (cut open at the border): looking into it shows its inner side
    z, y, x = np.indices((20, 20, 20)).astype(np.float32)
    f = 8 - np.sqrt((x - 9.5) ** 2 + (y - 9.5) ** 2 + (z - 0.0) ** 2)
    mesh = isosurface(Volume(f), 0.0)  # open where it meets z = 0
    from_above = render_mesh(mesh, view="z", size=(120, 120))
    from_below = render_mesh(mesh, view=(0, -90), size=(120, 120))
    c = silhouette(from_above)
    assert np.array_equal(c, silhouette(from_below)[:, ::-1]) or \
        abs(int(c.sum()) - int(silhouette(from_below).sum())) < 0.02 * c.sum()
    assert from_below[c].mean() < from_above[c].mean()


def test_turntable_same_scale_and_differs():
    mesh = box_mesh((12.0, 6.0, 4.0))
    images = render_turntable(mesh, 4, view=(0.0, 0.0), size=(120, 90))
    assert len(images) == 4
    areas = [silhouette(im).sum() for im in images]
    # views 0 and 2 (and 1 and 3) see the same box side: same area at a common scale
    assert areas[0] == pytest.approx(areas[2], rel=0.02)
    assert areas[1] == pytest.approx(areas[3], rel=0.02)
    # the long side (12 x 4) against the short side (6 x 4)
    assert areas[1] / areas[0] == pytest.approx(2.0, rel=0.08)


def test_parsers():
    assert parse_color("white") == (1.0, 1.0, 1.0)
    assert parse_color("#ff8000") == pytest.approx((1.0, 128 / 255, 0.0))
    assert parse_color("#f80") == pytest.approx((1.0, 136 / 255, 0.0))
    assert parse_color("0.1,0.2,0.3") == pytest.approx((0.1, 0.2, 0.3))
    assert parse_color("255,128,0") == pytest.approx((1.0, 128 / 255, 0.0))
    assert parse_color((0, 0, 1)) == (0.0, 0.0, 1.0)
    for bad in ["nocolor", "1,2", "-1,0,0", "300,0,0"]:
        with pytest.raises(VolwarpError):
            parse_color(bad)
    assert parse_view("x") == (0.0, 0.0)
    assert parse_view("30,-20") == (30.0, -20.0)
    for bad in ["up", "10,100", "1,2,3"]:
        with pytest.raises(VolwarpError):
            parse_view(bad)
    assert parse_size("1024x768") == (1024, 768)
    for bad in ["1024", "0x10", "10x99999", "axb"]:
        with pytest.raises(VolwarpError):
            parse_size(bad)
