"""`volwarp mesh` end to end: outputs, statistics, renders, errors and exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.images import read_image
from volwarp_cli.volume import Volume


@pytest.fixture
def messages():
    """Messages logged by the "volwarp" logger during the test.

    (The CLI's log handler writes to the sys.stderr of the first command run
    in the process, so CliRunner does not see later commands' log lines.)
    """
    import logging

    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    handler = Keep(level=logging.DEBUG)
    logger = logging.getLogger("volwarp")
    logger.addHandler(handler)
    yield records
    logger.removeHandler(handler)


@pytest.fixture
def sphere_file(tmp_path):
    """A smooth sphere field (radius 9, positive inside) with world geometry, as NRRD."""
    r = 9.0
    z, y, x = np.indices((26, 24, 28)).astype(np.float32)
    f = r - np.sqrt(((x - 14) * 0.8) ** 2 + (y - 12) ** 2 + ((z - 13) * 1.0) ** 2)
    vol = Volume(f.astype(np.float32), spacing=(0.8, 1.0, 1.0), origin=(-20.0, 5.0, 100.0))
    path = tmp_path / "sphere.nrrd"
    write_volume(vol, path)
    center = np.array([-20.0 + 14 * 0.8, 5.0 + 12, 100.0 + 13])
    return path, r, center


def test_mesh_stats_json_and_ply(run, sphere_file, tmp_path):
    path, r, center = sphere_file
    out = tmp_path / "s.ply"
    res = run("mesh", path, "-o", out, "--iso", "0", "--json")
    assert res.code == 0, res.stderr
    st = json.loads(res.stdout)
    assert st["closed"] is True and st["components"] == 1
    assert st["volume"] == pytest.approx(4 / 3 * np.pi * r**3, rel=0.01)
    assert st["area"] == pytest.approx(4 * np.pi * r**2, rel=0.02)
    np.testing.assert_allclose(st["bbox_min"], center - r, atol=0.05)
    np.testing.assert_allclose(st["bbox_max"], center + r, atol=0.05)
    import trimesh

    m = trimesh.load(str(out), process=False)
    assert len(m.faces) == st["triangles"] and len(m.vertices) == st["vertices"]
    assert m.is_watertight and m.volume == pytest.approx(st["volume"], rel=1e-4)


def test_text_stats_and_default_iso(run, sphere_file, tmp_path, messages):
    path, _, _ = sphere_file
    res = run("mesh", path, "--stats", "-v")
    assert res.code == 0, res.stderr
    st = json.loads(run("mesh", path, "--json").stdout)
    assert f"triangles:  {st['triangles']}" in res.stdout
    assert f"components: {st['components']}" in res.stdout
    assert ("closed:     yes" if st["closed"] else "closed:     no") in res.stdout
    vol = read_volume(path)
    mid = 0.5 * (float(vol.data.min()) + float(vol.data.max()))
    # the default level is reported with --verbose
    assert any("middle of the value range" in m and f"{mid:g}" in m for m in messages)
    # the default level (middle of the range) is what --iso of that value gives
    a = json.loads(run("mesh", path, "--json").stdout)
    b = json.loads(run("mesh", path, "--json", "--iso", repr(mid)).stdout)
    assert a["triangles"] == b["triangles"] and a["iso"] == pytest.approx(mid)


@pytest.mark.parametrize("ext", ["ply", "stl", "obj", "vtp", "vtk"])
def test_every_format_and_deterministic(run, sphere_file, tmp_path, ext):
    import pyvista as pv

    path, _, _ = sphere_file
    a, b = tmp_path / f"a.{ext}", tmp_path / f"b.{ext}"
    assert run("mesh", path, "-o", a, "--iso", "0").code == 0
    assert run("mesh", path, "-o", b, "--iso", "0").code == 0
    assert a.read_bytes() == b.read_bytes()
    st = json.loads(run("mesh", path, "--iso", "0", "--json").stdout)
    m = pv.read(str(a))
    assert m.n_cells == st["triangles"]
    if ext != "stl":
        assert m.n_points == st["vertices"]


def test_smooth_decimate_largest_component(run, tmp_path):
    z, y, x = np.indices((30, 30, 44)).astype(np.float32)
    mask = (((x - 12) ** 2 + (y - 15) ** 2 + (z - 15) ** 2) <= 81) | \
           (((x - 33) ** 2 + (y - 15) ** 2 + (z - 15) ** 2) <= 25)
    path = tmp_path / "two.nrrd"
    write_volume(Volume(mask.astype(np.uint8)), path)
    base = json.loads(run("mesh", path, "--iso", "0.5", "--json").stdout)
    assert base["components"] == 2
    res = run("mesh", path, "--iso", "0.5", "--largest-component", "--smooth", "15",
              "--decimate", "0.5", "--json", "-o", tmp_path / "one.stl")
    assert res.code == 0, res.stderr
    st = json.loads(res.stdout)
    assert st["components"] == 1 and st["closed"]
    # the big ball (r = 9) survives, smoothed and decimated, its volume about the voxel count
    assert st["volume"] == pytest.approx(mask[:, :, :23].sum(), rel=0.05)
    assert st["bbox_min"][0] < 4 and st["bbox_max"][0] < 23
    assert st["triangles"] < 0.55 * (base["triangles"] * 0.8)
    # one iteration: VTK's filter finds no offset and collapses the mesh (0.5% of its volume,
    # "closed", exit 0, and VTK's message ahead of the JSON on stdout): refused, no output
    res = run("mesh", path, "--iso", "0.5", "--smooth", "1", "--json", "-o", tmp_path / "x.ply")
    assert res.code == 2 and "0 (off) or at least 2" in res.stderr and res.stdout == ""
    assert not (tmp_path / "x.ply").exists()
    two = json.loads(run("mesh", path, "--iso", "0.5", "--smooth", "2", "--json").stdout)
    assert two["volume"] == pytest.approx(base["volume"], rel=0.02)


def test_cap_closes_a_border_shape(run, tmp_path, messages):
    data = np.zeros((12, 12, 12), dtype=np.uint8)
    data[:, 3:9, 3:9] = 200  # a bar through the whole z extent
    path = tmp_path / "bar.nrrd"
    write_volume(Volume(data), path)
    # (as a label map its surface is closed at the border, as every label's: intensities)
    res = run("mesh", path, "--iso", "100", "--json", "--values", "intensity")
    assert res.code == 0
    assert json.loads(res.stdout)["closed"] is False
    assert any("--cap" in m for m in messages)  # the warning says how to close it
    res = run("mesh", path, "--iso", "100", "--json", "--cap", "--values", "intensity")
    st = json.loads(res.stdout)
    assert st["closed"] is True and st["volume"] > 0
    assert st["bbox_min"][2] == pytest.approx(-0.5) and st["bbox_max"][2] == pytest.approx(11.5)


def test_inside_below_for_distance_fields(run, sphere_file, tmp_path):
    path, r, _ = sphere_file
    vol = read_volume(path)
    neg = tmp_path / "neg.nrrd"
    write_volume(vol.with_data(-vol.data), neg)
    st = json.loads(run("mesh", neg, "--iso", "0", "--inside", "below", "--json").stdout)
    assert st["volume"] == pytest.approx(4 / 3 * np.pi * r**3, rel=0.01)


def test_render_png_size_and_turntable(run, sphere_file, tmp_path):
    path, _, _ = sphere_file
    png = tmp_path / "s.png"
    res = run("mesh", path, "--iso", "0", "--render", png, "--size", "320x200",
              "--view", "30,10", "--color", "steelblue", "--background", "#000000")
    assert res.code == 0, res.stderr
    img = read_image(png, normalize=False)
    assert img.shape == (200, 320, 3) and img.dtype == np.uint8
    assert tuple(img[0, 0]) == (0, 0, 0)
    covered = img.max(axis=2) > 8
    assert 0.1 < covered.mean() < 0.9
    # turntable: N frames named after --render
    res = run("mesh", path, "--iso", "0", "--render", tmp_path / "t.png", "--turntable", "3",
              "--size", "64x48")
    assert res.code == 0, res.stderr
    names = sorted(p.name for p in tmp_path.glob("t-*.png"))
    assert names == ["t-000.png", "t-001.png", "t-002.png"]
    assert not (tmp_path / "t.png").exists()


def test_render_of_the_coronal_scan(run, data_dir, tmp_path):
    """A real scan with a rotated direction matrix renders upright (z up) and closed pieces."""
    png = tmp_path / "head.png"
    res = run("mesh", data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd", "--iso", "60", "--cap",
              "--render", png, "--view", "x", "--size", "200x200", "--json")
    assert res.code == 0, res.stderr
    st = json.loads(res.stdout)
    assert st["closed"] is True
    vol = read_volume(data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd")
    lo, hi = vol.world_bounds()
    assert np.all(np.array(st["bbox_min"]) >= lo - 3.0)
    assert np.all(np.array(st["bbox_max"]) <= hi + 3.0)
    assert read_image(png).shape == (200, 200, 3)


def test_iso_outside_range_is_an_error_and_writes_nothing(run, sphere_file, tmp_path,
                                                          messages):
    path, _, _ = sphere_file
    out = tmp_path / "e.ply"
    res = run("mesh", path, "-o", out, "--iso", "1000")
    assert res.code == 1
    assert "outside the data range" in res.stderr and res.stderr.count("\n") == 1
    assert not out.exists()
    # --allow-empty: a warning, exit 0, an empty (valid) mesh written
    res = run("mesh", path, "-o", out, "--iso", "1000", "--allow-empty", "--json",
              "--render", tmp_path / "e.png", "--size", "20x10")
    assert res.code == 0
    assert any("empty" in m for m in messages)
    assert json.loads(res.stdout)["triangles"] == 0
    assert out.exists() and b"element face 0" in out.read_bytes()
    assert np.all(read_image(tmp_path / "e.png") == 1.0)


def test_a_volume_of_one_value_says_so(run, tmp_path):
    """A label filling the whole grid was said as "iso level 0.5 is outside the data range
    [1, 1]", a plain constant volume as a level "never crossed": one value everywhere."""
    path = tmp_path / "one.nrrd"
    write_volume(Volume(np.ones((6, 6, 6), np.uint8)), path)
    for extra in ([], ["--labels"]):
        out = tmp_path / ("o_{label}.ply" if extra else "o.ply")
        res = run("mesh", path, "-o", out, *extra)
        assert res.code == 1 and res.stderr.count("\n") == 1, res.stderr
        assert "is 1: there is no surface at any level" in res.stderr
    assert not list(tmp_path.glob("o*.ply"))


def test_level_never_crossed_is_an_error(run, tmp_path):
    path = tmp_path / "flat.nrrd"
    data = np.zeros((5, 5, 5), dtype=np.uint8)
    data[2, 2, 2] = 10
    write_volume(Volume(data), path)
    # at the minimum every sample counts as above the level: nothing is crossed (the ids
    # taken as intensities: as a label map, a level selecting voxel 0 too is refused)
    res = run("mesh", path, "--iso", "0", "--values", "intensity", "-o", tmp_path / "x.ply")
    assert res.code == 1 and "never crossed" in res.stderr
    assert not (tmp_path / "x.ply").exists()
    # a sample exactly at the level counts as above it: the lone voxel is a small closed surface
    res = run("mesh", path, "--iso", "10", "--values", "intensity", "--json")
    assert res.code == 0 and json.loads(res.stdout)["closed"] is True


def test_bad_outputs_fail_before_work(run, sphere_file, tmp_path):
    path, _, _ = sphere_file
    res = run("mesh", path, "-o", tmp_path / "m.off", "--iso", "0")
    assert res.code == 2 and "unknown mesh extension" in res.stderr
    res = run("mesh", path, "-o", tmp_path / "missing" / "m.ply", "--iso", "0")
    assert res.code == 1 and "does not exist" in res.stderr
    # an existing folder, or a file where the folder should be
    res = run("mesh", path, "-o", tmp_path, "--iso", "0")  # click refuses it: usage error
    assert res.code == 2 and "directory" in res.stderr
    (tmp_path / "plain").write_text("x")
    res = run("mesh", path, "-o", tmp_path / "plain" / "m.ply", "--iso", "0")
    assert res.code == 1
    res = run("mesh", path, "--iso", "0", "--render", tmp_path / "missing" / "x.png")
    assert res.code == 1 and "does not exist" in res.stderr


@pytest.fixture
def read_only_folder(tmp_path):
    """A folder nothing can be written in, for root too.

    As root (CI) folder permissions are ignored: a read-only tmpfs mounted
    there (skipped only where mounting is impossible); otherwise mode 0500.
    """
    import os
    import subprocess

    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() != 0:
        ro.chmod(0o500)
        yield ro
        ro.chmod(0o700)
        return
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(ro)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"root, and no read-only tmpfs can be mounted: {mounted.stderr.strip()}")
    try:
        yield ro
    finally:
        subprocess.run(["umount", str(ro)], check=True)


