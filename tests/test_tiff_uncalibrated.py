"""Plain TIFFs whose voxel size the file does not give: read as ImageJ reads them, and said.

The reference is ImageJ 1.x's ``ij.io.TiffDecoder`` (written out in
:func:`_imagej_pixel_size`): XResolution 72 per inch, what image editors,
Pillow and export tools write when they know no size, is uncalibrated (1 x 1
pixel), and so are resolution tags without a ResolutionUnit. volwarp read
72 dpi as 0.353 mm voxels and a 300 "dpi" without a unit as 0.0033 mm ones,
silently; and a plain stack's z spacing, which no plain TIFF holds, was 1 mm
beside x and y in micrometres without a word. A zero resolution, or one of
denominator 0, gave x 1 beside y's tag: now no size, as ImageJ reads it.
"""

from __future__ import annotations

import logging
import struct

import numpy as np
import pytest
import tifffile
from PIL import Image

from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_header
from volwarp_cli.runscope import run_scope

STACK = (np.arange(6 * 5 * 7) % 251).astype(np.uint8).reshape(6, 5, 7)


def _imagej_pixel_size(path):
    """x and y pixel size and unit as ImageJ's TiffDecoder reads a plain TIFF (no description)."""
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        size, unit = [1.0, 1.0], None
        for axis, tag in enumerate(("XResolution", "YResolution")):
            if tag in tags:
                num, den = tags[tag].value
                scale = num / den if den else 0.0
                if scale:
                    size[axis] = 1.0 / scale
        code = int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else None
        if code == 1:
            unit = " "
        elif code == 2:
            if size[0] == 1.0 / 72.0:
                size = [1.0, 1.0]
            else:
                unit = "inch"
        elif code == 3:
            unit = "cm"
    return (size, unit) if unit is not None else ([1.0, 1.0], None)  # (FileOpener: no unit)


def _no_unit_tag(src, dst):
    """``src`` with its ResolutionUnit entries renamed to a private tag (no unit in the file)."""
    raw = bytearray(src.read_bytes())
    with tifffile.TiffFile(src) as tif:
        for page in tif.pages:
            at = page.tags["ResolutionUnit"].offset
            assert struct.unpack_from("<H", raw, at)[0] == 296
            struct.pack_into("<H", raw, at, 65000)
    dst.write_bytes(bytes(raw))


def _pillow(path, **kwargs):
    frames = [Image.fromarray(p) for p in STACK]
    frames[0].save(path, save_all=True, append_images=frames[1:], **kwargs)


def _uncalibrated_files(tmp_path):
    """Plain TIFFs ImageJ calibrates to 1 x 1 pixels, as their writers make them."""
    files = {}
    files["pillow_72dpi"] = tmp_path / "pillow_72dpi.tif"
    _pillow(files["pillow_72dpi"], dpi=(72, 72))
    files["pillow_no_dpi"] = tmp_path / "pillow_no_dpi.tif"
    _pillow(files["pillow_no_dpi"])
    files["tifffile_72_inch"] = tmp_path / "tifffile_72_inch.tif"
    tifffile.imwrite(files["tifffile_72_inch"], STACK, resolution=(72, 72),
                     resolutionunit="INCH")
    base = tmp_path / "base.tif"
    tifffile.imwrite(base, STACK, resolution=(300, 300), resolutionunit="INCH")
    files["300_without_unit"] = tmp_path / "no_unit.tif"
    _no_unit_tag(base, files["300_without_unit"])
    return files


