"""OME-Zarr outputs other readers take wrong without a word: oblique grids, label maps.

NGFF 0.4/0.5 hold a scale and a translation only, and say a segmentation is one
by its ``image-label`` metadata: what volwarp keeps in its own attribute (a
rotation, that the samples are ids) no other reader sees.
"""

import logging

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.io import read_volume, write_volume


def _rotated(angle_deg, base=np.eye(3)):
    """``base`` turned by ``angle_deg`` degrees about z."""
    a = np.radians(angle_deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ base


def _source(tmp_path, direction, data=None):
    """A NRRD of ``direction`` (SimpleITK's writing: the reference placement)."""
    if data is None:
        data = np.random.default_rng(0).integers(0, 1000, (9, 11, 13)).astype(np.int16)
    img = sitk.GetImageFromArray(data)
    img.SetSpacing((0.7, 0.9, 2.5))
    img.SetOrigin((-10.0, 20.0, 30.0))
    img.SetDirection(np.asarray(direction, dtype=np.float64).ravel().tolist())
    path = tmp_path / "src.nrrd"
    sitk.WriteImage(img, str(path))
    return path


def _oblique_warnings(caplog):
    return [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and "oblique" in r.getMessage()]


@pytest.mark.parametrize("version", ["0.4", "0.5"])
def test_an_oblique_grid_written_to_ome_zarr_warns_once_naming_its_angle(tmp_path, caplog,
                                                                          version):
    """A grid turned 20 degrees (no flip or swap near it) is stored with its rotation
    in volwarp's attribute only: ome-zarr-py, ngff-zarr, napari place it axis-aligned,
    every voxel but the first misplaced (here by up to 7 mm), and nothing said so."""
    src = _source(tmp_path, _rotated(20.0))
    out = tmp_path / "o.ome.zarr"
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        write_volume(read_volume(src), out, ome_zarr_version=version, pyramid=1)
    warned = _oblique_warnings(caplog)
    assert len(warned) == 1, warned
    assert "20 degrees" in warned[0] and str(out) in warned[0]
    assert ".nrrd" in warned[0] and ".nii.gz" in warned[0]
    # (what the warning says: ome-zarr-py places the last voxel away from SimpleITK's point)
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    node = list(Reader(parse_url(str(out)))())[0]
    scale, translation = node.metadata["coordinateTransformations"][0]
    kji = np.array(node.data[0].shape) - 1
    theirs = (np.array(translation["translation"]) + np.array(scale["scale"]) * kji)[::-1]
    ref = sitk.ReadImage(str(src))
    # (the store's last voxel, reindexed by no flip or swap, is the source's last voxel)
    truth = np.array(ref.TransformIndexToPhysicalPoint([int(n) - 1 for n in ref.GetSize()]))
    assert np.linalg.norm(theirs - truth) > 1.0


def test_an_oblique_grid_written_by_blocks_warns_once(tmp_path, caplog):
    """The writer by blocks (commands' large outputs) says it as the in-memory one."""
    from volwarp_cli.geometry import Geometry
    from volwarp_cli.io.blockwrite import open_block_output

    geom = Geometry((13, 11, 9), (0.5, 0.6, 0.7), (1.0, -2.0, 3.0), _rotated(-30.0))
    data = np.random.default_rng(1).integers(-500, 500, geom.shape).astype(np.int16)
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        out = open_block_output(tmp_path / "b.ome.zarr", geom.header("int16", space="LPS"),
                                chunks_zyx=(4, 5, 6), labels=False)
        for box in out.blocks():
            out.write(box, data[box.slices])
        out.commit()
    warned = _oblique_warnings(caplog)
    assert len(warned) == 1 and "30 degrees" in warned[0], warned


@pytest.mark.parametrize("direction", [
    np.diag([-1.0, -1.0, 1.0]),  # RAS
    np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),  # sagittal: swapped
    _rotated(np.degrees(1e-6), np.diag([-1.0, -1.0, 1.0])),  # RAS, 1e-6 rad of noise
    _rotated(np.degrees(1e-6)),  # LPS, 1e-6 rad of noise
], ids=["ras", "swapped", "ras-noise", "lps-noise"])
def test_a_grid_the_reindexing_places_gives_no_warning(tmp_path, caplog, direction):
    """Flips and swaps are stored exactly; a 1e-6 rad tilt moves no voxel of the grid
    by a thousandth of a voxel in other readers: nothing to say of either."""
    src = _source(tmp_path, direction)
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        write_volume(read_volume(src), tmp_path / "o.ome.zarr")
    assert not _oblique_warnings(caplog)


