"""No output of any command may replace one of its inputs (DESIGN.md, "Inputs are never overwritten").

Every command and every output option is tried against an input: the same
name, a symbolic link to the input, the input through a linked folder, a hard
link, a detached header's data file, a pattern that names the input. Each
must be a usage error (exit 2, one line naming both files) before any work,
with every file of the folder untouched and nothing new in it. "Before any
work": the inputs' samples are truncated, so a command that read them first
would fail with exit 1 (a damaged file) instead.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from conftest import ball

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

WARP_SPEC = """version: 1
units: voxel
capture: {lattice: 5}
steps:
  - move:
      - {index: [2, 2, 2], by: [1.0, 0.0, 0.0]}
"""
TRANSFORM = "version: 1\ntranslate: [1.0, 0.0, 0.0]\n"
CAMERA = """{
  "volwarp_camera": 1,
  "frame": "LPS",
  "projection": "parallel",
  "position": [34.50000000000001, 34.5, 34.50000000000001],
  "focal_point": [14.500000000000004, 14.500000000000002, 14.500000000000004],
  "view_up": [-0.4082482904638631, -0.408248290463863, 0.816496580927726],
  "direction_of_projection": [-0.5773502691896258, -0.5773502691896257, -0.5773502691896258],
  "view_right": [-0.7071067811865475, 0.7071067811865476, 0.0],
  "parallel_scale": 11.340230290662861,
  "pixels_per_unit": 2.6454489222058326,
  "image_size": [80, 60],
  "bounds": [4.5, 24.5, 4.5, 24.5, 4.5, 24.5],
  "source": "ball_30_uint8.nrrd"
}"""
SWEEP_SPEC = """version: 1
grid: {spacing: 1.0, margin: 1}
sweeps:
  - name: rod
    template: {disc: {radius: 2}}
    trajectory: [{line: {from: [0, 0, 0], to: [0, 0, 6]}}]
