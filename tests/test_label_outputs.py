"""A label map's outputs stay a label map's: the command's choice, or the file's own word.

A review found ids invented in OME-Zarr pyramids: `apply` resampled a map as
labels and then let the writer's rule, on the resampled samples alone, take
the mean of its levels; `api.write` did the same to a map read from a DICOM
SEG. And a NIfTI of intent NIFTI_INTENT_LABEL was warped as intensities,
blending its ids, although the file says it holds labels.
"""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from volwarp_cli import api
from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume


def _levels(path):
    group = zarr.open_group(str(path), mode="r")
    attrs = group.attrs.asdict()
    method = (attrs.get("ome") or attrs)["multiscales"][0].get("type")
    return method, [set(np.unique(np.asarray(group[k])).tolist())
                    for k in sorted(group.array_keys())]


def _blocks(shape, n, seed, size=2):
    """``n`` cubes of ``size`` voxels, ids 10, 20, ... on zeros (uint16)."""
    rng = np.random.default_rng(seed)
    data = np.zeros(shape, np.uint16)
    for k, (z, y, x) in enumerate(rng.integers(0, min(shape) - size, (n, 3))):
        data[z:z + size, y:y + size, x:x + size] = 10 * (k + 1)
    return data


@pytest.mark.parametrize("values", [(), ("--labels",)])
def test_apply_writes_a_label_maps_pyramid_by_the_mode(run, tmp_path, values):
    """Landmark cubes resampled to a coarser grid: as labels by the rule (or as asked for
    sparse points the rule takes for intensities), and every level of the store takes
    the mode: no level holds an id the input lacks (the mean invented 1, 5, 6, ...)."""
    data = _blocks((32, 32, 32), 20, 1, size=2 if not values else 1)
    write_volume(Volume(data), tmp_path / "lm.nrrd")
    write_volume(Volume(np.zeros((16, 16, 16), np.uint8), spacing=(2.0, 2.0, 2.0)),
                 tmp_path / "ref.nrrd")
    (tmp_path / "t.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 0.5 0.3 0.2\nFixedParameters: 0 0 0\n")
    res = run("apply", tmp_path / "lm.nrrd", "-t", tmp_path / "t.tfm", "--reference",
              tmp_path / "ref.nrrd", "-o", tmp_path / "o.ome.zarr", "--pyramid", "2", "-v",
              *values)
    assert res.code == 0, res.stderr
    assert "values: labels" in res.stderr
    method, levels = _levels(tmp_path / "o.ome.zarr")
    ids = set(np.unique(data).tolist())
    assert method == "mode" and all(level <= ids for level in levels), (method, levels)


def test_a_segmentations_pyramid_is_written_by_the_mode_through_the_api(tmp_path):
    """A map read from a DICOM SEG (its key says so) written by api.write with a pyramid:
    the mode, as `convert` does; the sparse dots fail the rule's region test, and the
    mean invented ids."""
    data = np.zeros((6, 20, 22), np.uint16)
    for k in range(12):
        data[k % 6, 1 + k, 2 + k] = 50 * (k + 1)
    vol = Volume(data, meta={"DICOM_Modality": "SEG"})
    api.write(vol, tmp_path / "s.ome.zarr", pyramid=1)
    method, levels = _levels(tmp_path / "s.ome.zarr")
    assert method == "mode" and all(level <= set(np.unique(data).tolist()) for level in levels)


def test_a_nifti_of_intent_label_is_warped_as_labels(run, tmp_path):
    """Single-voxel landmarks (which the rule takes for intensities) in a NIfTI whose
    intent is NIFTI_INTENT_LABEL: warped as labels, no id invented (a blend did)."""
    import nibabel as nib

    data = np.zeros((24, 24, 24), np.uint16)
    rng = np.random.default_rng(4)
    data.flat[rng.choice(data.size, 30, replace=False)] = np.arange(1, 31) * 25
    img = nib.Nifti1Image(np.ascontiguousarray(data.transpose(2, 1, 0)), np.eye(4))
    img.header.set_intent("label")
    nib.save(img, tmp_path / "lm.nii.gz")
    (tmp_path / "w.yaml").write_text(
        "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\nsteps:\n"
        "  - move:\n      - {index: [2, 2, 2], by: [1.3, -0.7, 0.4]}\n")
    res = run("warp", tmp_path / "lm.nii.gz", "--spec", tmp_path / "w.yaml", "-o",
              tmp_path / "o.nii.gz", "-v")
    assert res.code == 0, res.stderr
    assert "values: labels (read from a NIfTI label map (intent NIFTI_INTENT_LABEL)" \
        in res.stderr, res.stderr
    out = api.read(tmp_path / "o.nii.gz").data
    assert set(np.unique(out).tolist()) <= set(np.unique(data).tolist())