def test_read_only_folder(run, sphere_file, read_only_folder):
    path, _, _ = sphere_file
    with pytest.raises(OSError):  # the folder is what the test says it is
        (read_only_folder / "probe").write_bytes(b"x")
    res = run("mesh", path, "-o", read_only_folder / "m.ply", "--iso", "0")
    assert res.code == 1 and "not writable" in res.stderr
    assert list(read_only_folder.iterdir()) == []


def test_bad_render_options_and_usage(run, sphere_file, tmp_path):
    path, _, _ = sphere_file
    res = run("mesh", path, "--render", tmp_path / "x.gifx")
    assert res.code == 2 and "unknown image extension" in res.stderr
    for args in (["--size", "big"], ["--view", "sideways"], ["--color", "blurple"],
                 ["--decimate", "1.5"], ["--smooth", "-2"]):
        res = run("mesh", path, "--render", tmp_path / "x.png", *args)
        assert res.code == 2, args
        assert not (tmp_path / "x.png").exists()
    res = run("mesh", path)
    assert res.code == 2 and "nothing to do" in res.stderr
    res = run("mesh", path, "--turntable", "4", "--stats")
    assert res.code == 2 and "--render" in res.stderr
    res = run("mesh", tmp_path / "nope.nrrd", "--stats")
    assert res.code == 1


