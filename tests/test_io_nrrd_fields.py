"""NRRD details other readers get right: compressed byte skips, hex data, named field errors.

References: SimpleITK (teem's NrrdIO inside ITK) and pynrrd read the same files (teem's rules:
a byte skip of compressed data counts decompressed bytes, and -1 means the samples are the
stream's last bytes).
"""

from __future__ import annotations

import bz2
import gzip
import json

import nrrd as pynrrd
import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume

DATA = np.arange(3 * 4 * 5, dtype=np.int16).reshape(5, 4, 3) * 7 - 100


def _header(encoding: str, extra: str = "") -> bytes:
    return (f"NRRD0004\ntype: short\ndimension: 3\nsizes: 3 4 5\nendian: little\n"
            f"encoding: {encoding}\nspacings: 1 2 3\n{extra}\n").encode()


def _compress(encoding: str, raw: bytes) -> bytes:
    return gzip.compress(raw, mtime=0) if encoding == "gzip" else bz2.compress(raw)


@pytest.mark.parametrize("encoding", ["gzip", "bzip2"])
@pytest.mark.parametrize("skip", [-1, 0, 11])
def test_compressed_byte_skip_counts_decompressed_bytes(tmp_path, encoding, skip):
    junk = bytes(range(37))  # a stream prefix the samples follow
    payload = DATA.astype("<i2").tobytes()
    stream = payload if skip == 0 else (junk + payload if skip == -1 else junk[:skip] + payload)
    path = tmp_path / "s.nrrd"
    path.write_bytes(_header(encoding, f"byte skip: {skip}\n") + _compress(encoding, stream))
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.data, DATA)
    if encoding == "gzip":  # ITK reads NRRD through teem's own NrrdIO (built without bzip2)
        np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(path))), DATA)
    if skip <= 0:  # pynrrd skips compressed bytes for a positive skip (teem: decompressed)
        ref, _ = pynrrd.read(str(path), index_order="C")
        np.testing.assert_array_equal(vol.data, ref)


def test_compressed_byte_skip_past_the_stream_is_an_error(tmp_path):
    path = tmp_path / "s.nrrd"
    path.write_bytes(_header("gzip", "byte skip: 1000\n") + gzip.compress(b"\0" * 20, mtime=0))
    with pytest.raises(FormatError, match=r"s\.nrrd.*ends inside 'byte skip'"):
        read_volume(path)


def test_compressed_tail_shorter_than_the_samples_is_truncated(tmp_path):
    path = tmp_path / "s.nrrd"
    path.write_bytes(_header("gzip", "byte skip: -1\n") + gzip.compress(b"\0" * 20, mtime=0))
    with pytest.raises(FormatError, match=r"s\.nrrd.*truncated.*expected 120 bytes"):
        read_volume(path)


def test_hex_encoding_matches_pynrrd(tmp_path):
    text = DATA.astype("<i2").tobytes().hex()
    lines = "\n".join(text[i:i + 34] for i in range(0, len(text), 34))  # white space between
    path = tmp_path / "h.nrrd"
    path.write_bytes(_header("hex") + lines.encode() + b"\n")
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.data, DATA)
    np.testing.assert_array_equal(vol.spacing, [1, 2, 3])


@pytest.mark.parametrize("body,match", [
    (b"00 01 zz", r"not pairs of hex digits.*'zz'"),
    (b"0001", r"hex data is truncated: expected 120 bytes of samples, found 2"),
])
def test_bad_hex_data_is_named(tmp_path, body, match):
    path = tmp_path / "h.nrrd"
    path.write_bytes(_header("hex") + body)
    with pytest.raises(FormatError, match=match):
        read_volume(path)