"""


def _volume(path: Path, truncate: bool = True) -> None:
    write_volume(Volume(ball(12)), path)
    if truncate and path.suffix == ".nrrd":  # header intact, samples cut short
        data = path.read_bytes()
        path.write_bytes(data[:-100])


def _folder(tmp: Path) -> Path:
    """The inputs every case draws on (volumes truncated unless a case needs to read them)."""
    _volume(tmp / "vol.nrrd")
    write_volume(Volume(ball(12)), tmp / "det.nhdr")
    (tmp / "det.raw").write_bytes((tmp / "det.raw").read_bytes()[:-100])
    _volume(tmp / "f_002.nrrd")
    _volume(tmp / "other.nrrd")
    (tmp / "spec.yaml").write_text(WARP_SPEC)
    (tmp / "turn.yaml").write_text(TRANSFORM)
    (tmp / "sweep.yaml").write_text(SWEEP_SPEC)
    (tmp / "plain.raw").write_bytes(bytes(100))  # short of 12^3
    (tmp / "p.csv").write_text("x,y,z\n1,2,3\n")
    (tmp / "m.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    (tmp / "cam.json").write_text(CAMERA)
    os.link(tmp / "vol.nrrd", tmp / "hard.nrrd")
    os.symlink("vol.nrrd", tmp / "link.nrrd")
    os.symlink(".", tmp / "here")
    os.symlink("vol.nrrd", tmp / "link.png")
    os.symlink("vol.nrrd", tmp / "link.ply")
    os.symlink("vol.nrrd", tmp / "m_1.ply")
    os.symlink("vol.nrrd", tmp / "seg_1.ply")
    os.symlink("vol.nrrd", tmp / "t-001.png")
    os.symlink("vol.nrrd", tmp / "r_1.png")
    os.symlink("vol.nrrd", tmp / "link.vwc")
    os.symlink("spec.yaml", tmp / "spec_link.nrrd")
    os.symlink("spec.yaml", tmp / "spec_link.tfm")
    return tmp


#: (case id, argv, the input the message must name, the output it must name)
CASES = [
    # convert
    ("convert-same", ["convert", "vol.nrrd", "-o", "vol.nrrd"], "vol.nrrd", "vol.nrrd"),
    ("convert-symlink", ["convert", "vol.nrrd", "-o", "link.nrrd"], "vol.nrrd", "link.nrrd"),
    ("convert-linked-folder", ["convert", "vol.nrrd", "-o", "here/vol.nrrd"], "vol.nrrd",
     "here/vol.nrrd"),
    ("convert-hardlink", ["convert", "hard.nrrd", "-o", "vol.nrrd"], "hard.nrrd", "vol.nrrd"),
    ("convert-data-file", ["convert", "det.nhdr", "-o", "det.raw"], "det.nhdr", "det.raw"),
    ("convert-header-over-data", ["convert", "det.nhdr", "-o", "det.nhdr"], "det.nhdr",
     "det.nhdr"),
    ("convert-writes-data-over-input", ["convert", "plain.raw", "--raw-shape", "12", "12", "12",
                                        "--raw-dtype", "uint8", "-o", "plain.nhdr"],
     "plain.raw", "plain.nhdr"),
    # capture
    ("capture-symlink", ["capture", "vol.nrrd", "-o", "link.vwc"], "vol.nrrd", "link.vwc"),
    # distance
    ("distance-same", ["distance", "vol.nrrd", "--iso", "0.5", "-o", "vol.nrrd"], "vol.nrrd",
     "vol.nrrd"),
    ("distance-data-file", ["distance", "det.nhdr", "--iso", "0.5", "-o", "det.raw"],
     "det.nhdr", "det.raw"),
    ("distance-update-field", ["distance", "--update", "vol.nrrd", "--transform", "turn.yaml",
                               "-o", "vol.nrrd"], "vol.nrrd", "vol.nrrd"),
    # mesh
    ("mesh-output", ["mesh", "vol.nrrd", "--iso", "0.5", "-o", "link.ply"], "vol.nrrd",
     "link.ply"),
    ("mesh-render", ["mesh", "vol.nrrd", "--iso", "0.5", "--render", "link.png"], "vol.nrrd",
     "link.png"),
    ("mesh-camera", ["mesh", "vol.nrrd", "--iso", "0.5", "--render", "r.png", "--camera-from",
                     "cam.json", "--camera-to", "cam.json"], "cam.json", "cam.json"),
    ("mesh-labels-pattern", ["mesh", "vol.nrrd", "--labels", "-o", "seg_{label}.ply"],
     "vol.nrrd", "seg_1.ply"),
    ("mesh-turntable", ["mesh", "vol.nrrd", "--iso", "0.5", "--render", "t.png", "--turntable",
                        "3"], "vol.nrrd", "t-001.png"),
    # warp
    ("warp-same", ["warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "vol.nrrd"], "vol.nrrd",
     "vol.nrrd"),
    ("warp-over-spec", ["warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "spec_link.nrrd"],
     "spec.yaml", "spec_link.nrrd"),
    ("warp-frames-to", ["warp", "f_002.nrrd", "--spec", "spec.yaml", "-o", "o.nrrd",
                        "--frames-to", "f_{frame:03d}.nrrd"], "f_002.nrrd",
     "f_{frame:03d}.nrrd"),
    ("warp-displacement-to", ["warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "o.nrrd",
                              "--displacement-to", "vol.nrrd"], "vol.nrrd", "vol.nrrd"),
    ("warp-forward-field-to", ["warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "o.nrrd",
                               "--forward-field-to", "here/vol.nrrd"], "vol.nrrd",
     "here/vol.nrrd"),
    ("warp-jacobian-to", ["warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "o.nrrd",
                          "--jacobian-to", "link.nrrd"], "vol.nrrd", "link.nrrd"),
    ("warp-transform-to", ["warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "o.nrrd",
                           "--transform-to", "spec_link.tfm"], "spec.yaml", "spec_link.tfm"),
    ("warp-points-to", ["warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "o.nrrd",
                        "--points-in", "p.csv", "--points-to", "p.csv"], "p.csv", "p.csv"),
    ("warp-mesh-to", ["warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "o.nrrd",
                      "--mesh-in", "m.ply", "--mesh-to", "m.ply"], "m.ply", "m.ply"),
    # morph
    ("morph-output-pattern", ["morph", "f_002.nrrd", "other.nrrd", "--iso", "0.5", "--frames",
                              "3", "-o", "f_{i:03d}.nrrd"], "f_002.nrrd", "f_002.nrrd"),
    ("morph-mesh-to", ["morph", "vol.nrrd", "other.nrrd", "--iso", "0.5", "--frames", "3",
                       "-o", "o_{i}.nrrd", "--mesh-to", "m_{i}.ply"], "vol.nrrd", "m_1.ply"),
    ("morph-render-to", ["morph", "vol.nrrd", "other.nrrd", "--iso", "0.5", "--frames", "3",
                         "-o", "o_{i}.nrrd", "--render-to", "r_{i}.png"], "vol.nrrd",
     "r_1.png"),
    ("morph-sheet", ["morph", "vol.nrrd", "other.nrrd", "--iso", "0.5", "--frames", "3",
                     "-o", "o_{i}.nrrd", "--render-to", "rr_{i}.png", "--sheet", "link.png"],
     "vol.nrrd", "link.png"),
]


def _snapshot(folder: Path) -> dict[str, tuple]:
    """Every entry of the folder: a link's target, a file's bytes and times."""
    out = {}
    for p in sorted(folder.iterdir()):
        if p.is_symlink():
            out[p.name] = ("link", os.readlink(p))
        elif p.is_file():
            st = p.stat()
            out[p.name] = ("file", p.read_bytes(), st.st_mtime_ns, st.st_ino)
    return out


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_an_output_over_an_input_is_refused_before_any_work(run, tmp_path, monkeypatch, case):
    name, argv, input_name, output_name = case
    folder = _folder(tmp_path)
    monkeypatch.chdir(folder)
    before = _snapshot(folder)
    res = run(*argv)
    assert res.code == 2, res
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("volwarp: error:"), res.stderr
    assert "never replaces an input" in lines[0], lines[0]
    if output_name is not None:
        assert output_name in lines[0] and input_name in lines[0], lines[0]
    assert _snapshot(folder) == before


def test_the_check_follows_links_to_the_spec(run, tmp_path, monkeypatch):
    """A sweep's output that is a link to its own spec is refused."""
    folder = _folder(tmp_path)
    monkeypatch.chdir(folder)
    before = _snapshot(folder)
    res = run("sweep", "sweep.yaml", "-o", "spec_link.nrrd")
    assert res.code == 2, res
    assert _snapshot(folder) == before