def test_convert_to_ome_zarr_of_an_oblique_scan_says_it_on_stderr(tmp_path):
    """`volwarp convert` (the command users run) prints the warning, once."""
    import subprocess
    import sys

    src = _source(tmp_path, _rotated(20.0))
    out = tmp_path / "c.ome.zarr"
    proc = subprocess.run([sys.executable, "-m", "volwarp_cli", "convert", str(src), "-o", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    lines = [x for x in proc.stderr.splitlines() if "oblique" in x]
    assert len(lines) == 1 and "warning" in lines[0], proc.stderr
    back = read_volume(out)  # (volwarp itself reads it where it lies)
    np.testing.assert_allclose(back.direction, _rotated(20.0), atol=1e-12)


def _label_map():
    seg = np.zeros((10, 12, 14), dtype=np.uint16)
    seg[2:8, 3:9, 4:10] = 3
    seg[4:6, 5:7, 6:12] = 1000
    seg[1:3, 1:4, 1:4] = 7
    return seg


@pytest.mark.parametrize("version", ["0.4", "0.5"])
@pytest.mark.parametrize("pyramid", [0, 1])
def test_a_label_map_store_carries_ngff_image_label(tmp_path, version, pyramid):
    """A label map stored as OME-Zarr said it held ids in volwarp's attribute only:
    ome-zarr-py (napari's reader) saw an image of intensities. NGFF 0.4 says a group with
    ``image-label`` is a segmentation ("unlisted groups MAY be labels"); ome-zarr-py and
    ome-zarr-models recognise one at a store's root, NGFF's label schema validates it."""
    import zarr
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Label, Reader
    from ome_zarr_models import open_ome_zarr

    src = _source(tmp_path, np.eye(3), _label_map())
    out = tmp_path / "l.ome.zarr"
    write_volume(read_volume(src), out, ome_zarr_version=version, pyramid=pyramid)
    attrs = dict(zarr.open_group(str(out), mode="r").attrs)
    ome = attrs["ome"] if version == "0.5" else attrs
    assert ome["image-label"] == {"version": version}
    from ngff_zarr.validate import validate  # (NGFF's own JSON schema of a label image)

    validate(attrs, version=version, model="label")
    node = list(Reader(parse_url(str(out)))())[0]
    assert node.load(Label) is not None
    model = open_ome_zarr(zarr.open_group(str(out), mode="r"))
    assert type(model).__name__ == "ImageLabel", type(model)
    back = read_volume(out)  # (volwarp: a label map still, its samples unchanged)
    from volwarp_cli.labelmap import segmentation_of

    assert segmentation_of(back.meta)
    assert np.array_equal(back.data, _label_map())


@pytest.mark.parametrize("dtype", ["int16", "float32"])
def test_no_image_label_on_intensities_or_float_samples(tmp_path, dtype):
    """A scan's intensities are no segmentation; a float32 map of ids is a label map to
    volwarp (its levels take the mode) but NGFF label images are integer types only."""
    import zarr

    data = (np.random.default_rng(2).normal(0, 300, (10, 12, 14)).astype(np.int16)
            if dtype == "int16" else _label_map().astype(np.float32))
    src = _source(tmp_path, np.eye(3), data)
    out = tmp_path / "i.ome.zarr"
    write_volume(read_volume(src), out, pyramid=1)
    attrs = dict(zarr.open_group(str(out), mode="r").attrs)
    assert "image-label" not in attrs["ome"]
    if dtype == "float32":
        assert attrs["volwarp"]["downsampling"] == "mode"


def test_a_label_map_written_by_blocks_carries_image_label_as_in_memory(tmp_path):
    """By blocks without levels, the store is the in-memory one, image-label included."""
    import zarr

    from volwarp_cli.geometry import Geometry
    from volwarp_cli.io.blockwrite import open_block_output

    seg = _label_map()
    geom = Geometry(seg.shape, (0.5, 0.6, 0.7), (1.0, -2.0, 3.0), np.eye(3))
    out = open_block_output(tmp_path / "b.ome.zarr", geom.header("uint16", space="LPS"),
                            chunks_zyx=(4, 5, 6))
    for box in out.blocks():
        out.write(box, seg[box.slices])
    out.commit()
    write_volume(geom.volume(seg, space="LPS"), tmp_path / "w.ome.zarr")
    a = dict(zarr.open_group(str(tmp_path / "b.ome.zarr"), mode="r").attrs)
    b = dict(zarr.open_group(str(tmp_path / "w.ome.zarr"), mode="r").attrs)
    assert a["ome"]["image-label"] == {"version": "0.5"}
    assert a == b
