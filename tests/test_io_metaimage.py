"""MetaImage (.mha/.mhd) reading and writing, checked against SimpleITK (ITK's MetaIO).

Files SimpleITK writes read back with the same samples and geometry, files
volwarp writes open in SimpleITK with the same physical points, round trips
keep samples, geometry and meta, the data layouts ITK reads (big-endian,
HeaderSize, LIST, printf patterns, 4-D and multi-channel) read right, and
damaged headers and data are one-line errors naming the file and the field.
"""

from __future__ import annotations

import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volwarp_cli.errors import BadUsage, ChoiceNeeded, FormatError, VolwarpError
from volwarp_cli.io.metaimage import (
    anatomical_orientation,
    looks_like_metaimage,
    read_metaimage,
    write_metaimage,
)
from volwarp_cli.volume import Volume

DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64"]
LPS = "left-posterior-superior"


def _rotation(ax: float, ay: float, az: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


DIRECTION = _rotation(0.3, -0.7, 1.1)  # not symmetric: a transposed matrix would show
SPACING = np.array([0.5, 0.8125, 2.25])
ORIGIN = np.array([-12.5, 3.25, 101.0])


def _samples(dtype: str, shape=(4, 5, 6), seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return (rng.standard_normal(shape) * 1e3).astype(dt)
    info = np.iinfo(dt)
    return rng.integers(info.min, info.max, size=shape, dtype=dt, endpoint=True)


def _sitk_image(data: np.ndarray, direction=DIRECTION, spacing=SPACING, origin=ORIGIN):
    img = sitk.GetImageFromArray(data)
    img.SetSpacing([float(v) for v in spacing])
    img.SetOrigin([float(v) for v in origin])
    img.SetDirection([float(v) for v in np.asarray(direction).ravel()])  # row-major
    return img


def _volume(dtype="int16", shape=(4, 5, 6), meta=None, seed=0) -> Volume:
    return Volume(_samples(dtype, shape, seed), spacing=SPACING, origin=ORIGIN,
                  direction=DIRECTION, space=LPS, meta=meta or {})


def _header(tmp_path, name: str, fields: str, payload: bytes = b"", *, dims="4 3 2",
            etype="MET_UCHAR", data_file="LOCAL"):
    """A hand-written MetaImage file: ``fields`` go between NDims and DimSize."""
    text = (f"ObjectType = Image\nNDims = 3\n{fields}DimSize = {dims}\n"
            f"ElementType = {etype}\nElementDataFile = {data_file}\n")
    path = tmp_path / name
    path.write_bytes(text.encode() + payload)
    return path


# -- files written by SimpleITK -------------------------------------------------------

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("suffix", [".mha", ".mhd"])
@pytest.mark.parametrize("compress", [False, True])
def test_reads_files_simpleitk_writes(tmp_path, dtype, suffix, compress):
    data = _samples(dtype)
    path = tmp_path / f"itk{suffix}"
    sitk.WriteImage(_sitk_image(data), str(path), compress)
    if suffix == ".mhd":
        assert (tmp_path / ("itk.zraw" if compress else "itk.raw")).exists()
    vol = read_metaimage(path)
    assert vol.data.shape == data.shape and vol.data.dtype == data.dtype
    assert vol.data.tobytes() == data.tobytes()  # bit for bit (NaN-safe, -0.0-safe)
    np.testing.assert_allclose(vol.spacing, SPACING, rtol=0, atol=1e-12)
    np.testing.assert_allclose(vol.origin, ORIGIN, rtol=0, atol=1e-12)
    np.testing.assert_allclose(vol.direction, DIRECTION, rtol=0, atol=1e-12)
    assert vol.space == LPS and vol.file_space == LPS
    # AnatomicalOrientation and CenterOfRotation say nothing the geometry does not
    assert vol.meta == {}


def test_transform_matrix_lists_direction_columns(tmp_path):
    """ITK writes TransformMatrix column after column; volwarp reads it the same way."""
    direction = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
    path = tmp_path / "perm.mha"
    sitk.WriteImage(_sitk_image(_samples("uint8"), direction=direction), str(path))
    vol = read_metaimage(path)
    np.testing.assert_array_equal(vol.direction, direction)
    itk = sitk.ReadImage(str(path))
    for ijk in [(1, 0, 0), (0, 1, 0), (0, 0, 1), (3, 2, 1)]:
        np.testing.assert_allclose(vol.index_to_world(ijk),
                                   itk.TransformIndexToPhysicalPoint(ijk), atol=1e-12)


def test_geometry_synonyms_and_element_size_as_itk_reads_them(tmp_path):
    payload = bytes(range(24))
    cases = [
        "Origin = 1 2 3\nRotation = 0 1 0 -1 0 0 0 0 1\nElementSize = 2 3 4\n",
        "Position = 1 2 3\nOrientation = 0 0 1 0 1 0 -1 0 0\n",
        "Offset = 4 5 6\nOrigin = 4.0 5 6e0\nElementSize = 2 3 4\nElementSpacing = 5 6 7\n",
    ]
    for n, fields in enumerate(cases):
        path = _header(tmp_path, f"syn{n}.mha", fields, payload)
        vol = read_metaimage(path)
        itk = sitk.ReadImage(str(path))
        np.testing.assert_array_equal(vol.spacing, itk.GetSpacing())
        np.testing.assert_array_equal(vol.origin, itk.GetOrigin())
        np.testing.assert_array_equal(vol.direction.ravel(), itk.GetDirection())
        np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(itk))


@pytest.mark.parametrize("fields, itk_takes", [
    ("TransformMatrix = 0 1 0 -1 0 0 0 0 1\nRotation = 1 0 0 0 1 0 0 0 1\n", "direction"),
    ("Origin = 1 2 3\nOffset = 4 5 6\n", "origin"),
    ("Offset = 4 5 6\nPosition = 7 8 9\n", "origin"),
], ids=["TransformMatrix-Rotation", "Origin-Offset", "Offset-Position"])
def test_synonyms_that_disagree_are_refused(tmp_path, fields, itk_takes):
    """ITK takes TransformMatrix over Rotation, Origin over Offset over Position, whatever
    their order; volwarp took the last one: another grid, exit 0. The header contradicts
    itself: refused, naming both fields."""
    path = _header(tmp_path, "two.mha", fields, bytes(range(24)))
    itk = sitk.ReadImage(str(path))
    last = {"direction": np.eye(3).ravel(), "origin": [7, 8, 9] if "Position" in fields
            else [4, 5, 6]}[itk_takes]
    got = itk.GetDirection() if itk_takes == "direction" else itk.GetOrigin()
    assert not np.allclose(got, last)  # (ITK did not take the last one)
    first, second = (line.split(" = ")[0] for line in fields.splitlines())
    with pytest.raises(FormatError, match=f"gives {first} = .* and {second} = .*disagree"):
        read_metaimage(path)


def test_byte_order_synonyms_that_disagree_are_refused(tmp_path):
    payload = np.arange(24, dtype=">u2").tobytes()
    path = _header(tmp_path, "msb.mha", "BinaryDataByteOrderMSB = True\n"
                   "ElementByteOrderMSB = False\n", payload, etype="MET_USHORT")
    with pytest.raises(FormatError, match="BinaryDataByteOrderMSB = True and "
                                          "ElementByteOrderMSB = False"):
        read_metaimage(path)
    path.write_bytes(path.read_bytes().replace(b"MSB = False", b"MSB = 1    "))
    assert np.array_equal(read_metaimage(path).data.ravel(), np.arange(24))


def test_anatomical_orientation_is_kept_only_when_it_disagrees_and_is_not_geometry(tmp_path):
    path = _header(tmp_path, "ao.mha", "AnatomicalOrientation = LPS\nCenterOfRotation = 1 2 3\n"
                   "Comment = scanned today\nModality = MET_MOD_CT\nPatientThing = x y\n",
                   bytes(24))
    vol = read_metaimage(path)
    itk = sitk.ReadImage(str(path))
    assert itk.GetDirection() == (1, 0, 0, 0, 1, 0, 0, 0, 1)  # ITK ignores it too
    np.testing.assert_array_equal(vol.direction, np.eye(3))
    assert vol.meta == {"MetaImage_AnatomicalOrientation": "LPS",
                        "MetaImage_CenterOfRotation": "1 2 3",
                        "MetaImage_Comment": "scanned today",
                        "MetaImage_Modality": "MET_MOD_CT",
                        "PatientThing": "x y"}
    assert itk.GetMetaData("PatientThing") == "x y"  # ITK's name for a user field too


def test_anatomical_orientation_matches_itk(tmp_path):
    rng = np.random.default_rng(3)
    s = np.sqrt(0.5)
    dirs = [np.eye(3), np.diag([-1.0, 1, -1]), np.array([[0.0, 0, 1], [1, 0, 0], [0, -1, 0]]),
            np.array([[s, -s, 0], [s, s, 0], [0, 0, 1]]), DIRECTION]
    dirs += [np.linalg.qr(rng.standard_normal((3, 3)))[0] for _ in range(40)]
    path = tmp_path / "o.mha"
    for d in dirs:
        sitk.WriteImage(_sitk_image(np.zeros((2, 2, 2), np.uint8), direction=d), str(path))
        line = [t for t in path.read_bytes()[:600].decode("latin-1").splitlines()
                if t.startswith("AnatomicalOrientation")][0]
        assert anatomical_orientation(d) == line.split("= ")[1], d
    assert anatomical_orientation(np.eye(3)) == "RAI"


# -- files written by volwarp, read by SimpleITK ----------------------------------------

@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("suffix", [".mha", ".mhd"])
@pytest.mark.parametrize("compress", [False, True])
def test_simpleitk_reads_files_volwarp_writes(tmp_path, dtype, suffix, compress):
    vol = _volume(dtype, seed=1)
    path = tmp_path / f"vw{suffix}"
    write_metaimage(vol, path, compress=compress)
    if suffix == ".mhd":
        data_file = tmp_path / ("vw.zraw" if compress else "vw.raw")
        assert data_file.exists()
        assert f"ElementDataFile = {data_file.name}\n" in path.read_text()
    itk = sitk.ReadImage(str(path))
    arr = sitk.GetArrayFromImage(itk)
    assert arr.dtype == vol.data.dtype and arr.tobytes() == vol.data.tobytes()
    np.testing.assert_allclose(itk.GetSpacing(), SPACING, rtol=0, atol=1e-12)
    np.testing.assert_allclose(itk.GetOrigin(), ORIGIN, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.reshape(itk.GetDirection(), (3, 3)), DIRECTION, rtol=0,
                               atol=1e-12)
    for ijk in [(0, 0, 0), (10, 10, 5)]:
        np.testing.assert_allclose(itk.TransformIndexToPhysicalPoint(ijk),
                                   vol.index_to_world(ijk), rtol=0, atol=1e-9)


@pytest.mark.parametrize("compress", [False, True])
def test_big_endian_output_reads_in_simpleitk_and_volwarp(tmp_path, compress):
    vol = _volume("float64", seed=2)
    path = tmp_path / "be.mha"
    write_metaimage(vol, path, compress=compress, byte_order="big")
    assert b"BinaryDataByteOrderMSB = True\n" in path.read_bytes()
    if not compress:  # the samples really are big-endian on disk
        assert path.read_bytes().endswith(vol.data.astype(">f8").tobytes())
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(path))), vol.data)
    back = read_metaimage(path)
    assert back.data.tobytes() == vol.data.tobytes() and back.data.dtype.isnative