def test_a_tiff_of_no_voxel_size_is_read_as_imagej_reads_it_and_said(tmp_path, caplog):
    for name, path in _uncalibrated_files(tmp_path).items():
        size, unit = _imagej_pixel_size(path)
        assert (size, unit) == ([1.0, 1.0], None), name
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="volwarp"):
            vol = read_volume(path)
        np.testing.assert_array_equal(vol.spacing, [1.0, 1.0, 1.0], err_msg=name)
        assert "unit" not in vol.meta, name
        np.testing.assert_array_equal(vol.data, STACK)
        said = [r.getMessage() for r in caplog.records if "no voxel size" in r.getMessage()]
        assert len(said) == 1 and "x and y" in said[0] and " z " in said[0], (name, said)
        assert "Fiji" in said[0] and "no option" in said[0], said
        header, _ = open_volume_header(path, require_lazy=True)
        np.testing.assert_array_equal(header.spacing, vol.spacing)


def test_a_calibrated_plain_stack_says_its_z_spacing_is_not_in_the_file(tmp_path, caplog):
    path = tmp_path / "cm.tif"
    tifffile.imwrite(path, STACK, resolution=(40, 40), resolutionunit="CENTIMETER")
    size, unit = _imagej_pixel_size(path)
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [size[0] * 10, size[1] * 10, 1.0])
    assert unit == "cm" and vol.meta["unit"] == "mm"
    said = [r.getMessage() for r in caplog.records if "no voxel size" in r.getMessage()]
    assert len(said) == 1 and "z (" in said[0] and "x and y" not in said[0], said
    # one page: nothing is missing, nothing said
    one = tmp_path / "one.tif"
    tifffile.imwrite(one, STACK[0], resolution=(40, 40), resolutionunit="CENTIMETER")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        np.testing.assert_allclose(read_volume(one).spacing, [0.25, 0.25, 1.0])
    assert not caplog.records


@pytest.mark.parametrize("unit", ["pixel", None, "furlong"])
def test_an_imagej_stack_in_no_length_is_said(tmp_path, caplog, unit):
    """Its numbers as they are (ImageJ's too), taken as mm: said, as NRRD's unknown units are."""
    path = tmp_path / "ij.tif"
    meta = {"axes": "ZYX", "spacing": 2.0, **({"unit": unit} if unit else {})}
    tifffile.imwrite(path, STACK, imagej=True, resolution=(4, 4), metadata=meta)
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [0.25, 0.25, 2.0])
    said = [r.getMessage() for r in caplog.records if "no voxel size" in r.getMessage()]
    assert len(said) == 1 and "x, y and z" in said[0], said
    # volwarp's own copy of it keeps its numbers, and says nothing more
    from volwarp_cli.io import write_volume

    write_volume(vol, tmp_path / "again.tif")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        np.testing.assert_array_equal(read_volume(tmp_path / "again.tif").spacing, vol.spacing)
    assert not caplog.records


