"""Options and errors as README and DESIGN say, where a review found them otherwise.

Each case ran before with another exit code, or took an option and did
nothing with it (exit 0, no word).
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume


@pytest.fixture
def blob(tmp_path):
    z, y, x = np.mgrid[:12, :12, :12]
    data = (100 * np.exp(-((x - 6) ** 2 + (y - 5) ** 2 + (z - 6) ** 2) / 12)).astype(np.float32)
    write_volume(Volume(data, spacing=(1.0, 1.0, 2.0)), tmp_path / "blob.nrrd")
    return tmp_path / "blob.nrrd"


@pytest.mark.parametrize("args, message", [
    (["-o", "x.nrrd", "--pyramid", "2"], "--pyramid writes extra levels of OME-Zarr"),
    (["-o", "x.nii", "--byte-order", "big"], "NIfTI little-endian only"),
    (["-o", "x.nii", "--volume-index", "1"], "--volume-index"),
])
def test_an_option_the_output_or_input_cannot_take_is_a_usage_error(run, blob, tmp_path,
                                                                    monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    res = run("convert", blob, *args)
    assert res.code == 2 and message in res.stderr, res
    assert not list(tmp_path.glob("x.*"))


def test_a_bad_memory_limit_in_the_environment_is_a_usage_error(run, blob, tmp_path,
                                                                monkeypatch):
    monkeypatch.setenv("VOLWARP_MEMORY_LIMIT", "abc")
    res = run("convert", blob, "-o", tmp_path / "x.nrrd")
    assert res.code == 2 and "VOLWARP_MEMORY_LIMIT='abc'" in res.stderr, res


@pytest.mark.parametrize("command", ["warp", "apply"])
def test_labels_asked_for_on_fractional_samples_is_a_usage_error(run, blob, tmp_path, command):
    """(distance said so with exit 2 already)."""
    if command == "warp":
        spec = tmp_path / "s.yaml"
        spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 5}\nsteps: []\n")
        extra = ["--spec", spec]
    else:
        tfm = tmp_path / "t.tfm"
        tfm.write_text("#Insight Transform File V1.0\n#Transform 0\n"
                       "Transform: AffineTransform_double_3_3\n"
                       "Parameters: 1 0 0 0 1 0 0 0 1 0 0 0\nFixedParameters: 0 0 0\n")
        extra = ["-t", tfm]
    res = run(command, blob, *extra, "-o", tmp_path / "o.nrrd", "--values", "labels")
    assert res.code == 2 and "not all integers" in res.stderr, res
    assert not (tmp_path / "o.nrrd").exists()


@pytest.mark.parametrize("output, option, said", [
    ("x.nii", "--compress", "--compress does not apply to"),
    ("x.raw", "--compress", "--compress does not apply to"),
    ("x.nrrd", "--ome-zarr-version=0.4", "--ome-zarr-version does not apply to"),
])
def test_a_writer_option_the_format_has_no_use_for_is_said(run, blob, tmp_path, output,
                                                           option, said):
    """Said, not refused: a command's writer options go to all its outputs, and apply
    where they can (-o x.nrrd --compress --jacobian-to j.nii)."""
    res = run("convert", blob, "-o", tmp_path / output, option)
    assert res.code == 0, res
    assert said in res.stderr and res.stderr.count("warning:") == 1, res.stderr
    assert (tmp_path / output).is_file()
    res = run("convert", blob, "-o", tmp_path / "plain.nrrd")
    assert res.code == 0 and "warning" not in res.stderr


@pytest.mark.parametrize("args", [["--color", "red"], ["--view", "front"],
                                  ["--render-size", "10x10"], ["--background-color", "red"]])
def test_mesh_picture_options_without_a_picture_are_refused(run, blob, tmp_path, args):
    res = run("mesh", blob, "--iso", "50", "-o", tmp_path / "m.ply", *args)
    assert res.code == 2 and "give --render OUT.png" in res.stderr, res
    assert not (tmp_path / "m.ply").exists()
    res = run("mesh", blob, "--iso", "50", "-o", tmp_path / "m.ply", *args,
              "--render", tmp_path / "m.png")
    assert res.code == 0, res
    assert (tmp_path / "m.png").is_file()


@pytest.mark.parametrize("command", ["morph", "sweep"])
def test_morph_and_sweep_picture_options_without_a_picture_are_refused(run, tmp_path,
                                                                      command):
    from volwarp_cli.warmup import write_inputs

    (tmp_path / "in").mkdir()
    p = write_inputs(str(tmp_path / "in"))  # (absolute: no name another test's run declared)
    if command == "morph":
        args = ["morph", p["blob"], p["egg"], "--frames", "2", "--iso", "50", "--grid",
                "union", "-o", tmp_path / "out_f{i}.nrrd"]
        render = ["--render-to", tmp_path / "r{i}.png"]
    else:
        args = ["sweep", p["line"], "-o", tmp_path / "out_{field}.nrrd"]
        render = ["--render", tmp_path / "r.png"]
    res = run(*args, "--view", "front", "--render-size", "40x30")
    assert res.code == 2 and "--view, --render-size shape the picture" in res.stderr, res
    assert not list(tmp_path.glob("out_*"))
    res = run(*args, "--view", "front", "--render-size", "40x30", *render)
    assert res.code == 0, res
    assert list(tmp_path.glob("r*.png"))


@pytest.mark.parametrize("suffix", [".nrrd", ".nii.gz", ".mha"])
def test_convert_keeps_the_provenance_of_its_input_s_samples(run, tmp_path, suffix):
    """A format change is not how the samples were made: a warp's provenance (its command
    and its spec's hash) survives a conversion; the other key/values too."""
    vol = Volume(np.arange(64, dtype=np.int16).reshape(4, 4, 4),
                 meta={"patient": "x", "volwarp_command": "warp", "volwarp_input": "a.nrrd",
                       "volwarp_spec_sha256": "ab" * 32, "volwarp_version": "0.1.0"})
    write_volume(vol, tmp_path / "in.nrrd")
    res = run("convert", tmp_path / "in.nrrd", "-o", tmp_path / f"out{suffix}")
    assert res.code == 0, res
    out = read_volume(tmp_path / f"out{suffix}")
    assert out.meta["volwarp_command"] == "warp"
    assert out.meta["volwarp_spec_sha256"] == "ab" * 32
    if suffix != ".nii.gz":  # (NIfTI keeps volwarp's own keys only)
        assert out.meta["patient"] == "x"
    assert np.array_equal(out.data, vol.data)


