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


# -- no SPACE= marker in a mesh's provenance but volwarp's own ---------------------------


def _slicer_frame(path, fmt):
    """The frame 3D Slicer's vtkMRMLModelStorageNode reads (its search, on VTK's readers)."""
    vtk = pytest.importorskip("vtk")

    def search(text):
        return "RAS" if "SPACE=RAS" in text else "LPS" if "SPACE=LPS" in text else None

    if fmt == "obj":
        r = vtk.vtkOBJReader()
        r.SetFileName(str(path))
        r.Update()
        return search(r.GetComment() or "")
    if fmt == "ply":  # (the first comment naming a frame)
        r = vtk.vtkPLYReader()
        r.SetFileName(str(path))
        r.Update()
        found = (search(r.GetComments().GetValue(i))
                 for i in range(r.GetComments().GetNumberOfValues()))
        return next((f for f in found if f), None)
    r = vtk.vtkSTLReader() if fmt == "stl" else vtk.vtkPolyDataReader()
    r.SetFileName(str(path))
    r.Update()
    return search(r.GetHeader() or "")


@pytest.mark.parametrize("fmt", ["obj", "ply", "stl", "vtk", "vtp"])
def test_a_space_mark_in_an_input_name_is_not_written(run, tmp_path, fmt):
    """An input named x_SPACE=RAS.nrrd in an OBJ's comments made Slicer mirror the mesh."""
    nrrd = pytest.importorskip("nrrd")
    src = tmp_path / "x_SPACE=RAS.nrrd"
    nrrd.write(str(src), np.pad(np.ones((6, 6, 6), np.float32), 3), index_order="C")
    out = tmp_path / f"m.{fmt}"
    res = run("mesh", src, "--iso", "0.5", "-o", out)
    assert res.code == 0, res
    data = out.read_bytes()
    if fmt == "vtp":  # (Slicer reads a VTP's frame from its field data, not comments)
        assert data.count(b"SPACE=") == 0
    else:
        assert data.count(b"SPACE=") == 1 and data.count(b"SPACE=LPS") == 1
        assert _slicer_frame(out, fmt) == "LPS"
    if fmt in ("obj", "ply", "vtp"):  # (the provenance still names the input)
        assert b"volwarp_input=x_SPACE\\x3dRAS.nrrd" in data
