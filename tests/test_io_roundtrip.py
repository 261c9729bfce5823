"""Round trips of every format x dtype x byte order, and cross-checks with independent readers."""

from __future__ import annotations

import gzip

import nrrd as pynrrd
import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.errors import BadUsage, ChoiceNeeded
from volwarp_cli.io import RawLayout, read_volume, write_volume
from volwarp_cli.io.common import SUPPORTED_DTYPES
from volwarp_cli.volume import Volume

DTYPES = list(SUPPORTED_DTYPES)


def sample_volume(dtype, shape_zyx=(5, 6, 7)) -> Volume:
    rng = np.random.default_rng(7)
    dt = np.dtype(dtype)
    if dt.kind == "f":
        data = rng.normal(0, 1000, shape_zyx).astype(dt)
        data.flat[0] = np.finfo(dt).max
        data.flat[1] = np.finfo(dt).tiny
    else:
        info = np.iinfo(dt)
        data = rng.integers(info.min, info.max, shape_zyx, endpoint=True, dtype=dt)
        data.flat[0] = info.min
        data.flat[1] = info.max
    a = np.deg2rad(20.0)
    direction = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return Volume(data, spacing=(0.7, 1.3, 2.9), origin=(-3.25, 11.5, 101.0), direction=direction,
                  space="left-posterior-superior")


def assert_same_geometry(a: Volume, b: Volume, atol=1e-12):
    np.testing.assert_allclose(b.spacing, a.spacing, rtol=0, atol=atol)
    np.testing.assert_allclose(b.origin, a.origin, rtol=0, atol=atol)
    np.testing.assert_allclose(b.direction, a.direction, rtol=0, atol=atol)


FORMATS = [
    ("x.nrrd", {}, ("little", "big")),
    ("x.nrrd", {"compress": True}, ("little", "big")),
    ("x.nhdr", {}, ("little", "big")),
    ("x.tif", {}, ("little", "big")),
    ("x.tif", {"compress": True}, ("little",)),
    ("x.nii", {}, ("little",)),
    ("x.nii.gz", {}, ("little",)),
]


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name,kwargs,orders", FORMATS, ids=lambda v: str(v))
def test_round_trip_is_bit_identical(tmp_path, dtype, name, kwargs, orders):
    vol = sample_volume(dtype)
    for order in orders:
        path = tmp_path / f"{order}-{name}"
        write_volume(vol, path, byte_order=order, **kwargs)
        back = read_volume(path)
        assert back.data.dtype == np.dtype(dtype)
        assert back.data.shape == vol.data.shape
        assert back.data.tobytes() == vol.data.tobytes()
        # NIfTI stores its matrices as float32: geometry is exact to float32 precision there.
        assert_same_geometry(vol, back, atol=1e-5 if ".nii" in name else 1e-12)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("order", ["little", "big"])
def test_raw_round_trip(tmp_path, dtype, order):
    vol = sample_volume(dtype)
    path = tmp_path / "x.raw"
    write_volume(vol, path, byte_order=order)
    assert path.stat().st_size == vol.data.nbytes
    layout = RawLayout(shape=vol.shape_xyz, dtype=dtype, endian=order,
                       spacing=tuple(vol.spacing), origin=tuple(vol.origin))
    back = read_volume(path, raw=layout)
    assert back.data.tobytes() == vol.data.tobytes()
    np.testing.assert_array_equal(back.spacing, vol.spacing)
    np.testing.assert_array_equal(back.origin, vol.origin)
    # big-endian bytes really are big-endian on disk
    expect = vol.data.astype(vol.data.dtype.newbyteorder("<" if order == "little" else ">"))
    assert path.read_bytes() == expect.tobytes()


def test_raw_header_bytes(tmp_path):
    data = np.arange(24, dtype=np.uint16).reshape(2, 3, 4)
    path = tmp_path / "h.bin"
    path.write_bytes(b"HEADER!!" + data.astype(">u2").tobytes())
    vol = read_volume(path, raw=RawLayout(shape=(4, 3, 2), dtype="uint16", endian="big",
                                          header_bytes=8))
    np.testing.assert_array_equal(vol.data, data)


