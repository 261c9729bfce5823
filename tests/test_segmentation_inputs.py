"""DICOM SEG and RTSTRUCT as label-map inputs of every command, and warped maps written back.

The input options (``--reference``, ``--segment``, ``--structure``) reach every
command through ``load_input`` / ``lazy_input``, so a SEG through ``distance``
is the distance of the same label map read from NRRD, an RTSTRUCT through
``mesh --labels`` the meshes of its rasterised map, a warped RTSTRUCT written
back against its series reads back as the warped map, and a batch manifest's
``reference`` column gives each scan its series.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
pytest.importorskip("highdicom")

from test_dicom_seg import labels_fixture, make_seg, masks_of, write_ct  # noqa: E402
from test_rtstruct import square, world, write_rtstruct  # noqa: E402

from volwarp_cli.io import read_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402

RS_SHAPE = (5, 14, 16)  # z, y, x


def split_nrrd(path: Path) -> tuple[list[bytes], bytes]:
    """An attached, uncompressed NRRD's header lines and its sample bytes."""
    raw = path.read_bytes()
    head, data = raw.split(b"\n\n", 1)
    return head.split(b"\n"), data


def same_but_input_name(a: Path, b: Path) -> None:
    """Byte-equal NRRD files but for the provenance line naming the input file."""
    (ha, da), (hb, db) = split_nrrd(a), split_nrrd(b)
    assert da == db
    assert [x for x in ha if not x.startswith(b"volwarp_input:=")] == \
        [x for x in hb if not x.startswith(b"volwarp_input:=")]


@pytest.fixture
def seg_case(tmp_path):
    folder = tmp_path / "ct"
    paths = write_ct(folder)
    seg = make_seg(paths, masks_of(labels_fixture()), "BINARY", tmp_path / "seg.dcm")
    return folder, seg


def liver_and_ptv(out: Path, folder: Path, paths) -> Path:
    """An RTSTRUCT of ROIs 3 (liver, slices 1-3) and 7 (PTV, slices 2-3) on the series."""
    vol = read_dicom(folder)
    return write_rtstruct(out, paths, {
        3: ("liver", [("CLOSED_PLANAR", world(vol, k, square(2.5, 2.5, 8.5, 9.5)))
                      for k in (1, 2, 3)]),
        7: ("PTV", [("CLOSED_PLANAR", world(vol, k, square(10.5, 3.5, 13.5, 7.5)))
                    for k in (2, 3)])})


@pytest.fixture
def rs_case(tmp_path):
    folder = tmp_path / "ct"
    paths = write_ct(folder, RS_SHAPE, spacing=(0.9, 0.6, 2.0))
    return folder, liver_and_ptv(tmp_path / "rs.dcm", folder, paths)


@pytest.mark.parametrize("grid", ["own", "reference"])
def test_seg_through_distance_equals_the_nrrd_label_maps(seg_case, tmp_path, run, grid):
    folder, seg = seg_case
    ref = ["--reference", folder] if grid == "reference" else []
    lab = tmp_path / "lab.nrrd"
    assert run("convert", seg, *ref, "-o", lab).code == 0
    a, b = tmp_path / "a.nrrd", tmp_path / "b.nrrd"
    res = run("distance", seg, *ref, "-o", a)
    assert res.code == 0, res.stderr
    assert run("distance", lab, "-o", b).code == 0
    same_but_input_name(a, b)
    # one segment as a 0/1 mask, by blocks too
    c, d = tmp_path / "c.nrrd", tmp_path / "d.nrrd"
    assert run("distance", seg, "--segment", "2", "--chunked", "-o", c).code == 0
    assert run("convert", seg, "--segment", "2", "-o", lab).code == 0
    assert run("distance", lab, "-o", d).code == 0
    same_but_input_name(c, d)


def test_rtstruct_structure_through_distance(rs_case, tmp_path, run):
    folder, rs = rs_case
    out, mask, want = tmp_path / "d.nrrd", tmp_path / "ptv.nrrd", tmp_path / "w.nrrd"
    res = run("distance", rs, "--reference", folder, "--structure", "PTV", "-o", out)
    assert res.code == 0, res.stderr
    assert run("convert", rs, "--reference", folder, "--structure", "PTV", "-o", mask).code == 0
    assert read_volume(mask).data.sum() == 2 * 3 * 4
    assert run("distance", mask, "-o", want).code == 0
    same_but_input_name(out, want)


