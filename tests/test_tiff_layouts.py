"""TIFF layouts that were read silently wrong, read or refused as the file says.

Each file is written here with tifffile, as the programs that make them do:
an OME-TIFF of several images and a tifffile file of several series (once one
z stack of every plane, with the first image's spacing), shaped stacks with
time or channel axes (once stacked along z), Fiji's signed 16-bit stacks
(uint16 with a straight-line calibration: once 32768 too high), ResolutionUnit
millimetre and micrometre (micrometres once read as mm) and a volumetric tiled
page (once refused as damaged). The whole and the block-wise readers agree.
"""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from volwarp_cli.errors import BadUsage, ChoiceNeeded, FormatError
from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_header

RNG = np.random.default_rng(11)
STACK = RNG.integers(0, 100, (4, 9, 11)).astype(np.uint16)


def _both(path, **kw):
    """The whole read, checked against the block-wise one (every sample, and a reversed box)."""
    vol = read_volume(path, **kw)
    header, arr = open_volume_header(path, require_lazy=True, **kw)
    assert arr.dtype == vol.data.dtype
    np.testing.assert_array_equal(np.asarray(arr[...]), vol.data)
    np.testing.assert_array_equal(np.asarray(arr[1:3, ::-2, 4:]), vol.data[1:3, ::-2, 4:])
    np.testing.assert_allclose(header.spacing, vol.spacing)
    np.testing.assert_allclose(header.origin, vol.origin)
    return vol


def _two_ome_images(path):
    with tifffile.TiffWriter(path, ome=True) as w:
        w.write(STACK, metadata={"axes": "ZYX", "PhysicalSizeX": 0.5, "PhysicalSizeY": 0.5,
                                 "PhysicalSizeZ": 2.0, "PhysicalSizeXUnit": "mm",
                                 "PhysicalSizeYUnit": "mm", "PhysicalSizeZUnit": "mm"})
        w.write(STACK[:3] + 1000, metadata={
            "axes": "ZYX", "PhysicalSizeX": 0.7, "PhysicalSizeY": 0.7, "PhysicalSizeZ": 3.0,
            "PhysicalSizeXUnit": "mm", "PhysicalSizeYUnit": "mm", "PhysicalSizeZUnit": "mm"})


def _two_series(path):
    tifffile.imwrite(path, STACK, photometric="minisblack")
    tifffile.imwrite(path, STACK + 500, photometric="minisblack", append=True)


@pytest.mark.parametrize("write,count", [(_two_ome_images, 2), (_two_series, 2)])
def test_a_tiff_of_several_images_needs_volume_index(tmp_path, write, count):
    """Never one stack of every image's planes with the first one's spacing."""
    path = tmp_path / f"{write.__name__}.tif"
    write(path)
    with pytest.raises(ChoiceNeeded) as exc:
        read_volume(path)
    assert str(exc.value).startswith(f"{path}: TIFF holds {count} images")
    assert "--volume-index 0..1" in str(exc.value)
    with pytest.raises(ChoiceNeeded):
        open_volume_header(path)
    with pytest.raises(BadUsage, match="outside 0..1"):
        read_volume(path, volume_index=2)


def test_volume_index_picks_an_ome_image_with_its_own_spacing(tmp_path):
    path = tmp_path / "two.ome.tif"
    _two_ome_images(path)
    first = _both(path, volume_index=0)
    np.testing.assert_array_equal(first.data, STACK)
    np.testing.assert_allclose(first.spacing, (0.5, 0.5, 2.0))
    second = _both(path, volume_index=1)
    np.testing.assert_array_equal(second.data, STACK[:3] + 1000)
    np.testing.assert_allclose(second.spacing, (0.7, 0.7, 3.0))


def test_volume_index_picks_a_tifffile_series(tmp_path):
    path = tmp_path / "two.tif"
    _two_series(path)
    np.testing.assert_array_equal(_both(path, volume_index=1).data, STACK + 500)


