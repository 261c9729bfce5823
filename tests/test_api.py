"""volwarp_cli.api: what a function returns, written with api.write, is its command's output.

Byte for byte, file against file, for each operation (capture, warp of
intensities, of a label map and of a capture file, sweep, mesh, distance); a spec
given as a dict is the spec given as a file, and a bad one fails the same
way, at the same key.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from volwarp_cli import api
from volwarp_cli.errors import BadUsage, SpecError
from volwarp_cli.runscope import run_scope

ROOT = Path(__file__).resolve().parent.parent
BALL = ROOT / "tests" / "data" / "ball_30_uint8.nrrd"
SPECS = ROOT / "specs"
#: the bundled ball warped as intensities (the tripled placement resamples every voxel)
INTENSITY_SPEC = SPECS / "warp-ball-voxel.yaml"
#: the bundled ball (a 0/200 mask) warped as labels, the grid grown by the spec's pad
LABELS_SPEC = SPECS / "warp-ball.yaml"


@pytest.fixture(autouse=True)
def _own_run():
    """Each test is a run of its own: the inputs its API calls read end with it."""
    with run_scope():
        yield


def _same_bytes(a: Path, b: Path) -> None:
    assert a.read_bytes() == b.read_bytes(), (a, b)


def test_capture_writes_the_command_s_capture_file(run, tmp_path):
    cli, mine = tmp_path / "cli.vwc", tmp_path / "api.vwc"
    res = run("capture", BALL, "-o", cli, "--lattice", "6", "7", "8", "--oversample", "2",
              "--pad", "3")
    assert res.code == 0, res.stderr
    cap = api.capture(BALL, lattice=(6, 7, 8), oversample=2, pad=3)
    api.write(cap, mine)
    _same_bytes(cli, mine)
    # the same volume given as a Volume makes the same capture (a capture records no input name)
    api.write(api.capture(api.read(BALL), lattice=(6, 7, 8), oversample=2, pad=3),
              tmp_path / "vol.vwc")
    _same_bytes(cli, tmp_path / "vol.vwc")


def test_warp_of_intensities_is_the_command_s_output(run, tmp_path):
    cli, mine = tmp_path / "cli.nrrd", tmp_path / "api.nrrd"
    assert run("warp", BALL, "--spec", INTENSITY_SPEC, "-o", cli).code == 0
    out = api.warp(BALL, INTENSITY_SPEC)
    api.write(out, mine)
    _same_bytes(cli, mine)
    assert out.meta["volwarp_input"] == BALL.name
    # the spec's SHA-256 is hashlib's (the digest is computed without loading OpenSSL)
    import hashlib

    assert out.meta["volwarp_spec_sha256"] == hashlib.sha256(
        Path(INTENSITY_SPEC).read_bytes()).hexdigest()


def test_warp_of_a_label_map_is_the_command_s_output(run, tmp_path):
    cli, mine = tmp_path / "cli.nrrd", tmp_path / "api.nrrd"
    res = run("warp", BALL, "--spec", LABELS_SPEC, "-o", cli, "--json")
    assert res.code == 0, res.stderr
    assert '"values": "labels"' in res.stdout
    out = api.warp(BALL, LABELS_SPEC)
    assert set(np.unique(out.data)) <= {0, 200}  # labels, never a blend of them
    api.write(out, mine)
    _same_bytes(cli, mine)


@pytest.mark.parametrize("spec, capture_args", [
    (INTENSITY_SPEC, ["--lattice", "7", "8", "9", "--placement", "tripled", "--oversample",
                      "1.5", "--sampling", "nearest", "--values", "intensity"]),
    (LABELS_SPEC, ["--lattice", "9", "--oversample", "2"]),  # its labels, held exactly
], ids=["intensity", "labels"])
def test_warp_of_a_capture_file_is_the_command_s_output(run, tmp_path, spec, capture_args):
    scene = tmp_path / "ball.vwc"
    assert run("capture", BALL, "-o", scene, *capture_args).code == 0
    cli, mine = tmp_path / "cli.nrrd", tmp_path / "api.nrrd"
    res = run("warp", scene, "--spec", spec, "-o", cli)
    assert res.code == 0, res.stderr
    out = api.warp(scene, spec)
    api.write(out, mine)
    _same_bytes(cli, mine)
    assert out.meta["volwarp_input"] == "ball.vwc"


def test_sweep_fields_are_the_command_s_files(run, tmp_path):
    spec = SPECS / "sweep-at-size.yaml"
    res = run("sweep", spec, "-o", tmp_path / "cli_{field}.nrrd", "--shape", 20, 16, 12,
              "--dtype", "uint8")
    assert res.code == 0, res.stderr
    fields = api.sweep(spec, shape=(20, 16, 12), dtype="uint8")
    assert list(fields) == ["opacity", "red", "green", "blue", "geometry"]
    api.write(fields, tmp_path / "api_{field}.nrrd")
    for name in fields:
        _same_bytes(tmp_path / f"cli_{name}.nrrd", tmp_path / f"api_{name}.nrrd")
    assert fields["opacity"].data.any()


def test_morph_frames_are_the_command_s_files(run, tmp_path):
    """Frames, an attribute and meshes of a moved target on another grid (a spec dict)."""
    ball, block = ROOT / "tests" / "data" / "ball_30_uint8.nrrd", ROOT / "tests" / "data" / \
        "block_int16_aniso.nrrd"
    spec = {"version": 1, "source": {"volume": str(ball), "iso": 100},
            "target": {"volume": str(block), "iso": -1300},
            "align": {"target": {"scale": 1.5, "rotate": [0, 0, 15],
                                 "translate": [21.0, -40.0, 3.0]}},
            "times": [0.0, 0.4, 1.0], "output": "density",
            # (the 0/200 ball is a mask, a label map by the rule: blended as asked)
            "attributes": [{"name": "grey", "source": str(ball), "target": str(block),
                            "dtype": "float32", "values": "intensity"}]}
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(spec))
    res = run("morph", "--spec", path, "-o", tmp_path / "cli_{i}.nrrd",
              "--mesh-to", tmp_path / "cli_{i}.ply")
    assert res.code == 0, res.stderr
    frames = api.morph(path, meshes=True)
    assert [f.t for f in frames] == [0.0, 0.4, 1.0]
    for f in frames:
        api.write(f.volume, tmp_path / f"api_{f.index}.nrrd")
        api.write(f.attributes["grey"], tmp_path / f"api_{f.index}_grey.nrrd")
        api.write(f.mesh, tmp_path / f"api_{f.index}.ply")
        for name in (f"{f.index}.nrrd", f"{f.index}_grey.nrrd", f"{f.index}.ply"):
            _same_bytes(tmp_path / f"cli_{name}", tmp_path / f"api_{name}")
    # the density moves from the ball to the block
    assert not np.array_equal(frames[0].volume.data, frames[-1].volume.data)
    # a dict spec: the same frames, no spec hash recorded
    again = api.morph(spec)
    assert np.array_equal(again[1].volume.data, frames[1].volume.data)
    assert "volwarp_spec_sha256" not in again[1].volume.meta
    assert "volwarp_spec_sha256" in frames[1].volume.meta


def test_mesh_is_the_command_s_file(run, tmp_path):
    cli, mine = tmp_path / "cli.ply", tmp_path / "api.ply"
    res = run("mesh", BALL, "-o", cli, "--iso", "100", "--smooth", "5", "--cap")
    assert res.code == 0, res.stderr
    surface = api.mesh(BALL, iso=100, smooth=5, cap=True)
    api.write(surface, mine)
    _same_bytes(cli, mine)
    # a Volume: the same surface; the file records no input name
    again = api.mesh(api.read(BALL), iso=100, smooth=5, cap=True)
    assert np.array_equal(again.vertices, surface.vertices)
    assert np.array_equal(again.faces, surface.faces)
    assert "volwarp_input" not in again.meta and surface.meta["volwarp_input"] == BALL.name


def test_mesh_labels_are_the_command_s_files(run, tmp_path):
    """``labels=True`` is ``--labels``: a mesh per label, each the bytes of its file (the API
    had no way to it: ``TypeError: unexpected keyword argument 'labels'``)."""
    from volwarp_cli.volume import Volume

    ids = np.zeros((24, 22, 20), np.uint8)
    ids[3:9, 4:10, 2:8], ids[12:20, 10:18, 9:17] = 2, 9
    api.write(Volume(ids, spacing=(0.5, 0.7, 1.1)), tmp_path / "ids.nrrd")
    res = run("mesh", tmp_path / "ids.nrrd", "--labels", "-o", tmp_path / "cli_{label}.ply",
              "--smooth", "3")
    assert res.code == 0, res.stderr
    meshes = api.mesh(tmp_path / "ids.nrrd", labels=True, smooth=3)
    assert list(meshes) == [2, 9]
    for label, surface in meshes.items():
        api.write(surface, tmp_path / f"api_{label}.ply")
        _same_bytes(tmp_path / f"cli_{label}.ply", tmp_path / f"api_{label}.ply")
    one = api.mesh(tmp_path / "ids.nrrd", label=9, smooth=3)
    assert np.array_equal(one.vertices, meshes[9].vertices)
    with pytest.raises(BadUsage, match="exclude each other"):
        api.mesh(tmp_path / "ids.nrrd", labels=True, label=2)
    with pytest.raises(BadUsage, match="--iso does not apply"):
        api.mesh(tmp_path / "ids.nrrd", labels=True, iso=1)


@pytest.mark.parametrize("options, kwargs", [
    (["--iso", "100", "--surface", "voxel"], dict(iso=100, surface="voxel")),
    (["--iso", "100", "--metric", "minnorm", "--unsigned"],
     dict(iso=100, metric="minnorm", unsigned=True)),
    (["--iso", "60", "--max-distance", "3"], dict(iso=60, max_distance=3)),
    (["--values", "labels"], dict(values="labels")),
], ids=["exact", "minnorm", "band", "labels"])
def test_distance_is_the_command_s_file(run, tmp_path, options, kwargs):
    cli, mine = tmp_path / "cli.nrrd", tmp_path / "api.nrrd"
    res = run("distance", BALL, "-o", cli, *options)
    assert res.code == 0, res.stderr
    field = api.distance(BALL, **kwargs)
    assert field.data.dtype == np.float32 and field.data.min() <= 0 < field.data.max()
    api.write(field, mine)
    _same_bytes(cli, mine)


def test_a_spec_dict_is_the_spec_file():
    ball = api.read(BALL)
    data = yaml.safe_load(INTENSITY_SPEC.read_text())
    data["capture"]["lattice"] = tuple(data["capture"]["lattice"])  # tuples read as lists
    from_file = api.warp(ball, INTENSITY_SPEC)
    from_dict = api.warp(ball, data)
    assert from_dict.data.dtype == from_file.data.dtype
    assert np.array_equal(from_dict.data, from_file.data)
    assert from_dict.same_grid(from_file, atol=0)
    # provenance: what is known (no file to hash, no input file's name)
    assert "volwarp_spec_sha256" in from_file.meta and "volwarp_input" not in from_file.meta
    assert {k: v for k, v in from_file.meta.items() if k != "volwarp_spec_sha256"} == \
        from_dict.meta


@pytest.mark.parametrize("breaking", [
    lambda d: d["steps"][1]["drag"][0].__setitem__("to", [12.0, "x", 14.5]),  # the schema
    lambda d: d["steps"][0]["move"][0].__setitem__("index", [3, 30, 4]),  # past the lattice
    lambda d: d.__setitem__("capture", dict(d["capture"], placement="tripled",
                                            lattice=[5, 8, 9])),  # a rule of the spec
], ids=["schema", "lattice-index", "tripled-lattice"])
def test_a_bad_spec_dict_fails_as_its_file(run, tmp_path, breaking):
    data = yaml.safe_load(INTENSITY_SPEC.read_text())
    breaking(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(SpecError) as from_file:
        api.warp(BALL, path)
    with pytest.raises(SpecError) as from_dict:
        api.warp(BALL, data)
    assert type(from_dict.value) is type(from_file.value)
    assert from_dict.value.key == from_file.value.key is not None
    assert from_dict.value.message == from_file.value.message
    assert from_file.value.line is not None and from_dict.value.line is None
    res = run("warp", BALL, "--spec", path, "-o", tmp_path / "out.nrrd")
    assert res.code == 2 and f"{from_file.value.key}: " in res.stderr


@pytest.mark.parametrize("value, what", [
    (math.nan, "must be a finite number"),
    (object(), "cannot read a object"),
], ids=["nan", "object"])
def test_a_spec_dict_holds_plain_finite_data(value, what):
    data = yaml.safe_load(INTENSITY_SPEC.read_text())
    data["steps"][0]["move"][0]["by"][1] = value
    with pytest.raises(SpecError, match=what) as err:
        api.warp(BALL, data)
    assert err.value.key == "steps[0].move[0].by[1]"


def test_a_recursive_spec_dict_is_refused():
    data = yaml.safe_load(INTENSITY_SPEC.read_text())
    data["steps"][0]["move"].append(data["steps"])
    with pytest.raises(SpecError, match="contains itself") as err:
        api.warp(BALL, data)
    assert err.value.key == "steps[0].move[1]"  # (where the value holds itself)


def test_write_never_replaces_an_input(tmp_path):
    copy = tmp_path / "ball.nrrd"
    copy.write_bytes(BALL.read_bytes())
    vol = api.read(copy)
    with pytest.raises(BadUsage, match="never replaces an input"):
        api.write(vol, copy)
    assert copy.read_bytes() == BALL.read_bytes()
    with pytest.raises(BadUsage, match="must end in .vwc"):
        api.write(api.capture(vol, lattice=6), tmp_path / "scene.nrrd")


@pytest.mark.parametrize("kwargs, match", [
    (dict(iso="0.5"), "iso must be a finite number"),
    (dict(iso=float("nan")), "iso must be a finite number"),
    (dict(iso=100, max_distance="3"), "max_distance must be a finite number"),
    (dict(iso=100, max_distance=float("inf")), "max_distance must be a finite number"),
    (dict(iso=100, max_distance=0), "max_distance must be positive"),
    (dict(label="2"), "label must be a whole number"),
    (dict(label=2.0), "label must be a whole number"),
    (dict(iso=100, unsigned="no"), "unsigned must be True or False"),
])
def test_distance_refuses_wrong_arguments_as_the_command_does(kwargs, match):
    with pytest.raises(BadUsage, match=match):
        api.distance(BALL, **kwargs)


@pytest.mark.parametrize("kwargs, match", [
    (dict(lattice=3), "at least 4 control points"),
    (dict(lattice=(4, 5)), "give one size or three"),
    (dict(lattice=5, placement="tripled"), "at least 6 control points"),
    (dict(placement="bogus"), "placement"),
    (dict(sampling="bogus"), "sampling"),
    (dict(pad=-3), "pad: voxels per side"),
    (dict(pad=(1, -1, 1)), "pad: voxels per side"),
])
def test_capture_refuses_what_the_command_refuses_as_usage(tmp_path, kwargs, match):
    """The command's exit 2 is the API's BadUsage: a lattice of 3 and an unknown sampling
    were plain VolwarpErrors (exit 1's class), and a negative pad wrote a .vwc that no
    command could read (found by a review)."""
    with pytest.raises(BadUsage, match=match):
        api.capture(BALL, **kwargs)


def test_a_missing_input_is_a_volwarp_error_in_every_api_function(tmp_path):
    """api.read said so; mesh, warp and distance raised a bare FileNotFoundError."""
    from volwarp_cli.errors import VolwarpError

    missing = tmp_path / "none.nrrd"
    for call in (lambda: api.read(missing), lambda: api.mesh(missing, iso=1),
                 lambda: api.distance(missing, iso=1),
                 lambda: api.warp(missing, SPECS / "warp-ball.yaml")):
        with pytest.raises(VolwarpError, match="none.nrrd: no such file"):
            call()


def test_an_infinite_band_is_a_usage_error_of_the_command(run, tmp_path):
    res = run("distance", BALL, "-o", tmp_path / "d.nrrd", "--iso", "100", "--max-distance",
              "inf")
    assert res.code == 2 and "finite" in res.stderr and not (tmp_path / "d.nrrd").exists()
