"""Outputs that destroy an input, or an earlier output of the same run, by another spelling.

A folder input read through links (a DICOM series of links to slices kept
elsewhere, an OME-Zarr store whose array is a link into another store) reads
files outside the folder: an output named after a link's target replaced a
slice of the series, or the store's array, with exit 0. A morph pattern
whose frames differ as strings but name one file (links, ``a{i}/../f``) kept
one frame of them, with exit 0. Each must be one usage error line (exit 2)
with every file left as it was.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pydicom
from conftest import ball
from test_io_dicom import write_series

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

SPEC = """version: 1
units: voxel
capture: {lattice: 5}
steps:
  - move:
      - {index: [2, 2, 2], by: [1.0, 0.0, 0.0]}
"""


def _snapshot(folder: Path) -> dict[str, tuple]:
    """Every entry under ``folder``: a link's target, a file's bytes and inode."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_symlink():
            out[str(p)] = ("link", os.readlink(p))
        elif p.is_file():
            out[str(p)] = ("file", p.read_bytes(), p.stat().st_ino)
        else:
            out[str(p)] = ("folder",)
    return out


def _one_error_line(res) -> str:
    lines = res.stderr.strip().splitlines()
    assert res.code == 2 and len(lines) == 1 and lines[0].startswith("volwarp: error:"), res
    return lines[0]


def test_an_output_over_the_target_of_a_series_link_is_refused(run, tmp_path, monkeypatch):
    """A reference series of links: the RTSTRUCT written over the CT slice a link leads to."""
    monkeypatch.chdir(tmp_path)
    stored = np.zeros((4, 6, 6), np.int16)
    stored[1:3, 2:4, 2:4] = 100
    slices = write_series(tmp_path / "pacs", stored, series="1.2.826.0.1.3680043.8.498.9")
    (tmp_path / "links").mkdir()
    for f in slices:
        os.symlink(f"../pacs/{f.name}", tmp_path / "links" / f.name)
    labels = Volume((stored > 0).astype(np.uint8), spacing=(0.7, 0.8, 2.5),
                    origin=(-10.0, 20.0, 30.0))
    write_volume(labels, tmp_path / "lab.nrrd")
    target = tmp_path / "pacs" / slices[0].name
    pixels = pydicom.dcmread(target).pixel_array.copy()
    before = _snapshot(tmp_path)
    res = run("convert", "lab.nrrd", "--reference", "links", "--dicom-type", "rtstruct",
              "-o", f"pacs/{slices[0].name}")
    line = _one_error_line(res)
    assert "never replaces an input" in line and f"links/{slices[0].name}" in line, line
    assert _snapshot(tmp_path) == before
    np.testing.assert_array_equal(pydicom.dcmread(target).pixel_array, pixels)
    # beside the series' files, not one of them: written
    res = run("convert", "lab.nrrd", "--reference", "links", "--dicom-type", "rtstruct",
              "-o", "pacs/rs.dcm")
    assert res.code == 0, res


def test_a_store_output_over_a_store_the_input_links_into_is_refused(run, tmp_path,
                                                                     monkeypatch):
    """A store whose array is a link into another store: the warp replaced that store."""
    monkeypatch.chdir(tmp_path)
    write_volume(Volume(ball(12) * 200), tmp_path / "other.ome.zarr")
    (tmp_path / "scan.ome.zarr").mkdir()
    (tmp_path / "scan.ome.zarr" / "zarr.json").write_bytes(
        (tmp_path / "other.ome.zarr" / "zarr.json").read_bytes())
    os.symlink("../other.ome.zarr/0", tmp_path / "scan.ome.zarr" / "0")
    (tmp_path / "spec.yaml").write_text(SPEC)
    before = _snapshot(tmp_path)
    res = run("warp", "scan.ome.zarr", "--spec", "spec.yaml", "-o", "other.ome.zarr")
    line = _one_error_line(res)
    assert "never replaces an input" in line and "other.ome.zarr" in line, line
    assert _snapshot(tmp_path) == before