def test_a_tiff_of_one_stack_takes_volume_index_0_only(tmp_path):
    path = tmp_path / "one.tif"
    tifffile.imwrite(path, STACK, imagej=True, metadata={"axes": "ZYX"})
    np.testing.assert_array_equal(read_volume(path, volume_index=0).data, STACK)
    with pytest.raises(BadUsage, match="outside 0..0"):
        read_volume(path, volume_index=1)


@pytest.mark.parametrize("axes,what", [("TZYX", "2 time points"), ("CZYX", "2 channels"),
                                       (None, "2 entries along an unnamed axis")])
def test_a_shaped_stack_with_a_second_axis_is_refused(tmp_path, axes, what):
    path = tmp_path / "s.tif"
    tifffile.imwrite(path, np.stack([STACK, STACK + 1]), photometric="minisblack",
                     metadata={"axes": axes} if axes else {})
    with pytest.raises(FormatError) as exc:
        read_volume(path)
    assert str(exc.value).startswith(f"{path}: TIFF image has {what}")
    with pytest.raises(FormatError) as lazy:
        open_volume_header(path)
    assert str(lazy.value) == str(exc.value)


def test_a_shaped_stack_with_a_size_1_axis_is_its_z_stack(tmp_path):
    path = tmp_path / "s.tif"
    tifffile.imwrite(path, STACK[None], photometric="minisblack", metadata={"axes": "CZYX"})
    np.testing.assert_array_equal(_both(path).data, STACK)


def test_fiji_signed_16_bit_stack_is_read_as_int16(tmp_path):
    signed = RNG.integers(-1024, 2000, (5, 6, 7)).astype(np.int16)
    path = tmp_path / "signed.tif"
    tifffile.imwrite(path, (signed.astype(np.int32) + 32768).astype(np.uint16), imagej=True,
                     metadata={"axes": "ZYX", "cf": 0, "c0": -32768.0, "c1": 1.0,
                               "vunit": "Gray Value"})
    vol = _both(path)
    assert vol.data.dtype == np.int16
    np.testing.assert_array_equal(vol.data, signed)
    # (a stack over 4 GiB is read by box in the file's byte order, ImageJ's big-endian:
    # the same int16 samples as the whole read's, not float32)
    from volwarp_cli.io.tiff import calibrate

    big_endian = (signed.astype(np.int32) + 32768).astype(">u2")
    out = calibrate(big_endian, (-32768.0, 1.0))
    assert out.dtype == np.int16
    np.testing.assert_array_equal(out, signed)


def test_an_imagej_straight_line_calibration_gives_float32(tmp_path):
    path = tmp_path / "cal.tif"
    tifffile.imwrite(path, STACK.astype(np.uint8), imagej=True,
                     metadata={"axes": "ZYX", "cf": 0, "c0": -10.0, "c1": 0.5})
    vol = _both(path)
    assert vol.data.dtype == np.float32
    np.testing.assert_array_equal(vol.data, (-10.0 + 0.5 * STACK).astype(np.float32))


def test_another_imagej_calibration_function_is_refused(tmp_path):
    path = tmp_path / "poly.tif"
    tifffile.imwrite(path, STACK, imagej=True,
                     metadata={"axes": "ZYX", "cf": 1, "c0": 1.0, "c1": 2.0, "c2": 3.0})
    with pytest.raises(FormatError, match="calibration function 1 is not a straight line"):
        read_volume(path)


@pytest.mark.parametrize("unit,mm", [("MILLIMETER", 0.25), ("MICROMETER", 0.00025),
                                     ("CENTIMETER", 2.5), ("INCH", 6.35)])
def test_resolution_units_of_tifffile_are_read_in_mm(tmp_path, unit, mm):
    path = tmp_path / "r.tif"
    tifffile.imwrite(path, STACK, resolution=(4.0, 4.0), resolutionunit=unit,
                     photometric="minisblack")
    vol = _both(path)
    np.testing.assert_allclose(vol.spacing[:2], (mm, mm))
    assert vol.meta["unit"] == "mm"


