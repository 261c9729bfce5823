"""--camera-to / --camera-from / --orientation-labels on the commands that render."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.images import read_image
from volwarp_cli.volume import Volume

DATA = Path(__file__).parent / "data"


@pytest.fixture
def blob(tmp_path):
    z, y, x = np.mgrid[:40, :40, :40].astype(np.float32)
    data = 200 / (1 + np.exp(np.sqrt((x - 20) ** 2 + (y - 18) ** 2 + (z - 21) ** 2) - 12))
    write_volume(Volume(data.astype(np.float32), spacing=(1.0, 1.0, 1.2)), tmp_path / "b.nrrd")
    return tmp_path / "b.nrrd"


def test_mesh_camera_round_trip_gives_the_same_picture(run, blob, tmp_path):
    a = tmp_path / "a.png"
    cam = tmp_path / "cam.json"
    res = run("mesh", blob, "--iso", "100", "--render", a, "--view", "patient-left",
              "--camera-to", cam)
    assert res.code == 0, res.stderr
    camera = json.loads(cam.read_text())
    assert {"position", "focal_point", "view_up", "parallel_scale"} <= set(camera)
    b = tmp_path / "b.png"
    res = run("mesh", blob, "--iso", "100", "--render", b, "--camera-from", cam)
    assert res.code == 0, res.stderr
    assert np.array_equal(read_image(a), read_image(b))
    # a grown "after" object seen through the same camera keeps the framing: the picture
    # differs, but not because the camera was refitted to it
    c = tmp_path / "c.png"
    assert run("mesh", blob, "--iso", "60", "--render", c, "--camera-from", cam).code == 0
    assert read_image(c).shape == read_image(a).shape


def test_camera_options_need_a_render_and_exclude_view(run, blob, tmp_path):
    res = run("mesh", blob, "--iso", "100", "-o", tmp_path / "m.ply", "--camera-to",
              tmp_path / "c.json")
    assert res.code == 2 and "--render" in res.stderr
    (tmp_path / "bad.json").write_text("{\"position\": [0, 0]}")
    res = run("mesh", blob, "--iso", "100", "--render", tmp_path / "r.png", "--camera-from",
              tmp_path / "bad.json")
    assert res.code == 2 and "bad.json" in res.stderr
    assert not (tmp_path / "r.png").exists()


def test_scan_renders_carry_orientation_letters_by_default(run, tmp_path):
    """A scan read from a file with a patient frame gets the letters; --no-orientation-labels
    takes them off, and only the edges' pixels change."""
    scan = DATA / "mri_t1_head_coronal_2x2x3mm.nrrd"
    vol = read_volume(scan)
    iso = 0.5 * float(vol.data.max())
    with_letters = tmp_path / "l.png"
    without = tmp_path / "n.png"
    assert run("mesh", scan, "--iso", iso, "--render", with_letters, "--view", "anterior",
               "--render-size", "200x160").code == 0
    assert run("mesh", scan, "--iso", iso, "--render", without, "--view", "anterior",
               "--render-size", "200x160", "--no-orientation-labels").code == 0
    a, b = read_image(with_letters), read_image(without)
    diff = np.any(a != b, axis=-1)
    assert diff.any()
    rows, cols = np.nonzero(diff)
    h, w = diff.shape
    # every changed pixel lies near an edge of the picture
    near = (rows < 0.2 * h) | (rows > 0.8 * h) | (cols < 0.2 * w) | (cols > 0.8 * w)
    assert near.all()


def test_sweep_and_morph_write_and_reuse_cameras(run, tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\ngrid: {spacing: 0.5}\nfields:\n  opacity: {value: 0.8}\n"
                    "trajectory:\n  - line: {from: [0, 0, 0], to: [0, 0, 8]}\n"
                    "scale: [3, 3]\n")  # along z, no up: the default frame
    cam = tmp_path / "cam.json"
    assert run("sweep", spec, "-o", tmp_path / "o_{field}.nrrd", "--render", tmp_path / "a.png",
               "--camera-to", cam).code == 0
    res = run("sweep", spec, "-o", tmp_path / "p_{field}.nrrd", "--render", tmp_path / "b.png",
              "--camera-from", cam)
    assert res.code == 0, res.stderr
    assert np.array_equal(read_image(tmp_path / "a.png"), read_image(tmp_path / "b.png"))
    ball = DATA / "ball_30_uint8.nrrd"
    cam2 = tmp_path / "m.json"
    res = run("morph", ball, ball, "--frames", "2", "--iso", "100", "-o",
              tmp_path / "f_{i}.nrrd", "--render-to", tmp_path / "f_{i}.png", "--camera-to", cam2)
    assert res.code == 0, res.stderr
    res = run("morph", ball, ball, "--frames", "2", "--iso", "100", "-o",
              tmp_path / "g_{i}.nrrd", "--render-to", tmp_path / "g_{i}.png", "--camera-from",
              cam2)
    assert res.code == 0, res.stderr
    for i in range(2):
        assert np.array_equal(read_image(tmp_path / f"f_{i}.png"),
                              read_image(tmp_path / f"g_{i}.png"))


def test_a_camera_file_with_a_key_twice_is_refused_and_a_bom_read(run, blob, tmp_path):
    """A key given twice was last-wins (a render came out tiny, exit 0) while the YAML specs
    refuse it; a byte-order mark was refused while the specs read it."""
    cam = tmp_path / "cam.json"
    assert run("mesh", blob, "--iso", "100", "--render", tmp_path / "a.png",
               "--camera-to", cam).code == 0
    text = cam.read_text()
    twice = tmp_path / "twice.json"
    twice.write_text(text.replace('"parallel_scale":', '"parallel_scale": 0.5, "parallel_scale":',
                                  1))
    res = run("mesh", blob, "--iso", "100", "--render", tmp_path / "b.png", "--camera-from",
              twice)
    assert res.code == 2
    assert "'parallel_scale' is given twice" in res.stderr and str(twice) in res.stderr
    assert not (tmp_path / "b.png").exists()
    bom = tmp_path / "bom.json"
    bom.write_bytes(b"\xef\xbb\xbf" + text.encode())
    res = run("mesh", blob, "--iso", "100", "--render", tmp_path / "c.png", "--camera-from", bom)
    assert res.code == 0, res.stderr
    assert np.array_equal(read_image(tmp_path / "a.png"), read_image(tmp_path / "c.png"))
