"""OME-TIFF voxel sizes: ``PhysicalSizeX/Y/Z`` and their units, converted to mm.

The expected values come from the OME-XML itself, parsed here with tifffile's own
``xml2dict`` (not volwarp's parser), and converted with the units' definitions.
SimpleITK is no reference for these files: its TIFF reader ignores the OME-XML and
reports the baseline resolution tags (x, y) and 1 for z whatever ``PhysicalSizeZ``
says (despite documentation suggesting otherwise), so it is only used where the
file has no PhysicalSize and the resolution tags are the spacing.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import SimpleITK as sitk
import tifffile

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io import tiff as tiff_io

DATA = np.arange(3 * 4 * 5, dtype=np.uint16).reshape(3, 4, 5)  # z, y, x

#: millimetres per unit, from the units' definitions (independent of tiff.py's table)
MM_PER = {"nm": 1e-6, "\u00b5m": 1e-3, "um": 1e-3, "mm": 1.0, "cm": 10.0, "m": 1000.0,
          "\u00c5": 1e-7, "in": 25.4}


def write_ome(path, metadata, data=DATA, **kwargs):
    tifffile.imwrite(path, data, ome=True, photometric="minisblack",
                     metadata={"axes": "ZYX", **metadata}, **kwargs)
    return path


def ome_pixels(path) -> dict:
    """The Pixels attributes of the file's OME-XML, by tifffile's parser."""
    with tifffile.TiffFile(path) as tif:
        return tifffile.xml2dict(tif.ome_metadata)["OME"]["Image"]["Pixels"]


def expected_mm(pixels: dict, axis: str) -> float:
    unit = pixels.get(f"PhysicalSize{axis}Unit", "\u00b5m")  # the OME schema's default
    return float(pixels[f"PhysicalSize{axis}"]) * MM_PER[unit]


@pytest.mark.parametrize("unit,size,mm", [
    ("nm", 250.0, 0.00025),
    ("\u00b5m", 0.5, 0.0005),
    ("um", 0.5, 0.0005),
    ("mm", 0.75, 0.75),
    ("cm", 0.2, 2.0),
    ("m", 0.001, 1.0),
    ("\u00c5", 5000.0, 0.0005),
    ("in", 0.01, 0.254),
    (None, 2.0, 0.002),  # no unit: micrometres, the schema's default
])
def test_physical_size_units_give_spacing_in_mm(tmp_path, unit, size, mm):
    meta = {"PhysicalSizeX": size, "PhysicalSizeY": 2 * size, "PhysicalSizeZ": 3 * size}
    if unit is not None:
        meta.update({f"PhysicalSize{a}Unit": unit for a in "XYZ"})
    path = write_ome(tmp_path / "u.ome.tif", meta)
    pixels = ome_pixels(path)
    assert (unit is None) == ("PhysicalSizeXUnit" not in pixels)
    expect = [expected_mm(pixels, a) for a in "XYZ"]
    np.testing.assert_allclose(expect, [mm, 2 * mm, 3 * mm], rtol=1e-12)
    vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, expect, rtol=1e-12)
    assert vol.meta["unit"] == "mm"
    np.testing.assert_array_equal(vol.data, DATA)


def test_z_spacing_comes_from_physical_size_z(tmp_path):
    """The reported bug: PhysicalSizeZ = 3 mm came out as z spacing 1."""
    path = write_ome(tmp_path / "z.ome.tif", {
        "PhysicalSizeX": 500, "PhysicalSizeXUnit": "nm",
        "PhysicalSizeY": 0.5, "PhysicalSizeYUnit": "\u00b5m",
        "PhysicalSizeZ": 3, "PhysicalSizeZUnit": "mm"})
    vol = read_volume(path)
    assert vol.spacing[2] == 3.0
    np.testing.assert_allclose(vol.spacing, [0.0005, 0.0005, 3.0], rtol=1e-12)
    # SimpleITK does not read the OME-XML: it would say 1 for every axis here
    assert sitk.ReadImage(str(path)).GetSpacing() == (1.0, 1.0, 1.0)


def test_physical_size_beats_resolution_tags(tmp_path):
    # the tags say 20 pixels per cm (0.5 mm); the OME-XML says 2 um x 4 um x 1.5 um
    path = write_ome(tmp_path / "r.ome.tif",
                     {"PhysicalSizeX": 2, "PhysicalSizeY": 4, "PhysicalSizeZ": 1.5},
                     resolution=(20, 20), resolutionunit="CENTIMETER")
    # SimpleITK reads only the tags: 0.5 mm
    np.testing.assert_allclose(sitk.ReadImage(str(path)).GetSpacing()[:2], [0.5, 0.5])
    vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [0.002, 0.004, 0.0015], rtol=1e-12)
    assert vol.meta["unit"] == "mm"


def test_no_physical_size_keeps_the_resolution_tags(tmp_path):
    """Without PhysicalSize the spacing is what it was: the tags for x and y, 1 for z,
    the same x and y SimpleITK reports."""
    path = write_ome(tmp_path / "n.ome.tif", {}, resolution=(20, 40),
                     resolutionunit="CENTIMETER")
    assert not any(k.startswith("PhysicalSize") for k in ome_pixels(path))
    vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [0.5, 0.25, 1.0], rtol=1e-12)
    assert vol.meta["unit"] == "mm"
    np.testing.assert_allclose(sitk.ReadImage(str(path)).GetSpacing()[:2], vol.spacing[:2])
    # and with no resolution at all: 1, 1, 1 and no unit claimed
    plain = write_ome(tmp_path / "p.ome.tif", {})
    vol = read_volume(plain)
    np.testing.assert_array_equal(vol.spacing, [1.0, 1.0, 1.0])
    assert "unit" not in vol.meta


def test_missing_physical_size_z_keeps_1_and_warns(tmp_path, caplog):
    path = write_ome(tmp_path / "xy.ome.tif", {"PhysicalSizeX": 0.5, "PhysicalSizeXUnit": "mm",
                                               "PhysicalSizeY": 0.25, "PhysicalSizeYUnit": "mm"})
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [0.5, 0.25, 1.0], rtol=1e-12)
    assert any("PhysicalSizeZ" in r.getMessage() and "xy.ome.tif" in r.getMessage()
               for r in caplog.records)


@pytest.mark.parametrize("unit", ["pixel", "reference frame"])
def test_size_in_a_unit_that_is_no_length_is_ignored(tmp_path, unit):
    path = write_ome(tmp_path / "px.ome.tif", {
        "PhysicalSizeX": 7, "PhysicalSizeXUnit": unit, "PhysicalSizeY": 7,
        "PhysicalSizeYUnit": unit, "PhysicalSizeZ": 3, "PhysicalSizeZUnit": "mm"},
        resolution=(20, 20), resolutionunit="CENTIMETER")
    vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [0.5, 0.5, 3.0], rtol=1e-12)


def test_ome_xml_is_parsed_once_per_read(tmp_path, monkeypatch):
    path = write_ome(tmp_path / "once.ome.tif", {"PhysicalSizeZ": 3, "PhysicalSizeZUnit": "mm"})
    calls = []
    real = tiff_io._parse_ome_pixels
    monkeypatch.setattr(tiff_io, "_parse_ome_pixels", lambda tif: calls.append(1) or real(tif))
    assert read_volume(path).spacing[2] == 3.0
    assert len(calls) == 1


def test_volwarp_written_tiff_is_unaffected(tmp_path):
    from volwarp_cli.volume import Volume

    vol = Volume(DATA, spacing=(0.1, 0.2, 0.3))
    write_volume(vol, tmp_path / "v.tif")
    np.testing.assert_array_equal(read_volume(tmp_path / "v.tif").spacing, [0.1, 0.2, 0.3])