def test_header_fields_in_the_order_itk_writes_them(tmp_path):
    vol = _volume("uint16", meta={"Foo": "bar baz", "MetaImage_Comment": "c"})
    img = _sitk_image(vol.data)
    img.SetMetaData("Foo", "bar baz")
    img.SetMetaData("Comment", "c")
    for compress in (False, True):
        ours, theirs = tmp_path / "ours.mhd", tmp_path / "theirs.mhd"
        write_metaimage(vol, ours, compress=compress)
        sitk.WriteImage(img, str(theirs), compress)

        def keys(p):
            return [line.split(" = ")[0] for line in p.read_text().splitlines()]

        assert keys(ours) == keys(theirs)
        assert "AnatomicalOrientation = " + anatomical_orientation(DIRECTION) in ours.read_text()


# -- volwarp round trips --------------------------------------------------------------

@pytest.mark.parametrize("suffix,compress,order", [(".mha", False, "little"),
                                                   (".mha", True, "big"),
                                                   (".mhd", False, "big"),
                                                   (".mhd", True, "little")])
def test_round_trip_is_bit_identical_and_keeps_meta(tmp_path, suffix, compress, order):
    meta = {"MetaImage_Comment": "a comment = with equals", "MetaImage_Modality": "MET_MOD_MR",
            "MetaImage_CenterOfRotation": "1.5 2 3", "Foo": "bar baz",
            "volwarp_history": "warp x.yaml"}
    vol = _volume("float32", meta=meta, seed=4)
    path = tmp_path / f"rt{suffix}"
    write_metaimage(vol, path, compress=compress, byte_order=order)
    back = read_metaimage(path)
    assert back.data.tobytes() == vol.data.tobytes()
    np.testing.assert_array_equal(back.spacing, vol.spacing)  # exact: floats written by repr
    np.testing.assert_array_equal(back.origin, vol.origin)
    np.testing.assert_array_equal(back.direction, vol.direction)
    assert back.meta == meta


