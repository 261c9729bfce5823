"""Label maps known by what their files say, whatever their samples look like.

A 3D Slicer segmentation of single-voxel fiducials (its ``Segment*`` keys), an
OME-Zarr labels image (``image-label``) and a volume whose ``volwarp_values``
says labels were taken for intensities where the neighbour rule could not tell
(ids 10..60 blended into 0..34 by ``apply``, exit 0; a pyramid of a warp's
labels took the mean); a float map whose NIfTI intent says labels but holds a
NaN was blended too. Each is checked against SimpleITK's nearest neighbour or
the ids it holds.
"""

from __future__ import annotations

import json

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

POINTS = [(5, 6, 7), (10, 30, 12), (20, 20, 20), (25, 8, 30), (33, 15, 22), (12, 22, 33)]


def _fiducials():
    d = np.zeros((40, 40, 40), np.uint8)
    for i, p in enumerate(POINTS):
        d[p] = 10 * (i + 1)
    return d


@pytest.fixture
def affine(tmp_path):
    a = sitk.AffineTransform(3)
    a.SetMatrix([0.95, 0.1, 0.02, -0.08, 1.03, 0.05, 0.01, -0.04, 0.98])
    a.SetTranslation([0.37, -0.61, 0.23])
    a.SetCenter([20, 20, 20])
    path = tmp_path / "aff.tfm"
    sitk.WriteTransform(a, str(path))
    return path, a


def test_a_slicer_segmentation_of_fiducials_is_resampled_as_labels(run, tmp_path, affine):
    tfm, a = affine
    img = sitk.GetImageFromArray(_fiducials())
    for i in range(len(POINTS)):
        for key, value in (("ID", f"Segment_{i + 1}"), ("Name", f"fiducial{i + 1}"),
                           ("LabelValue", str(10 * (i + 1))), ("Layer", "0")):
            img.SetMetaData(f"Segment{i}_{key}", value)
    src = tmp_path / "fid.seg.nrrd"
    sitk.WriteImage(img, str(src))
    out = tmp_path / "moved.seg.nrrd"
    res = run("apply", src, "-t", tfm, "-o", out, "-v")
    assert res.code == 0, res.stderr
    assert "read from a 3D Slicer segmentation (its Segment keys)" in res.stderr
    got = read_volume(out).data
    ref = sitk.GetArrayFromImage(sitk.Resample(img, img, a, sitk.sitkNearestNeighbor, 0))
    assert set(np.unique(got)) <= {0, 10, 20, 30, 40, 50, 60}  # (no blend: 1..34 before)
    assert np.count_nonzero(got != ref) <= 2  # (ties at exact half voxels, as SimpleITK's)
    # a distance field of it is no label map: its Segment keys are not carried
    dist = tmp_path / "d.nrrd"
    assert run("distance", src, "--label", "30", "-o", dist).code == 0
    assert not [k for k in read_volume(dist).meta if k.startswith("Segment")]


def test_a_label_map_with_a_nan_is_not_blended(run, tmp_path, affine):
    tfm, _ = affine
    a = np.zeros((30, 30, 30), np.float32)
    a[5:15, 5:15, 5:15], a[18:26, 18:26, 18:26] = 1, 2
    a[0, 0, 0] = np.nan
    img = nib.Nifti1Image(a, np.eye(4))
    img.header.set_intent("label")
    src = tmp_path / "lab.nii.gz"
    nib.save(img, src)
    res = run("apply", src, "-t", tfm, "-o", tmp_path / "o.nii.gz")
    assert res.code == 2
    assert "intent NIFTI_INTENT_LABEL), but some of its samples are NaN" in res.stderr
    assert not (tmp_path / "o.nii.gz").exists()
    res = run("apply", src, "-t", tfm, "-o", tmp_path / "o.nii.gz", "--values", "intensity")
    assert res.code == 0, res.stderr  # (the user's choice)


def test_an_ome_zarr_labels_image_is_warped_as_labels(run, tmp_path):
    store = tmp_path / "fid.ome.zarr"
    write_volume(Volume(_fiducials()), store)
    zarr_json = store / "zarr.json"
    attrs = json.loads(zarr_json.read_text())
    attrs["attributes"]["ome"]["image-label"] = {"version": "0.5"}
    zarr_json.write_text(json.dumps(attrs))
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 6, oversample: 2}\nsteps:\n"
                    "  - move:\n      - {index: [3, 3, 3], by: [2.3, -1.7, 1.1]}\n")
    out = tmp_path / "w.nrrd"
    res = run("warp", store, "--spec", spec, "-o", out, "-v")
    assert res.code == 0, res.stderr
    assert "read from an OME-Zarr labels image (image-label)" in res.stderr
    assert set(np.unique(read_volume(out).data)) <= {0, 10, 20, 30, 40, 50, 60}