def test_mesh_takes_a_float_map_of_whole_ids_as_distance_does(run, tmp_path):
    """`mesh --label/--labels` refused a float32 segmentation (nibabel and MONAI write
    them) that `distance --label` takes: it now meshes it as the same map in integers,
    and refuses a float map whose samples are not whole ids."""
    from volwarp_cli.surface.mesh_io import read_mesh

    ids = np.zeros((12, 14, 16), np.int16)
    ids[2:6, 3:8, 4:9], ids[7:10, 3:11, 2:6] = 2, 5
    write_volume(Volume(ids), tmp_path / "i.nrrd")
    write_volume(Volume(ids.astype(np.float32)), tmp_path / "f.nrrd")
    for kind in ("i", "f"):
        assert run("mesh", tmp_path / f"{kind}.nrrd", "--labels", "-o",
                   tmp_path / f"{kind}_{{label}}.ply").code == 0
        assert run("mesh", tmp_path / f"{kind}.nrrd", "--label", "5", "-o",
                   tmp_path / f"{kind}5.ply").code == 0
    for name in ("_2.ply", "_5.ply", "5.ply"):
        a, b = read_mesh(tmp_path / f"i{name}"), read_mesh(tmp_path / f"f{name}")
        assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    half = ids.astype(np.float32) * 0.75  # (1.5 and 3.75: no whole ids)
    write_volume(Volume(half), tmp_path / "h.nrrd")
    res = run("mesh", tmp_path / "h.nrrd", "--labels", "-o", tmp_path / "h_{label}.ply")
    assert res.code == 1 and "needs a label map (integer ids); its float samples include 1.5" \
        in res.stderr, res.stderr


@pytest.fixture
def intent_map(tmp_path):
    """A NIfTI label map (intent NIFTI_INTENT_LABEL): two blocks of ids 3 and 9."""
    import nibabel as nib

    data = np.zeros((16, 20, 24), np.uint8)
    data[4:12, 5:15, 6:14] = 3
    data[6:10, 8:12, 15:20] = 9
    img = nib.Nifti1Image(np.ascontiguousarray(data.transpose(2, 1, 0)), np.eye(4))
    img.header.set_intent("label")
    nib.save(img, tmp_path / "lm.nii.gz")
    return tmp_path / "lm.nii.gz"