def test_rtstruct_through_mesh_labels_equals_its_rasterised_map(rs_case, tmp_path, run):
    folder, rs = rs_case
    lab = tmp_path / "lab.nrrd"
    assert run("convert", rs, "--reference", folder, "-o", lab).code == 0
    res = run("mesh", rs, "--reference", folder, "--labels", "-o", tmp_path / "rs_{label}.ply",
              "--json")
    assert res.code == 0, res.stderr
    want = run("mesh", lab, "--labels", "-o", tmp_path / "lab_{label}.ply", "--json")
    assert want.code == 0, want.stderr
    assert json.loads(res.stdout) == json.loads(want.stdout)
    assert set(json.loads(res.stdout)) == {"3", "7"}
    for n in (3, 7):  # the same bytes but for the input's name in the provenance comment
        got = (tmp_path / f"rs_{n}.ply").read_bytes()
        assert b"rs.dcm" in got
        assert got.replace(b"rs.dcm", b"lab.nrrd") == (tmp_path / f"lab_{n}.ply").read_bytes()


def test_rtstruct_without_its_series_is_one_usage_line(rs_case, tmp_path, run):
    folder, rs = rs_case
    for argv in (("distance", rs, "-o", tmp_path / "d.nrrd"),
                 ("mesh", rs, "--labels", "-o", tmp_path / "m_{label}.ply")):
        res = run(*argv)
        assert res.code == 2 and "--reference" in res.stderr
        assert len(res.stderr.strip().splitlines()) == 1
    assert not list(tmp_path.glob("d.nrrd")) and not list(tmp_path.glob("m_*"))
    # the segmentation options on an input that is no segmentation
    lab = tmp_path / "lab.nrrd"
    assert run("convert", rs, "--reference", folder, "-o", lab).code == 0
    res = run("distance", lab, "--structure", "PTV", "-o", tmp_path / "d.nrrd")
    assert res.code == 2 and "--structure" in res.stderr
    res = run("distance", folder, "--reference", folder, "-o", tmp_path / "d.nrrd")
    assert res.code == 2 and "--reference" in res.stderr and "SEG and RTSTRUCT" in res.stderr


def test_info_of_an_rtstruct_on_its_series(rs_case, run):
    folder, rs = rs_case
    res = run("info", rs, "--reference", folder, "--json")
    assert res.code == 0, res.stderr
    desc = json.loads(res.stdout)
    assert desc["shape"] == [16, 14, 5] and desc["dicom_type"] == "RTSTRUCT"
    assert [s["name"] for s in desc["structures"]] == ["liver", "PTV"]
    assert desc["max"] == 7


WARP_SPEC = """version: 1
units: voxel
capture: {lattice: [6, 6, 5], oversample: 1}
steps:
  - move:
      - {index: [2, 2, 2], by: [3.0, 2.0, 0.0]}
      - {index: [3, 3, 2], by: [3.0, 2.0, 0.0]}
      - {index: [2, 3, 2], by: [3.0, 2.0, 0.0]}
      - {index: [3, 2, 2], by: [3.0, 2.0, 0.0]}
"""


@pytest.mark.parametrize("dicom_type", ["rtstruct", "labelmap-seg"])
def test_warp_then_write_back_against_the_reference(rs_case, tmp_path, run, dicom_type):
    folder, rs = rs_case
    spec = tmp_path / "w.yaml"
    spec.write_text(WARP_SPEC)
    warped = tmp_path / "warped.nrrd"
    res = run("warp", rs, "--reference", folder, "--spec", spec, "-o", warped)
    assert res.code == 0, res.stderr
    moved = read_volume(warped)
    lab = tmp_path / "lab.nrrd"
    assert run("convert", rs, "--reference", folder, "-o", lab).code == 0
    before = read_volume(lab)
    assert moved.same_grid(before) and not np.array_equal(moved.data, before.data)
    assert set(np.unique(moved.data)) <= {0, 3, 7}
    out = tmp_path / "out.dcm"
    res = run("convert", warped, "--reference", folder, "--dicom-type", dicom_type, "-o", out)
    assert res.code == 0, res.stderr
    back = tmp_path / "back.nrrd"
    assert run("convert", out, "--reference", folder, "-o", back).code == 0
    np.testing.assert_array_equal(read_volume(back).data, moved.data)