def test_output_is_deterministic(tmp_path):
    vol = _volume("int32", meta={"b": "2", "a": "1"})
    for suffix, data_name in ((".mha", None), (".mhd", "x.zraw")):
        first = tmp_path / f"x{suffix}"
        write_metaimage(vol, first, compress=True)
        blobs = [first.read_bytes()] + ([(tmp_path / data_name).read_bytes()] if data_name else [])
        write_metaimage(vol.with_data(vol.data.copy(), meta={"a": "1", "b": "2"}), first,
                        compress=True)
        again = [first.read_bytes()] + ([(tmp_path / data_name).read_bytes()] if data_name
                                        else [])
        assert blobs == again
    assert not [p for p in tmp_path.iterdir() if ".part" in p.name]  # no temporaries left


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(shape=st.tuples(*[st.integers(1, 5)] * 3), dtype=st.sampled_from(DTYPES),
       angles=st.tuples(*[st.floats(-3.1, 3.1)] * 3),
       spacing=st.tuples(*[st.floats(1e-3, 1e3)] * 3),
       origin=st.tuples(*[st.floats(-1e6, 1e6)] * 3), compress=st.booleans(),
       order=st.sampled_from(["little", "big"]), suffix=st.sampled_from([".mha", ".mhd"]),
       seed=st.integers(0, 1000))
