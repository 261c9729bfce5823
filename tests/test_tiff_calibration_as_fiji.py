"""ImageJ stacks from other writers read with the voxel size Fiji shows.

The reference is ImageJ 1.x's own reading (``ij.io.TiffDecoder`` and
``FileOpener.setCalibration``/``decodeDescriptionString``), written out here
from tifffile's tags: the resolution tags in pixels per unit, ResolutionUnit 3
naming centimetres, the description's ``unit`` replacing it (with its one
conversion: centimetre tags and ``unit=um`` are micrometres times 10^4), and
a voxel depth of 1 unit where the description has no ``spacing`` (ImageJ
writes none for a depth of exactly 1). Once, volwarp read a micron stack
without ``spacing`` 1 mm deep (1000x), and centimetre tags under ``unit=um``
10^4 times too small.
"""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_header

STACK = np.arange(5 * 4 * 3, dtype=np.uint16).reshape(5, 4, 3)
#: ImageJ's length units in mm (those these files use)
_UNIT_MM = {"micron": 1e-3, "um": 1e-3, "mm": 1.0, "cm": 10.0}


def _fiji_voxel_mm(path):
    """The voxel size in mm (None without a length unit) that ImageJ 1.x calibrates ``path`` with."""
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        size = [1.0, 1.0, 1.0]
        for axis, tag in enumerate(("XResolution", "YResolution")):
            if tag in tags:
                num, den = tags[tag].value
                size[axis] = den / num
        unit = None
        code = int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else None
        if code == 3:
            unit = "cm"
        ij = tif.imagej_metadata
        if ij is not None:
            described = str(ij.get("unit", ""))
            if unit == "cm" and described == "um":
                size[0] *= 1e4
                size[1] *= 1e4
            unit = described
            if "spacing" in ij:
                size[2] = abs(float(ij["spacing"]))
    scale = _UNIT_MM.get(unit)
    return None if scale is None else [v * scale for v in size]


@pytest.mark.parametrize("kwargs,expected", [
    # Fiji's stack of 0.5 x 0.5 x 1 micron voxels (ImageJ writes no spacing=1)
    (dict(resolution=(2.0, 2.0), metadata={"unit": "micron", "axes": "ZYX"}),
     [0.0005, 0.0005, 0.001]),
    # pixels per centimetre under unit=um: ImageJ converts them to micrometres
    (dict(resolution=(2e4, 2e4), resolutionunit="CENTIMETER",
          metadata={"unit": "um", "spacing": 2.0, "axes": "ZYX"}), [0.0005, 0.0005, 0.002]),
    # the same tags under another spelling of the micron: no conversion in ImageJ
    (dict(resolution=(2.0, 2.0), resolutionunit="CENTIMETER",
          metadata={"unit": "micron", "spacing": 2.0, "axes": "ZYX"}), [0.0005, 0.0005, 0.002]),
    (dict(resolution=(1 / 0.3, 1 / 0.4), metadata={"unit": "mm", "spacing": 1.5, "axes": "ZYX"}),
     [0.3, 0.4, 1.5]),
])
def test_an_imagej_stack_has_the_voxel_size_fiji_shows(tmp_path, kwargs, expected):
    path = tmp_path / "fiji.tif"
    tifffile.imwrite(path, STACK, imagej=True, **kwargs)
    np.testing.assert_allclose(_fiji_voxel_mm(path), expected, rtol=1e-6)
    vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, expected, rtol=1e-6)
    assert vol.meta.get("unit") == "mm"
    header, _ = open_volume_header(path, require_lazy=True)
    np.testing.assert_allclose(header.spacing, vol.spacing)


@pytest.mark.parametrize("given,missing", [("X", "Y"), ("Y", "X")])
def test_an_ome_size_given_for_x_or_y_only_is_both_as_bio_formats_reads_it(tmp_path, caplog,
                                                                           given, missing):
    """Bio-Formats' calibration takes a missing PhysicalSizeX/Y as the other one.

    volwarp read the missing axis from the resolution tags tifffile leaves at 1
    (no unit) beside the other one's 0.0005 mm: voxels 2000 times longer in y.
    """
    import logging

    path = tmp_path / "x.ome.tif"
    tifffile.imwrite(path, STACK, ome=True, photometric="minisblack", metadata={
        "axes": "ZYX", f"PhysicalSize{given}": 0.5, f"PhysicalSize{given}Unit": "\u00b5m",
        "PhysicalSizeZ": 2.0, "PhysicalSizeZUnit": "\u00b5m"})
    with tifffile.TiffFile(path) as tif:
        pixels = tifffile.xml2dict(tif.ome_metadata)["OME"]["Image"]["Pixels"]
    assert f"PhysicalSize{missing}" not in pixels
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, [0.0005, 0.0005, 0.002], rtol=1e-12)
    assert any(f"no PhysicalSize{missing}" in r.getMessage() for r in caplog.records)
    header, _ = open_volume_header(path, require_lazy=True)
    np.testing.assert_allclose(header.spacing, vol.spacing)
