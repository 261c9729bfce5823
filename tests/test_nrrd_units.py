"""NRRD length units: numbers in microns or centimetres are read as millimetres' worth.

SimpleITK reads NRRD numbers as they are, whatever ``space units`` say: its
geometry times the unit's size in millimetres is the reference. Before, a
file in microns was read (and written to NIfTI, TIFF, OME-Zarr labelled mm)
1000 times too large.
"""

from __future__ import annotations

import subprocess
import sys

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.lazy import open_volume_lazy

DATA = np.arange(210, dtype="<i2").reshape(5, 6, 7)  # z y x


def _attached(path, header_lines):
    text = "NRRD0004\ntype: short\ndimension: 3\nsizes: 7 6 5\nendian: little\nencoding: raw\n"
    path.write_bytes((text + "".join(f"{line}\n" for line in header_lines) + "\n").encode()
                     + DATA.tobytes())
    return path


def _oblique(tmp_path, units):
    return _attached(tmp_path / "oblique.nrrd", [
        "space: right-anterior-superior",
        "space directions: (0.9,0.1,0) (-0.1,0.9,0) (0,0,2.5)",
        "space origin: (10,-20,30)",
        f"space units: {units}"])


@pytest.mark.parametrize("units, mm", [('"microns" "microns" "microns"', 1e-3),
                                       ('"um" "um" "um"', 1e-3), ('"cm" "cm" "cm"', 10.0),
                                       ('"mm" "mm" "mm"', 1.0), ('"m" "m" "m"', 1e3)])
def test_space_units_scale_the_geometry_to_millimetres(tmp_path, units, mm, run):
    path = _oblique(tmp_path, units)
    ref = sitk.ReadImage(str(path))
    for vol in (read_volume(path), open_volume_lazy(path, require_lazy=True)[0]):
        np.testing.assert_allclose(vol.spacing, np.array(ref.GetSpacing()) * mm, rtol=1e-12)
        np.testing.assert_allclose(vol.origin, np.array(ref.GetOrigin()) * mm, rtol=1e-12)
        np.testing.assert_allclose(np.ravel(vol.direction), ref.GetDirection(), atol=1e-12)
    res = run("info", path)
    assert res.code == 0
    assert res.stderr.count("converted to millimetres") == (mm != 1.0)


def test_units_beside_spacings_scale_each_axis(tmp_path):
    path = _attached(tmp_path / "cm.nrrd", ["spacings: 0.5 0.25 2", "axis mins: 1 2 3",
                                            'units: "cm" "mm" "microns"'])
    ref = sitk.ReadImage(str(path))
    vol = read_volume(path)
    scale = np.array([10.0, 1.0, 1e-3])
    np.testing.assert_allclose(vol.spacing, np.array(ref.GetSpacing()) * scale, rtol=1e-12)
    np.testing.assert_allclose(vol.origin, np.array(ref.GetOrigin()) * scale, rtol=1e-12)


def test_a_converted_file_says_millimetres_to_other_tools(tmp_path):
    path = _oblique(tmp_path, '"microns" "microns" "microns"')
    ref = sitk.ReadImage(str(path))
    want = np.array(ref.GetSpacing()) * 1e-3
    nii, again = tmp_path / "out.nii", tmp_path / "again.nrrd"
    for out in (nii, again):
        run = subprocess.run([sys.executable, "-m", "volwarp_cli", "convert", str(path), "-o",
                              str(out)], capture_output=True, text=True)
        assert run.returncode == 0, run.stderr
        assert run.stderr.count("converted to millimetres") == 1
    img = nib.load(nii)
    assert img.header.get_xyzt_units()[0] == "mm"
    np.testing.assert_allclose(img.header.get_zooms(), want, rtol=1e-6)
    # the NRRD written holds millimetres and says so: read again, nothing is scaled twice
    assert '"mm" "mm" "mm"' in again.read_bytes().split(b"\n\n")[0].decode()
    np.testing.assert_allclose(sitk.ReadImage(str(again)).GetSpacing(), want, rtol=1e-12)
    np.testing.assert_allclose(read_volume(again).spacing, want, rtol=1e-12)
    np.testing.assert_array_equal(read_volume(again).data, DATA)


def test_a_unit_that_is_no_length_is_said_and_the_numbers_kept(tmp_path, run):
    path = _oblique(tmp_path, '"pixel" "pixel" "pixel"')
    vol = read_volume(path)
    np.testing.assert_allclose(vol.spacing, sitk.ReadImage(str(path)).GetSpacing(), rtol=1e-12)
    assert "not a length volwarp knows" in run("info", path).stderr


def test_a_units_field_of_the_wrong_length_is_refused(tmp_path):
    path = _oblique(tmp_path, '"mm" "mm"')
    with pytest.raises(Exception, match="'space units' has 2 entries"):
        read_volume(path)


def test_written_files_keep_reading_as_before(tmp_path):
    from volwarp_cli.volume import Volume

    out = tmp_path / "plain.nrrd"
    write_volume(Volume(DATA.astype(np.float32), spacing=(0.5, 0.5, 2.0)), out)
    np.testing.assert_allclose(read_volume(out).spacing, (0.5, 0.5, 2.0))