def test_morph_frames_that_name_one_file_through_links_are_refused(run, tmp_path,
                                                                   monkeypatch):
    """'d{i}/f.nrrd' with every d{i} a link to one folder, 'a{i}/../g.nrrd': one frame left."""
    monkeypatch.chdir(tmp_path)
    write_volume(Volume(ball(12) * 200), tmp_path / "a.nrrd")
    write_volume(Volume(ball(12, radius=3) * 200), tmp_path / "b.nrrd")
    (tmp_path / "out").mkdir()
    for i in range(3):
        os.symlink("out", tmp_path / f"d{i}")
        (tmp_path / f"a{i}").mkdir()
    for argv in (["-o", "d{i}/f.nrrd"], ["-o", "a{i}/../g.nrrd"],
                 ["-o", "m_{i}.nrrd", "--mesh-to", "d{i}/m.ply"]):
        before = _snapshot(tmp_path)
        res = run("morph", "a.nrrd", "b.nrrd", "--iso", "100", "--frames", "3", *argv)
        line = _one_error_line(res)
        assert "gives frames 0 and 1 the same file" in line, line
        assert _snapshot(tmp_path) == before


def test_an_output_inside_a_store_another_output_writes_is_refused(run, tmp_path, monkeypatch):
    """-o o.ome.zarr --frames-to 'o.ome.zarr/f_{frame}.nrrd': the frames went into the earlier
    store, which the new one replaced (exit 0, every frame lost); --jacobian-to inside it
    failed after the work. Both ways round, and for a morph's meshes: refused before any."""
    monkeypatch.chdir(tmp_path)
    write_volume(Volume(ball(12) * 200), tmp_path / "a.nrrd")
    write_volume(Volume(ball(12, radius=3) * 200), tmp_path / "b.nrrd")
    (tmp_path / "spec.yaml").write_text(SPEC)
    for name in ("o.ome.zarr", "m_1.ome.zarr"):  # (earlier runs' stores)
        write_volume(Volume(ball(12)), tmp_path / name)
    cases = [
        ["warp", "a.nrrd", "--spec", "spec.yaml", "-o", "o.ome.zarr",
         "--frames-to", "o.ome.zarr/f_{frame}.nrrd"],
        ["warp", "a.nrrd", "--spec", "spec.yaml", "-o", "o.ome.zarr",
         "--jacobian-to", "o.ome.zarr/0/j.nrrd"],
        ["morph", "a.nrrd", "b.nrrd", "--iso", "100", "--frames", "3",
         "-o", "m_{i}.ome.zarr", "--mesh-to", "m_1.ome.zarr/m{i}.ply"],
    ]
    for argv in cases:
        before = _snapshot(tmp_path)
        line = _one_error_line(run(*argv))
        assert "lies inside" in line and "which -o writes" in line, line
        assert _snapshot(tmp_path) == before


def test_a_store_that_holds_an_output_named_before_it_is_refused():
    """The other order: the file claimed first, then the store around it."""
    import pytest

    from volwarp_cli.errors import BadUsage
    from volwarp_cli.io.inputs import claim_output
    from volwarp_cli.runscope import run_scope

    with run_scope():
        claim_output("/tmp/x/s.ome.zarr/0/j.nrrd", "--jacobian-to")
        claim_output("/tmp/x/s2.ome.zarr", "-o")  # (beside it: fine)
        with pytest.raises(BadUsage, match="holds /tmp/x/s.ome.zarr/0/j.nrrd"):
            claim_output("/tmp/x/s.ome.zarr", "-o")


def test_batch_steps_writing_into_one_anothers_store_are_refused(run, tmp_path):
    """A step's '{stem}.ome.zarr/sdf.nrrd' beside another's '{stem}.ome.zarr': the store's
    rename took the file with it (or took it in: every step redone at every run)."""
    write_volume(Volume(ball(12) * 200), tmp_path / "a.nrrd")
    for first, second, how in (("{stem}.ome.zarr", "{stem}.ome.zarr/sdf.nrrd", "lies inside"),
                               ("{stem}.ome.zarr/sdf.nrrd", "{stem}.ome.zarr", "holds")):
        manifest = tmp_path / "m.yaml"
        manifest.write_text(f"""version: 1
inputs: {{list: [a.nrrd]}}
output_dir: out
steps:
  - {{name: one, run: {'convert' if first.endswith('zarr') else 'distance'}, output: "{first}",
     options: {'[]' if first.endswith('zarr') else '["--iso", "100"]'}}}
  - {{name: two, run: {'convert' if second.endswith('zarr') else 'distance'}, output: "{second}",
     options: {'[]' if second.endswith('zarr') else '["--iso", "100"]'}}}
""")
        before = _snapshot(tmp_path)
        line = _one_error_line(run("batch", str(manifest)))
        assert how in line and "step 'one'" in line, line
        assert _snapshot(tmp_path) == before