@pytest.mark.parametrize("field,value,match", [
    ("spacings", "a 1 1", r"'spacings' must be numbers, got 'a 1 1'"),
    ("spacings", "1 0 1", r"'spacings' must be positive"),
    ("axis mins", "x 0 0", r"'axis mins' must be numbers, got 'x 0 0'"),
    ("line skip", "abc", r"'line skip' must be a whole number, got 'abc'"),
    ("byte skip", "1.5", r"'byte skip' must be a whole number, got '1.5'"),
    ("byte skip", "-2", r"'byte skip' must be at least -1, got -2"),
    ("space origin", "(1,b,3)", r"'space origin': cannot read vector"),
])
def test_malformed_numeric_fields_name_the_field(tmp_path, field, value, match):
    extra = f"{field}: {value}\n"
    if field == "space origin":
        extra = "space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n" + extra
    text = _header("raw", extra).decode().replace("spacings: 1 2 3\n", "" if field in (
        "spacings", "space origin") else "spacings: 1 2 3\n")
    path = tmp_path / "bad.nrrd"
    path.write_bytes(text.encode() + DATA.astype("<i2").tobytes())
    with pytest.raises(FormatError, match=r"bad\.nrrd: " + match):
        read_volume(path)


def test_huge_space_directions_are_refused_without_numpy_warnings(tmp_path, recwarn):
    # the axis' length overflowed (a RuntimeWarning on stderr, then an internal error); a
    # length of 1.4e200 is finite, but distances and mesh vertices of it are not
    path = tmp_path / "big.nrrd"
    extra = "space: LPS\nspace directions: (1e200,1e200,0) (0,1,0) (0,0,1)\n"
    text = _header("raw", extra).decode().replace("spacings: 1 2 3\n", "")
    path.write_bytes(text.encode() + DATA.astype("<i2").tobytes())
    with pytest.raises(FormatError, match=r"big\.nrrd: 'space directions': spacing 1\.41421e\+200 "
                       "along x is outside"):
        read_volume(path)
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


@pytest.mark.parametrize("dirs,match", [("(0,0,0) (0,1,0) (0,0,1)", "a zero axis"),
                                        ("(inf,0,0) (0,1,0) (0,0,1)", "a non-finite axis")])
def test_degenerate_space_directions_are_named(tmp_path, dirs, match):
    path = tmp_path / "bad.nrrd"
    text = _header("raw", f"space: LPS\nspace directions: {dirs}\n").decode().replace(
        "spacings: 1 2 3\n", "")
    path.write_bytes(text.encode() + DATA.astype("<i2").tobytes())
    with pytest.raises(FormatError, match=r"bad\.nrrd: 'space directions' has " + match):
        read_volume(path)


@pytest.mark.parametrize("cut", [4, 40])
def test_bzip2_missing_its_last_bytes_is_truncated_naming_the_file(run, tmp_path, cut):
    # was a blank line and "volwarp: error: aborted" (the stream's EOFError from its last read)
    path = tmp_path / "cut.nrrd"
    stream = bz2.compress(DATA.astype("<i2").tobytes())
    path.write_bytes(_header("bzip2") + stream[:-cut])
    res = run("info", path)
    assert res.code == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "cut.nrrd: compressed data is truncated" in lines[0], res.stderr


