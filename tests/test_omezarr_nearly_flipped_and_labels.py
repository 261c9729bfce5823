"""OME-Zarr stores as other NGFF readers (ome-zarr-py) place them, against SimpleITK.

NGFF 0.4/0.5 hold a scale and a translation only: what a reader that knows
nothing else sees of a volwarp store is its array in its own index frame.
"""

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.io import read_volume, write_volume


def _tilted(direction, angle):
    """``direction`` turned by ``angle`` radians about z (a scanner's tilt, float noise)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ direction


def _ome_zarr_py_world(path):
    """World points (x, y, z) of every voxel of level 0 as ome-zarr-py's metadata gives them."""
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    node = list(Reader(parse_url(str(path)))())[0]
    data = np.asarray(node.data[0])
    scale, translation = node.metadata["coordinateTransformations"][0]
    kji = np.indices(data.shape).reshape(3, -1).T
    world = np.asarray(translation["translation"]) + np.asarray(scale["scale"]) * kji
    return data, kji, world[:, ::-1]


@pytest.mark.parametrize("version", ["0.4", "0.5"])
@pytest.mark.parametrize("base", [np.diag([-1.0, -1.0, 1.0]),  # RAS
                                  np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0],
                                            [0.0, -1.0, 0.0]])])  # sagittal
def test_a_nearly_flipped_scan_is_where_other_readers_look(tmp_path, version, base):
    """A RAS scan whose direction is 2e-6 rad off its flips (a scanner's tilt, float32
    noise of a NIfTI sform) was written unreindexed, as an oblique one: ome-zarr-py and
    ngff-zarr saw it mirrored in x and y (every voxel up to the scan's extent away), exit
    0, no word. It is reindexed by its nearest flips and swaps: other readers see every
    voxel within the tilt of where SimpleITK puts it, and volwarp reads it back exactly."""
    rng = np.random.default_rng(0)
    data = rng.integers(0, 1000, (9, 11, 13)).astype(np.int16)
    img = sitk.GetImageFromArray(data)
    img.SetSpacing((0.7, 0.9, 2.5))
    img.SetOrigin((-10.0, 20.0, 30.0))
    img.SetDirection(_tilted(base, 2e-6).ravel().tolist())
    src = tmp_path / "src.nrrd"
    sitk.WriteImage(img, str(src))
    out = tmp_path / "v.ome.zarr"
    write_volume(read_volume(src), out, ome_zarr_version=version)

    stored, kji, world = _ome_zarr_py_world(out)
    ref = sitk.ReadImage(str(src))
    ref_data = sitk.GetArrayFromImage(ref)
    for (k, j, i), point in zip(kji, world, strict=True):
        idx = ref.TransformPhysicalPointToContinuousIndex(point.tolist())
        near = np.rint(idx).astype(int)
        assert np.allclose(idx, near, atol=1e-3), (point, idx)  # (the tilt: 1e-4 voxel)
        assert stored[k, j, i] == ref_data[near[2], near[1], near[0]]

    back = read_volume(out)  # volwarp: exact, the tilt kept
    ijk = np.indices(back.data.shape).reshape(3, -1).T[:, ::-1]
    pts = back.index_to_world(ijk)
    exact = np.array([ref.TransformPhysicalPointToContinuousIndex(p.tolist()) for p in pts])
    np.testing.assert_allclose(exact, np.rint(exact), atol=1e-9)
    exact = np.rint(exact).astype(int)
    assert np.array_equal(back.data[ijk[:, 2], ijk[:, 1], ijk[:, 0]],
                          ref_data[exact[:, 2], exact[:, 1], exact[:, 0]])


@pytest.mark.parametrize("chunks", [(5, 8, 6), None])
def test_a_nearly_flipped_grid_by_blocks_is_the_in_memory_store(tmp_path, chunks):
    """Written by blocks (staged, or a shard a block), the store of a nearly flipped and
    permuted grid is the one write_volume makes: reindexed alike, the tilt kept."""
    import zarr

    from volwarp_cli.geometry import Geometry
    from volwarp_cli.io.blockwrite import open_block_output

    base = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    geom = Geometry((13, 22, 17), (0.5, 0.6, 0.7), (1.0, -2.0, 3.0), _tilted(base, 3e-7))
    data = np.random.default_rng(1).integers(-500, 500, geom.shape).astype(np.int16)
    header = geom.header("int16", meta={"volwarp_command": "test"}, space="LPS")
    out = open_block_output(tmp_path / "b.ome.zarr", header, chunks_zyx=chunks, pyramid=1,
                            labels=False)
    for box in out.blocks():
        out.write(box, data[box.slices])
    out.commit()
    write_volume(geom.volume(data, meta={"volwarp_command": "test"}, space="LPS"),
                 tmp_path / "w.ome.zarr", pyramid=1)
    a, b = zarr.open_group(tmp_path / "b.ome.zarr"), zarr.open_group(tmp_path / "w.ome.zarr")
    assert dict(a.attrs) == dict(b.attrs)
    for level in ("0", "1"):
        assert np.array_equal(a[level][...], b[level][...])
    back = read_volume(tmp_path / "b.ome.zarr")
    assert back.shape_xyz != geom.shape_xyz  # (reindexed: axes swapped)
    ijk = np.indices(back.data.shape).reshape(3, -1).T[:, ::-1]
    idx = geom.world_to_index(back.index_to_world(ijk))
    np.testing.assert_allclose(idx, np.rint(idx), atol=1e-9)
    idx = np.rint(idx).astype(int)
    assert np.array_equal(back.data[ijk[:, 2], ijk[:, 1], ijk[:, 0]],
                          data[idx[:, 2], idx[:, 1], idx[:, 0]])


def test_an_ngff_labels_image_inside_its_store_is_read_as_a_label_map(tmp_path):
    """NGFF keeps a segmentation at ``image.ome.zarr/labels/<name>``, a folder without a
    ``.zarr`` suffix: volwarp looked for DICOM files there ("a folder with no DICOM
    files"), so the image-label groups formats.md says it reads as label maps could not
    be given. A folder holding Zarr metadata is a store."""
    import zarr
    from ome_zarr.writer import write_image, write_labels

    from volwarp_cli.io import volume_format
    from volwarp_cli.labelmap import segmentation_of

    image = np.arange(6 * 7 * 8, dtype=np.uint16).reshape(6, 7, 8)
    seg = (image // 100).astype(np.uint8)
    store = tmp_path / "img.ome.zarr"
    group = zarr.open_group(str(store), mode="w")
    write_image(image, group, axes="zyx", scale_factors=[],
                scale={"z": 2.0, "y": 0.5, "x": 0.5},
                axes_units={"z": "micrometer", "y": "micrometer", "x": "micrometer"})
    write_labels(seg, group, name="cells", axes="zyx", scaler=None, scale_factors=[])
    path = store / "labels" / "cells"
    assert volume_format(path, reading=True) == "omezarr"
    vol = read_volume(path)
    assert np.array_equal(vol.data, seg)
    assert "image-label" in segmentation_of(vol.meta)
