"""Damaged and malformed volume files: every one is a clear error naming the file.

Truncated TIFFs (at every byte), TIFFs whose pages disagree with their own
metadata, ASCII NRRD values a type cannot hold, detached NRRD headers naming
impossible numbers of files, NIfTI files with empty axes, and geometry whose
direction matrix is singular.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import warnings

import nibabel as nib
import numpy as np
import pytest

from volwarp_cli.errors import FormatError, VolwarpError
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

VOLWARP = [sys.executable, "-m", "volwarp_cli"]


def _limit_memory():  # for subprocesses that, unfixed, would eat all memory
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))


def _cli(*args, cwd=None, timeout=60):
    return subprocess.run(VOLWARP + [str(a) for a in args], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout, preexec_fn=_limit_memory)


def _assert_one_line_error(proc, *needles):
    assert proc.returncode == 1, (proc.returncode, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("volwarp: error: ")
    assert "internal error" not in lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


# -- TIFF ---------------------------------------------------------------------

def _stack(dtype="uint8", shape=(3, 4, 5)) -> np.ndarray:
    return (np.arange(np.prod(shape)) % 97 + 1).astype(dtype).reshape(shape)


def _ifds(raw: bytes) -> list[tuple[int, int]]:
    """(offset of each IFD, offset of its next-IFD pointer) of a little-endian classic TIFF."""
    assert raw[:4] == b"II*\0"
    out = []
    off = struct.unpack_from("<I", raw, 4)[0]
    while off:
        ntags = struct.unpack_from("<H", raw, off)[0]
        out.append((off, off + 2 + 12 * ntags))
        off = struct.unpack_from("<I", raw, off + 2 + 12 * ntags)[0]
    return out


def _check_every_cut(tmp_path, raw: bytes, expect: np.ndarray, step: int = 1) -> int:
    """Each prefix of ``raw`` reads as the whole volume or fails naming the file."""
    cut = tmp_path / "cut.tif"
    failures = 0
    for n in range(0, len(raw), step):
        cut.write_bytes(raw[:n])
        try:
            vol = read_volume(cut)
        except FormatError as exc:
            assert str(exc).startswith(f"{cut}: "), (n, str(exc))
            assert "\n" not in str(exc)
            failures += 1
            continue
        # only a cut that removed nothing the reader needs may read, and then in full
        assert vol.data.shape == expect.shape, (n, vol.data.shape)
        np.testing.assert_array_equal(vol.data, expect, err_msg=f"cut at {n}")
    return failures


def test_tiff_cut_at_every_byte_never_reads_fewer_slices(tmp_path, capfd):
    data = _stack("uint8")
    write_volume(Volume(data), tmp_path / "s.tif")  # ImageJ stack: images=3
    raw = (tmp_path / "s.tif").read_bytes()
    failures = _check_every_cut(tmp_path, raw, data)
    assert failures > len(raw) * 0.9
    # tifffile's own complaints ("<tifffile.TiffPages @8> invalid page offset ...")
    # stay off stderr: the command line prints one line of its own
    assert capfd.readouterr().err == ""


def test_compressed_shaped_tiff_cut_points(tmp_path, capfd):
    data = _stack("int32")  # not an ImageJ type: tifffile's shaped metadata (shape [3, 4, 5])
    write_volume(Volume(data), tmp_path / "s.tif", compress=True)
    raw = (tmp_path / "s.tif").read_bytes()
    failures = _check_every_cut(tmp_path, raw, data, step=3)
    assert failures == len(range(0, len(raw), 3))  # every byte of a compressed file matters
    assert capfd.readouterr().err == ""


def test_reviewer_cut_imagej_stack_reports_truncation(tmp_path):
    """`head -c 2000 t8.tif > cut.tif`: one page of an 8-page stack used to read as 1 slice."""
    data = _stack("uint8", (8, 16, 20))
    write_volume(Volume(data), tmp_path / "t8.tif")
    (tmp_path / "cut.tif").write_bytes((tmp_path / "t8.tif").read_bytes()[:2000])
    with pytest.raises(FormatError, match=r"cut\.tif: TIFF is truncated or damaged"):
        read_volume(tmp_path / "cut.tif")


@pytest.mark.parametrize("dtype,source", [("uint8", "ImageJ metadata"),
                                          ("int32", "tifffile metadata")])
def test_tiff_with_fewer_pages_than_its_metadata_declares(tmp_path, dtype, source):
    """A well-formed chain of pages, but ending early (the last page's link set to 0)."""
    data = _stack(dtype, (4, 4, 5))
    write_volume(Volume(data), tmp_path / "s.tif")
    raw = bytearray((tmp_path / "s.tif").read_bytes())
    struct.pack_into("<I", raw, _ifds(bytes(raw))[1][1], 0)  # keep pages 0 and 1
    (tmp_path / "short.tif").write_bytes(bytes(raw))
    with pytest.raises(FormatError) as info:
        read_volume(tmp_path / "short.tif")
    msg = str(info.value)
    assert msg.startswith(f"{tmp_path / 'short.tif'}: ")
    assert "has 2 pages" in msg and "declares 4" in msg and source in msg


def test_ome_tiff_with_fewer_pages_than_its_metadata_declares(tmp_path):
    import tifffile

    data = _stack("uint16", (4, 4, 5))
    tifffile.imwrite(tmp_path / "s.ome.tif", data, ome=True, photometric="minisblack",
                     metadata={"axes": "ZYX"})
    np.testing.assert_array_equal(read_volume(tmp_path / "s.ome.tif").data, data)
    raw = bytearray((tmp_path / "s.ome.tif").read_bytes())
    struct.pack_into("<I", raw, _ifds(bytes(raw))[2][1], 0)  # keep pages 0..2
    (tmp_path / "short.ome.tif").write_bytes(bytes(raw))
    with pytest.raises(FormatError, match=r"short\.ome\.tif: TIFF has 3 pages but its OME "
                                          r"metadata declares 4"):
        read_volume(tmp_path / "short.ome.tif")


def test_imagej_stack_with_one_ifd_reads_every_plane(tmp_path):
    """ImageJ writes stacks over 4 GiB with one IFD and the planes back to back: all are read."""
    data = _stack("uint16", (3, 4, 5))
    write_volume(Volume(data), tmp_path / "s.tif")
    raw = bytearray((tmp_path / "s.tif").read_bytes())
    struct.pack_into("<I", raw, _ifds(bytes(raw))[0][1], 0)  # page 0 is now the only IFD
    (tmp_path / "one.tif").write_bytes(bytes(raw))
    vol = read_volume(tmp_path / "one.tif")
    np.testing.assert_array_equal(vol.data, data)
    # ... but not when the file is too short to hold them
    import tifffile

    with tifffile.TiffFile(tmp_path / "one.tif") as tif:
        end = tif.pages[0].dataoffsets[0] + data.nbytes
    (tmp_path / "one_cut.tif").write_bytes(bytes(raw[:end - 1]))
    with pytest.raises(FormatError, match="has 1 page but its ImageJ metadata"):
        read_volume(tmp_path / "one_cut.tif")


@pytest.mark.parametrize("dtype", ["int8", "uint32", "int32", "float64"])
@pytest.mark.parametrize("nz", [3, 4])
def test_non_imagej_tiff_of_three_or_four_slices_is_not_written_as_rgb(tmp_path, dtype, nz):
    """tifffile took a [3|4, y, x] stack for one RGB(A) page: it read back as 3 samples/pixel."""
    data = _stack(dtype, (nz, 4, 5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # tifffile's "stored as RGB" DeprecationWarning
        write_volume(Volume(data), tmp_path / "s.tif")
    np.testing.assert_array_equal(read_volume(tmp_path / "s.tif").data, data)


def test_tiff_whose_pages_loop_is_refused(tmp_path):
    """A next-page link back to page 0: tifffile alone goes round until memory runs out."""
    write_volume(Volume(_stack()), tmp_path / "s.tif")
    raw = bytearray((tmp_path / "s.tif").read_bytes())
    chain = _ifds(bytes(raw))
    struct.pack_into("<I", raw, chain[1][1], chain[0][0])
    (tmp_path / "loop.tif").write_bytes(bytes(raw))
    proc = _cli("info", "loop.tif", cwd=tmp_path, timeout=30)
    _assert_one_line_error(proc, "loop.tif:", "loops")


def test_truncated_tiff_on_the_command_line(tmp_path):
    data = _stack("uint8", (8, 16, 20))
    write_volume(Volume(data), tmp_path / "t8.tif")
    raw = (tmp_path / "t8.tif").read_bytes()
    for n in (2000, 300, 6):  # page links, a tag value, the header itself cut
        (tmp_path / "cut.tif").write_bytes(raw[:n])
        proc = _cli("info", "cut.tif", cwd=tmp_path)
        _assert_one_line_error(proc, "cut.tif:")
        assert "tifffile" not in proc.stderr and "Error" not in proc.stderr, proc.stderr


# -- NRRD: ASCII values -------------------------------------------------------

def _ascii_nrrd(path, type_name, values, sizes=None):
    sizes = sizes or (len(values), 1, 1)
    path.write_text(f"NRRD0004\ntype: {type_name}\ndimension: 3\n"
                    f"sizes: {' '.join(map(str, sizes))}\nencoding: ascii\n\n"
                    + " ".join(values) + "\n")
    return path


@pytest.mark.parametrize("type_name,bad,why", [
    ("uint8", "300", "out of range"),
    ("uint8", "-1", "out of range"),
    ("uint8", "2.5", "not a whole number"),
    ("uint8", "nan", "not a number"),
    ("uint8", "inf", "infinite"),
    ("int8", "128", "out of range"),
    ("int16", "40000", "out of range"),
    ("uint16", "65536", "out of range"),
    ("int32", "2147483648", "out of range"),
    ("uint32", "1e10", "out of range"),
    ("uint32", "0.001", "not a whole number"),
])
def test_ascii_integer_value_the_type_cannot_hold(tmp_path, type_name, bad, why):
    path = _ascii_nrrd(tmp_path / "a.nrrd", type_name, ["1", "2", bad, "4", "7.5"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning from a cast either
        with pytest.raises(FormatError) as info:
            read_volume(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: ")
    assert f"'{bad}' (sample 2)" in msg and why in msg  # the first bad value, not 7.5


def test_ascii_integer_values_that_fit_are_read_exactly(tmp_path):
    cases = {"uint8": ["0", "255", "1e2", "7.0"], "int8": ["-128", "127", "-0", "3"],
             "uint32": ["4294967295", "0", "12", "1"], "int32": ["-2147483648", "2147483647",
                                                                 "5", "6"]}
    for type_name, values in cases.items():
        vol = read_volume(_ascii_nrrd(tmp_path / f"{type_name}.nrrd", type_name, values))
        assert vol.data.dtype == np.dtype(type_name)
        np.testing.assert_array_equal(vol.data.ravel(), [int(float(v)) for v in values])


def test_ascii_float_keeps_nan_and_infinity_like_binary_data(tmp_path):
    values = ["1.5", "nan", "-inf", "inf", "3.4028234e38"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ascii_vol = read_volume(_ascii_nrrd(tmp_path / "a.nrrd", "float", values))
    data = np.array([float(v) for v in values], dtype=np.float32)
    (tmp_path / "b.nrrd").write_bytes(
        b"NRRD0004\ntype: float\ndimension: 3\nsizes: 5 1 1\nendian: little\nencoding: raw\n\n"
        + data.astype("<f4").tobytes())
    binary_vol = read_volume(tmp_path / "b.nrrd")
    assert ascii_vol.data.tobytes() == binary_vol.data.tobytes()
    # a finite value too large for float32 would silently become infinity: refused
    with pytest.raises(FormatError, match=r"a2\.nrrd: ascii data value '1e39' \(sample 1\) "
                                          r"is outside the range of float32"):
        read_volume(_ascii_nrrd(tmp_path / "a2.nrrd", "float", ["0", "1e39", "1"]))
    assert read_volume(_ascii_nrrd(tmp_path / "a3.nrrd", "double", ["0", "1e39", "1"])
                       ).data.ravel()[1] == 1e39


def test_ascii_non_number_is_named(tmp_path):
    path = _ascii_nrrd(tmp_path / "a.nrrd", "uint8", ["1", "x7", "3"])
    with pytest.raises(FormatError, match=r"a\.nrrd: ascii data value 'x7' \(sample 1\) is not"):
        read_volume(path)


# -- NRRD: detached data files ------------------------------------------------

SIZES = (4, 3, 6)  # x, y, z: 6 slices of 12 samples


def _pattern_header(tmp_path, data_file: str, name="p.nhdr"):
    path = tmp_path / name
    path.write_text("NRRD0005\ntype: uint8\ndimension: 3\nsizes: 4 3 6\nencoding: raw\n"
                    f"data file: {data_file}\n")
    return path


def _slices(tmp_path, count: int, fmt="sl%02d.raw", start=0):
    data = np.arange(72, dtype=np.uint8).reshape(6, 3, 4)
    for i, chunk in enumerate(np.split(data.ravel(), count)):
        (tmp_path / (fmt % (start + i))).write_bytes(chunk.tobytes())
    return data


def test_huge_file_number_range_is_refused_at_once(tmp_path):
    """`data file: sl%03d.raw 0 99999999 1` used to build a list until the machine gave up."""
    for hi in ("99999999", "999999999999"):
        _pattern_header(tmp_path, f"sl%03d.raw 0 {hi} 1", name="big.nhdr")
        proc = _cli("info", "big.nhdr", cwd=tmp_path, timeout=30)
        _assert_one_line_error(proc, "big.nhdr:", f"names {int(hi) + 1} files")


@pytest.mark.parametrize("spec,files,ok", [
    ("sl%02d.raw 0 5 1", 6, True),          # one file per slice (teem's default)
    ("sl%02d.raw 0 2 1", 3, True),          # slabs of 2 slices: 3 divides 6
    ("sl%02d.raw 1 6 1", 6, True),          # numbering from 1
    ("sl%02d.raw 0 10 2", 6, True),         # every second number
    ("sl%02d.raw 0 2 1 3", 3, True),        # subdim = dimension: slabs
    ("sl%02d.raw 0 17 1 1", 18, True),      # subdim 1: one row per file
    ("sl%02d.raw 0 0 1 3", 1, True),        # one file, a 3-D piece
    ("sl%02d.raw 0 3 1", 4, False),         # 4 files do not split 6 slices
    ("sl%02d.raw 0 6 1", 7, False),         # more files than slices
    ("sl%02d.raw 0 5 1 1", 6, False),       # subdim 1 needs 18 files
    ("sl%02d.raw 0 5 1 4", 6, False),       # subdim beyond the dimension
    ("sl%02d.raw 0 5 1 0", 6, False),
    ("sl%02d.raw 5 0 1", 6, False),         # max not reached from min
    ("sl%02d.raw 0 5 0", 6, False),         # step 0
    ("sl%02d.raw 0 five 1", 6, False),      # not a number
])
def test_file_number_pattern_must_split_the_data(tmp_path, spec, files, ok):
    lo, step = int(spec.split()[1]), (int(spec.split()[3]) if ok else 1)
    data = None
    if ok:
        data = np.arange(72, dtype=np.uint8).reshape(6, 3, 4)
        for i, chunk in enumerate(np.split(data.ravel(), files)):
            (tmp_path / f"sl{lo + i * step:02d}.raw").write_bytes(chunk.tobytes())
    else:
        _slices(tmp_path, 6)
    path = _pattern_header(tmp_path, spec)
    if ok:
        np.testing.assert_array_equal(read_volume(path).data, data)
    else:
        with pytest.raises(FormatError) as info:
            read_volume(path)
        assert str(info.value).startswith(f"{path}: "), str(info.value)
        assert "'data file'" in str(info.value)


def test_descending_file_numbers_are_read_in_their_order(tmp_path):
    data = np.arange(72, dtype=np.uint8).reshape(6, 3, 4)
    for i, z in enumerate(range(5, -1, -1)):
        (tmp_path / f"sl{z:02d}.raw").write_bytes(data[i].tobytes())
    np.testing.assert_array_equal(
        read_volume(_pattern_header(tmp_path, "sl%02d.raw 5 0 -1")).data, data)


def test_bad_pattern_format_is_a_clear_error(tmp_path):
    _slices(tmp_path, 6)
    with pytest.raises(FormatError, match=r"p\.nhdr: 'data file' pattern 'sl%d%d\.raw'"):
        read_volume(_pattern_header(tmp_path, "sl%d%d.raw 0 5 1"))


def test_list_of_data_files_must_split_the_data(tmp_path):
    data = _slices(tmp_path, 6)
    names = "\n".join(f"sl{i:02d}.raw" for i in range(6))
    path = _pattern_header(tmp_path, "LIST\n" + names)
    np.testing.assert_array_equal(read_volume(path).data, data)
    path = _pattern_header(tmp_path, "LIST\n" + names.rsplit("\n", 1)[0])  # 5 files
    with pytest.raises(FormatError, match=r"p\.nhdr: 'data file' names 5 files"):
        read_volume(path)
    path = _pattern_header(tmp_path, "LIST 2\n" + names)  # 2-D pieces: one per slice
    np.testing.assert_array_equal(read_volume(path).data, data)
    path = _pattern_header(tmp_path, "LIST 1\n" + names)  # 1-D pieces: 18 needed
    with pytest.raises(FormatError, match="need 18"):
        read_volume(path)
    # fields after LIST and a blank line before the names (not teem's form) still read
    path = _pattern_header(tmp_path, "LIST\nspacings: 1 1 2\nkey:=v\n\n" + names)
    vol = read_volume(path)
    np.testing.assert_array_equal(vol.data, data)
    assert vol.spacing.tolist() == [1, 1, 2] and vol.meta["key"] == "v"


# -- NIfTI --------------------------------------------------------------------

def _nifti_with_dims(path, dims):
    raw = bytearray(nib.Nifti1Image(np.zeros((3, 4, 5), np.int16), np.eye(4)).to_bytes())
    struct.pack_into("<8h", raw, 40, *dims)
    path.write_bytes(bytes(raw))
    return path


@pytest.mark.parametrize("dims", [
    [3, 0, 5, 5, 1, 1, 1, 1],   # the reviewer's zero.nii: crashed `info` with a TypeError
    [3, 3, 4, 0, 1, 1, 1, 1],
    [3, -3, 4, 5, 1, 1, 1, 1],
    [4, 3, 4, 5, 0, 1, 1, 1],   # no volumes
    [0, 3, 4, 5, 1, 1, 1, 1],   # no axes
])
def test_nifti_with_an_empty_or_negative_axis_is_refused(tmp_path, dims):
    path = _nifti_with_dims(tmp_path / "zero.nii", dims)
    with pytest.raises(FormatError) as info:
        read_volume(path)
    assert str(info.value).startswith(f"{path}: NIfTI sizes must be positive")


def test_zero_size_nifti_on_the_command_line(run, tmp_path):
    path = _nifti_with_dims(tmp_path / "zero.nii", [3, 0, 5, 5, 1, 1, 1, 1])
    res = run("info", path)
    assert res.code == 1, res
    assert res.stderr.strip().splitlines() == [
        f"volwarp: error: {path}: NIfTI sizes must be positive, got (0, 5, 5) "
        "(header dim [3, 0, 5, 5, 1, 1, 1, 1])"]


def test_nifti_header_nibabel_refuses_is_one_clear_error(tmp_path, capfd):
    path = _nifti_with_dims(tmp_path / "bad.nii", [9, 3, 4, 5, 1, 1, 1, 1])
    with pytest.raises(FormatError, match=r"bad\.nii: not a readable NIfTI file"):
        read_volume(path)
    assert capfd.readouterr().err == ""  # nibabel's "sizeof_hdr should be 348" notes


# -- singular directions ------------------------------------------------------

def test_singular_nrrd_directions_name_the_file(tmp_path, run):
    path = tmp_path / "sing.nrrd"
    path.write_bytes(b"NRRD0005\ntype: uint8\ndimension: 3\nsizes: 2 2 2\n"
                     b"space dimension: 3\nspace directions: (1,0,0) (1,0,0) (0,0,1)\nencoding: raw\n\n"
                     + bytes(8))
    with pytest.raises(FormatError, match=r"sing\.nrrd: 'space directions': direction matrix "
                       "is singular"):
        read_volume(path)
    res = run("info", path)
    assert res.code == 1
    assert res.stderr.strip().splitlines() == [
        f"volwarp: error: {path}: 'space directions': direction matrix is singular (its axes "
        "lie in one plane)"]


def test_singular_nifti_matrix_names_the_file(tmp_path):
    img = nib.Nifti1Image(np.zeros((3, 4, 5), np.int16), None)
    img.set_sform(np.array([[1.0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), code=1)
    img.set_qform(None, code=0)
    nib.save(img, tmp_path / "sing.nii")
    with pytest.raises(FormatError, match=r"sing\.nii: sform \(srow_x, srow_y, srow_z\): "
                       "direction matrix is singular"):
        read_volume(tmp_path / "sing.nii")


def test_raw_geometry_errors_name_the_file(tmp_path):
    from volwarp_cli.io import RawLayout

    (tmp_path / "v.raw").write_bytes(bytes(8))
    with pytest.raises(VolwarpError, match=r"v\.raw: --raw-spacing: spacing must be positive"):
        read_volume(tmp_path / "v.raw", raw=RawLayout(shape=(2, 2, 2), dtype="uint8",
                                                      spacing=(1.0, 0.0, 1.0)))


@pytest.mark.parametrize("axes, shape, what", [("CZYX", (2, 3, 8, 9), "2 channels"),
                                               ("TZYX", (3, 2, 8, 9), "3 time points")])
def test_ome_tiff_with_channels_or_time_points_is_refused(tmp_path, axes, shape, what):
    """An OME-TIFF's planes are channels x time points x z: read as z slices they would
    make a wrong volume, so more than one channel or time point is refused (as ImageJ
    hyperstacks are)."""
    import tifffile

    from volwarp_cli.io import read_volume

    path = tmp_path / "h.ome.tif"
    tifffile.imwrite(path, np.zeros(shape, np.uint8), ome=True, metadata={"axes": axes})
    with pytest.raises(FormatError, match=what):
        read_volume(path)
    single = tmp_path / "s.ome.tif"
    tifffile.imwrite(single, np.arange(3 * 8 * 9, dtype=np.uint8).reshape(3, 8, 9), ome=True,
                     metadata={"axes": "ZYX"})
    assert read_volume(single).data.shape == (3, 8, 9)


@pytest.mark.parametrize("name,spacing,match", [
    ("t.tif", (1e-12, 1, 1), r"t\.tif: spacing 1e-12 cannot be stored in TIFF's XResolution"),
    ("t.tif", (1, 1e12, 1), r"t\.tif: spacing 1e\+12 cannot be stored in TIFF's YResolution"),
])
def test_geometry_a_format_cannot_hold_is_a_clear_error(run, tmp_path, name, spacing, match):
    """Was an internal error (tifffile's rational); NRRD and MetaImage hold such numbers
    exactly. (A spacing NIfTI's float32 cannot hold, 1e300, is no volume's any more:
    tests/test_geometry_finite.py.)"""
    src = tmp_path / "s.nrrd"
    write_volume(Volume(np.zeros((2, 2, 2), np.uint8), spacing=spacing), src)
    res = run("convert", src, "-o", tmp_path / name)
    assert res.code == 1 and len(res.stderr.strip().splitlines()) == 1, res
    import re
    assert re.search(match, res.stderr), res.stderr
    assert not (tmp_path / name).exists()
    write_volume(read_volume(src), tmp_path / "ok.mha")
    np.testing.assert_array_equal(read_volume(tmp_path / "ok.mha").spacing, spacing)


# -- descriptors --------------------------------------------------------------------------

def _damaged(folder, name: str):
    """A file (or folder) of format ``name`` cut short or with a garbled chunk."""
    data = np.arange(6 * 7 * 8, dtype=np.int16).reshape(6, 7, 8)
    path = folder / name
    write_volume(Volume(data), path, compress=name.endswith((".gz", "z.nrrd")))
    if name.endswith(".ome.zarr"):
        chunk = max((p for p in path.rglob("*") if p.is_file() and "json" not in p.name
                     and not p.name.startswith(".z")), key=lambda p: p.stat().st_size)
        chunk.write_bytes(b"\x28\xb5\x2f\xfd" + b"\xff" * 40)  # a zstd frame of garbage
        return path
    cut = path.with_suffix(".raw") if name.endswith(".nhdr") else (
        path.with_suffix(".raw") if name.endswith(".mhd") else path)
    cut.write_bytes(cut.read_bytes()[:-50])
    return path


@pytest.mark.parametrize("name", ["a.nrrd", "gz.nrrd", "a.nhdr", "a.nii", "a.nii.gz", "a.mha",
                                  "a.mhd", "a.tif", "a.ome.zarr"])
def test_a_damaged_file_leaves_no_descriptor_open(tmp_path, name):
    """Every reader closes what it opened on its error paths, before the error leaves it
    (checked while the error's traceback, which holds the readers' frames, is alive): a
    batch of thousands of scans would otherwise run out of descriptors."""
    from conftest import open_files

    from volwarp_cli.io.lazy import open_volume_lazy

    path = _damaged(tmp_path, name)
    for read in (read_volume, open_volume_lazy):
        for _ in range(3):
            try:
                got = read(path)
            except VolwarpError as exc:
                assert str(exc).startswith(str(tmp_path)), str(exc)  # (naming the file)
                assert open_files(tmp_path) == [], (read.__name__, exc)
                continue
            assert read is open_volume_lazy, f"{name}: a damaged file was read"
            try:  # lazily opened: the damage may show on reading
                np.asarray(got[1][...])
            except VolwarpError as exc:
                assert str(exc).startswith(str(tmp_path)), str(exc)
                assert open_files(tmp_path) == [], exc
            del got  # the array's file, open while the array lives, is closed with it
            assert open_files(tmp_path) == [], read.__name__


@pytest.mark.parametrize("name", ["a.nrrd", "a.nii", "a.mha", "a.tif", "a.ome.zarr"])
def test_a_lazy_array_closes_its_file_when_dropped(tmp_path, name):
    from conftest import open_files

    from volwarp_cli.io.lazy import open_volume_lazy

    data = np.arange(6 * 7 * 8, dtype=np.int16).reshape(6, 7, 8)
    write_volume(Volume(data), tmp_path / name)
    for _ in range(3):
        _, arr = open_volume_lazy(tmp_path / name, require_lazy=True)
        np.testing.assert_array_equal(arr[2:4, 1:5, 3:7], data[2:4, 1:5, 3:7])
        if hasattr(arr, "close"):  # (an OME-Zarr store holds no file between reads)
            arr.close()
        assert open_files(tmp_path) == [], name
        np.testing.assert_array_equal(arr[2:4], data[2:4])  # (reopened on the next read)
        del arr
        assert open_files(tmp_path) == [], name


def _nrrd(path, fields, payload=b""):
    path.write_bytes(("NRRD0004\n" + "".join(f"{f}\n" for f in fields) + "\n").encode()
                     + payload)
    return path


@pytest.mark.parametrize("case", ["no-endian", "misspelt-field", "twice", "dirs-and-spacings",
                                  "byte-skip-short"])
def test_nrrd_headers_teem_refuses_are_refused(tmp_path, case):
    """Read with exit 0 before, with wrong samples or geometry: no 'endian' (a big-endian
    file byte-swapped), 'spacing' for 'spacings' (the spacing lost), a field given twice
    (the last won), 'spacings' beside 'space directions' (dropped), 'byte skip: -1' on a
    short file (the header's text read as samples). teem, ITK and pynrrd refuse each."""
    from volwarp_cli.io import read_volume

    data = (np.arange(24, dtype=">i2") * 40 - 300).tobytes()
    base = ["type: short", "dimension: 3", "sizes: 4 3 2", "encoding: raw"]
    fields, payload, says = {
        "no-endian": (base, data, "no 'endian' field"),
        "misspelt-field": (base + ["endian: big", "spacing: 0.5 0.5 2.5"], data,
                           "unknown NRRD field 'spacing'"),
        "twice": (base + ["endian: big", "space origin: (0,0,0)", "space: LPS",
                          "space directions: (1,0,0) (0,1,0) (0,0,1)",
                          "space origin: (100,0,0)"], data, "'space origin' is given twice"),
        "dirs-and-spacings": (base + ["endian: big", "space: LPS", "spacings: 2 2 2",
                                      "space directions: (1,0,0) (0,1,0) (0,0,1)"], data,
                              "'spacings' beside 'space directions'"),
        "byte-skip-short": (base + ["endian: big", "byte skip: -1"], data[:-20],
                            "data is truncated"),
    }[case]
    with pytest.raises(FormatError, match=says):
        read_volume(_nrrd(tmp_path / "x.nrrd", fields, payload))