def test_an_output_that_is_a_new_file_beside_the_input_is_written(run, tmp_path, monkeypatch):
    """The rule refuses only real collisions: the same folder, other names, works."""
    _volume(tmp_path / "vol.nrrd", truncate=False)
    write_volume(Volume(ball(12)), tmp_path / "det.nhdr")
    monkeypatch.chdir(tmp_path)
    assert run("convert", "vol.nrrd", "-o", "vol2.nrrd").code == 0
    assert run("convert", "det.nhdr", "-o", "copy.nhdr").code == 0
    assert run("distance", "det.nhdr", "--iso", "0.5", "-o", "det_sdf.nrrd").code == 0
    assert np.array_equal(np.fromfile(tmp_path / "copy.raw", np.uint8),
                          np.fromfile(tmp_path / "det.raw", np.uint8))


def test_a_writer_refuses_a_file_a_reader_opened_even_unannounced(tmp_path):
    """The write-time check: a file a reader opened is never replaced, declared or not."""
    from volwarp_cli.errors import BadUsage
    from volwarp_cli.io import read_volume
    from volwarp_cli.runscope import run_scope

    write_volume(Volume(ball(12)), tmp_path / "a.nhdr")
    before = (tmp_path / "a.raw").read_bytes()
    with run_scope():
        vol = read_volume(tmp_path / "a.nhdr")
        with pytest.raises(BadUsage, match="read as an input"):
            write_volume(vol, tmp_path / "a.raw")
    assert (tmp_path / "a.raw").read_bytes() == before