def test_property_round_trip(tmp_path, shape, dtype, angles, spacing, origin, compress, order,
                             suffix, seed):
    vol = Volume(_samples(dtype, shape, seed), spacing=spacing, origin=origin,
                 direction=_rotation(*angles), space=LPS)
    # a folder per example: hypothesis reuses tmp_path, and a .mhd may not replace a data
    # file its header does not name (an earlier example's .raw beside a .zraw header)
    path = Path(tempfile.mkdtemp(dir=tmp_path)) / f"p{suffix}"
    write_metaimage(vol, path, compress=compress, byte_order=order)
    back = read_metaimage(path)
    assert back.data.shape == vol.data.shape and back.data.dtype == vol.data.dtype
    assert back.data.tobytes() == vol.data.tobytes()
    np.testing.assert_array_equal(back.spacing, vol.spacing)
    np.testing.assert_array_equal(back.origin, vol.origin)
    np.testing.assert_array_equal(back.direction, vol.direction)
    assert back.meta == {}


# -- data layouts -----------------------------------------------------------------------

@pytest.mark.parametrize("key", ["BinaryDataByteOrderMSB", "ElementByteOrderMSB"])
def test_big_endian_input(tmp_path, key):
    data = np.arange(24, dtype=np.uint16) * 1000 + 7
    path = _header(tmp_path, "msb.mha", f"{key} = True\n", data.astype(">u2").tobytes(),
                   etype="MET_USHORT")
    vol = read_metaimage(path)
    np.testing.assert_array_equal(vol.data.ravel(), data)
    np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(sitk.ReadImage(str(path))))