def test_a_recorded_labels_choice_makes_a_pyramid_of_modes(run, tmp_path):
    lab = np.zeros((32, 32, 32), np.int16)
    for i, p in enumerate(POINTS):
        lab[tuple(min(c, 31) for c in p)] = 10 * (i + 1)
    src = tmp_path / "lab.nrrd"
    write_volume(Volume(lab, meta={"volwarp_values": "labels"}), src)
    res = run("convert", src, "-o", tmp_path / "p.ome.zarr", "--pyramid", "1", "-v")
    assert res.code == 0, res.stderr
    assert "by the mode (a label map)" in res.stderr
    assert "is a label map by its record (volwarp_values)" in run("info", src).stdout


@pytest.mark.parametrize("way", [[], ["--chunked", "--block", "5", "--scheduler", "processes",
                                      "--threads", "2"]])
def test_apply_says_the_labels_no_output_voxel_holds(run, tmp_path, way):
    """One-voxel lines resampled onto a 2 mm grid fall between its voxels: nearest neighbour
    loses them (as SimpleITK's does), and apply said nothing, where warp's report names
    them. The labels missing from the whole output are said once, by blocks too."""
    t = np.zeros((40, 40, 40), np.uint8)
    t[20, 20, 5:35], t[5:35, 10, 10], t[15, 5:35, 30] = 1, 2, 3
    t[2:8, 2:8, 2:8] = 4  # (a block: kept)
    src, ref = tmp_path / "thin.nrrd", tmp_path / "ref.nrrd"
    write_volume(Volume(t), src)
    write_volume(Volume(np.zeros((20, 20, 20), np.uint8), spacing=(2.0, 2.0, 2.0),
                        origin=(0.5, 0.5, 0.5)), ref)
    ident = tmp_path / "id.tfm"
    sitk.WriteTransform(sitk.AffineTransform(3), str(ident))
    out = tmp_path / "o.nrrd"
    res = run("apply", src, "-t", ident, "--reference", ref, "-o", out, *way)
    assert res.code == 0, res.stderr
    got = read_volume(out).data
    held = set(np.unique(got).tolist())
    assert held == {0, 4}
    lines = [ln for ln in res.stderr.splitlines() if "in no output voxel" in ln]
    assert len(lines) == 1
    assert "3 of the input's 4 labels are in no output voxel (1, 2, 3)" in lines[0]


def test_a_label_map_warped_as_intensities_does_not_keep_its_label_keys(run, tmp_path, affine):
    """``--values intensity`` blends the ids: the output kept the map's Segment keys (or
    NIfTI intent), so the next command took the blend for a label map, or asked. A
    convert's too: told they are intensities, its cast and pyramid treat them so."""
    tfm, _ = affine
    img = sitk.GetImageFromArray(_fiducials())
    img.SetMetaData("Segment0_LabelValue", "10")
    img.SetMetaData("Segment0_Name", "first")
    src = tmp_path / "fid.seg.nrrd"
    sitk.WriteImage(img, str(src))
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 6, oversample: 2}\nsteps:\n"
                    "  - move:\n      - {index: [3, 3, 3], by: [2.3, -1.7, 1.1]}\n")
    for args, out in ((["warp", src, "--spec", spec], "w.nrrd"),
                      (["apply", src, "-t", tfm], "a.nrrd"),
                      (["convert", src], "c.nrrd")):  # (its samples the ids, cast: said so)
        res = run(*args, "--values", "intensity", "--dtype", "float32", "-o", tmp_path / out)
        assert res.code == 0, res.stderr
        meta = read_volume(tmp_path / out).meta
        assert not [k for k in meta if k.startswith("Segment")], meta
        res = run("apply", tmp_path / out, "-t", tfm, "-o", tmp_path / ("again_" + out), "-v")
        assert res.code == 0, res.stderr
        assert "values: intensity" in res.stderr
    # a label warp keeps them
    assert run("warp", src, "--spec", spec, "-o", tmp_path / "l.nrrd").code == 0
    assert read_volume(tmp_path / "l.nrrd").meta["Segment0_Name"] == "first"