def test_raw_input(run, tmp_path):
    z, y, x = np.indices((16, 16, 16))
    data = ((x - 7.5) ** 2 + (y - 7.5) ** 2 + (z - 7.5) ** 2 <= 25).astype(np.uint8) * 100
    raw = tmp_path / "ball.raw"
    raw.write_bytes(data.tobytes())
    res = run("mesh", raw, "--raw-shape", "16", "16", "16", "--raw-dtype", "uint8",
              "--raw-spacing", "2", "2", "2", "--iso", "50", "--json")
    assert res.code == 0, res.stderr
    st = json.loads(res.stdout)
    assert st["closed"] and st["volume"] == pytest.approx(8 * (data > 0).sum(), rel=0.08)


def test_nan_samples_are_refused(run, tmp_path):
    data = np.zeros((6, 6, 6), dtype=np.float32)
    data[3, 3, 3] = np.nan
    path = tmp_path / "nan.nrrd"
    write_volume(Volume(data), path)
    res = run("mesh", path, "--iso", "0.5", "--stats")
    assert res.code == 1 and "NaN" in res.stderr


@pytest.fixture
def two_labels(tmp_path):
    """A ball of label 7 (radius 8) beside a box of label 300 touching the volume's border,
    anisotropic spacing, as uint16 NRRD."""
    z, y, x = np.indices((30, 28, 40))
    lab = np.zeros((30, 28, 40), np.uint16)
    lab[(x - 12) ** 2 + (y - 14) ** 2 + (z - 15) ** 2 <= 64] = 7
    lab[5:25, 4:24, 26:40] = 300  # reaches x's last plane
    spacing = (0.5, 1.0, 2.0)
    path = tmp_path / "seg.nrrd"
    write_volume(Volume(lab, spacing=spacing), path)
    return path, lab, float(np.prod(spacing))