def test_header_size_minus_one_and_positive(tmp_path):
    data = bytes(range(100, 124))
    (tmp_path / "tail.raw").write_bytes(b"some leading junk" + data)
    tail = _header(tmp_path, "tail.mhd", "HeaderSize = -1\n", data_file="tail.raw")
    (tmp_path / "skip.raw").write_bytes(b"abcde" + data)
    skip = _header(tmp_path, "skip.mhd", "HeaderSize = 5\n", data_file="skip.raw")
    local = _header(tmp_path, "local.mha", "HeaderSize = -1\n", data)
    # in a LOCAL file a positive HeaderSize counts from the start of the file (as ITK reads it)
    text_len = len(_header(tmp_path, "probe.mha", "HeaderSize = 000\n").read_bytes())
    offset = _header(tmp_path, "offset.mha", f"HeaderSize = {text_len + 4:03d}\n",
                     b"junk" + data)
    for path in (tail, skip, local, offset):
        vol = read_metaimage(path)
        assert vol.data.tobytes() == data, path
        np.testing.assert_array_equal(vol.data, sitk.GetArrayFromImage(sitk.ReadImage(str(path))))


def test_compressed_without_size_and_ascii(tmp_path):
    data = bytes(range(24))
    z = _header(tmp_path, "z.mha", "CompressedData = True\n", zlib.compress(data, 9))
    text = _header(tmp_path, "a.mha", "BinaryData = False\n",
                   " ".join(str(b) for b in data).encode() + b"\n")
    for path in (z, text):
        assert read_metaimage(path).data.tobytes() == data
    # (ITK itself fails to inflate LOCAL data without CompressedDataSize: "Uncompress failed")
    np.testing.assert_array_equal(read_metaimage(text).data,
                                  sitk.GetArrayFromImage(sitk.ReadImage(str(text))))


def test_list_and_pattern_data_files(tmp_path):
    data = _samples("int16", (3, 4, 5), seed=5)
    for k in range(3):
        (tmp_path / f"slice{k + 1:03d}.raw").write_bytes(data[k].astype("<i2").tobytes())
    names = b"".join(f"slice{k + 1:03d}.raw\n".encode() for k in range(3))
    cases = {
        "list.mhd": ("LIST", names),
        "list2d.mhd": ("LIST 2D", names),
        "pattern.mhd": ("slice%03d.raw 1 3 1", b""),
        "pattern_min.mhd": ("slice%03d.raw 1", b""),
    }
    for name, (spec, payload) in cases.items():
        path = _header(tmp_path, name, "", payload, dims="5 4 3", etype="MET_SHORT",
                       data_file=spec)
        vol = read_metaimage(path)
        np.testing.assert_array_equal(vol.data, data, err_msg=name)
        np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(path))), data,
                                      err_msg=name)
    # a LIST of 1-D pieces (one row per file) needs one file per row
    rows = data.reshape(-1, 5)
    for k, row in enumerate(rows):
        (tmp_path / f"row{k}.raw").write_bytes(row.astype("<i2").tobytes())
    path = _header(tmp_path, "rows.mhd", "",
                   b"".join(f"row{k}.raw\n".encode() for k in range(len(rows))),
                   dims="5 4 3", etype="MET_SHORT", data_file="LIST 1")
    np.testing.assert_array_equal(read_metaimage(path).data, data)
    # a pattern stepping down
    for k in range(3):
        (tmp_path / f"down_{10 - 2 * k}.raw").write_bytes(data[k].astype("<i2").tobytes())
    path = _header(tmp_path, "down.mhd", "", dims="5 4 3", etype="MET_SHORT",
                   data_file="down_%d.raw 10 6 -2")
    np.testing.assert_array_equal(read_metaimage(path).data, data)