def test_list_and_pattern_headers_stand_for_every_data_file(tmp_path):
    """A NRRD LIST header and a MetaImage %d pattern: each listed file is the input's."""
    from volwarp_cli.errors import BadUsage
    from volwarp_cli.io.inputs import input_files, refuse_output_over_input

    (tmp_path / "s0.raw").write_bytes(bytes(4))
    (tmp_path / "s1.raw").write_bytes(bytes(4))
    (tmp_path / "list.nhdr").write_text(
        "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n"
        "data file: LIST\ns0.raw\ns1.raw\n")
    (tmp_path / "pat.mhd").write_text(
        "ObjectType = Image\nNDims = 3\nDimSize = 2 2 2\nElementType = MET_UCHAR\n"
        "ElementDataFile = s%d.raw 0 1 1\n")
    for header in ("list.nhdr", "pat.mhd"):
        files = input_files(tmp_path / header)
        assert [p.name for p in files] == [header, "s0.raw", "s1.raw"]
        with pytest.raises(BadUsage, match="s1.raw"):
            refuse_output_over_input(tmp_path / "s1.raw", [tmp_path / header])


def test_a_dicom_series_folder_owns_its_files(tmp_path):
    """Inside an input folder (a DICOM series, a store) no output may go: an existing file is
    the input's, and a new one would be read with it next time (a rerun would then refuse)."""
    from volwarp_cli.errors import BadUsage
    from volwarp_cli.io.inputs import refuse_output_over_input

    series = tmp_path / "series"
    series.mkdir()
    (series / "IM0001").write_bytes(b"x")
    with pytest.raises(BadUsage, match="input folder"):
        refuse_output_over_input(series / "IM0001", [series])
    (tmp_path / "store.zarr").mkdir()
    (tmp_path / "store.zarr" / "x.nrrd").write_bytes(b"x")
    with pytest.raises(BadUsage, match="inside it"):  # replacing the store would delete it
        refuse_output_over_input(tmp_path / "store.zarr", [tmp_path / "store.zarr" / "x.nrrd"])
    with pytest.raises(BadUsage, match="an output inside it"):
        refuse_output_over_input(series / "new.nrrd", [series])
    refuse_output_over_input(tmp_path / "new.nrrd", [series])  # beside it: fine


@pytest.mark.parametrize("pattern, hit", [
    ("f_{frame:03d}.nrrd", True), ("f_{frame}.nrrd", True), ("g_{frame:03d}.nrrd", False),
    ("f_{frame:03d}.nii.gz", False), ("sub/f_{frame}.nrrd", False),
    ("f_{frame:4d}.nrrd", True), ("f{frame}.nrrd", False),  # (a number never gives "_002")
    ("{frame}/f_002.nrrd", False),  # (the folder part is a number, not the whole path)
])
def test_a_pattern_is_refused_when_it_can_name_an_input(tmp_path, monkeypatch, pattern, hit):
    from volwarp_cli.errors import BadUsage
    from volwarp_cli.io.inputs import refuse_pattern_over_input

    monkeypatch.chdir(tmp_path)
    (tmp_path / "sub").mkdir()
    (tmp_path / "f_002.nrrd").write_bytes(b"")
    if hit:
        with pytest.raises(BadUsage, match="f_002.nrrd"):
            refuse_pattern_over_input(pattern, inputs=["f_002.nrrd"])
    else:
        refuse_pattern_over_input(pattern, inputs=["f_002.nrrd"])