@pytest.mark.parametrize("label", [7, 300])
def test_mesh_label_is_closed_with_the_labels_volume(run, two_labels, tmp_path, label):
    path, lab, voxel = two_labels
    res = run("mesh", path, "--label", str(label), "-o", tmp_path / "l.ply", "--json")
    assert res.code == 0, res.stderr
    st = json.loads(res.stdout)
    assert st["closed"] is True and st["components"] == 1  # the box is capped at the border
    want = float((lab == label).sum()) * voxel
    assert st["volume"] == pytest.approx(want, rel=0.04)
    assert st["iso"] == 0.5


def test_mesh_labels_writes_one_mesh_per_label(run, two_labels, tmp_path):
    from volwarp_cli.surface.mesh_io import read_mesh

    path, lab, voxel = two_labels
    res = run("mesh", path, "--labels", "-o", tmp_path / "seg_{label}.ply", "--json")
    assert res.code == 0, res.stderr
    st = json.loads(res.stdout)
    assert sorted(st) == ["300", "7"]
    for label in (7, 300):
        mesh = read_mesh(tmp_path / f"seg_{label}.ply")
        assert mesh.n_faces == st[str(label)]["triangles"] > 0
        assert st[str(label)]["volume"] == pytest.approx(float((lab == label).sum()) * voxel,
                                                         rel=0.04)