def test_four_d_and_multichannel_files_need_a_volume_index(tmp_path):
    four = _samples("float32", (3, 2, 4, 5), seed=6)  # [t, z, y, x]
    p4 = tmp_path / "t.mha"
    sitk.WriteImage(sitk.JoinSeries([sitk.GetImageFromArray(v) for v in four]), str(p4))
    assert b"NDims = 4\n" in p4.read_bytes()
    with pytest.raises(ChoiceNeeded, match=r"t\.mha: has 3 volumes; select one with "
                                          r"--volume-index 0\.\.2"):
        read_metaimage(p4)
    with pytest.raises(BadUsage, match=r"t\.mha: --volume-index 3 is out of range"):
        read_metaimage(p4, 3)
    np.testing.assert_array_equal(read_metaimage(p4, 2).data, four[2])
    vec = _samples("uint8", (2, 4, 5, 3), seed=7)  # [z, y, x, channel]
    pv = tmp_path / "v.mha"
    sitk.WriteImage(sitk.GetImageFromArray(vec, isVector=True), str(pv), True)
    with pytest.raises(ChoiceNeeded, match=r"v\.mha: has 3 components per voxel"):
        read_metaimage(pv)
    for c in range(3):
        np.testing.assert_array_equal(read_metaimage(pv, c).data, vec[..., c])
    plain = tmp_path / "plain.mha"
    write_metaimage(_volume(), plain)
    with pytest.raises(BadUsage, match=r"plain\.mha: --volume-index 1 given"):
        read_metaimage(plain, 1)
    single = tmp_path / "single.mha"  # a 4-D file holding one volume reads without an index
    sitk.WriteImage(sitk.JoinSeries([sitk.GetImageFromArray(four[0])]), str(single))
    np.testing.assert_array_equal(read_metaimage(single).data, four[0])


# -- bad input ------------------------------------------------------------------------

def test_truncated_and_oversized_data(tmp_path):
    vol = _volume("int16")
    path = tmp_path / "cut.mha"
    write_metaimage(vol, path)
    raw = path.read_bytes()
    path.write_bytes(raw[:-7])
    with pytest.raises(FormatError, match=rf"cut\.mha: data is truncated: expected "
                                          rf"{vol.data.nbytes} bytes of samples, found "
                                          rf"{vol.data.nbytes - 7}"):
        read_metaimage(path)
    path.write_bytes(raw + b"\0\0")
    with pytest.raises(FormatError, match=rf"cut\.mha: file has {vol.data.nbytes + 2} bytes of "
                                          rf"samples, expected {vol.data.nbytes}"):
        read_metaimage(path)
    det = tmp_path / "det.mhd"
    write_metaimage(vol, det)
    (tmp_path / "det.raw").write_bytes((tmp_path / "det.raw").read_bytes()[:10])
    with pytest.raises(FormatError, match=r"det\.raw: data is truncated: expected 240 bytes"):
        read_metaimage(det)


def test_missing_data_files(tmp_path):
    path = _header(tmp_path, "gone.mhd", "", data_file="gone.raw")
    with pytest.raises(FormatError, match=r"gone\.mhd: data file .*gone\.raw.*No such file"):
        read_metaimage(path)
    path = _header(tmp_path, "pat.mhd", "", data_file="s%02d.raw 0 1 1", dims="4 3 2")
    (tmp_path / "s00.raw").write_bytes(bytes(12))
    with pytest.raises(FormatError, match=r"pat\.mhd: data file .*s01\.raw"):
        read_metaimage(path)
    path = _header(tmp_path, "few.mhd", "", b"s00.raw\n", data_file="LIST")
    with pytest.raises(FormatError, match=r"few\.mhd: ElementDataFile LIST names 1 file, "
                                          r"but DimSize 4 3 2 in 2-D pieces needs 2"):
        read_metaimage(path)
    path = _header(tmp_path, "many.mhd", "", b"s00.raw\ns00.raw\ns00.raw\n", data_file="LIST")
    with pytest.raises(FormatError, match=r"many\.mhd: ElementDataFile LIST names more"):
        read_metaimage(path)
    path = _header(tmp_path, "cnt.mhd", "", data_file="s%02d.raw 0 5 1", dims="4 3 2")
    with pytest.raises(FormatError, match=r"cnt\.mhd: ElementDataFile pattern names 6 files"):
        read_metaimage(path)
    with pytest.raises(FormatError, match=r"nothere\.mha: cannot open"):
        read_metaimage(tmp_path / "nothere.mha")


