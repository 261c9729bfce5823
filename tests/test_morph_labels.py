"""`morph` of label maps: each shape is what `distance` takes, never its ids' values.

A review found morph taking a label map's ids as intensities (the shape was the
samples above ``--iso``, on a sub-voxel surface between ids): renaming id 2 to
1000 moved frame 0's surface by up to 0.83 mm, a level of 0.5 dropped the
voxels of negative ids, and label-map attributes were blended into ids neither
map has. Now a shape follows the label rule as ``distance`` does (the labels'
voxel surface, its refusals, ``--values``, ``--label``), in memory and by
blocks, and a label-map attribute is refused unless it says ``values: intensity``.
"""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

GEOMETRY = {"spacing": (1.0, 0.8, 1.5), "origin": (2.0, -3.0, 1.0)}
BLOCKS = ["--chunked", "--block", "7,9,11"]


def _boxes(a: int, b: int, shift: int = 0) -> np.ndarray:
    """Two touching boxes of ids ``a`` and ``b`` (their shared face a level between ids)."""
    data = np.zeros((20, 22, 26), np.int16)
    data[5:15, 6:16, 5 + shift:12 + shift] = a
    data[7:13, 6:16, 12 + shift:19 + shift] = b
    return data


def _write(path, data):
    write_volume(Volume(data, **GEOMETRY), path)
    return path


def _frames(tmp_path, prefix, n=3):
    return [read_volume(tmp_path / f"{prefix}_{i}.nrrd").data for i in range(n)]


@pytest.mark.parametrize("mode", [[], BLOCKS], ids=["memory", "blocks"])
@pytest.mark.parametrize("iso", [[], ["--iso", "0.5"]], ids=["no-iso", "iso"])
def test_renaming_an_id_changes_no_frame(run, tmp_path, mode, iso):
    """Ids 1/2, 1/1000 and 3/2 (ordered the other way): the same frames, byte for byte."""
    names = {}
    for a, b in ((1, 2), (1, 1000), (3, 2)):
        names[a, b] = (_write(tmp_path / f"s_{a}_{b}.nrrd", _boxes(a, b)),
                       _write(tmp_path / f"t_{a}_{b}.nrrd", _boxes(b, a, shift=4)))
        res = run("morph", *names[a, b], "--frames", 3, *iso, *mode,
                  "-o", tmp_path / f"m_{a}_{b}_{{i}}.nrrd")
        assert res.code == 0, res.stderr
    first = _frames(tmp_path, "m_1_2")
    for a, b in ((1, 1000), (3, 2)):
        for i, frame in enumerate(_frames(tmp_path, f"m_{a}_{b}")):
            assert np.array_equal(frame, first[i]), (a, b, i)


@pytest.mark.parametrize("mode", [[], BLOCKS], ids=["memory", "blocks"])
@pytest.mark.parametrize("shape", [[], ["--iso", "0.5"], ["--label", "2"]],
                         ids=["all", "iso", "label-2"])
def test_frame_0_of_a_map_with_itself_is_distance_s_field(run, tmp_path, mode, shape):
    """Frame 0 (and 1) of a map morphed into itself: `distance`'s voxel-surface field."""
    path = _write(tmp_path / "map.nrrd", _boxes(1, 2))
    assert run("distance", path, *shape, "-o", tmp_path / "d.nrrd").code == 0
    res = run("morph", path, path, "--frames", 2, *shape, *mode, "-o", tmp_path / "m_{i}.nrrd")
    assert res.code == 0, res.stderr
    field = read_volume(tmp_path / "d.nrrd").data
    for frame in _frames(tmp_path, "m", 2):
        assert np.array_equal(frame, field)


def _atlas() -> np.ndarray:
    """Four ids, two of them negative, in regions."""
    data = np.zeros((20, 22, 26), np.int16)
    for k, v in enumerate((-300, -5, 3, 1000)):
        data[4:16, 4 + 4 * k:8 + 4 * k, 5:21] = v
    return data