def test_batch_manifest_reference_column(rs_case, tmp_path, run):
    """Each scan of a CSV table gets the series in its row's ``reference`` cell."""
    folder, rs = rs_case
    other = tmp_path / "b" / "ct"
    paths = write_ct(other, RS_SHAPE, spacing=(0.9, 0.6, 2.0), seed=5)
    vol = read_dicom(other)
    rs_b = write_rtstruct(tmp_path / "b" / "rs_b.dcm", paths, {
        4: ("PTV", [("CLOSED_PLANAR", world(vol, 1, square(1.5, 1.5, 4.5, 4.5)))])})
    table = tmp_path / "scans.csv"
    table.write_text(f"path,reference\nrs.dcm,ct\n{rs_b.relative_to(tmp_path)},b/ct\n")
    manifest = tmp_path / "m.yaml"
    manifest.write_text(
        "version: 1\ninputs: {csv: scans.csv, settle: 0}\noutput_dir: out\nsteps:\n"
        "  - name: ptv\n    run: distance\n    output: '{stem}_ptv.nrrd'\n"
        "    options: [--reference, '{reference}', --structure, PTV]\n")
    res = run("batch", manifest, "-q")
    assert res.code == 0, res.stderr

    def statuses():
        res = run("batch", manifest, "-q", "--report-json", tmp_path / "r.json")
        assert res.code == 0, res.stderr
        report = json.loads((tmp_path / "r.json").read_text())
        return {s["scan"]: s["status"] for s in report["scans"]}

    # up to date on a second run; a changed reference series redoes its scan only
    assert statuses() == {"rs": "skipped", "b/rs_b": "skipped"}
    ds = pydicom.dcmread(paths[0])
    ds.PixelData = np.full((ds.Rows, ds.Columns), 7, "<i2").tobytes()
    ds.save_as(paths[0], enforce_file_format=True)
    assert statuses() == {"rs": "skipped", "b/rs_b": "ok"}
    # (read after the batches: this process notes what it reads as the run's inputs)
    for name, scan, ref in (("rs_ptv.nrrd", rs, folder), ("b/rs_b_ptv.nrrd", rs_b, other)):
        mask, want = tmp_path / f"mask_{scan.stem}.nrrd", tmp_path / f"want_{scan.stem}.nrrd"
        assert run("convert", scan, "--reference", ref, "--structure", "PTV", "-o",
                   mask).code == 0
        assert run("distance", mask, "-o", want).code == 0
        np.testing.assert_array_equal(read_volume(tmp_path / "out" / name).data,
                                      read_volume(want).data)


def test_batch_reference_placeholder_misuse(tmp_path, run):
    """``{reference}`` needs a table with the column, a whole value, an input option."""
    (tmp_path / "a.nrrd").write_bytes(b"")
    table = tmp_path / "scans.csv"
    table.write_text("path\na.nrrd\n")

    def manifest(inputs, options):
        m = tmp_path / "m.yaml"
        m.write_text(f"version: 1\ninputs: {inputs}\noutput_dir: out\nsteps:\n"
                     f"  - name: d\n    run: distance\n    output: '{{stem}}.nrrd'\n"
                     f"    options: {options}\n")
        return run("batch", m)

    for inputs, options, says in (
            ("{glob: '*.nrrd'}", "[--reference, '{reference}']", "inputs.csv"),
            ("{csv: scans.csv}", "[--reference, '{reference}']", "'reference' column"),
            ("{csv: scans.csv}", "[--reference, 'x/{reference}']", "whole option value"),
            ("{csv: with.csv}", "[--metric, '{reference}']", "input option")):
        (tmp_path / "with.csv").write_text("path,reference\na.nrrd,ct\n")
        res = manifest(inputs, options)
        assert res.code == 2 and says in res.stderr, (options, res.stderr)
        assert len(res.stderr.strip().splitlines()) == 1
