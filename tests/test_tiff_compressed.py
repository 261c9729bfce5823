"""Compressed TIFF stacks read as tifffile reads them, whole and by box.

LZW (ImageJ's, Pillow's ``tiff_lzw``, most microscope software's), zstd,
JPEG, PackBits and the floating-point predictor (3) need tifffile's codecs
from ``imagecodecs``: without it every such stack was refused ("cannot read
TIFF data (<COMPRESSION.LZW: 5> requires the 'imagecodecs' package)"), whole
and by box. imagecodecs is now a dependency; the samples are tifffile's
``imread``'s, bit for bit (JPEG's lossy decoding too), in every layout.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import tifffile

from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_lazy

RNG = np.random.default_rng(44)


def _stack(dtype, shape=(6, 33, 41)):
    """Samples a predictor has work on (smooth ramps and noise), the type's extremes too."""
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        return (RNG.standard_normal(shape) * 100).astype(dtype)
    info = np.iinfo(dtype)
    z, y, x = np.indices(shape)
    span = int(info.max) - int(info.min) + 1
    v = (z * 1000 + y * 37 + x * 11 + RNG.integers(0, 50, shape)) % span + int(info.min)
    out = v.astype(dtype)
    out.flat[0], out.flat[1] = info.min, info.max
    return out


#: name: (samples, tifffile.imwrite's options)
CASES = {
    "lzw_uint16": (_stack("uint16"), dict(compression="lzw")),
    "lzw_pred2_uint8": (_stack("uint8"), dict(compression="lzw", predictor=True)),
    "lzw_pred2_int16_big": (_stack("int16"), dict(compression="lzw", predictor=True,
                                                  byteorder=">")),
    "lzw_pred2_rows5_int32": (_stack("int32"), dict(compression="lzw", predictor=True,
                                                    rowsperstrip=5)),
    "lzw_pred2_tiled_bigtiff_uint16": (_stack("uint16"), dict(
        compression="lzw", predictor=True, tile=(16, 32), bigtiff=True)),
    "lzw_pred3_bigtiff_float64": (_stack("float64"), dict(compression="lzw", predictor=3,
                                                          bigtiff=True)),
    "deflate_pred3_float32": (_stack("float32"), dict(compression="zlib", predictor=3)),
    "deflate_pred3_float32_big": (_stack("float32"), dict(compression="zlib", predictor=3,
                                                          byteorder=">")),
    "deflate_pred3_tiled_float32": (_stack("float32"), dict(compression="zlib", predictor=3,
                                                            tile=(16, 16))),
    "zstd_float32": (_stack("float32"), dict(compression="zstd")),
    "zstd_tiled_int32": (_stack("int32"), dict(compression="zstd", tile=(16, 16))),
    "packbits_uint16": (_stack("uint16"), dict(compression="packbits")),
    "packbits_uint8": (_stack("uint8"), dict(compression="packbits")),
    "jpeg_uint8": (_stack("uint8", (5, 48, 64)), dict(compression="jpeg")),
    "jpeg_q40_rows16_uint8": (_stack("uint8", (5, 48, 64)), dict(
        compression="jpeg", compressionargs={"level": 40}, rowsperstrip=16)),
    "jpeg_tiled_bigtiff_uint8": (_stack("uint8", (5, 48, 64)), dict(
        compression="jpeg", tile=(16, 32), bigtiff=True)),
    "lzw_volumetric_float32": (_stack("float32"), dict(
        compression="lzw", predictor=True, tile=(2, 16, 16), volumetric=True)),
    "ome_zstd_pred2_uint16": (_stack("uint16"), dict(
        compression="zstd", predictor=True, ome=True, metadata={"axes": "ZYX"})),
}
# ImageJ stacks (no hyperstack: z only), as tifffile writes them with a compression
for _c, _dt in (("lzw", "uint8"), ("lzw", "int16"), ("zstd", "uint16"),
                ("packbits", "float32"), ("jpeg", "uint8")):
    CASES[f"imagej_{_c}_{_dt}"] = (_stack(_dt, (5, 48, 64)), dict(
        imagej=True, compression=_c, metadata={"axes": "ZYX", "spacing": 2.5, "unit": "um"}))
CASES["imagej_lzw_pred2_uint16"] = (_stack("uint16"), dict(
    imagej=True, compression="lzw", predictor=True, metadata={"axes": "ZYX"}))
CASES["imagej_deflate_pred3_float32"] = (_stack("float32"), dict(
    imagej=True, compression="zlib", predictor=3, metadata={"axes": "ZYX"}))

#: Pillow's multi-page TIFFs through libtiff (compression, samples, Pillow's image mode)
PILLOW = {
    "pillow_lzw_uint8": ("tiff_lzw", _stack("uint8"), None),
    "pillow_lzw_uint16": ("tiff_lzw", _stack("uint16"), None),
    "pillow_lzw_float32": ("tiff_lzw", _stack("float32"), "F"),
    "pillow_packbits_uint8": ("packbits", _stack("uint8"), None),
    "pillow_jpeg_uint8": ("jpeg", _stack("uint8", (4, 48, 64)), None),
}