def test_a_file_a_spec_names_is_an_input(run, tmp_path, monkeypatch):
    """A morph spec's shapes and a sweep's template images are inputs too (named by the spec)."""
    import shutil

    specs = Path(__file__).parent.parent / "specs"
    monkeypatch.chdir(tmp_path)
    _volume(tmp_path / "f_1.nrrd")  # truncated: read first, it would fail with exit 1
    _volume(tmp_path / "b.nrrd")
    (tmp_path / "m.yaml").write_text("version: 1\nsource: {volume: f_1.nrrd, iso: 0.5}\n"
                                     "target: {volume: b.nrrd, iso: 0.5}\nframes: 3\n")
    (tmp_path / "templates").mkdir()
    for name in ("bottle_opacity.png", "bottle_colour.png", "bottle_geometry.png"):
        shutil.copy(specs / "templates" / name, tmp_path / "templates" / name)
    shutil.copy(specs / "sweep-bottle.yaml", tmp_path / "s.yaml")
    before = _snapshot(tmp_path), _snapshot(tmp_path / "templates")
    res = run("morph", "--spec", "m.yaml", "-o", "f_{i}.nrrd")
    assert res.code == 2 and "f_1.nrrd would overwrite the input" in res.stderr, res
    res = run("sweep", "s.yaml", "-o", "x_{field}.nrrd", "--render",
              "templates/bottle_colour.png")
    assert res.code == 2 and "bottle_colour.png would overwrite the input" in res.stderr, res
    # --camera-to is checked again once the spec has named its inputs: before any work
    res = run("sweep", "s.yaml", "-o", "x_{field}.nrrd", "--render", "x.png", "--camera-to",
              "templates/bottle_colour.png")
    assert res.code == 2 and "--camera-to templates/bottle_colour.png would" in res.stderr, res
    res = run("morph", "--spec", "m.yaml", "-o", "g_{i}.nrrd", "--render-to", "g_{i}.png",
              "--camera-to", "b.nrrd")
    assert res.code == 2 and "--camera-to b.nrrd would overwrite the input" in res.stderr, res
    assert (_snapshot(tmp_path), _snapshot(tmp_path / "templates")) == before


def test_a_pattern_of_numbers_never_names_an_input_of_letters(run, tmp_path, monkeypatch):
    """`head_{frame:03d}.nrrd` gives head_000.nrrd, head_001.nrrd...: never head_t1.nrrd."""
    monkeypatch.chdir(tmp_path)
    _volume(tmp_path / "head_t1.nrrd", truncate=False)
    (tmp_path / "spec.yaml").write_text(WARP_SPEC)
    res = run("warp", "head_t1.nrrd", "--spec", "spec.yaml", "-o", "w.nrrd", "--frames-to",
              "head_{frame:03d}.nrrd")
    assert res.code == 0, res
    assert (tmp_path / "head_000.nrrd").exists() and (tmp_path / "head_001.nrrd").exists()


def test_the_message_names_the_option(run, tmp_path, monkeypatch):
    monkeypatch.chdir(_folder(tmp_path))
    res = run("warp", "vol.nrrd", "--spec", "spec.yaml", "-o", "o.nrrd", "--jacobian-to",
              "vol.nrrd")
    assert res.code == 2 and "error: --jacobian-to vol.nrrd would overwrite" in res.stderr, res


@pytest.mark.parametrize("argv, message", [
    (["warp", "b.nrrd", "--spec", "spec.yaml", "-o", "q.nrrd", "--jacobian-to", "q.nrrd"],
     "--jacobian-to q.nrrd and -o name the same file"),
    (["mesh", "b.nrrd", "--iso", "0.5", "-o", "m.ply", "--render", "r.png", "--camera-to",
      "m.ply"], "name the same file m.ply"),
    (["morph", "b.nrrd", "b.nrrd", "--iso", "0.5", "--frames", "2", "-o", "f{i}.nrrd",
      "--render-to", "r{i}.png", "--sheet", "r0.png"], "--sheet r0.png and --render-to"),
    (["warp", "b.nrrd", "--spec", "spec.yaml", "-o", "q.nhdr", "--jacobian-to", "q.raw"],
     "name the same file"),  # (q.nhdr's data file)
])
def test_two_outputs_of_one_command_at_one_path_are_refused(run, tmp_path, monkeypatch, argv,
                                                           message):
    """The last write won, silently (the volume lost): now a usage error before any work."""
    monkeypatch.chdir(tmp_path)
    _volume(tmp_path / "b.nrrd", truncate=False)
    (tmp_path / "spec.yaml").write_text(WARP_SPEC)
    before = _snapshot(tmp_path)
    res = run(*argv)
    assert res.code == 2 and message in res.stderr, res
    assert _snapshot(tmp_path) == before
