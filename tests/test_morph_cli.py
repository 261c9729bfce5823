"""`volwarp morph` on files: short form, specs in specs/, meshes, renders, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

SPECS = Path(__file__).parent.parent / "specs"


def radial(n, c):
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float64)
    return np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2)


@pytest.fixture
def shapes(tmp_path):
    n = 32
    ball = (1 / (1 + np.exp((radial(n, (15.5, 15.5, 15.5)) - 9.0) / 0.8)) * 200).astype(np.uint8)
    two = np.maximum(6 - radial(n, (9, 15.5, 15.5)), 6 - radial(n, (23, 15.5, 15.5)))
    lobes = (1 / (1 + np.exp(-two / 0.8)) * 200).astype(np.uint8)
    kw = {"spacing": (1.0, 1.0, 1.5), "origin": (-4.0, 2.0, 7.0)}
    write_volume(Volume(ball, **kw), tmp_path / "ball.nrrd")
    write_volume(Volume(lobes, **kw), tmp_path / "lobes.nrrd")
    return tmp_path


def test_short_form_writes_frames_with_geometry(run, shapes):
    r = run("morph", shapes / "ball.nrrd", shapes / "lobes.nrrd", "--frames", 3, "--iso", 100,
            "-o", shapes / "f_{i:02d}.nrrd")
    assert r.code == 0, r.stderr
    src = read_volume(shapes / "ball.nrrd")
    tgt = read_volume(shapes / "lobes.nrrd")
    frames = [read_volume(shapes / f"f_{i:02d}.nrrd") for i in range(3)]
    for i, f in enumerate(frames):
        assert f.same_grid(src) and f.data.dtype == np.float32
        assert float(f.meta["volwarp_morph_t"]) == i / 2
    np.testing.assert_array_equal(frames[0].data < 0, src.data >= 100)
    np.testing.assert_array_equal(frames[2].data < 0, tgt.data >= 100)


def test_times_and_t_in_pattern_and_determinism(run, shapes):
    args = ("morph", shapes / "ball.nrrd", shapes / "lobes.nrrd", "--times", "0.25,0.75",
            "--iso", 100)
    assert run(*args, "-o", shapes / "a_{t:.2f}.nrrd").code == 0
    assert run(*args, "-o", shapes / "b_{t:.2f}.nrrd").code == 0
    for t in ("0.25", "0.75"):
        assert (shapes / f"a_{t}.nrrd").read_bytes() == (shapes / f"b_{t}.nrrd").read_bytes()


def test_density_output(run, shapes):
    r = run("morph", shapes / "ball.nrrd", shapes / "lobes.nrrd", "--frames", 2, "--iso", 100,
            "--density", "-o", shapes / "d_{i}.nrrd")
    assert r.code == 0, r.stderr
    d0 = read_volume(shapes / "d_0.nrrd").data
    src = read_volume(shapes / "ball.nrrd").data
    assert d0.min() == 0.0 and d0.max() == 1.0
    np.testing.assert_array_equal(d0 > 0.5, src >= 100)


def test_mesh_and_render_outputs(run, shapes):
    r = run("morph", shapes / "ball.nrrd", shapes / "lobes.nrrd", "--frames", 3, "--iso", 100,
            "-o", shapes / "f_{i}.nrrd", "--mesh-to", shapes / "f_{i}.ply",
            "--render-to", shapes / "f_{i}.png", "--sheet", shapes / "sheet.png",
            "--size", "160x120")
    assert r.code == 0, r.stderr
    import trimesh

    from volwarp_cli.io.images import read_image

    m0 = trimesh.load(shapes / "f_0.ply")
    m2 = trimesh.load(shapes / "f_2.ply")
    assert m0.is_watertight and m2.is_watertight
    assert m0.body_count == 1 and m2.body_count == 2  # topology follows the morph
    # the ball's volume: radius 9 mm in x, y and 9 voxels = 13.5 mm along z
    assert abs(m0.volume - 4 / 3 * np.pi * 9 * 9 * 13.5) < 0.03 * m0.volume
    img = read_image(shapes / "f_1.png")
    assert img.shape == (120, 160, 3) and img.std() > 0.05
    sheet = read_image(shapes / "sheet.png")
    assert sheet.shape[0] > 240 and sheet.shape[1] > 320


@pytest.mark.parametrize("option", [("--view", "sideways"), ("--size", "big")])
def test_bad_render_options_are_usage_errors_before_any_work(run, shapes, option):
    r = run("morph", shapes / "ball.nrrd", shapes / "lobes.nrrd", "--frames", 2, "--iso", 100,
            "-o", shapes / "bad_{i}.nrrd", "--render-to", shapes / "bad_{i}.png", *option)
    assert r.code == 2 and option[0] in r.stderr
    assert not list(shapes.glob("bad_*"))


def test_spec_with_attributes_and_source_range(run, shapes):
    (shapes / "m.yaml").write_text(
        "version: 1\n"
        "source: {volume: ball.nrrd, iso: 100}\n"
        "target: {volume: lobes.nrrd, iso: 100}\n"
        "times: [0, 0.5, 1]\n"
        "output: density\n"
        "density: {range: source}\n"
        "attributes:\n"
        "  - {name: grey, source: ball.nrrd, target: lobes.nrrd}\n")
    r = run("morph", "--spec", shapes / "m.yaml", "-o", shapes / "m_{i}.nrrd")
    assert r.code == 0, r.stderr
    src = read_volume(shapes / "ball.nrrd").data
    tgt = read_volume(shapes / "lobes.nrrd").data
    f0 = read_volume(shapes / "m_0.nrrd").data
    assert f0.dtype == np.uint8 and f0.max() == src.max() and f0.min() == src.min()
    np.testing.assert_array_equal(f0 >= 100, src >= 100)
    g0 = read_volume(shapes / "m_0_grey.nrrd").data
    g1 = read_volume(shapes / "m_1_grey.nrrd").data
    g2 = read_volume(shapes / "m_2_grey.nrrd").data
    np.testing.assert_array_equal(g0, src)
    np.testing.assert_array_equal(g2, tgt)
    mid = np.rint(0.5 * src.astype(np.float64) + 0.5 * tgt)
    assert np.abs(g1.astype(np.float64) - mid).max() <= 1


def test_spec_errors_point_at_keys(run, shapes):
    out = shapes / "x_{i}.nrrd"
    cases = {
        "frames: 3\nwarp:\n  source_points: [[1, 2, 3], [4, 5, 6]]\n  target_points: [[1, 2, 3]]\n":
            "warp.target_points",
        "times: [0, 1.5]\n": "times[1]",
        "frames: 3\nwarp: {kind: gaussian, pairs: [[[1, 2, 3], [2, 2, 3]]]}\n": "sigma",
        "frames: 3\nalign: {target: {scale: 0}}\n": "align.target.scale",
        "frames: 3\nmetric: cosine\n": "metric",
    }
    head = "version: 1\nsource: {volume: ball.nrrd, iso: 100}\ntarget: {volume: lobes.nrrd, iso: 100}\n"
    for body, key in cases.items():
        (shapes / "bad.yaml").write_text(head + body)
        r = run("morph", "--spec", shapes / "bad.yaml", "-o", out)
        assert r.code == 2, (body, r.stderr)
        assert key in r.stderr, (key, r.stderr)
        assert "bad.yaml:" in r.stderr
    assert not list(shapes.glob("x_*"))


def test_cli_errors(run, shapes):
    other = read_volume(shapes / "ball.nrrd")
    write_volume(other.with_data(other.data, spacing=(2.0, 2.0, 2.0)), shapes / "coarse.nrrd")
    r = run("morph", shapes / "ball.nrrd", shapes / "coarse.nrrd", "--frames", 2, "--iso", 100,
            "-o", shapes / "x_{i}.nrrd")
    assert r.code == 2 and "different grids" in r.stderr and "--grid" in r.stderr
    r = run("morph", shapes / "ball.nrrd", shapes / "coarse.nrrd", "--frames", 2, "--iso", 100,
            "--grid", "union", "-o", shapes / "u_{i}.nrrd")
    assert r.code == 0, r.stderr
    r = run("morph", shapes / "ball.nrrd", shapes / "lobes.nrrd", "--frames", 2, "--iso", 250,
            "-o", shapes / "x_{i}.nrrd")
    assert r.code == 1 and "empty" in r.stderr and r.stderr.count("ball.nrrd") == 1, r.stderr
    r = run("morph", shapes / "ball.nrrd", shapes / "lobes.nrrd", "--frames", 3, "--iso", 100,
            "-o", shapes / "x.nrrd")
    assert r.code == 2 and "{i}" in r.stderr
    r = run("morph", shapes / "ball.nrrd", shapes / "lobes.nrrd", "--times", "0,1.2", "--iso",
            100, "-o", shapes / "x_{i}.nrrd")
    assert r.code == 2 and "[0, 1]" in r.stderr
    r = run("morph", shapes / "ball.nrrd", "--frames", 3, "--iso", 100, "-o", shapes / "x_{i}.nrrd")
    assert r.code == 2
    r = run("morph", "--spec", SPECS / "morph-ball-block.yaml", shapes / "ball.nrrd",
            "-o", shapes / "x_{i}.nrrd")
    assert r.code == 2
    assert not list(shapes.glob("x*"))


def test_frames_keep_the_source_s_key_values_and_its_patient_frame(run, tmp_path):
    """Every command keeps its input's key/values and frame; morph's frames had neither
    (`space` gone, a custom key lost), in memory and by blocks alike (found by a review).
    The frames name LPS (the frame grid is in volwarp's LPS world) where an input names a
    patient frame; the source's earlier provenance is replaced."""
    from volwarp_cli import api

    z, y, x = np.indices((20, 20, 20))
    ball = (6 - np.sqrt((x - 10.0) ** 2 + (y - 10) ** 2 + (z - 10) ** 2)).astype(np.float32)
    src = tmp_path / "ras.nrrd"
    write_volume(Volume(ball, space="right-anterior-superior",
                        meta={"my_key": "hello", "volwarp_command": "distance",
                              "volwarp_distance": "values=labels labels=all",
                              "DICOM_StudyInstanceUID": "1.2.3", "DICOM_Modality": "SEG",
                              "DICOM_Segment_1_Label": "liver",
                              "DICOM_SeriesInstanceUID": "4.5.6"}), src)
    plain = tmp_path / "plain.nrrd"
    write_volume(Volume(ball), plain)
    for extra, name in (([], "m"), (["--chunked", "--max-distance", "5"], "c")):
        res = run("morph", src, src, "--frames", "2", "--iso", "0",
                  "-o", tmp_path / f"{name}_{{i}}.nrrd", *extra)
        assert res.code == 0, res.stderr
        for i in (0, 1):
            frame = read_volume(tmp_path / f"{name}_{i}.nrrd")
            assert frame.space == "left-posterior-superior", (name, i)
            assert frame.meta["my_key"] == "hello" and frame.meta["volwarp_command"] == "morph"
            # (the subject's kept; what described the source's own samples not: a frame
            # written back as a SEG named its shape after the source's segment 1)
            assert frame.meta["DICOM_StudyInstanceUID"] == "1.2.3"
            assert not {"DICOM_Modality", "DICOM_Segment_1_Label", "DICOM_SeriesInstanceUID",
                        "volwarp_distance"} & set(frame.meta)
    assert run("morph", plain, plain, "--frames", "2", "--iso", "0",
               "-o", tmp_path / "p_{i}.nrrd").code == 0
    assert read_volume(tmp_path / "p_0.nrrd").space is None  # (as its inputs: none named)
    frames = api.morph({"version": 1, "source": {"volume": str(src), "iso": 0},
                        "target": {"volume": str(plain), "iso": 0}, "frames": 2,
                        "grid": "union"})
    assert frames[0].volume.space == "left-posterior-superior"
    assert frames[0].volume.meta["my_key"] == "hello"


def test_a_frame_without_a_surface_is_said_not_written_silently(run, tmp_path):
    """Two small balls far apart: the middle frame's blend is positive everywhere (no
    shape), and its --mesh-to file an empty mesh, exit 0 without a word before (a review);
    a vanishing shape is a morph's right, so it is a warning naming the frame's file."""
    import logging

    from volwarp_cli.surface.mesh_io import read_mesh

    z, y, x = np.indices((16, 16, 40))
    for name, cx in (("a", 6.0), ("b", 33.0)):
        d = (np.sqrt((x - cx) ** 2 + (y - 8.0) ** 2 + (z - 8.0) ** 2) - 3).astype(np.float32)
        write_volume(Volume(d), tmp_path / f"{name}.nrrd")
    said: list[str] = []

    class Keep(logging.Handler):  # (the command's own handler writes to the first run's
        def emit(self, record):    # stderr: the logger's records are kept here)
            said.append(record.getMessage())

    keep = Keep(level=logging.WARNING)
    logging.getLogger("volwarp").addHandler(keep)
    try:
        res = run("morph", tmp_path / "a.nrrd", tmp_path / "b.nrrd", "--frames", 3, "--iso", 0,
                  "--inside", "below", "-o", tmp_path / "h_{i}.nrrd",
                  "--mesh-to", tmp_path / "h_{i}.ply")
    finally:
        logging.getLogger("volwarp").removeHandler(keep)
    assert res.code == 0, res.stderr
    assert read_mesh(tmp_path / "h_1.ply").n_faces == 0
    assert read_mesh(tmp_path / "h_0.ply").n_faces > 0
    said = [m for m in said if "no surface" in m]
    assert len(said) == 1 and "frame 1 (t = 0.5)" in said[0] and "h_1.ply" in said[0], said