def test_mesh_label_usage_errors(run, two_labels, tmp_path, sphere_file):
    path, _, _ = two_labels
    res = run("mesh", path, "--labels", "-o", tmp_path / "seg.ply")
    assert res.code == 2 and "{label}" in res.stderr
    res = run("mesh", path, "--label", "7", "--iso", "3", "--stats")
    assert res.code == 2 and "--iso does not apply" in res.stderr
    for args in (["--label", "7"], ["--labels"]):  # was accepted and ignored
        res = run("mesh", path, *args, "--inside", "below", "--stats")
        assert res.code == 2 and "--inside does not apply" in res.stderr, res
    res = run("mesh", path, "--label", "8", "--stats")
    assert res.code == 1 and "does not occur" in res.stderr
    res = run("mesh", sphere_file[0], "--label", "1", "--stats")
    assert res.code == 1 and "integer" in res.stderr
    # a pattern that gives two labels (1 and 12: their first digit) one file: the second
    # mesh would replace the first (exit 0, before); refused before any is written
    lab = np.zeros((12, 12, 12), np.uint8)
    lab[2:5, 2:5, 2:5], lab[7:10, 2:5, 2:5] = 1, 12
    write_volume(Volume(lab), tmp_path / "two.nrrd")
    res = run("mesh", tmp_path / "two.nrrd", "--labels", "-o", tmp_path / "s_{label!s:.1}.ply")
    assert res.code == 2 and "names labels 1 and 12 both" in res.stderr, res.stderr
    assert not list(tmp_path.glob("s_*.ply"))