def test_capture_values_labels_of_fractions_is_refused_at_once(run, tmp_path):
    """The capture accepted it (exit 0) and every warp of the file then failed."""
    src = tmp_path / "f.nrrd"
    write_volume(Volume(np.random.default_rng(0).random((12, 13, 14), dtype=np.float32)), src)
    res = run("capture", src, "-o", tmp_path / "f.vwc", "--values", "labels")
    assert res.code == 2 and "needs integer ids" in res.stderr
    assert not (tmp_path / "f.vwc").exists()


@pytest.mark.parametrize("ext", ["nrrd", "nii.gz", "mha", "ome.zarr"])
def test_labels_given_against_the_rule_are_recorded_for_the_next_command(run, tmp_path, affine,
                                                                        ext):
    """Six single-voxel ids are intensities by the rule: ``--values labels`` kept them, but the
    output did not say so, and the next command blended them (exit 0). The choice is recorded;
    the next ``apply`` resamples the output by nearest neighbour, as SimpleITK does."""
    tfm, a = affine
    src = tmp_path / "fid.nrrd"
    write_volume(Volume(_fiducials()), src)
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 5}\nsteps:\n"
                    "  - move:\n      - {index: [2, 2, 2], by: [0.0, 0.0, 0.0]}\n")
    for cmd, args in (("warp", ["--spec", spec]), ("apply", ["-t", tfm])):
        kept = tmp_path / f"{cmd}.{ext}"
        res = run(cmd, src, *args, "--values", "labels", "-o", kept)
        assert res.code == 0, res.stderr
        assert read_volume(kept).meta.get("volwarp_values") == "labels"
        again = tmp_path / f"again_{cmd}.nrrd"
        res = run("apply", kept, "-t", tfm, "-o", again, "-v")
        assert res.code == 0, res.stderr
        assert "values: labels (recorded in the file (volwarp_values))" in res.stderr
        img = sitk.GetImageFromArray(read_volume(kept).data)
        ref = sitk.GetArrayFromImage(sitk.Resample(img, img, a, sitk.sitkNearestNeighbor, 0))
        got = read_volume(again).data
        assert set(np.unique(got)) <= {0, 10, 20, 30, 40, 50, 60}  # (blended before)
        assert np.count_nonzero(got != ref) <= 2
    # convert --values labels records it too, and so does the library's warp
    res = run("convert", src, "--values", "labels", "--dtype", "int16", "-o",
              tmp_path / f"c.{ext}")
    assert res.code == 0, res.stderr
    assert read_volume(tmp_path / f"c.{ext}").meta.get("volwarp_values") == "labels"
    from volwarp_cli import api

    assert api.warp(src, spec, values="labels").meta.get("volwarp_values") == "labels"
    # where the rule agrees (a label map of regions), the output is the rule's, byte for byte
    regions = np.zeros((20, 20, 20), np.uint8)
    regions[3:9, 4:12, 5:15] = 2
    regions[10:17, 6:14, 2:10] = 5
    write_volume(Volume(regions), tmp_path / "regions.nrrd")
    outs = []
    for extra in ([], ["--values", "labels"]):
        outs.append(tmp_path / f"r{len(outs)}.nrrd")
        assert run("warp", tmp_path / "regions.nrrd", "--spec", spec, *extra, "-o",
                   outs[-1]).code == 0
        outs.append(tmp_path / f"c{len(outs)}.nrrd")  # (and convert's, the same rule)
        assert run("convert", tmp_path / "regions.nrrd", "--dtype", "uint16", *extra, "-o",
                   outs[-1]).code == 0
    assert outs[0].read_bytes() == outs[2].read_bytes()
    assert outs[1].read_bytes() == outs[3].read_bytes()
    assert not any("volwarp_values" in read_volume(o).meta for o in outs[2:])
    # ... but a record of intensities it carried (a warp of a capture made --values
    # intensity) is replaced: the next command blended the labels kept
    write_volume(Volume(regions, meta={"volwarp_values": "intensity"}), tmp_path / "ri.nrrd")
    for cmd, args in (("warp", ["--spec", spec]), ("apply", ["-t", tfm])):
        out = tmp_path / f"ri_{cmd}.{ext}"
        assert run(cmd, tmp_path / "ri.nrrd", *args, "--values", "labels", "-o", out).code == 0
        assert read_volume(out).meta.get("volwarp_values") == "labels"
    assert api.warp(tmp_path / "ri.nrrd", spec, values="labels").meta["volwarp_values"] == \
        "labels"
    # (and the library's intensity warp of an output that records labels drops the record)
    kept = api.warp(tmp_path / f"warp.{ext}", spec, values="intensity", dtype="float32")
    assert "volwarp_values" not in kept.meta
