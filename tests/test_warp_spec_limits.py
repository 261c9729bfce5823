"""Warp specs and options whose values a run cannot hold: refused with where they came from.

Found by a hunt of the warp's specs (session 38): a background beyond float32 became inf
in the output where nothing landed, exit 0; a lattice or pad of 1e300 ended in an
internal OverflowError, and 100000 in a memory refusal without the spec's key.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume


@pytest.fixture
def vol(tmp_path):
    z, y, x = np.mgrid[:20, :20, :20].astype(np.float32)
    smooth = 100 * np.exp(-((x - 10) ** 2 + (y - 9) ** 2 + (z - 11) ** 2) / 30)  # (intensities)
    write_volume(Volume(smooth.astype(np.float32)), tmp_path / "b.nrrd")
    return tmp_path / "b.nrrd"


def _spec(tmp_path, text):
    (tmp_path / "w.yaml").write_text("version: 1\n" + text + "steps:\n  - move:\n"
                                     "      - {index: [2, 2, 2], by: [1, 0, 0]}\n")
    return tmp_path / "w.yaml"


@pytest.mark.parametrize("where", ["spec", "option"])
def test_a_background_a_float32_output_cannot_hold_is_refused(run, tmp_path, vol, where):
    spec = _spec(tmp_path, "units: voxel\ngrid: grow\n"
                 + ("background: 1e39\n" if where == "spec" else ""))
    extra = ["--background-value", "1e39"] if where == "option" else []
    res = run("warp", vol, "--spec", spec, "-o", tmp_path / "o.nrrd", *extra)
    assert res.code == 2 and "beyond what float32 holds" in res.stderr, res.stderr
    assert not (tmp_path / "o.nrrd").exists()
    res = run("warp", vol, "--spec", spec, "-o", tmp_path / "o.nrrd", "--dtype", "float64", *extra)
    assert res.code == 0, res.stderr


@pytest.mark.parametrize("capture, key", [("lattice: 1e300", "capture.lattice"),
                                          ("lattice: [7, 7, 100000]", "capture.lattice[2]"),
                                          ("pad: 1e300", "capture.pad")])
def test_a_lattice_or_pad_beyond_reason_is_a_spec_error(run, tmp_path, vol, capture, key):
    spec = _spec(tmp_path, f"units: voxel\ncapture: {{{capture}}}\n")
    res = run("warp", vol, "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 2, res.stderr
    assert f"w.yaml:3: {key}:" in res.stderr and "maximum" in res.stderr


@pytest.mark.parametrize("text, was", [("010", 8), ("1:30", 90), ("1_000", 1000), ("0b11", 3)])
def test_numbers_yaml_versions_read_apart_are_refused(tmp_path, text, was):
    """PyYAML reads specs as YAML 1.1: a zero-padded 010 was 8 (a generated spec's index,
    silently another control point), 1:30 was 90; YAML 1.2 and JSON read them otherwise."""
    from volwarp_cli.errors import SpecError
    from volwarp_cli.spec.loader import parse_spec_text

    with pytest.raises(SpecError, match=rf"x\.yaml:3: steps\[0\]\.move\[0\]\.index\[0\]: "
                                        rf"{text} is {was} to YAML 1\.1"):
        parse_spec_text(f"version: 1\nsteps:\n  - move: [{{index: [{text}, 2, 2], by: [1, 0, 0]}}]\n",
                        "x.yaml", tmp_path)
    for plain in ("10", "0", "-0.25", "1e5", "007.5", '"010"'):
        parse_spec_text(f"version: 1\nx: {plain}\n", "x.yaml", tmp_path)