def test_a_label_map_is_meshed_as_its_labels_not_its_ids(run, two_labels, tmp_path):
    """DESIGN.md: mesh follows the label rule. The old default (the middle of the range,
    150 for ids 0, 7, 300) meshed the box of 300 alone; the rule gives the surface of
    every voxel with a non-zero label, closed at the border as a label's is."""
    from volwarp_cli.surface.mesh_io import read_mesh

    path, lab, voxel = two_labels
    res = run("mesh", path, "-o", tmp_path / "all.ply", "--json")
    assert res.code == 0, res.stderr
    st = json.loads(res.stdout)
    assert (st["values"], st["values_why"]) == ("labels", "looks like a label map: 3 labels")
    assert st["closed"] is True and st["components"] == 2 and st["iso"] == 0.5
    assert st["volume"] == pytest.approx(float((lab != 0).sum()) * voxel, rel=0.04)
    # the ids never count: renamed ids give the same file, byte for byte
    renamed = np.select([lab == 7, lab == 300], [2, 1], 0).astype(np.uint16)
    write_volume(Volume(renamed, spacing=(0.5, 1.0, 2.0)), tmp_path / "renamed.nrrd")
    assert run("mesh", tmp_path / "renamed.nrrd", "-o", tmp_path / "renamed.ply").code == 0
    a, b = read_mesh(tmp_path / "all.ply"), read_mesh(tmp_path / "renamed.ply")
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert b"volwarp_values=labels" in (tmp_path / "all.ply").read_bytes()[:2000]
    # a level that selects exactly the non-zero labels is the same surface
    res = run("mesh", path, "--iso", "1", "-o", tmp_path / "iso1.ply")
    assert res.code == 0, res.stderr
    assert np.array_equal(read_mesh(tmp_path / "iso1.ply").vertices, a.vertices)
    # the ids as intensities only when asked: the old answer, the box of 300 at 150
    st = json.loads(run("mesh", path, "--values", "intensity", "--cap", "--json").stdout)
    assert (st["values"], st["iso"]) == ("intensity", 150.0)
    assert st["volume"] == pytest.approx(float((lab == 300).sum()) * voxel, rel=0.06)


def test_a_label_map_level_between_ids_is_refused(run, two_labels, tmp_path):
    path, _, _ = two_labels
    out = tmp_path / "m.ply"
    out.write_bytes(b"old")
    for args, said in ((["--iso", "100"], "--iso 100 selects other voxels"),
                       (["--iso", "0.5", "--inside", "below"], "--iso 0.5 --inside below"),
                       (["--inside", "below"], "--inside goes with --iso V")):
        res = run("mesh", path, *args, "-o", out)
        assert res.code == 2 and said in res.stderr and "--values intensity" in res.stderr, res
        assert out.read_bytes() == b"old"
    res = run("mesh", path, "--label", "7", "--values", "intensity", "--stats")
    assert res.code == 2 and "--values intensity" in res.stderr
    # floats with a fraction are no label map: --values labels is refused, naming why
    data = np.full((6, 6, 6), 0.25, np.float32)
    data[2:4, 2:4, 2:4] = 3.5
    write_volume(Volume(data), tmp_path / "f.nrrd")
    res = run("mesh", tmp_path / "f.nrrd", "--values", "labels", "--stats")
    assert res.code == 2 and "not all integers" in res.stderr


def test_the_api_mesh_follows_the_label_rule_as_the_command_does(run, two_labels, tmp_path):
    from volwarp_cli import api
    from volwarp_cli.errors import BadUsage
    from volwarp_cli.surface.mesh_io import read_mesh

    path, _, _ = two_labels
    assert run("mesh", path, "-o", tmp_path / "cli.ply").code == 0
    mesh = api.mesh(path)
    assert np.array_equal(mesh.vertices, read_mesh(tmp_path / "cli.ply").vertices)
    assert mesh.meta["volwarp_values"] == "labels"
    with pytest.raises(BadUsage, match="selects other voxels"):
        api.mesh(path, iso=100)
    assert api.mesh(path, iso=100, values="intensity").n_faces > 0