@pytest.fixture(scope="module")
def stacks(tmp_path_factory):
    """name: (path, tifffile.imread's samples as (z, y, x)), read when written."""
    from PIL import Image

    folder = tmp_path_factory.mktemp("codecs")
    out = {}
    for name, (data, options) in CASES.items():
        path = folder / f"{name}.{'ome.tif' if options.get('ome') else 'tif'}"
        if not options.get("imagej") and not options.get("ome"):
            options = {"photometric": "minisblack", **options}
        tifffile.imwrite(path, data, **options)
        out[name] = path
    for name, (compression, data, mode) in PILLOW.items():
        pages = [Image.fromarray(s, mode=mode) if mode else Image.fromarray(s) for s in data]
        path = folder / f"{name}.tif"
        pages[0].save(path, save_all=True, append_images=pages[1:], compression=compression)
        out[name] = path
    refs = {}
    for name, path in out.items():
        with tifffile.TiffFile(path) as tif:  # (the compression asked for is the file's)
            assert tif.pages[0].compression != 1, name
        ref = tifffile.imread(path)
        refs[name] = (path, ref.reshape((-1,) + ref.shape[-2:]))
    return refs


NAMES = [*CASES, *PILLOW]
BOXES = [np.s_[:, :, :], np.s_[1:4, 2:19, 0:7], np.s_[2, :, 5:], np.s_[::2, 3, ::-3],
         np.s_[-2:, 17:, 29:], np.s_[::-2, ::-1]]


def _same(got, ref, what):
    got = np.asarray(got)
    assert got.dtype.newbyteorder("=") == ref.dtype.newbyteorder("="), what
    assert got.shape == ref.shape, what
    # bit for bit: -0.0 and NaN payloads too
    assert np.ascontiguousarray(got.astype(got.dtype.newbyteorder("="))).tobytes() == \
        np.ascontiguousarray(ref.astype(ref.dtype.newbyteorder("="))).tobytes(), what


@pytest.mark.parametrize("name", NAMES)
def test_a_compressed_stack_reads_whole_as_tifffile_reads_it(stacks, name):
    path, ref = stacks[name]
    _same(read_volume(path).data, ref, name)


@pytest.mark.parametrize("name", NAMES)
def test_a_compressed_stack_reads_by_box_as_tifffile_reads_it(stacks, name):
    path, ref = stacks[name]
    _, samples = open_volume_lazy(path, require_lazy=True)
    assert type(samples).__name__ == "_ZarrView", name  # (pages decoded box by box)
    for box in BOXES:
        _same(samples[box], ref[box], f"{name} {box}")


@pytest.mark.parametrize("name", ["lzw_pred2_int16_big", "deflate_pred3_tiled_float32",
                                  "jpeg_tiled_bigtiff_uint8", "imagej_zstd_uint16",
                                  "pillow_lzw_float32"])
def test_a_command_by_blocks_reads_a_compressed_stack_as_tifffile(stacks, name, run, tmp_path):
    """apply's identity, nearest, by blocks of 2x16x16: the input read box by box."""
    path, ref = stacks[name]
    sitk.WriteTransform(sitk.Transform(3, sitk.sitkIdentity), str(tmp_path / "id.tfm"))
    out = tmp_path / "o.nrrd"
    res = run("apply", path, "-t", tmp_path / "id.tfm", "--interpolation", "nearest",
              "--chunked", "--block", "2,16,16", "-o", out)
    assert res.code == 0, res
    _same(read_volume(out).data, ref, name)


def test_imagecodecs_is_a_runtime_dependency():
    """Installed by hand, it hid a missing declaration: a fresh install read no LZW stack."""
    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    names = [d.split(">")[0].split("=")[0].split("<")[0].strip()
             for d in project["project"]["dependencies"]]
    assert "imagecodecs" in names


def test_a_compression_tifffile_cannot_decode_is_one_line_before_any_work(run, tmp_path):
    """PixarLog (libtiff's, no codec in tifffile): refused naming it, exit 1, no output. It
    was refused only as its samples were read: after the stack's own warning (no voxel
    size), a second line, and by blocks at the first block."""
    data = _stack("uint16", (4, 20, 24))
    path = tmp_path / "pixarlog.tif"
    tifffile.imwrite(path, data, imagej=True, compression="zlib", metadata={"axes": "ZYX"})
    raw = bytearray(path.read_bytes())
    with tifffile.TiffFile(path) as tif:
        at = [page.tags["Compression"].valueoffset for page in tif.pages]
    for offset in at:
        raw[offset:offset + 2] = (32909).to_bytes(2, "little")
    path.write_bytes(bytes(raw))
    line = f"volwarp: error: {path}: cannot read TIFF data (<COMPRESSION.PIXARLOG: 32909> " \
           "not supported)"
    sitk.WriteTransform(sitk.Transform(3, sitk.sitkIdentity), str(tmp_path / "id.tfm"))
    out = tmp_path / "out"
    out.mkdir()
    for args in (["info", path], ["convert", path, "-o", out / "c.nrrd"],
                 ["apply", path, "-t", tmp_path / "id.tfm", "--chunked", "-o", out / "a.nrrd"],
                 ["mesh", path, "--iso", 100, "-o", out / "m.ply"]):
        res = run(*args)
        assert (res.code, res.stderr.strip()) == (1, line), (args[0], res)
        assert list(out.iterdir()) == [], args[0]
