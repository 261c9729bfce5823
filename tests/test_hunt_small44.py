"""Small traps: a stray Zarr file in a DICOM folder, SPACE= markers in mesh provenance,
a gzip file named .nii, and an oversample too coarse for a capture's lattice."""

from __future__ import annotations

import numpy as np
import pytest
from test_io_dicom import write_series

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume

# -- a stray .zattrs / zarr.json in a DICOM series folder -------------------------------


@pytest.mark.parametrize("stray, text", [(".zattrs", "{}"),
                                         ("zarr.json", '{"zarr_format": 3, "node_type": '
                                                       '"group", "attributes": {}}')])
def test_a_dicom_folder_with_stray_zarr_metadata_names_both(run, tmp_path, stray, text):
    """Refused as "no multiscales" only, the user (who has a DICOM series) was misled;
    it is not read as DICOM either (a Zarr store's chunks can pass for DICOM)."""
    folder = tmp_path / "series"
    write_series(folder, np.arange(6 * 5 * 7, dtype=np.int16).reshape(6, 5, 7))
    (folder / stray).write_text(text)
    with pytest.raises(FormatError, match=rf"DICOM files.*\({stray}\).*move {stray} out"):
        read_volume(folder)
    res = run("info", folder)
    assert res.code == 1 and "DICOM" in res.stderr and stray in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    (folder / stray).unlink()
    assert read_volume(folder).data.shape == (6, 5, 7)


def test_a_zarr_folder_without_dicom_keeps_its_message(tmp_path):
    folder = tmp_path / "store"
    folder.mkdir()
    (folder / ".zattrs").write_text("{}")
    with pytest.raises(FormatError, match="no OME-NGFF 'multiscales'") as err:
        read_volume(folder)
    assert "DICOM" not in str(err.value)