def test_a_tiff_render_carries_no_time_stamp(run, tmp_path):
    """Identical runs give identical bytes: the TIFF writer stamped the time of writing."""
    import tifffile

    src = Path(__file__).parent / "data" / "ball_30_uint8.nrrd"
    out = tmp_path / "r.tif"
    assert run("mesh", src, "--iso", "100", "--render", out, "--render-size", "60x40").code == 0
    with tifffile.TiffFile(out) as tif:
        tags = {t.name: t.value for t in tif.pages[0].tags.values()}
    assert tags.get("DateTime", "") == "" and "XMP" not in tags, tags


def test_a_mask_is_meshed_at_its_level_as_asked(run, tmp_path):
    """A mask (two values) mixes no ids: its --iso, --inside and --cap mean what they say.
    The label rule had replaced a given --iso 50 by its indicator's 0.5 and capped the
    border unasked; a 100/200 mask (no 0) failed as if empty; an all-zero map read from a
    SEG ignored --allow-empty (a review of this session's change)."""
    data_dir = Path(__file__).parent / "data"
    st = json.loads(run("mesh", data_dir / "ball_30_uint8.nrrd", "--iso", "50", "--json").stdout)
    assert st["iso"] == 50.0 and st["values"] == "intensity"
    assert st["volume"] == pytest.approx(4467.19, rel=1e-4)  # (at 50 of 0..200: a larger ball)
    slab = np.zeros((10, 12, 14), np.uint8)
    slab[:, :, :5] = 1  # touches the border at x = 0
    write_volume(Volume(slab), tmp_path / "slab.nrrd")
    st = json.loads(run("mesh", tmp_path / "slab.nrrd", "--iso", "0.5", "--json").stdout)
    assert st["closed"] is False  # (open at the border, as asked: no --cap)
    ball = np.where(read_volume(data_dir / "ball_30_uint8.nrrd").data > 0, 200, 100)
    write_volume(Volume(ball.astype(np.uint8)), tmp_path / "b.nrrd")
    res = run("mesh", tmp_path / "b.nrrd", "--json")
    assert res.code == 0, res.stderr
    assert json.loads(res.stdout)["iso"] == 150.0 and json.loads(res.stdout)["components"] == 1
    empty = Volume(np.zeros((6, 6, 6), np.uint8), meta={"DICOM_Modality": "SEG"})
    write_volume(empty, tmp_path / "e.nrrd")
    for extra in ([], ["--values", "labels"]):
        res = run("mesh", tmp_path / "e.nrrd", "--allow-empty", "-o", tmp_path / "e.ply", *extra)
        assert res.code == 0, (extra, res.stderr)
    res = run("mesh", tmp_path / "e.nrrd", "--values", "labels", "-o", tmp_path / "e2.ply")
    assert res.code == 1 and "--allow-empty" in res.stderr


def test_an_empty_surfaces_render_and_camera_frame_the_volume(run, tmp_path):
    """--allow-empty rendered with a camera at the world's origin: its --camera-to file
    framed nothing of a volume far from it, and a later render through it of a surface
    that appeared was empty (a review). The camera of an empty surface frames the
    volume's box, as the surface would."""
    data = np.zeros((12, 14, 16), np.float32)
    data[4:8, 5:9, 6:10] = 200
    src = tmp_path / "far.nrrd"
    write_volume(Volume(data, origin=np.array([500.0, 300.0, -200.0])), src)
    cam = tmp_path / "e.json"
    res = run("mesh", src, "--iso", "300", "--allow-empty", "--render", tmp_path / "e.png",
              "--camera-to", cam)
    assert res.code == 0, res.stderr
    focal = np.array(json.loads(cam.read_text())["focal_point"])
    assert np.all(focal >= [499.5, 299.5, -200.5]) and np.all(focal <= [515.5, 313.5, -188.5])
    res = run("mesh", src, "--iso", "100", "--render", tmp_path / "after.png",
              "--camera-from", cam)
    assert res.code == 0 and "outside the camera's picture" not in res.stderr, res.stderr
    image = read_image(tmp_path / "after.png")
    assert len(np.unique(image.reshape(-1, image.shape[-1]), axis=0)) > 2  # (a surface drawn)