@pytest.mark.parametrize("ext", [".nrrd", ".mha", ".nhdr"])
def test_utf8_key_values_and_file_names_are_read_and_written_as_utf8(tmp_path, run, ext):
    """3D Slicer and ITK write header text as UTF-8 (segment names, "Läsion"); read as
    Latin-1 it came out "LÃ¤sion" in info, NIfTI and OME-Zarr, and what is no Latin-1 was
    written as "?" (a detached header's data file name too). A Latin-1 header still reads."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    img = sitk.GetImageFromArray(DATA)
    img.SetMetaData("Segment0_Name", "Läsion")
    sitk.WriteImage(img, str(tmp_path / f"slicer{ext}"))
    vol = read_volume(tmp_path / f"slicer{ext}")
    assert vol.meta["Segment0_Name"] == "Läsion"
    res = run("info", tmp_path / f"slicer{ext}", "--json")
    assert res.code == 0 and json.loads(res.stdout)["meta"]["Segment0_Name"] == "Läsion"
    res = run("convert", tmp_path / f"slicer{ext}", "-o", tmp_path / "c.nii")
    assert res.code == 0 and read_volume(tmp_path / "c.nii").meta["Segment0_Name"] == "Läsion"
    # written: every character kept, as SimpleITK reads it; a data file named in UTF-8
    out = tmp_path / f"肝臓{ext}"
    write_volume(Volume(DATA, meta={"organ": "肝臓 – Läsion"}), out)
    back = read_volume(out)
    assert back.meta["organ"] == "肝臓 – Läsion" and np.array_equal(back.data, DATA)
    theirs = sitk.ReadImage(str(out))
    assert theirs.GetMetaData("organ") == "肝臓 – Läsion"
    np.testing.assert_array_equal(sitk.GetArrayFromImage(theirs), DATA)
    if ext == ".nrrd":  # an older header in Latin-1 still reads
        raw = (tmp_path / "slicer.nrrd").read_bytes().replace("Läsion".encode(),
                                                             "Läsion".encode("latin-1"))
        (tmp_path / "latin.nrrd").write_bytes(raw)
        assert read_volume(tmp_path / "latin.nrrd").meta["Segment0_Name"] == "Läsion"


@pytest.mark.parametrize("ext", [".nhdr", ".mhd", ".nrrd"])
def test_a_file_name_that_is_not_utf8_is_written_and_read_as_its_bytes(tmp_path, run, ext):
    """A Latin-1 file system's name (byte 0xE9): writing a header that names it (a
    detached data file, the input in the provenance) crashed once headers were UTF-8
    ('internal error: UnicodeEncodeError', a review); before, it was written as '?', a
    data file reference that named no file. Its bytes go in as they are and open it."""
    import os

    from volwarp_cli.io import mapped, write_volume
    from volwarp_cli.volume import Volume

    name = os.fsdecode(b"caf\xe9" + ext.encode())
    src = os.fsdecode(bytes(tmp_path) + b"/in\xe9.nrrd")
    write_volume(Volume(DATA), src)
    with open(src, "rb") as fh:  # (a mapped input's SIGBUS guard, told the temporaries'
        mapped.guard(fh, src)    # names: it took them as UTF-8 and crashed on this one)
    res = run("convert", src, "-o", tmp_path / name)
    assert res.code == 0, res.stderr
    back = read_volume(tmp_path / name)
    np.testing.assert_array_equal(back.data, DATA)
    out = tmp_path / f"d{ext}"  # (a command whose provenance names the input)
    res = run("distance", src, "--values", "intensity", "--iso", "100", "-o", out)
    assert res.code == 0, res.stderr
    assert read_volume(out).meta["volwarp_input"] == "iné.nrrd"  # (Latin-1 read: é)
    if ext != ".nrrd":  # the header names its data file by the same bytes
        header = (tmp_path / name).read_bytes()
        assert b"caf\xe9.raw" in header


_ESCAPED = {"multi": "line one\nline two", "back": "C:\\dir\\name", "lit": "a\\nb",
            "tail": "ends\\", "k\\ey": "v"}


def test_key_values_take_teems_escapes_as_itk_writes_and_reads_them(tmp_path):
    """A backslash is ``\\\\`` and a newline ``\\n`` in a NRRD key/value (teem, so ITK and Slicer).

    Read literally, ITK's ``C:\\\\dir`` came out with doubled backslashes and
    a two-line value as one with ``\\n`` in it; written back, a newline became
    a space. Both directions are checked against SimpleITK.
    """
    from volwarp_cli import api
    from volwarp_cli.volume import Volume

    image = sitk.GetImageFromArray(np.zeros((2, 2, 2), np.uint8))
    for key, value in _ESCAPED.items():
        image.SetMetaData(key, value)
    sitk.WriteImage(image, str(tmp_path / "itk.nrrd"))
    meta = read_volume(tmp_path / "itk.nrrd").meta
    assert {k: meta[k] for k in _ESCAPED} == _ESCAPED

    api.write(Volume(np.zeros((2, 2, 2), np.uint8), meta=dict(_ESCAPED)), tmp_path / "vw.nrrd")
    back = sitk.ReadImage(str(tmp_path / "vw.nrrd"))
    assert {k: back.GetMetaData(k) for k in _ESCAPED} == _ESCAPED
    assert read_volume(tmp_path / "vw.nrrd").meta == {**_ESCAPED, **{
        k: v for k, v in read_volume(tmp_path / "vw.nrrd").meta.items() if k not in _ESCAPED}}


def test_a_carriage_return_is_written_as_teem_writes_it(tmp_path):
    """Written as it was, a ``\\r`` in a value made a header line ITK cannot read ("didn't
    see ': ' or ':=' in line"); teem writes a space for it, and so for \\v and \\f."""
    from volwarp_cli import api
    from volwarp_cli.volume import Volume

    meta = {"cr": "x\ry", "vt": "a\vb", "ff": "p\fq", "tab": "a\tb"}
    api.write(Volume(np.zeros((2, 2, 2), np.uint8), meta=meta), tmp_path / "o.nrrd")
    theirs = sitk.ReadImage(str(tmp_path / "o.nrrd"))
    image = sitk.GetImageFromArray(np.zeros((2, 2, 2), np.uint8))
    for key, value in meta.items():
        image.SetMetaData(key, value)
    sitk.WriteImage(image, str(tmp_path / "itk.nrrd"))
    expect = {"cr": "x y", "vt": "a b", "ff": "p q", "tab": "a\tb"}
    assert {k: theirs.GetMetaData(k) for k in meta} == expect
    assert {k: read_volume(tmp_path / "o.nrrd").meta[k] for k in meta} == expect
    assert {k: read_volume(tmp_path / "itk.nrrd").meta[k] for k in meta} == expect


def test_a_backslash_before_anything_else_is_kept_as_teem_keeps_it(tmp_path):
    path = tmp_path / "h.nrrd"
    path.write_bytes(b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 1 1 1\nencoding: raw\n"
                     b"a:=x\\Py\nb:=tail\\\nc:=q\\\\n\nd:=t\\tz\n\n\0")
    mine = read_volume(path).meta
    theirs = sitk.ReadImage(str(path))
    assert {k: mine[k] for k in "abcd"} == {k: theirs.GetMetaData(k) for k in "abcd"} \
        == {"a": "x\\Py", "b": "tail\\", "c": "q\\n", "d": "t\\tz"}


@settings(max_examples=60, deadline=None)
@given(st.dictionaries(st.text(alphabet=st.characters(blacklist_categories=("Cs",),
                                                      blacklist_characters="\r\v\f:="),
                               min_size=1, max_size=8).filter(lambda k: not k.startswith("#")),
                       st.text(alphabet=st.characters(blacklist_categories=("Cs",),
                                                      blacklist_characters="\r\v\f"),
                               max_size=12),
                       max_size=4))
def test_any_key_values_come_back_from_a_nrrd_as_written(meta):
    import tempfile

    from volwarp_cli import api
    from volwarp_cli.volume import Volume

    meta = {k: v for k, v in meta.items() if not k.startswith(("NRRD_", "volwarp_"))}
    with tempfile.TemporaryDirectory() as tmp:
        api.write(Volume(np.zeros((1, 1, 1), np.uint8), meta=meta), f"{tmp}/m.nrrd")
        got = read_volume(f"{tmp}/m.nrrd").meta
    assert {k: got.get(k) for k in meta} == meta


@pytest.mark.parametrize("ext, key", [(".nrrd", "#note"), (".nrrd", "a:=b"), (".nrrd", ""),
                                      (".mha", "ElementDataFile"), (".mha", "a=b")])
def test_a_key_the_header_cannot_hold_is_dropped_with_a_warning(tmp_path, ext, key):
    import logging

    from volwarp_cli import api
    from volwarp_cli.volume import Volume

    records = []
    handler = logging.Handler()
    handler.emit = records.append
    logging.getLogger("volwarp").addHandler(handler)
    try:
        api.write(Volume(np.arange(8, dtype=np.uint8).reshape(2, 2, 2),
                         meta={key: "x", "kept": "y"}), tmp_path / f"o{ext}")
    finally:
        logging.getLogger("volwarp").removeHandler(handler)
    back = read_volume(tmp_path / f"o{ext}")
    assert back.meta["kept"] == "y" and key not in back.meta
    assert np.array_equal(back.data, np.arange(8, dtype=np.uint8).reshape(2, 2, 2))
    said = [r.getMessage() for r in records if repr(key) in r.getMessage()]
    assert len(said) == 1 and "not written" in said[0]


@pytest.mark.parametrize("fields, components", [
    ("kinds: RGB-color domain domain\nspacings: nan 0.5 0.5", 3),
    ("kinds: domain domain list\nspacings: 0.5 0.5 nan", 5),
    ("kinds: vector domain domain\nspace dimension: 2\nspace directions: none (0.5,0) (0,0.5)",
     3),
], ids=["rgb", "list", "none-direction"])
def test_a_2d_image_of_components_is_refused_not_read_as_a_volume(tmp_path, run, fields,
                                                                    components):
    """A 3-D NRRD with a non-spatial axis is a 2-D image of several components per pixel
    (ITK reads it so: 5x4 pixels of 3 components); its components were read as the x axis,
    spacing 1, exit 0. Refused whole and by box alike, nothing written."""
    from volwarp_cli.io.lazy import open_volume_lazy

    data = (np.arange(60) % 256).astype(np.uint8)
    path = tmp_path / "image.nrrd"
    path.write_bytes(f"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 3 4 5\nencoding: raw\n"
                     f"{fields}\n\n".encode() + data.tobytes())
    image = sitk.ReadImage(str(path))  # (ITK: a 2-D image of components)
    assert image.GetDimension() == 2 and image.GetNumberOfComponentsPerPixel() == components
    for read in (read_volume, open_volume_lazy):
        with pytest.raises(FormatError, match="a 2-D image with components per pixel"):
            read(path)
    res = run("convert", path, "-o", tmp_path / "out.nii.gz")
    assert res.code == 1 and "a 2-D image with components" in res.stderr
    assert not (tmp_path / "out.nii.gz").exists()


@pytest.mark.parametrize("kinds", ["domain domain domain", "space space space", "??? ??? ???",
                                   "domain domain time",
                                   "none none none"])
def test_spatial_kinds_of_a_3d_nrrd_still_read(tmp_path, kinds):
    path = tmp_path / "v.nrrd"
    path.write_bytes(_header("raw", f"kinds: {kinds}\n") + DATA.astype("<i2").tobytes())
    assert np.array_equal(read_volume(path).data, DATA)


def test_spaces_inside_vectors_are_read_as_itk_reads_them(tmp_path):
    """``(0.5, 0, 0)``: ITK (teem) reads a vector with spaces after its commas; volwarp
    refused it ("'space directions' has 9 entries")."""
    from volwarp_cli.io.lazy import open_volume_lazy

    path = tmp_path / "v.nrrd"
    path.write_bytes(
        b"NRRD0004\ntype: short\ndimension: 3\nsizes: 3 4 5\nendian: little\nencoding: raw\n"
        b"space: RAS\nspace directions: ( 0.5, 0, 0 ) (0, 0.7,0) (0,0, 1.1)\n"
        b"space origin: (1, 2, 3)\nmeasurement frame: (1, 0, 0) (0, 1, 0) (0, 0, 1)\n\n"
        + DATA.astype("<i2").tobytes())
    itk = sitk.ReadImage(str(path))
    for vol in (read_volume(path), open_volume_lazy(path)[0]):  # (the whole, the header)
        np.testing.assert_allclose(vol.spacing, itk.GetSpacing())
        np.testing.assert_allclose(vol.origin, itk.GetOrigin())
        np.testing.assert_allclose(np.ravel(vol.direction), itk.GetDirection())
    assert np.array_equal(read_volume(path).data, sitk.GetArrayFromImage(itk))