@pytest.mark.parametrize("mode", [[], BLOCKS], ids=["memory", "blocks"])
def test_negative_ids_are_labels_and_a_level_missing_them_is_distance_s_refusal(
        run, tmp_path, mode):
    atlas = _atlas()
    path = _write(tmp_path / "atlas.nrrd", atlas)
    # --iso 0.5 selects other voxels than the labels (it dropped ids -300 and -5): refused
    # as distance refuses it
    dist = run("distance", path, "--iso", "0.5", "-o", tmp_path / "d.nrrd")
    res = run("morph", path, path, "--frames", 2, "--iso", "0.5", *mode,
              "-o", tmp_path / "x_{i}.nrrd")
    assert dist.code == res.code == 2
    assert res.stderr == dist.stderr and "--values intensity" in res.stderr
    assert not list(tmp_path.glob("x_*"))
    res = run("morph", path, path, "--frames", 2, *mode, "-o", tmp_path / "m_{i}.nrrd")
    assert res.code == 0, res.stderr
    np.testing.assert_array_equal(_frames(tmp_path, "m", 2)[0] < 0, atlas != 0)


def test_the_alignment_centre_of_a_label_map_is_its_labels_centroid(run, tmp_path):
    """Turned half a turn about its centroid, a map of ids -5 and 3 in mirrored boxes
    lands on itself: frame 1 has frame 0's voxels (the centroid of id 3 alone, as a level
    of 0.5 took it, put it elsewhere)."""
    data = np.zeros((16, 20, 24), np.int16)
    data[4:12, 6:14, 3:9] = -5
    data[4:12, 6:14, 15:21] = 3
    path = _write(tmp_path / "pair.nrrd", data)
    spec = tmp_path / "m.yaml"
    spec.write_text(f"version: 1\nsource: {{volume: {path}}}\ntarget: {{volume: {path}}}\n"
                    "align: {target: {rotate: [0, 0, 180]}}\nframes: 2\n")
    res = run("morph", "--spec", spec, "-o", tmp_path / "m_{i}.nrrd")
    assert res.code == 0, res.stderr
    f0, f1 = _frames(tmp_path, "m", 2)
    assert np.count_nonzero(f0 < 0) == np.count_nonzero(data)
    np.testing.assert_array_equal(f1 < 0, f0 < 0)


def test_values_intensity_takes_the_ids_as_numbers(run, tmp_path):
    """The old rule on request: a level between ids, its surface moving with their values."""
    paths = [_write(tmp_path / f"s_{b}.nrrd", _boxes(1, b)) for b in (2, 1000)]
    for path, name in zip(paths, ("a", "b"), strict=True):
        res = run("morph", path, path, "--frames", 2, "--iso", "0.5", "--values", "intensity",
                  "-o", tmp_path / f"{name}_{{i}}.nrrd")
        assert res.code == 0, res.stderr
    assert not np.array_equal(_frames(tmp_path, "a", 1)[0], _frames(tmp_path, "b", 1)[0])
    res = run("morph", paths[0], paths[0], "--frames", 2, "--values", "intensity",
              "-o", tmp_path / "c_{i}.nrrd")
    assert res.code == 2 and "--iso V" in res.stderr


@pytest.mark.parametrize("mode", [[], BLOCKS], ids=["memory", "blocks"])
def test_the_frames_key_records_each_shape_s_choice(run, tmp_path, mode):
    """``volwarp_morph`` says what each shape was (distance's words), as distance's key does.

    The same map morphed as its labels and as a level of its ids gives other
    frames: a reader of a frame must be able to tell which it was.
    """
    path = _write(tmp_path / "s.nrrd", _boxes(1, 2))
    notes = {}
    for name, shape in (("labels", ["--label", "2"]),
                        ("intensity", ["--iso", "0.5", "--values", "intensity",
                                       "--max-distance", "4"])):
        res = run("morph", path, path, "--frames", 2, *shape, *mode,
                  "-o", tmp_path / f"{name}_{{i}}.nrrd")
        assert res.code == 0, res.stderr
        notes[name] = [read_volume(tmp_path / f"{name}_{i}.nrrd").meta["volwarp_morph"]
                       for i in range(2)]
        assert notes[name][0] == notes[name][1]
    assert "source: values=labels label=2" in notes["labels"][0]
    assert "target: values=labels label=2" in notes["labels"][0]
    assert "source: iso=0.5 inside=above values=intensity" in notes["intensity"][0]
    assert "target: iso=0.5 inside=above values=intensity" in notes["intensity"][0]