def test_the_warning_is_said_once_a_run(tmp_path, caplog):
    path = _uncalibrated_files(tmp_path)["pillow_72dpi"]
    with caplog.at_level(logging.WARNING, logger="volwarp"), run_scope():
        read_volume(path)
        open_volume_header(path, require_lazy=True)
    assert sum("no voxel size" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.parametrize("imagej", [False, True])
@pytest.mark.parametrize("num,den", [(0, 1), (4, 0), (0, 0)])
def test_a_resolution_of_zero_is_no_size_as_imagej_reads_it(tmp_path, run, caplog, imagej,
                                                            num, den):
    """x was read 1 (the tag skipped) beside y's 0.25 mm: a made-up, anisotropic voxel;
    then such files were refused (Pillow writes 0/1 for dpi=(0, 0)). ImageJ's TiffDecoder
    takes a zero resolution for a missing tag: y's then gives both axes, said."""
    path = tmp_path / "r.tif"
    meta = {"axes": "ZYX", "unit": "mm", "spacing": 2.0} if imagej else None
    tifffile.imwrite(path, STACK, imagej=imagej, metadata=meta, resolution=(4, 4),
                     **({} if imagej else {"resolutionunit": "MILLIMETER"}))
    raw = bytearray(path.read_bytes())
    with tifffile.TiffFile(path) as tif:
        for page in tif.pages:
            struct.pack_into("<II", raw, page.tags["XResolution"].valueoffset, num, den)
    path.write_bytes(bytes(raw))
    with caplog.at_level(logging.WARNING, logger="volwarp"), run_scope():
        vol = read_volume(path)
    assert np.allclose(vol.spacing[:2], [0.25, 0.25])
    assert any(f"XResolution is {num}/{den}, no size" in r.getMessage() for r in caplog.records)
    assert np.allclose(open_volume_header(path, require_lazy=True)[0].spacing[:2], [0.25, 0.25])
    res = run("convert", path, "-o", tmp_path / "out.nrrd")
    assert res.code == 0, res.stderr
    assert np.allclose(read_volume(tmp_path / "out.nrrd").spacing[:2], [0.25, 0.25])


def test_resolutions_of_zero_on_both_axes_are_uncalibrated(tmp_path, caplog):
    """Pillow's dpi=(0, 0): no size on either axis, read as a TIFF without the tags."""
    path = tmp_path / "z.tif"
    Image.fromarray(STACK[0]).save(path, dpi=(0, 0))
    with tifffile.TiffFile(path) as tif:
        assert tif.pages[0].tags["XResolution"].value[0] == 0
    with caplog.at_level(logging.WARNING, logger="volwarp"), run_scope():
        vol = read_volume(path)
    assert np.allclose(vol.spacing, [1, 1, 1])
    assert any("resolution tags of 0" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("kept", ["XResolution", "YResolution"])
def test_one_resolution_tag_gives_both_axes(tmp_path, caplog, kept):
    """The other axis was 1 mm beside the tag's 0.25 mm (ImageJ: 1 cm beside 0.025 cm)."""
    base, path = tmp_path / "base.tif", tmp_path / "one.tif"
    tifffile.imwrite(base, STACK, resolution=(40, 40), resolutionunit="CENTIMETER")
    gone = "YResolution" if kept == "XResolution" else "XResolution"
    raw = bytearray(base.read_bytes())
    with tifffile.TiffFile(base) as tif:
        for page in tif.pages:
            struct.pack_into("<H", raw, page.tags[gone].offset, 65001)
    path.write_bytes(bytes(raw))
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [0.25, 0.25, 1.0])
    assert any(f"no {gone}: it is {kept}" in r.getMessage() for r in caplog.records)
    header, _ = open_volume_header(path, require_lazy=True)
    np.testing.assert_array_equal(header.spacing, vol.spacing)


def test_a_sweep_template_stack_is_read_without_its_calibration_said(tmp_path):
    """A sweep places its template stack itself: the stack's missing voxel size is not said.

    ``info`` on the same stack says it (the warning above); a sweep over it
    said it too, though no spacing of the file is used there.
    """
    import subprocess
    import sys

    stack = np.zeros((4, 32, 32), np.uint8)
    stack[:, 8:24, 8:24] = 255
    tifffile.imwrite(tmp_path / "t.tif", stack, photometric="minisblack")
    (tmp_path / "s.yaml").write_text(
        "version: 1\ngrid: {spacing: 0.5}\n"
        "fields:\n  opacity: {frames: t.tif, path: {keyframes: [[0, 0], [1, 3]]}}\n"
        "trajectory:\n  - line: {from: [0, 0, 0], to: [10, 0, 0]}\nup: [0, 0, 1]\nscale: [4, 4]\n")
    run = [sys.executable, "-m", "volwarp_cli"]
    info = subprocess.run(run + ["info", "t.tif"], cwd=tmp_path, capture_output=True, text=True)
    assert info.returncode == 0 and "no voxel size in the TIFF" in info.stderr
    sweep = subprocess.run(run + ["sweep", "s.yaml", "-o", "o_{field}.nrrd"], cwd=tmp_path,
                           capture_output=True, text=True)
    assert sweep.returncode == 0, sweep.stderr
    assert "voxel size" not in sweep.stderr
    assert read_volume(tmp_path / "o_opacity.nrrd").data.max() > 0