@pytest.mark.parametrize("name", ["a.nrrd", "a.nhdr", "a.tif", "a.nii", "a.nii.gz", "a.raw"])
def test_writes_are_deterministic(tmp_path, name):
    vol = sample_volume("int16")
    vol.meta["note"] = "kept"
    for sub in ("one", "two"):
        (tmp_path / sub).mkdir()
        write_volume(vol, tmp_path / sub / name, compress=True)
    assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()


def test_meta_key_values_survive(tmp_path):
    vol = sample_volume("uint8")
    vol.meta.update({"modality": "MR", "patient position": "HFS", "NRRD_content": "a test"})
    for name in ("m.nrrd", "m.tif"):
        write_volume(vol, tmp_path / name)
        back = read_volume(tmp_path / name)
        for key in ("modality", "patient position", "NRRD_content"):
            assert back.meta[key] == vol.meta[key], (name, key)


# -- independent readers ------------------------------------------------------

def sitk_geometry(path):
    img = sitk.ReadImage(str(path))
    return (img.GetSize(), np.array(img.GetSpacing()), np.array(img.GetOrigin()),
            np.array(img.GetDirection()).reshape(3, 3), sitk.GetArrayFromImage(img))


@pytest.mark.parametrize("name", ["s.nrrd", "s.nii", "s.nii.gz", "s.nhdr"])
def test_simpleitk_reads_what_volwarp_writes(tmp_path, name):
    vol = sample_volume("int16")
    write_volume(vol, tmp_path / name, compress=name.endswith("nrrd"))
    size, spacing, origin, direction, arr = sitk_geometry(tmp_path / name)
    assert size == vol.shape_xyz
    np.testing.assert_allclose(spacing, vol.spacing, atol=1e-6)
    np.testing.assert_allclose(origin, vol.origin, atol=1e-5)
    np.testing.assert_allclose(direction, vol.direction, atol=1e-6)
    np.testing.assert_array_equal(arr, vol.data)  # SimpleITK's arrays are [z, y, x] too


def test_pynrrd_reads_what_volwarp_writes(tmp_path):
    vol = sample_volume("float32")
    write_volume(vol, tmp_path / "p.nrrd", byte_order="big", compress=True)
    data, header = pynrrd.read(str(tmp_path / "p.nrrd"), index_order="C")
    np.testing.assert_array_equal(data, vol.data)
    np.testing.assert_allclose(header["space origin"], vol.origin)
    # pynrrd's space directions rows are the axis vectors (x, y, z)
    np.testing.assert_allclose(np.asarray(header["space directions"]).T,
                               vol.direction * vol.spacing[None, :], atol=1e-12)
    assert header["space"] == "left-posterior-superior"


@pytest.mark.parametrize("name", ["t.nrrd", "t.nii.gz", "t.nii"])
def test_volwarp_reads_what_simpleitk_writes(tmp_path, name):
    rng = np.random.default_rng(3)
    arr = rng.integers(-300, 3000, (9, 8, 7)).astype(np.int16)
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((0.9, 1.1, 3.0))
    img.SetOrigin((10.0, -20.0, 30.5))
    a = np.deg2rad(15)
    d = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    img.SetDirection(d.ravel().tolist())
    sitk.WriteImage(img, str(tmp_path / name), useCompression=name.endswith("nrrd"))
    vol = read_volume(tmp_path / name)
    np.testing.assert_array_equal(vol.data, arr)
    np.testing.assert_allclose(vol.spacing, (0.9, 1.1, 3.0), atol=1e-5)
    np.testing.assert_allclose(vol.origin, (10.0, -20.0, 30.5), atol=1e-4)
    np.testing.assert_allclose(vol.direction, d, atol=1e-5)


