"""Emission-absorption ray casting: analytic compositing, silhouettes, orientation."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.render.raycast import camera, render_volume


def test_uniform_slab_composites_to_the_analytic_opacity():
    n, o = 41, 0.05
    vol = np.full((n, n, n), o, dtype=np.float32)
    img = render_volume(vol, view="front", size=(33, 33), step=0.5, shading=False, zoom=2.0)
    # a ray along +y through the centre crosses n - 1 voxel lengths
    expected = 1 - (1 - o) ** (n - 1)
    assert img[16, 16, 0] / 255 == pytest.approx(expected, abs=0.02)


@pytest.mark.parametrize("step", [0.25, 1.0])
def test_opacity_correction_makes_result_independent_of_step(step):
    vol = np.full((21, 21, 21), 0.1, dtype=np.float32)
    ref = render_volume(vol, view=(0, 0), size=(17, 17), step=0.5, shading=False, zoom=2.0)
    img = render_volume(vol, view=(0, 0), size=(17, 17), step=step, shading=False, zoom=2.0)
    assert abs(int(img[8, 8, 0]) - int(ref[8, 8, 0])) <= 6


def test_opaque_sphere_silhouette_has_the_right_area():
    n, r = 64, 20.0
    c = (n - 1) / 2
    z, y, x = np.mgrid[:n, :n, :n]
    d = np.sqrt((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2)
    vol = np.clip(r + 0.5 - d, 0, 1).astype(np.float32)
    size = 128
    img = render_volume(vol, view=(30, 40), size=(size, size), shading=False)
    lit = np.count_nonzero(img[:, :, 0] >= 128)  # accumulated opacity >= 1/2
    # the view frames the bounding sphere of the box: half height = |ext|/2 + 1 voxel
    half = 0.5 * np.sqrt(3) * (n - 1) + 1
    pix = 2 * half / size
    # the field falls from 1 to 0 between d = r - 0.5 and r + 0.5; grazing rays gather
    # half opacity a little outside d = r
    assert np.pi * r * r < lit * pix * pix < np.pi * (r + 0.7) ** 2


def test_colour_and_shading():
    vol = np.zeros((32, 32, 32), dtype=np.float32)
    vol[8:24, 8:24, 8:24] = 1
    red = [np.ones_like(vol), np.zeros_like(vol), np.zeros_like(vol)]
    img = render_volume(vol, colour=red, view=(20, 20), size=(64, 64))
    fg = img.max(axis=2) > 0
    assert np.all(img[fg][:, 1:] <= 64)  # red, plus a little specular
    assert img[fg][:, 0].max() > 200
    flat = render_volume(vol, colour=red, view=(20, 20), size=(64, 64), shading=False)
    assert flat[32, 32, 0] == 255


def test_orientation_of_the_views():
    vol = np.zeros((32, 32, 32), dtype=np.float32)
    vol[2:8, 14:18, 24:30] = 1  # low z, high x
    front = render_volume(vol, view="front", size=(64, 64), shading=False)
    ys, xs = np.nonzero(front[:, :, 0])
    assert xs.mean() > 32 and ys.mean() > 32  # right and bottom
    back = render_volume(vol, view="back", size=(64, 64), shading=False)
    assert np.nonzero(back[:, :, 0])[1].mean() < 32  # mirrored from behind
    top = render_volume(vol, view="top", size=(64, 64), shading=False)
    ys, xs = np.nonzero(top[:, :, 0])
    assert xs.mean() > 32


def test_background_and_deterministic():
    vol = np.zeros((16, 16, 16), dtype=np.float32)
    vol[4:12, 4:12, 4:12] = 0.3
    a = render_volume(vol, size=(40, 30), background=(0, 0, 1))
    b = render_volume(vol, size=(40, 30), background=(0, 0, 1))
    assert a.shape == (30, 40, 3) and np.array_equal(a, b)
    assert tuple(a[0, 0]) == (0, 0, 255)


def test_camera_follows_the_surface_views():
    """The ray caster looks from where `volwarp mesh --view` looks."""
    fwd, right, up = camera("front")  # from -y, looking along +y
    assert np.allclose(fwd, [0, 1, 0]) and np.allclose(right, [1, 0, 0]) and np.allclose(up, [0, 0, 1])
    fwd, right, up = camera((0, 0))  # from +x
    assert np.allclose(fwd, [-1, 0, 0]) and np.allclose(right, [0, 1, 0])
    fwd, right, up = camera("z")  # from above: x to the right, y up
    assert np.allclose(fwd, [0, 0, -1]) and np.allclose(right, [1, 0, 0])
    assert np.allclose(up, [0, 1, 0])
    with pytest.raises(VolwarpError):
        camera("north")
