"""Lazy inputs (volwarp_cli.io.lazy): the geometry of read_volume, slices of its samples."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
import tifffile

from volwarp_cli.errors import VolwarpError
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import RawLayout, read_volume, write_volume
from volwarp_cli.io.filearray import FileArray
from volwarp_cli.io.lazy import open_volume_lazy
from volwarp_cli.volume import Volume

RNG = np.random.default_rng(7)
DATA = RNG.integers(-2000, 2000, (6, 7, 9)).astype(np.int16)  # z, y, x
SLICES = [np.s_[:, :, :], np.s_[1:4, 2:7, 0:5], np.s_[5, :, 3:], np.s_[::2, 1, ::-3],
          np.s_[2:3, 6:7, 8:9]]


def check(path, *, lazy_type=None, **kw):
    geom, arr = open_volume_lazy(path, **kw)
    ref = read_volume(path, **{k: v for k, v in kw.items() if k != "require_lazy"})
    assert geom == Geometry.of(ref)
    assert tuple(arr.shape) == ref.data.shape
    assert np.dtype(arr.dtype).newbyteorder("=") == ref.data.dtype
    for s in SLICES:
        assert np.array_equal(np.asarray(arr[s]), ref.data[s]), s
    if lazy_type is not None:
        assert (type(arr).__name__ == lazy_type if isinstance(lazy_type, str)
                else isinstance(arr, lazy_type))
    return geom, arr


def oblique_volume(space="LPS"):
    c, s = np.cos(0.4), np.sin(0.4)
    direction = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Volume(DATA, spacing=(0.7, 0.8, 2.5), origin=(-3.0, 20.0, 5.5),
                  direction=direction, space=space)


@pytest.mark.parametrize("byte_order", ["little", "big"])
@pytest.mark.parametrize("name", ["v.nrrd", "v.nhdr", "v.mha", "v.mhd"])
def test_nrrd_and_metaimage_are_mapped(tmp_path, name, byte_order):
    path = tmp_path / name
    write_volume(oblique_volume(), path, byte_order=byte_order)
    _, arr = check(path, lazy_type=FileArray, require_lazy=True)
    assert not arr.writable


def test_a_ras_nrrd_from_simpleitk_and_pynrrd_like_headers(tmp_path):
    path = tmp_path / "ras.nrrd"
    body = DATA.astype("<i2").tobytes()
    header = ("NRRD0004\ntype: short\ndimension: 3\nspace: right-anterior-superior\n"
              "sizes: 9 7 6\nspace directions: (0.5,0,0) (0,0,-1.5) (0,2,0)\n"
              "kinds: domain domain domain\nendian: little\nencoding: raw\n"
              "space origin: (10,-20,30)\nline skip: 0\n\n")
    path.write_bytes(header.encode() + body)
    geom, _ = check(path, lazy_type=FileArray, require_lazy=True)
    img = sitk.ReadImage(str(path))
    for ijk in [(0, 0, 0), (8, 6, 5), (3, 2, 1)]:
        np.testing.assert_allclose(geom.index_to_world(ijk),
                                   img.TransformIndexToPhysicalPoint(ijk), atol=1e-12)


def test_raw_is_mapped_in_its_byte_order(tmp_path):
    path = tmp_path / "v.raw"
    path.write_bytes(b"\0" * 16 + DATA.astype(">i2").tobytes())
    layout = RawLayout(shape=(9, 7, 6), dtype="int16", endian="big", spacing=(1, 2, 3),
                       origin=(4, 5, 6), header_bytes=16)
    _, arr = check(path, lazy_type=FileArray, raw=layout, require_lazy=True)
    assert arr.dtype == np.dtype(">i2")


def test_tiff_stack_through_tifffiles_zarr(tmp_path):
    path = tmp_path / "v.tif"
    write_volume(oblique_volume(space=None), path)
    check(path, lazy_type="_ZarrView", require_lazy=True)
    plain = tmp_path / "p.tif"
    tifffile.imwrite(plain, DATA, resolution=(2.0, 4.0))
    check(plain, require_lazy=True)


def test_nifti_with_a_meaningful_sform(tmp_path):
    path = tmp_path / "v.nii"
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[-c, s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # a reflection and a turn
    aff = np.eye(4)
    aff[:3, :3] = rot @ np.diag([0.8, 0.9, 2.5])
    aff[:3, 3] = [90.0, -126.0, -72.0]
    img = nib.Nifti1Image(DATA.transpose(2, 1, 0), aff)
    img.set_sform(aff, code=2)
    img.set_qform(aff, code=1)  # (pixdim then matches: ITK checks the sform against it)
    nib.save(img, str(path))
    geom, _ = check(path, lazy_type="_NiftiView", require_lazy=True)
    ref = sitk.ReadImage(str(path))
    np.testing.assert_allclose(geom.index_to_world((8, 6, 5)),
                               ref.TransformIndexToPhysicalPoint((8, 6, 5)), atol=1e-5)


def test_omezarr_reads_chunks_on_demand(tmp_path):
    path = tmp_path / "v.ome.zarr"
    write_volume(oblique_volume(), path)
    check(path, lazy_type="LazyOmeZarr", require_lazy=True)


@pytest.mark.parametrize("name", ["v.nii.gz", "g.nrrd"])
def test_compressed_inputs_are_read_whole_or_refused(tmp_path, name):
    path = tmp_path / name
    write_volume(oblique_volume(), path, compress=True)
    _, arr = check(path)
    assert isinstance(arr, np.ndarray) and not isinstance(arr, np.memmap)
    with pytest.raises(VolwarpError, match="without loading"):
        open_volume_lazy(path, require_lazy=True)


def test_file_array_reads_and_writes_boxes_and_pickles(tmp_path):
    """The pread/pwrite array: any slicing reads as numpy's, boxes write in place (whole
    rows or row segments), a pickled copy reopens the file, a short file is an error."""
    import pickle

    from volwarp_cli.errors import FormatError

    rng = np.random.default_rng(4)
    data = rng.integers(-300, 300, (7, 9, 11)).astype(">i2")
    path = tmp_path / "a.raw"
    path.write_bytes(b"H" * 10 + data.tobytes())
    arr = FileArray(path, ">i2", 10, data.shape, writable=True)
    for s in SLICES + [np.s_[-1, -2, -3], np.s_[..., 4], np.s_[3:1, :, :]]:
        assert np.array_equal(arr[s], data[s]), s
    block = rng.integers(-9, 9, (3, 4, 5)).astype(np.int16)
    arr[2:5, 1:5, 3:8] = block  # row segments
    data[2:5, 1:5, 3:8] = block
    arr[6:7, :, :] = data[6:7] + 1  # whole rows at once
    data[6:7] += 1
    copy = pickle.loads(pickle.dumps(arr))
    assert copy._fd is None and np.array_equal(copy[:, :, :], data)
    assert path.read_bytes()[:10] == b"H" * 10
    with pytest.raises(IndexError):
        arr[::2, :, :] = 0
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(FormatError, match="truncated"):
        FileArray(path, ">i2", 10, data.shape)[6]
