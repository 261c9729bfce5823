"""Options that were parsed and ignored: each now acts or is a usage error (exit 2).

Found by a hunt through every command's --help (session 38). Each case asserts the
refusal (one line, exit 2, nothing written) or the effect that was missing.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ball

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume


@pytest.fixture
def files(tmp_path):
    write_volume(Volume(ball(24).astype(np.float32) * 100), tmp_path / "b.nrrd")
    labels = np.zeros((16, 16, 16), np.uint8)
    labels[3:9, 3:9, 3:9] = 2
    labels[9:14, 9:14, 9:14] = 5
    write_volume(Volume(labels), tmp_path / "lab.nrrd")
    (tmp_path / "t.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 1 2 3\nFixedParameters: 0 0 0\n")
    (tmp_path / "p.csv").write_text("x,y,z\n1,2,3\n4,5,6\n")
    return tmp_path


def _refused(res, *words):
    assert res.code == 2, res.stderr
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("volwarp: error: ")
    for w in words:
        assert w in res.stderr, res.stderr


@pytest.mark.parametrize("options, flag", [
    (["--compress"], "--compress"), (["--byte-order", "big"], "--byte-order"),
    (["--pyramid", "2"], "--pyramid"), (["--ome-zarr-version", "0.4"], "--ome-zarr-version"),
    (["--volume-index", "1"], "--volume-index"), (["--series", "2"], "--series"),
    (["--keep-phi"], "--keep-phi"), (["--chunked"], "--chunked"),
    (["--no-chunked"], "--no-chunked"), (["--block", "8"], "--block"),
])
def test_apply_with_points_only_refuses_a_volumes_options(run, files, options, flag):
    res = run("apply", "-t", files / "t.tfm", "--points-in", files / "p.csv", "--points-to",
              files / "q.csv", *options)
    _refused(res, f"{flag} applies to a volume")
    assert not (files / "q.csv").exists()


def test_info_of_a_capture_refuses_the_input_options(run, files):
    assert run("capture", files / "b.nrrd", "-o", files / "c.vwc").code == 0
    _refused(run("info", files / "c.vwc", "--keep-phi"), "not the capture file")
    assert run("info", files / "c.vwc").code == 0


def test_raw_endian_alone_is_refused(run, files):
    _refused(run("info", files / "b.nrrd", "--raw-endian", "big"), "need --raw-shape")


def test_convert_values_without_dtype_or_pyramid_is_refused(run, files):
    _refused(run("convert", files / "lab.nrrd", "-o", files / "o.nrrd", "--values", "labels"),
             "without either it changes nothing")
    assert not (files / "o.nrrd").exists()
    assert run("convert", files / "lab.nrrd", "-o", files / "o.nrrd", "--values", "labels",
               "--dtype", "uint16").code == 0


def test_mesh_cap_with_label_surfaces_is_refused(run, files):
    _refused(run("mesh", files / "lab.nrrd", "--label", "2", "--cap", "-o", files / "m.ply"),
             "--cap does not apply to --label/--labels")


def test_mesh_allow_empty_covers_an_absent_label(run, files):
    res = run("mesh", files / "lab.nrrd", "--label", "7", "-o", files / "m.ply")
    assert res.code == 1 and "label 7 does not occur" in res.stderr
    res = run("mesh", files / "lab.nrrd", "--label", "7", "-o", files / "m.ply",
              "--allow-empty")
    assert res.code == 0, res.stderr
    assert "label 7 does not occur" in res.stderr and (files / "m.ply").exists()


def test_a_sweep_specs_tau_with_the_direct_method_is_refused(run, tmp_path):
    (tmp_path / "s.yaml").write_text(
        "version: 1\ngrid: {spacing: 0.5}\nfields: {opacity: 1}\n"
        "trajectory:\n  - line: {from: [0, 0, 0], to: [5, 0, 0]}\n"
        "up: [0, 0, 1]\nscale: [2, 2]\nmethod: direct\ntau: 0.2\n")
    _refused(run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o.nrrd"),
             "s.yaml:9: tau: tau spaces the templates", "the direct method")
    assert run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o.nrrd", "--method",
               "voxelize").code == 0


def test_chunked_that_nothing_used_is_said(run, files):
    (files / "w.yaml").write_text(
        "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\nsteps:\n"
        "  - move:\n      - {index: [2, 2, 2], by: [1, 0, 0]}\n")
    res = run("warp", files / "b.nrrd", "--spec", files / "w.yaml", "--points-in",
              files / "p.csv", "--points-to", files / "q.csv", "--chunked")
    assert res.code == 0, res.stderr
    assert "--chunked not used" in res.stderr