def test_an_imagej_calibration_origin_places_the_stack(tmp_path):
    """Fiji's xorigin, yorigin, zorigin (pixels: pixel i lies at (i - xorigin) * width)
    were ignored: such a stack was read at the world's origin. Whole and by box."""
    path = tmp_path / "o.tif"
    tifffile.imwrite(path, STACK, imagej=True, resolution=(2.0, 4.0),
                     metadata={"axes": "ZYX", "spacing": 3.0, "unit": "micron",
                               "xorigin": 2.5, "yorigin": -1, "zorigin": 4})
    vol = _both(path)
    np.testing.assert_allclose(vol.spacing, (0.0005, 0.00025, 0.003))
    np.testing.assert_allclose(vol.origin, (-2.5 * 0.0005, 1 * 0.00025, -4 * 0.003))


def test_an_axis_aligned_volume_is_written_with_its_imagej_origin(tmp_path):
    """Fiji shows volwarp's coordinates: the origin in ImageJ's pixels, read back as
    ImageJ computes it; a rotated grid has no ImageJ calibration origin."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    data = STACK.astype(np.uint16)
    vol = Volume(data, spacing=np.array([0.5, 0.25, 2.0]), origin=np.array([-10.0, 3.0, 0.0]))
    write_volume(vol, tmp_path / "a.tif")
    with tifffile.TiffFile(tmp_path / "a.tif") as tif:
        ij = tif.imagej_metadata
    assert (ij["xorigin"], ij["yorigin"]) == (20.0, -12.0) and "zorigin" not in ij
    for axis, name in enumerate(("xorigin", "yorigin")):  # ImageJ's Calibration.getX(0)
        assert (0 - ij[name]) * vol.spacing[axis] == vol.origin[axis]
    assert np.array_equal(read_volume(tmp_path / "a.tif").origin, vol.origin)
    turned = Volume(data, spacing=vol.spacing, origin=vol.origin,
                    direction=np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]))
    write_volume(turned, tmp_path / "b.tif")
    with tifffile.TiffFile(tmp_path / "b.tif") as tif:
        assert "xorigin" not in tif.imagej_metadata
    back = read_volume(tmp_path / "b.tif")
    assert np.array_equal(back.origin, vol.origin) and np.array_equal(back.direction,
                                                                     turned.direction)


def test_a_volumetric_tiled_page_is_read(tmp_path):
    data = RNG.integers(0, 100, (8, 32, 32)).astype(np.uint16)
    path = tmp_path / "vol.tif"
    tifffile.imwrite(path, data, tile=(4, 16, 16), volumetric=True)
    np.testing.assert_array_equal(_both(path).data, data)


def test_a_calibration_changed_by_another_program_is_read_and_said(run, tmp_path):
    """volwarp stores its exact spacing beside the resolution tags and ImageJ's spacing; a
    program that recalibrates the stack (Fiji) keeps the key/values it does not know, and
    the stale copy overrode the calibration Fiji shows (0.9055 mm read for 0.75, exit 0)."""
    import tifffile

    from volwarp_cli.io import read_volume, write_volume
    from volwarp_cli.volume import Volume

    data = np.random.default_rng(0).random((6, 7, 8), dtype=np.float32)
    first = tmp_path / "a.tif"
    write_volume(Volume(data, spacing=(0.9055, 0.9055, 2.0), origin=(1.0, 2.0, 3.0)), first)
    assert run("info", first).stderr == ""  # (its own file: the exact copy, nothing said)
    with tifffile.TiffFile(first) as tif:
        md = dict(tif.imagej_metadata)
    for key in ("ImageJ", "images", "slices", "hyperstack", "mode"):
        md.pop(key, None)
    md.update(spacing=5.0, axes="ZYX")
    edited = tmp_path / "edited.tif"
    tifffile.imwrite(edited, data, imagej=True, resolution=(1 / 0.75, 1 / 0.75), metadata=md)
    vol = read_volume(edited)
    np.testing.assert_allclose(vol.spacing, (0.75, 0.75, 5.0), rtol=1e-6)
    np.testing.assert_array_equal(vol.origin, (1.0, 2.0, 3.0))  # (no calibration of its own)
    res = run("info", edited)
    assert res.code == 0
    assert "is not the spacing volwarp stored with it (0.9055 0.9055 2 mm)" in res.stderr
