"""Writing a SEG or RTSTRUCT against a reference folder holding several series.

``--series`` chooses the reference series when the input is a label map file:
before, the write said "choose one with --series", and ``--series`` said it
"applies to DICOM inputs" (it was passed to the NRRD's reader, never to the
reference's).
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

from test_dicom_seg import write_ct  # noqa: E402

from volwarp_cli.io import read_volume, write_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402
from volwarp_cli.volume import Volume  # noqa: E402

A_SHAPE, B_SHAPE = (4, 8, 9), (5, 10, 12)  # z, y, x


@pytest.fixture
def patient(tmp_path):
    """A folder with two series (different grids, one study), and a label map on the second's."""
    pat = tmp_path / "pat"
    study = pydicom.uid.generate_uid()
    write_ct(tmp_path / "a", A_SHAPE, spacing=(1.0, 1.0, 3.0), study_uid=study, seed=1)
    b_paths = write_ct(tmp_path / "b", B_SHAPE, spacing=(0.9, 0.6, 2.0), origin=(5.0, -3.0, 7.0),
                       study_uid=study, seed=2)
    pat.mkdir()
    for name in ("a", "b"):
        for f in (tmp_path / name).iterdir():
            f.rename(pat / f"{name}_{f.name}")
    uid_b = str(pydicom.dcmread(b_paths[0].parent.parent / "pat" / f"b_{b_paths[0].name}")
                .SeriesInstanceUID)
    b = read_dicom(pat, series=uid_b)
    lab = np.zeros(B_SHAPE, np.uint8)
    lab[1:4, 2:7, 3:9] = 4
    lab[2, 8, 10] = 9
    src = tmp_path / "lab.nii.gz"  # (no DICOM key/values: nothing names the series)
    write_volume(Volume(lab, spacing=b.spacing, origin=b.origin, direction=b.direction), src)
    return pat, uid_b, b, lab, src


@pytest.mark.parametrize("dicom_type", ["seg", "labelmap-seg", "rtstruct"])
def test_series_chooses_the_reference_series(patient, tmp_path, run, dicom_type):
    pat, uid_b, b, lab, src = patient
    out = tmp_path / "out.dcm"
    res = run("convert", src, "--reference", pat, "--dicom-type", dicom_type, "-o", out)
    assert res.code == 2 and "--series" in res.stderr and not out.exists()
    index = [c["series_uid"] for c in _candidates(run, pat)].index(uid_b)
    for choice in (uid_b, str(index)):
        res = run("convert", src, "--reference", pat, "--series", choice, "--dicom-type",
                  dicom_type, "-o", out)
        assert res.code == 0, res.stderr
        ds = pydicom.dcmread(out)
        if dicom_type == "rtstruct":
            refs = [se.SeriesInstanceUID for fr in ds.ReferencedFrameOfReferenceSequence
                    for st in fr.RTReferencedStudySequence for se in st.RTReferencedSeriesSequence]
        else:
            refs = [se.SeriesInstanceUID for se in ds.ReferencedSeriesSequence]
        assert refs == [uid_b]
        # read back on the chosen series: its grid, the map's labels
        back = read_dicom(out, reference=pat, series=uid_b)
        assert back.same_grid(b)
        want = lab if dicom_type != "seg" else np.select([lab == 4, lab == 9], [1, 2], 0)
        np.testing.assert_array_equal(back.data, want)
        nrrd = tmp_path / "back.nrrd"
        res = run("convert", out, "--reference", pat, "--series", choice, "-o", nrrd)
        assert res.code == 0, res.stderr
        np.testing.assert_array_equal(read_volume(nrrd).data, want)


def test_series_of_another_grid_is_the_grid_error(patient, tmp_path, run):
    pat, uid_b, b, lab, src = patient
    other = next(c["series_uid"] for c in _candidates(run, pat) if c["series_uid"] != uid_b)
    out = tmp_path / "out.dcm"
    res = run("convert", src, "--reference", pat, "--series", other, "--dicom-type", "seg",
              "-o", out)
    assert res.code == 1 and len(res.stderr.strip().splitlines()) == 1
    assert "is not the grid of the reference series" in res.stderr and not out.exists()


def _candidates(run, pat) -> list[dict]:
    import json

    res = run("info", pat, "--json")
    assert res.code == 0, res.stderr
    return json.loads(res.stdout)["candidates"]