def test_a_spec_says_the_choice_in_its_keys(run, tmp_path):
    """A spec's shape takes values and label; distance's refusals name its keys and line."""
    path = _write(tmp_path / "atlas.nrrd", _atlas())
    spec = tmp_path / "m.yaml"
    spec.write_text(f"version: 1\nsource: {{volume: {path}, label: -5}}\n"
                    f"target: {{volume: {path}, label: -5}}\nframes: 2\n")
    assert run("morph", "--spec", spec, "-o", tmp_path / "m_{i}.nrrd").code == 0
    assert run("distance", path, "--label", "-5", "-o", tmp_path / "d.nrrd").code == 0
    assert np.array_equal(_frames(tmp_path, "m", 1)[0], read_volume(tmp_path / "d.nrrd").data)
    spec.write_text(f"version: 1\nsource: {{volume: {path}}}\n"
                    f"target: {{volume: {path}, iso: 0.5}}\nframes: 2\n")
    res = run("morph", "--spec", spec, "-o", tmp_path / "x_{i}.nrrd")
    assert res.code == 2 and "m.yaml:3: target:" in res.stderr
    assert "iso: 0.5 selects" in res.stderr and "values: intensity" in res.stderr
    assert "--" not in res.stderr.split("m.yaml")[1]
    spec.write_text(f"version: 1\nsource: {{volume: {path}, values: intensity}}\n"
                    f"target: {{volume: {path}}}\nframes: 2\n")
    res = run("morph", "--spec", spec, "-o", tmp_path / "x_{i}.nrrd")
    assert res.code == 2 and "m.yaml:2: source: values: intensity needs iso: V" in res.stderr


def _attribute_spec(tmp_path, extra=""):
    shape = _write(tmp_path / "shape.nrrd", _boxes(1, 2))
    seg_a, seg_b = _boxes(10, 30), _boxes(30, 10)
    _write(tmp_path / "seg_a.nrrd", seg_a)
    _write(tmp_path / "seg_b.nrrd", seg_b)
    spec = tmp_path / "m.yaml"
    spec.write_text(f"version: 1\nsource: {{volume: {shape}, iso: 0.5}}\n"
                    f"target: {{volume: {shape}, iso: 0.5}}\nframes: 3\nattributes:\n"
                    f"  - {{name: seg, source: seg_a.nrrd, target: seg_b.nrrd{extra}}}\n")
    return spec


@pytest.mark.parametrize("mode", [[], BLOCKS], ids=["memory", "blocks"])
def test_a_label_map_attribute_is_refused_naming_the_way_to_blend_it(run, tmp_path, mode):
    """Ids 10 and 30 swapped: the middle frame held 20, an id neither map has."""
    spec = _attribute_spec(tmp_path)
    res = run("morph", "--spec", spec, *mode, "-o", tmp_path / "m_{i}.nrrd")
    assert res.code == 2
    assert len(res.stderr.strip().splitlines()) == 1
    assert "m.yaml:6: attributes[0]: attribute seg" in res.stderr
    assert "its source, seg_a.nrrd, is a label map" in res.stderr
    assert "set values: intensity on the attribute" in res.stderr
    assert not list(tmp_path.glob("m_*"))


def test_values_intensity_blends_a_label_map_attribute_as_asked(run, tmp_path):
    spec = _attribute_spec(tmp_path, ", values: intensity")
    res = run("morph", "--spec", spec, "-o", tmp_path / "m_{i}.nrrd")
    assert res.code == 0, res.stderr
    middle = read_volume(tmp_path / "m_1_seg.nrrd").data
    assert 20 in middle  # (10 and 30 blended)