def test_outputs_of_other_samples_do_not_keep_a_label_maps_marks(run, tmp_path, intent_map):
    """A distance field, a warp's Jacobian and morph frames computed from a label map kept
    its NIfTI intent (label): their OME-Zarr pyramids took the mode of distances, `apply`
    resampled a distance field by nearest neighbour, viewers showed it as labels."""
    import nibabel as nib

    d = tmp_path
    assert run("distance", intent_map, "-o", d / "sdf.nii.gz").code == 0
    assert nib.load(d / "sdf.nii.gz").header["intent_code"] == 0
    assert run("distance", intent_map, "-o", d / "sdf.ome.zarr", "--pyramid", "1").code == 0
    method, _ = _levels(d / "sdf.ome.zarr")
    level0, level1 = (np.asarray(zarr.open_group(str(d / "sdf.ome.zarr"), mode="r")[k])
                      for k in ("0", "1"))
    z, y, x = (n // 2 * 2 for n in level0.shape)
    mean = level0[:z, :y, :x].reshape(z // 2, 2, y // 2, 2, x // 2, 2).mean(axis=(1, 3, 5))
    assert method == "mean"
    np.testing.assert_allclose(level1[:z // 2, :y // 2, :x // 2], mean, atol=1e-5)
    (d / "t.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 0.5 0.25 0\nFixedParameters: 0 0 0\n")
    res = run("apply", d / "sdf.nii.gz", "-t", d / "t.tfm", "-o", d / "moved.nii.gz", "-v")
    assert res.code == 0 and "values: intensity" in res.stderr, res.stderr
    (d / "w.yaml").write_text(
        "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\nsteps:\n"
        "  - move:\n      - {index: [2, 2, 2], by: [1.3, -0.7, 0.4]}\n")
    res = run("warp", intent_map, "--spec", d / "w.yaml", "-o", d / "w.nii.gz",
              "--jacobian-to", d / "jac.nii.gz")
    assert res.code == 0, res.stderr
    assert nib.load(d / "w.nii.gz").header["intent_code"] == 1002  # (the warped map is one)
    assert nib.load(d / "jac.nii.gz").header["intent_code"] == 0
    res = run("morph", intent_map, intent_map, "--frames", "2", "-o", d / "f_{i}.nii.gz")
    assert res.code == 0, res.stderr
    assert nib.load(d / "f_0.nii.gz").header["intent_code"] == 0


def test_a_float_volume_its_keys_call_labels_takes_the_mode_only_of_ids(tmp_path):
    """In memory and by blocks: a SEG's keys on integer ids (floats too) give mode levels;
    on fractions (a field that kept the keys) the mean."""
    from volwarp_cli.box import Box
    from volwarp_cli.io.blockwrite import open_volume_blocks
    from volwarp_cli.io.omezarr import resolve_labels

    ids = np.zeros((8, 8, 8), np.float32)
    ids[2:6, 2:6, 2:6] = 7
    meta = {"DICOM_Modality": "SEG"}
    assert resolve_labels("auto", ids, meta) and resolve_labels("auto", ids.astype(np.uint8), meta)
    assert not resolve_labels("auto", ids + 0.25, meta)
    for data, want in ((ids, "mode"), (ids + 0.25, "mean")):
        vol = Volume(data, meta=meta)
        write_volume(vol, tmp_path / f"{want}.ome.zarr", pyramid=1)
        with open_volume_blocks(tmp_path / f"{want}_blocks.ome.zarr", vol.header,
                                pyramid=1) as out:
            out.write(Box.from_shape(data.shape), data)
        for name in (f"{want}.ome.zarr", f"{want}_blocks.ome.zarr"):
            assert _levels(tmp_path / name)[0] == want, name


def test_convert_takes_fractions_for_labels_no_more_than_the_other_commands(run, tmp_path):
    """`convert --values labels` of a float scan with fractions wrote pyramid levels of the
    block's mode (its minimum, for continuous values); warp, apply, distance and mesh
    refuse it: so does convert now, and nothing is written."""
    data = np.linspace(0, 1, 8 * 8 * 8, dtype=np.float32).reshape(8, 8, 8)
    write_volume(Volume(data), tmp_path / "f.nrrd")
    for command in (["convert"], ["mesh"]):
        out = tmp_path / ("o.ome.zarr" if command == ["convert"] else "o.ply")
        res = run(*command, tmp_path / "f.nrrd", "-o", out, "--values", "labels",
                  *(["--pyramid", "1"] if command == ["convert"] else []))
        assert res.code == 2 and "needs a label map (integer ids)" in res.stderr, res.stderr
        assert not out.exists()


def test_a_label_name_pattern_that_cannot_name_an_id_is_a_usage_error(run, tmp_path):
    """`{label:c}` of an id beyond Unicode ended in 'internal error: OverflowError'."""
    data = np.zeros((8, 8, 8), np.uint32)
    data[2:6, 2:6, 2:6] = 2**24 + 1
    data[1, 1, 1:3] = 65
    write_volume(Volume(data), tmp_path / "big.nrrd")
    res = run("mesh", tmp_path / "big.nrrd", "--labels", "-o", tmp_path / "c_{label:c}.ply")
    assert res.code == 2 and "cannot name label 16777217" in res.stderr, res.stderr
    assert not list(tmp_path.glob("c_*.ply"))


def test_info_says_a_nifti_of_intent_label_is_a_label_map(run, tmp_path):
    """Every command takes a NIfTI of intent label for a label map; `info` gave no hint
    where the rule alone would not (single voxels), and now says why it is one."""
    import json

    import nibabel as nib

    data = np.zeros((12, 12, 12), np.uint16)
    data[2, 3, 4], data[8, 9, 1] = 500, 700  # (two voxels: the rule says intensities)
    img = nib.Nifti1Image(np.ascontiguousarray(data.transpose(2, 1, 0)), np.eye(4))
    img.header.set_intent("label")
    nib.save(img, tmp_path / "dots.nii.gz")
    res = run("info", tmp_path / "dots.nii.gz", "--json")
    hint = json.loads(res.stdout)["label_map"]
    assert hint["labels"] == 3 and hint["values"] == [0, 500, 700]
    assert "intent NIFTI_INTENT_LABEL" in hint["why"]
    res = run("info", tmp_path / "dots.nii.gz")
    assert "hint:      is a NIfTI label map" in res.stdout
    nib.save(nib.Nifti1Image(np.ascontiguousarray(data.transpose(2, 1, 0)), np.eye(4)),
             tmp_path / "plain.nii.gz")
    assert "label_map" not in json.loads(run("info", tmp_path / "plain.nii.gz", "--json").stdout)


@pytest.mark.parametrize("command", ["apply", "warp", "warp-spec"])
def test_values_intensity_reaches_the_pyramid(run, tmp_path, command):
    """`--values intensity` on a label map: the output's pyramid levels took the mode anyway
    (the writer's rule on the nearest-resampled samples); convert's took the mean. Asked
    for, the levels take the mean in apply and warp too."""
    data = _blocks((24, 24, 24), 12, 7, size=4)
    write_volume(Volume(data), tmp_path / "lm.nrrd")
    (tmp_path / "t.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 0.5 0.3 0.2\nFixedParameters: 0 0 0\n")
    (tmp_path / "w.yaml").write_text(
        "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\n"
        + ("values: intensity\n" if command == "warp-spec" else "") + "steps:\n"
        "  - move:\n      - {index: [2, 2, 2], by: [1.3, -0.7, 0.4]}\n")
    how = (["-t", tmp_path / "t.tfm", "--interpolation", "nearest"] if command == "apply"
           else ["--spec", tmp_path / "w.yaml", "--pushforward", "nearest"])
    out = tmp_path / "o.ome.zarr"
    asked = [] if command == "warp-spec" else ["--values", "intensity"]
    res = run(command.split("-")[0], tmp_path / "lm.nrrd", *how, "-o", out, "--pyramid", "1",
              *asked)
    assert res.code == 0, res.stderr
    method, levels = _levels(out)
    assert method == "mean"
    assert not levels[1] <= set(np.unique(data).tolist())  # (means between the ids)


@pytest.mark.parametrize("chunked", [(), ("--chunked", "--block", "12")], ids=["memory", "blocks"])
def test_a_nearest_label_warps_predicted_volume_is_in_input_voxels(run, tmp_path, chunked):
    """`warp --pushforward nearest` of a label map reported predicted_mm3 oversample^3 too
    large (each domain voxel weighed 1; the box weighs its share of a voxel): an unmoved
    warp predicts each label's own volume, as the box pushforward does."""
    import json

    data = _blocks((24, 24, 24), 6, 5, size=5)
    write_volume(Volume(data, spacing=(0.5, 0.5, 2.0)), tmp_path / "lm.nrrd")
    (tmp_path / "w.yaml").write_text(
        "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 2}\nsteps:\n"
        "  - move:\n      - {index: [2, 2, 2], by: [0, 0, 0]}\n")
    for push in ("box", "nearest"):
        res = run("warp", tmp_path / "lm.nrrd", "--spec", tmp_path / "w.yaml", "-o",
                  tmp_path / f"{push}.nrrd", "--pushforward", push, "--json", *chunked)
        assert res.code == 0, res.stderr
        for entry in json.loads(res.stdout)["labels"]:
            assert entry["predicted_mm3"] == pytest.approx(entry["input_mm3"], rel=1e-6), push
