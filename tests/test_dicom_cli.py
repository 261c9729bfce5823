"""DICOM through the command line: choosing a series, converting, and options that do not apply.

The series are written with pydicom by ``test_io_dicom.write_series``; the reference
geometry is SimpleITK's ImageSeriesReader of the same files.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
from pydicom.data import get_testdata_file
from test_io_dicom import sitk_series, write_series

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume
from volwarp_cli.io.dicom import read_dicom

A, B = "1.2.826.0.1.3680043.8.498.1", "1.2.826.0.1.3680043.8.498.2"


@pytest.fixture
def two_series(tmp_path):
    rng = np.random.default_rng(5)
    stored = rng.integers(-1000, 3000, size=(6, 5, 7)).astype(np.int16)
    folder = tmp_path / "study"
    write_series(folder / "a", stored, series=A, orientation=(0, 1, 0, 0, 0, -1))
    write_series(folder / "b", stored[:3], series=B, names=[f"B{k}" for k in range(3)])
    return folder, stored


def test_info_lists_the_candidates_and_convert_needs_a_choice(run, two_series, tmp_path):
    folder, _ = two_series
    res = run("info", folder, "--json")
    assert res.code == 0, res
    desc = json.loads(res.stdout)
    assert desc["format"] == "dicom"
    assert [c["series_uid"] for c in desc["candidates"]] == [A, B]
    assert desc["candidates"][1]["shape_xyz"] == [7, 5, 3]
    text = run("info", folder).stdout
    assert "2 volumes (choose one with --series" in text and A in text and B in text
    out = tmp_path / "o.nrrd"
    res = run("convert", folder, "-o", out)
    assert res.code == 2, res
    assert A in res.stderr and B in res.stderr and "--series" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("choice", ["0", A])
def test_convert_a_chosen_series_matches_simpleitk(run, two_series, tmp_path, choice):
    folder, stored = two_series
    out = tmp_path / "a.nii.gz"
    res = run("convert", folder, "--series", choice, "-o", out)
    assert res.code == 0, res
    ref = sitk_series(folder / "a")
    img = sitk.ReadImage(str(out))
    for ijk in [(0, 0, 0), (6, 4, 5), (3, 2, 1)]:
        np.testing.assert_allclose(img.TransformIndexToPhysicalPoint(ijk),
                                   ref.TransformIndexToPhysicalPoint(ijk), atol=1e-4)
    np.testing.assert_array_equal(sitk.GetArrayFromImage(img), sitk.GetArrayFromImage(ref))
    vol = read_volume(out)
    assert vol.meta["DICOM_SeriesInstanceUID"] == A
    assert "DICOM_PatientName" not in vol.meta and "Doe" not in json.dumps(vol.meta)


def test_keep_phi_keeps_the_patients_name(run, two_series, tmp_path):
    folder, _ = two_series
    out = tmp_path / "a.nrrd"
    assert run("convert", folder, "--series", "0", "--keep-phi", "-o", out).code == 0
    assert read_volume(out).meta.get("DICOM_PatientName") == "Doe^Jane"


def test_dicom_options_for_another_format_are_usage_errors(run, data_dir, tmp_path):
    res = run("convert", data_dir / "ball_30_uint8.nrrd", "--series", "1", "-o",
              tmp_path / "x.nrrd")
    assert res.code == 2 and "applies to DICOM inputs" in res.stderr
    res = run("convert", data_dir / "ball_30_uint8.nrrd", "-o", tmp_path / "x.dcm")
    assert res.code == 2 and "does not write it" in res.stderr


def test_a_dicom_series_feeds_the_other_commands(run, two_series, tmp_path):
    folder, stored = two_series
    out = tmp_path / "d.nrrd"
    res = run("distance", folder / "b", "--iso", "1000", "-o", out)
    assert res.code == 0, res
    vol = read_volume(out)
    assert vol.shape_xyz == (7, 5, 3) and vol.meta["DICOM_SeriesInstanceUID"] == B


def test_pydicom_warnings_stay_off_stderr(tmp_path):
    """badVR.dcm made pydicom print a two-line UserWarning before volwarp's one line."""
    import subprocess
    import sys
    from pathlib import Path

    import pydicom.data

    path = Path(pydicom.data.__file__).parent / "test_files" / "badVR.dcm"
    res = subprocess.run([str(Path(sys.executable).parent / "volwarp"), "info", str(path)],
                         capture_output=True, text=True)
    assert res.returncode == 1
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("volwarp: error: "), res.stderr


def test_palette_colour_is_refused_naming_the_file(run, tmp_path):
    """PALETTE COLOR has one sample per pixel, but an index into colour tables, not a value.

    It was read silently as the indices; colour images are refused (docs/formats.md).
    """
    lut = (np.arange(256, dtype=np.uint16) * 256).tobytes()
    palette = {"PhotometricInterpretation": "PALETTE COLOR"}
    for c in ("Red", "Green", "Blue"):
        palette[f"{c}PaletteColorLookupTableDescriptor"] = [256, 0, 16]
        palette[f"{c}PaletteColorLookupTableData"] = lut
    stored = np.arange(3 * 4 * 5, dtype=np.int16).reshape(3, 4, 5) % 256
    write_series(tmp_path / "s", stored, shuffle=False, signed=False, per_slice=[palette] * 3)
    out = tmp_path / "o.nrrd"
    res = run("convert", tmp_path / "s", "-o", out)
    assert res.code == 1 and not out.exists(), res
    line, = res.stderr.strip().splitlines()
    assert line.startswith("volwarp: error: ") and "IM0000.dcm" in line, line
    assert "PALETTE COLOR" in line and "greyscale" in line, line
    with pytest.raises(FormatError, match="PALETTE COLOR"):  # pydicom's ultrasound sample
        read_dicom(get_testdata_file("OBXXXX1A_2frame.dcm"))