def test_convert_values_decides_the_ids_check_and_pyramid_method_only_the_levels(run, tmp_path):
    z, y, x = np.mgrid[:8, :8, :8]
    lab = np.where(x < 3, 0, np.where(y < 4, 300, 1000)).astype(np.uint16)
    write_volume(Volume(lab), tmp_path / "lab.nrrd")
    base = ["convert", tmp_path / "lab.nrrd", "--pyramid", "1", "--dtype", "uint8"]
    res = run(*base, "-o", tmp_path / "a.ome.zarr", "--pyramid-method", "mean",
              "--values", "labels")
    assert res.code == 2 and "would average label ids" in res.stderr, res
    for method in ("mode", "mean"):  # (mean: the levels averaged as asked, not the ids cut)
        res = run(*base, "-o", tmp_path / "b.ome.zarr", "--pyramid-method", method)
        assert res.code == 2 and "cannot hold its label ids 300, 1000" in res.stderr, res
    ramp = (np.arange(512, dtype=np.int16).reshape(8, 8, 8) - 100)  # intensities: mode's
    write_volume(Volume(ramp), tmp_path / "ramp.nrrd")             # levels, clipped samples
    res = run("convert", tmp_path / "ramp.nrrd", "--pyramid", "1", "--dtype", "uint8",
              "--pyramid-method", "mode", "-o", tmp_path / "r.ome.zarr")
    assert res.code == 0, res
    assert read_volume(tmp_path / "r.ome.zarr").data.max() == 255
    res = run(*base, "-o", tmp_path / "c.ome.zarr", "--pyramid-method", "mode",
              "--values", "intensity")  # (the way out the refusal names, taken)
    assert res.code == 0, res
    assert set(np.unique(read_volume(tmp_path / "c.ome.zarr").data)) == {0, 255}
    assert not (tmp_path / "a.ome.zarr").exists() and not (tmp_path / "b.ome.zarr").exists()


def test_compress_for_a_raw_output_is_said_by_blocks_as_in_memory(run, blob, tmp_path):
    """By blocks a raw output with --compress was refused ("a compressed or raw output
    cannot be written block by block"), in memory written and said: the same now."""
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 5}\n"
                    "steps:\n  - move: [{index: [2, 2, 2], by: [1, 0, 0]}]\n")
    outs = []
    for how in ([], ["--chunked", "--block", "4"]):
        out = tmp_path / f"w{len(outs)}.raw"
        res = run("warp", blob, "--spec", spec, "-o", out, "--compress", *how)
        assert res.code == 0, res
        assert "--compress does not apply to" in res.stderr
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]