@pytest.mark.parametrize("fields,message", [
    ("ElementSpacing = a 1 1\n", r"ElementSpacing: 'a 1 1' is not 3 numbers"),
    ("ElementSpacing = 1 1\n", r"ElementSpacing: expected 3 values, got 2"),
    ("ElementSpacing = 1 0 1\n", r"ElementSpacing must be positive"),
    ("ElementSize = 1 x 1\n", r"ElementSize: '1 x 1' is not 3 numbers"),
    ("Offset = 1 2 nan\n", r"Offset: values must be finite"),
    ("Origin = 1 2\n", r"Origin: expected 3 values, got 2"),
    ("TransformMatrix = 1 0 0 0 1 0 0 0\n", r"TransformMatrix: expected 9 values, got 8"),
    ("Rotation = 1 0 0 1 0 0 0 0 1\n", r"Rotation: direction matrix is singular"),
    ("HeaderSize = big\n", r"HeaderSize: 'big' is not 1 whole numbers"),
    ("HeaderSize = -4\n", r"HeaderSize must be -1"),
    ("BinaryData = maybe\n", r"BinaryData: 'maybe' is not True or False"),
    ("CompressedData = True\nCompressedDataSize = 1.5\n",
     r"CompressedDataSize: '1.5' is not 1 whole numbers"),
    ("ElementNumberOfChannels = two\n", r"ElementNumberOfChannels: 'two' is not"),
])
def test_bad_numeric_fields(tmp_path, fields, message):
    path = _header(tmp_path, "bad.mha", fields, bytes(24))
    with pytest.raises(FormatError, match=r"bad\.mha: " + message) as info:
        read_metaimage(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("text,message", [
    ("NDims = 3\nDimSize = 4 x 2\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
     r"DimSize: '4 x 2' is not 3 whole numbers"),
    ("NDims = 3\nDimSize = 4 0 2\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
     r"DimSize must be positive"),
    ("NDims = three\nDimSize = 4 3 2\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
     r"NDims: 'three' is not"),
    ("NDims = 2\nDimSize = 4 3\nElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
     r"volwarp reads 3-D volumes .* NDims 2"),
    ("NDims = 3\nDimSize = 4 3 2\nElementType = MET_FOO\nElementDataFile = LOCAL\n",
     r"ElementType: unknown type 'MET_FOO'"),
    ("NDims = 3\nDimSize = 4 3 2\nElementType = MET_LONG_LONG\nElementDataFile = LOCAL\n",
     r"ElementType MET_LONG_LONG: unsupported sample type 'int64'"),
    ("NDims = 3\nDimSize = 4 3 2\nElementDataFile = LOCAL\n", r"header has no 'ElementType'"),
    ("NDims = 3\nDimSize = 4 3 2\nElementType = MET_UCHAR\n",
     r"header has no 'ElementDataFile' field"),
    ("ObjectType = Transform\nNDims = 3\nDimSize = 4 3 2\nElementType = MET_UCHAR\n"
     "ElementDataFile = LOCAL\n", r"ObjectType is 'Transform'"),
    ("NRRD0004\ntype: uchar\n", r"not a MetaImage file"),
    ("NDims = 3\nthis line is wrong\nElementDataFile = LOCAL\n", r"malformed header line"),
    ("NDims = 3\nDimSize = 4 3 2\nElementType = MET_UCHAR\nElementDataFile = s%d.raw 0 1\n",
     r"ElementDataFile pattern needs <min> <max> <step>"),
    ("NDims = 3\nDimSize = 4 3 2\nElementType = MET_UCHAR\nElementDataFile = s%d.raw 0 1 0\n",
     r"ElementDataFile pattern has step 0"),
    ("NDims = 3\nDimSize = 4 3 2\nElementType = MET_UCHAR\nElementDataFile = s%d.raw a 1 1\n",
     r"ElementDataFile pattern needs whole numbers"),
    ("NDims = 3\nDimSize = 4 3 2\nElementType = MET_UCHAR\nElementDataFile = LIST x\n",
     r"ElementDataFile: LIST takes one optional dimension"),
])
def test_bad_headers(tmp_path, text, message):
    path = tmp_path / "bad.mha"
    path.write_bytes(text.encode() + (bytes(24) if "ElementDataFile" in text else b""))
    with pytest.raises(FormatError, match=r"bad\.mha: " + message):
        read_metaimage(path)


def test_corrupt_and_wrong_size_compressed_data(tmp_path):
    data = bytes(range(24))
    good = zlib.compress(data)
    corrupt = good[:2] + bytes(b ^ 0x5A for b in good[2:])
    cases = [
        (corrupt, r"corrupt compressed data"),
        (zlib.compress(data[:20]), r"data is truncated: expected 24 bytes, found 20"),
        (zlib.compress(data + b"more"), r"compressed data holds more than 24 bytes"),
        (good[:-6], r"(compressed )?data is truncated"),
    ]
    for n, (payload, message) in enumerate(cases):
        path = _header(tmp_path, f"z{n}.mha", "CompressedData = True\n", payload)
        with pytest.raises(FormatError, match=rf"z{n}\.mha: {message}"):
            read_metaimage(path)
    path = _header(tmp_path, "size.mha",
                   f"CompressedData = True\nCompressedDataSize = {len(good) + 5}\n", good)
    with pytest.raises(FormatError, match=rf"size\.mha: compressed data is truncated: "
                                          rf"CompressedDataSize is {len(good) + 5} bytes, "
                                          rf"found {len(good)}"):
        read_metaimage(path)
    path = _header(tmp_path, "extra.mha",
                   f"CompressedData = True\nCompressedDataSize = {len(good)}\n", good + b"xx")
    with pytest.raises(FormatError, match=rf"extra\.mha: file has {len(good) + 2} bytes of "
                                          rf"compressed data"):
        read_metaimage(path)


def test_content_check_and_unwritable_data_file_names(tmp_path):
    write_metaimage(_volume(), tmp_path / "ok.mha")
    sitk.WriteImage(_sitk_image(_samples("uint8")), str(tmp_path / "itk.mhd"))
    for name in ("ok.mha", "itk.mhd"):
        assert looks_like_metaimage((tmp_path / name).read_bytes()[:352])
    assert looks_like_metaimage(b"NDims = 3\nDimSize = 1 1 1\n")
    for head in (b"NRRD0004\n", b"II*\0", b"\x1f\x8b\x08", b"", b"= 3\n", b"key: value\n"):
        assert not looks_like_metaimage(head), head
    with pytest.raises(VolwarpError, match=r"cannot be named 'a%d\.raw'"):
        write_metaimage(_volume(), tmp_path / "a%d.mhd")
    assert not (tmp_path / "a%d.mhd").exists() and not (tmp_path / "a%d.raw").exists()


def test_a_key_value_a_header_line_cannot_hold_is_said(tmp_path, run):
    """A NRRD value with a line break, or outer spaces, came out changed in a .mha, silently."""
    from volwarp_cli.io import read_volume, write_volume

    src = tmp_path / "k.nrrd"
    write_volume(Volume(np.zeros((2, 3, 4), np.uint8),
                        meta={"note": "line one\nline two", "pad": "spaces   ", "ok": "fine"}),
                 src)
    res = run("convert", src, "-o", tmp_path / "k.mha")
    assert res.code == 0, res.stderr
    assert "key/values 'note', 'pad' written to the MetaImage header with their line breaks" \
        in res.stderr
    meta = read_volume(tmp_path / "k.mha").meta
    assert meta["note"] == "line one line two" and meta["pad"] == "spaces" and meta["ok"] == "fine"
    res = run("convert", src, "-o", tmp_path / "k2.nrrd")  # (NRRD holds them: nothing said)
    assert res.code == 0 and "MetaImage" not in res.stderr