def test_real_scan_matches_simpleitk_reference(data_dir):
    """The shared MRI (written by pynrrd): the geometry SimpleITK reports, per data/README.md."""
    path = data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd"
    vol = read_volume(path)
    assert vol.shape_xyz == (128, 128, 62)
    np.testing.assert_array_equal(vol.spacing, (2, 2, 3))
    np.testing.assert_array_equal(vol.origin, (0, 254, 0))
    np.testing.assert_array_equal(vol.direction, [[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    assert vol.data.min() == 0 and vol.data.max() == 255
    assert round(float(vol.data.mean()), 4) == 19.2298
    size, spacing, origin, direction, arr = sitk_geometry(path)
    np.testing.assert_array_equal(arr, vol.data)
    np.testing.assert_allclose(direction, vol.direction)


def test_colin27_against_simpleitk(data_dir):
    path = data_dir / "mri_colin27_brain_1mm.nrrd"
    vol = read_volume(path)
    size, spacing, origin, direction, arr = sitk_geometry(path)
    assert size == vol.shape_xyz == (181, 217, 181)
    np.testing.assert_allclose(origin, vol.origin)
    np.testing.assert_allclose(direction, vol.direction)
    np.testing.assert_array_equal(arr, vol.data)
    assert vol.data.dtype == np.uint8


def test_world_coordinates_agree_with_simpleitk(data_dir):
    vol = read_volume(data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd")
    img = sitk.ReadImage(str(data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd"))
    for ijk in [(0, 0, 0), (5, 17, 3), (127, 127, 61), (10.5, 3.25, 7.75)]:
        expect = img.TransformContinuousIndexToPhysicalPoint([float(v) for v in ijk])
        np.testing.assert_allclose(vol.index_to_world(ijk), expect, atol=1e-9)
        np.testing.assert_allclose(vol.world_to_index(expect), ijk, atol=1e-9)


def _nifti_with_forms(path, sform, scode, qform, qcode):
    import nibabel as nib

    img = nib.Nifti1Image(np.zeros((4, 5, 6), np.uint8), None)
    img.set_qform(qform, code=qcode)  # also sets pixdim from the qform's scales
    img.set_sform(sform, code=scode)
    nib.save(img, path)


def _affine(scales, shift, angle=0.0):
    a = np.deg2rad(angle)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    m = np.eye(4)
    m[:3, :3] = rot * np.asarray(scales, float)[None, :]
    m[:3, 3] = shift
    return m


@pytest.mark.parametrize("scode,qcode,sform_kind,expect_from", [
    (1, 1, "rotated", "sform"),      # scanner-coded sform wins
    (2, 1, "rotated", "qform"),      # aligned sform that disagrees with the qform loses
    (2, 1, "same", "sform"),         # forms agree: sform (higher precision)
    (2, 0, "rotated", "sform"),      # only the sform is coded
    (0, 1, "rotated", "qform"),      # only the qform is coded
])
def test_nifti_sform_qform_rule_matches_simpleitk(tmp_path, scode, qcode, sform_kind, expect_from):
    qform = _affine((2, 3, 4), (1, 2, 3))
    sform = qform if sform_kind == "same" else _affine((2, 3, 4), (10, 20, 30), angle=25)
    path = tmp_path / "f.nii"
    _nifti_with_forms(path, sform, scode, qform, qcode)
    chosen = sform if expect_from == "sform" else qform
    lps = np.diag([-1.0, -1.0, 1.0])
    vol = read_volume(path)
    np.testing.assert_allclose(vol.index_to_world_matrix[:3, :3], lps @ chosen[:3, :3], atol=1e-5)
    np.testing.assert_allclose(vol.origin, lps @ chosen[:3, 3], atol=1e-5)
    img = sitk.ReadImage(str(path))
    np.testing.assert_allclose(img.GetSpacing(), vol.spacing, atol=1e-5)
    np.testing.assert_allclose(img.GetOrigin(), vol.origin, atol=1e-5)
    np.testing.assert_allclose(np.reshape(img.GetDirection(), (3, 3)), vol.direction, atol=1e-5)


def test_nifti_4d_needs_volume_index(tmp_path):
    import nibabel as nib

    data = np.arange(4 * 5 * 6 * 3, dtype=np.int16).reshape(4, 5, 6, 3)
    nib.save(nib.Nifti1Image(data, np.eye(4)), tmp_path / "t.nii.gz")
    from volwarp_cli.errors import ChoiceNeeded
    with pytest.raises(ChoiceNeeded, match="4-D NIfTI with 3 volumes"):
        read_volume(tmp_path / "t.nii.gz")
    vol = read_volume(tmp_path / "t.nii.gz", volume_index=2)
    np.testing.assert_array_equal(vol.data, data[..., 2].transpose(2, 1, 0))


@pytest.mark.parametrize("unit, mm", [("micron", 1e-3), ("\\u00B5m", 1e-3), ("um", 1e-3),
                                      ("cm", 10.0), ("mm", 1.0), ("pixel", None)])
def test_tiff_imagej_spacing_read_from_fiji_style_file(tmp_path, unit, mm):
    """A stack written the way Fiji writes it (no volwarp keys): spacing from resolution + ImageJ,
    in ImageJ's unit, made millimetres (0.25 um voxels were read as 0.25 mm ones, and an
    OME-TIFF of the same stack as 0.00025 mm); no length unit (pixel): the numbers as they are."""
    import tifffile

    data = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5)
    tifffile.imwrite(tmp_path / "fiji.tif", data, imagej=True, resolution=(1 / 0.25, 1 / 0.5),
                     metadata={"axes": "ZYX", "spacing": 2.0, "unit": unit})
    vol = read_volume(tmp_path / "fiji.tif")
    np.testing.assert_array_equal(vol.data, data)
    np.testing.assert_allclose(vol.spacing, np.array([0.25, 0.5, 2.0]) * (mm or 1.0), rtol=1e-6)
    assert vol.meta["unit"] == ("mm" if mm is not None else unit)
    # what volwarp writes, tifffile's ImageJ reader sees with the same voxel size
    write_volume(vol, tmp_path / "out.tif")
    with tifffile.TiffFile(tmp_path / "out.tif") as tif:
        assert tif.is_imagej
        assert tif.imagej_metadata["spacing"] == pytest.approx(2.0 * (mm or 1.0))
        assert tif.imagej_metadata["unit"] == vol.meta["unit"]
        xres = tif.pages[0].tags["XResolution"].value
        assert abs(xres[1] / xres[0] - 0.25 * (mm or 1.0)) < 1e-6 * (mm or 1.0)
    if mm is not None:  # the same stack as an OME-TIFF in micrometres: the same voxels
        tifffile.imwrite(tmp_path / "ome.ome.tif", data, ome=True, metadata={
            "axes": "ZYX", "PhysicalSizeX": 0.25 * mm * 1e3, "PhysicalSizeXUnit": "\u00b5m",
            "PhysicalSizeY": 0.5 * mm * 1e3, "PhysicalSizeYUnit": "\u00b5m",
            "PhysicalSizeZ": 2.0 * mm * 1e3, "PhysicalSizeZUnit": "\u00b5m"})
        np.testing.assert_allclose(read_volume(tmp_path / "ome.ome.tif").spacing, vol.spacing,
                                   rtol=1e-6)


def test_detached_nhdr_written_by_another_program(tmp_path):
    data = np.arange(2 * 3 * 4, dtype=">f4").reshape(2, 3, 4)
    (tmp_path / "vol.raw.gz").write_bytes(gzip.compress(data.tobytes()))
    (tmp_path / "vol.nhdr").write_text(
        "NRRD0004\ntype: float\ndimension: 3\nsizes: 4 3 2\nendian: big\nencoding: gzip\n"
        "spacings: 0.5 0.5 2\ndata file: vol.raw.gz\n")
    vol = read_volume(tmp_path / "vol.nhdr")
    np.testing.assert_array_equal(vol.data, data.astype(np.float32))
    np.testing.assert_array_equal(vol.spacing, (0.5, 0.5, 2))


def test_ascii_and_bzip2_nrrd(tmp_path):
    import bz2

    data = np.arange(24, dtype=np.int32).reshape(2, 3, 4) - 5
    header = "NRRD0004\ntype: int\ndimension: 3\nsizes: 4 3 2\nencoding: {enc}\n{endian}\n"
    (tmp_path / "a.nrrd").write_bytes(header.format(enc="ascii", endian="").encode()
                                      + " ".join(map(str, data.ravel())).encode())
    (tmp_path / "b.nrrd").write_bytes(header.format(enc="bzip2", endian="endian: little\n").encode()
                                      + bz2.compress(data.astype("<i4").tobytes()))
    for name in ("a.nrrd", "b.nrrd"):
        np.testing.assert_array_equal(read_volume(tmp_path / name).data, data)


def test_multi_member_gzip_nrrd(tmp_path):
    """gzip files may hold several members back to back (e.g. from `cat a.gz b.gz`)."""
    data = np.arange(4 * 4 * 4, dtype=np.uint8).reshape(4, 4, 4)
    raw = data.tobytes()
    payload = gzip.compress(raw[:20]) + gzip.compress(raw[20:])
    (tmp_path / "m.nrrd").write_bytes(b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\n"
                                      b"encoding: gzip\n\n" + payload)
    np.testing.assert_array_equal(read_volume(tmp_path / "m.nrrd").data, data)


def test_multi_component_nrrd_reads_one_component(tmp_path):
    """`sweep --multi` writes 4-D vector NRRDs; each component reads back as a volume."""
    from volwarp_cli.io.nrrd import write_nrrd

    rng = np.random.default_rng(3)
    comps = [rng.random((3, 4, 5), dtype=np.float32) for _ in range(3)]
    base = Volume(comps[0], spacing=(0.5, 0.7, 2.0), origin=(1.0, -2.0, 3.0))
    write_nrrd(base, tmp_path / "m.nrrd", components=comps,
               component_names=["opacity", "red", "green"])
    for i, name in enumerate(["opacity", "red", "green"]):
        vol = read_volume(tmp_path / "m.nrrd", volume_index=i)
        np.testing.assert_array_equal(vol.data, comps[i])
        np.testing.assert_allclose(vol.spacing, (0.5, 0.7, 2.0))
        np.testing.assert_allclose(vol.origin, (1.0, -2.0, 3.0))
        assert vol.meta["volwarp_component"] == name
    with pytest.raises(ChoiceNeeded, match=r"3 components per voxel \(opacity red green\)"):
        read_volume(tmp_path / "m.nrrd")
    with pytest.raises(BadUsage, match="out of range"):  # (a usage error: exit 2)
        read_volume(tmp_path / "m.nrrd", volume_index=3)
    # pynrrd, an independent reader, sees the same samples on the vector axis
    data, _ = pynrrd.read(str(tmp_path / "m.nrrd"), index_order="C")
    np.testing.assert_array_equal(data[..., 1], comps[1])


def test_vector_nrrd_from_pynrrd_with_component_axis_last(tmp_path):
    data = np.arange(2 * 3 * 4 * 2, dtype=np.int16).reshape(2, 2, 3, 4)  # [c, z, y, x]
    pynrrd.write(str(tmp_path / "v.nrrd"), data, index_order="C",
               header={"kinds": ["domain", "domain", "domain", "vector"],
                       "space directions": [[2, 0, 0], [0, 1, 0], [0, 0, 1], [np.nan] * 3],
                       "space": "left-posterior-superior"})
    # NRRD order is fastest first: x, y, z, then the component axis (slowest)
    vol = read_volume(tmp_path / "v.nrrd", volume_index=1)
    np.testing.assert_array_equal(vol.data, data[1])
    np.testing.assert_allclose(vol.spacing, (2.0, 1.0, 1.0))


def test_volume_index_refused_where_it_means_nothing(tmp_path):
    from conftest import ball

    vol = Volume(ball(12))
    vol.data.tofile(tmp_path / "b.raw")
    with pytest.raises(BadUsage, match="--volume-index"):  # (usage errors: exit 2)
        read_volume(tmp_path / "b.raw", volume_index=0,
                    raw=RawLayout((12, 12, 12), vol.data.dtype.name))
    write_volume(vol, tmp_path / "b.nrrd")
    assert read_volume(tmp_path / "b.nrrd", volume_index=0).data.shape == vol.data.shape
    with pytest.raises(BadUsage, match="one component"):
        read_volume(tmp_path / "b.nrrd", volume_index=1)


@pytest.mark.parametrize("ext", [".png", ".tif"])
def test_rgba_image_keeps_unpremultiplied_colour(tmp_path, ext):
    """Half-transparent pixels keep their colour (PNG stores straight alpha)."""
    from volwarp_cli.io.images import read_image, write_image

    img = np.zeros((4, 5, 4), np.uint8)
    img[..., :3] = (200, 100, 50)
    img[..., 3] = [[0], [64], [128], [255]]
    path = tmp_path / f"rgba{ext}"
    write_image(path, img)
    back = read_image(path)
    np.testing.assert_allclose(back[1:, :, :3] * 255, np.broadcast_to([200, 100, 50], (3, 5, 3)),
                               atol=0.51)
    np.testing.assert_allclose(back[..., 3] * 255, img[..., 3], atol=0.51)
    if ext == ".png":  # an independent reader sees the same straight colour
        from PIL import Image

        np.testing.assert_array_equal(np.asarray(Image.open(path))[1:], img[1:])


def test_nrrd_mapped_read_gives_the_same_samples_read_only(tmp_path):
    """mmap=True maps raw native-order samples (read-only) and copies everything else."""
    rng = np.random.default_rng(3)
    data = rng.normal(size=(5, 6, 7)).astype(np.float32)
    vol = Volume(data, spacing=(0.5, 1.0, 2.0), origin=(1, 2, 3), meta={"k": "v"})
    cases = {"little.nrrd": {}, "big.nrrd": {"byte_order": "big"}, "gz.nrrd": {"compress": True}}
    for name, opts in cases.items():
        write_volume(vol, tmp_path / name, **opts)
        copied = read_volume(tmp_path / name)
        mapped = read_volume(tmp_path / name, mmap=True)
        assert np.array_equal(mapped.data, data) and np.array_equal(copied.data, data)
        assert mapped.meta == copied.meta and np.allclose(mapped.origin, copied.origin)
        assert copied.data.flags.writeable
        # only the raw file in this machine's byte order is mapped
        assert mapped.data.flags.writeable == (name != "little.nrrd")


def test_a_chain_through_every_format_keeps_key_values_exactly(tmp_path, data_dir):
    """NRRD -> NIfTI -> MetaImage -> TIFF -> NRRD (what `make demo` checks): samples,
    geometry and key/values come back as they were; no format adds keys of its own where
    its header holds nothing but its defaults (NIfTI's codes 1 and 1, mm)."""
    src = read_volume(data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd")
    src.meta["note"] = "kept"
    path = tmp_path / "a.nrrd"
    write_volume(src, path)
    for name in ("b.nii.gz", "c.mha", "d.tif", "e.nrrd"):
        write_volume(read_volume(path), tmp_path / name)
        path = tmp_path / name
    back = read_volume(path)
    assert back.meta == src.meta
    assert back.data.tobytes() == src.data.tobytes()
    assert_same_geometry(src, back, atol=1e-5)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("shape_zyx", [(5, 4, 1), (1, 4, 1), (3, 1, 1), (4, 1, 3)])
@pytest.mark.parametrize("name", ["x.tif", "x.nrrd", "x.mha", "x.nii.gz"])
def test_volumes_one_voxel_thick_round_trip(tmp_path, dtype, shape_zyx, name):
    """x one voxel thick: tifffile took the last axis of size 1 for samples and dropped it. A
    plain TIFF came back transposed (5 x 4 x 1 as 4 x 5 x 1, corners 10.9 mm off), an
    ImageJ one declared 5 images in one page and could not be read back."""
    vol = sample_volume(dtype, shape_zyx)
    write_volume(vol, tmp_path / name)
    back = read_volume(tmp_path / name)
    assert back.data.shape == vol.data.shape and np.array_equal(back.data, vol.data)
    assert_same_geometry(vol, back, atol=1e-5 if name.endswith(".nii.gz") else 1e-12)


def test_a_tiff_says_millimetres_whatever_unit_its_key_values_carry(tmp_path):
    """A key/value unit=micron (a stack read before) went into ImageJ's unit beside spacings
    in mm: Fiji's voxels 1000x too small. A unit of no length (pixel) is kept."""
    import tifffile

    for unit, written in (("micron", "mm"), ("pixel", "pixel")):
        vol = Volume(np.zeros((4, 3, 2), np.uint8), spacing=(0.5, 0.5, 2.0), meta={"unit": unit})
        write_volume(vol, tmp_path / f"{unit}.tif")
        with tifffile.TiffFile(tmp_path / f"{unit}.tif") as tif:
            assert tif.imagej_metadata["unit"] == written and tif.imagej_metadata["spacing"] == 2.0
        np.testing.assert_allclose(read_volume(tmp_path / f"{unit}.tif").spacing, (0.5, 0.5, 2.0))
