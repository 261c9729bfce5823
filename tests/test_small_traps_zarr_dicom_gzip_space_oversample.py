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


def test_dicom_options_for_a_series_with_stray_zarr_metadata_name_it(run, tmp_path):
    """``--series 0`` on such a folder was refused as "ser is not one" (a DICOM input),
    though it holds a series: the refusal names the stray file, on the command line and
    through the API alike."""
    from volwarp_cli import api
    from volwarp_cli.errors import BadUsage

    folder = tmp_path / "ser"
    write_series(folder, np.arange(6 * 5 * 7, dtype=np.int16).reshape(6, 5, 7))
    (folder / ".zattrs").write_text("{}")
    res = run("convert", folder, "--series", "0", "-o", tmp_path / "o.nrrd")
    assert res.code == 2 and "holds Zarr metadata (.zattrs) beside its DICOM files" in res.stderr
    assert not (tmp_path / "o.nrrd").exists()
    with pytest.raises(BadUsage, match=r"move \.zattrs out of it"):
        api.read(folder, series=0)
    (folder / ".zattrs").unlink()
    assert api.read(folder, series=0).data.shape == (6, 5, 7)


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


# -- a gzip file named .nii (or .nrrd, .mha, .tif) ----------------------------------------


@pytest.fixture
def nifti_pair(tmp_path):
    nib = pytest.importorskip("nibabel")
    img = nib.Nifti1Image(np.arange(24, dtype=np.int16).reshape(2, 3, 4), np.diag([1., 2, 3, 1]))
    nib.save(img, str(tmp_path / "a.nii"))
    nib.save(img, str(tmp_path / "a.nii.gz"))
    return tmp_path / "a.nii", tmp_path / "a.nii.gz"


def test_a_gzipped_nii_is_refused_naming_gzip(run, nifti_pair, tmp_path):
    """nibabel's "Cannot work out file type" reached the user; nibabel and SimpleITK both
    refuse the file, so volwarp does not read it either, and says why."""
    nib = pytest.importorskip("nibabel")
    sitk = pytest.importorskip("SimpleITK")
    bad = tmp_path / "gz.nii"
    bad.write_bytes(nifti_pair[1].read_bytes())
    with pytest.raises(nib.filebasedimages.ImageFileError):
        nib.load(str(bad))
    with pytest.raises(RuntimeError):
        sitk.ReadImage(str(bad))
    with pytest.raises(FormatError, match=r"gzip-compressed.*rename it \.nii\.gz"):
        read_volume(bad)
    for args in (("info", bad), ("convert", bad, "-o", tmp_path / "o.nrrd")):
        res = run(*args)
        assert res.code == 1 and "gzip-compressed" in res.stderr, res
        assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o.nrrd").exists()


@pytest.mark.parametrize("out", ["o.nii", "o.nii.gz"])
def test_volwarp_writes_gzip_only_under_gz(run, nifti_pair, tmp_path, out):
    res = run("convert", nifti_pair[0], "-o", tmp_path / out, "--compress")
    assert res.code == 0, res
    assert ((tmp_path / out).read_bytes()[:2] == b"\x1f\x8b") == out.endswith(".gz")


@pytest.mark.parametrize("ext", ["nrrd", "mha", "tif"])
def test_other_formats_gzipped_whole_are_said_so(run, nifti_pair, tmp_path, ext):
    import gzip

    plain = tmp_path / f"v.{ext}"
    assert run("convert", nifti_pair[0], "-o", plain).code == 0
    bad = tmp_path / f"gz.{ext}"
    bad.write_bytes(gzip.compress(plain.read_bytes()))
    res = run("info", bad)
    assert res.code == 1 and "gzip-compressed as a whole" in res.stderr, res


# -- an oversample that leaves the domain coarser than the input -------------------------

BALL = "tests/data/ball_30_uint8.nrrd"  # 30^3, a 0/200 ball


def _spec(tmp_path, oversample, lattice=5):
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\nvalues: intensity\n"
                    f"capture: {{lattice: {lattice}, oversample: {oversample}}}\n"
                    "steps:\n  - move:\n      - {index: [2, 2, 2], by: [1.0, 0.0, 0.0]}\n")
    return spec


@pytest.mark.parametrize("frames", [False, True])
def test_a_domain_coarser_than_the_input_is_a_spec_error(run, tmp_path, frames):
    """Oversample 0.06 on lattice 5 left 2 domain voxels per axis for the ball's 30: an
    all-zero output with exit 0, warned only as "not an integer"."""
    out = ["--frames-to", tmp_path / "f{frame}.nrrd"] if frames else ["-o", tmp_path / "o.nrrd"]
    res = run("warp", BALL, "--spec", _spec(tmp_path, 0.06), *out)
    assert res.code == 2, res
    assert "w.yaml:4: capture.oversample:" in res.stderr
    assert "smallest oversample accepted is 0.94" in res.stderr
    assert list(tmp_path.glob("*.nrrd")) == []


def test_the_smallest_accepted_oversample_warps_the_ball(run, tmp_path):
    nrrd = pytest.importorskip("nrrd")
    assert run("warp", BALL, "--spec", _spec(tmp_path, 0.93), "-o", tmp_path / "o.nrrd").code == 2
    res = run("warp", BALL, "--spec", _spec(tmp_path, 0.94), "-o", tmp_path / "o.nrrd")
    assert res.code == 0, res
    out, _ = nrrd.read(str(tmp_path / "o.nrrd"))
    ball, _ = nrrd.read(BALL)
    assert abs(float(out.sum()) / float(ball.sum()) - 1) < 0.05


def test_capture_refuses_it_at_its_option(run, tmp_path):
    res = run("capture", BALL, "--lattice", "5", "--oversample", "0.06", "-o", tmp_path / "c.vwc")
    assert res.code == 2 and "--oversample" in res.stderr and "0.94" in res.stderr, res
    assert not (tmp_path / "c.vwc").exists()


@pytest.mark.parametrize("size", [1, 7, 30, 181, 512])
@pytest.mark.parametrize("count", [4, 5, 9, 40])
def test_too_coarse_is_a_domain_smaller_than_the_input(size, count):
    """Refused exactly where the domain (D = R ceil(k I / R)) has fewer voxels than the
    input, and the value the message gives is accepted, 0.01 less refused."""
    import math
    import re

    from volwarp_cli.bspline.lattice import Lattice, too_coarse

    shape, lattice = (size, 8, 8), (count, 5, 5)
    for k in [0.01, 0.06, 0.1, 0.25, 0.5, 0.75, 0.9, 0.99, 1, 1.5, 2]:
        why = too_coarse(shape, lattice, k)
        grid = Lattice.create(shape, lattice, 1.0)  # (not refused: oversample 1)
        domain = [r * max(1, math.ceil(k * n / r - 1e-9)) for n, r in zip(shape, grid.regions, strict=True)]
        assert (why is not None) == any(d < n for d, n in zip(domain, shape, strict=True)), (k, why)
        if why is not None:
            least = float(re.search(r"accepted is ([0-9.]+)", why).group(1))
            assert too_coarse(shape, lattice, least) is None
            assert least <= 1
            assert too_coarse(shape, lattice, least - 0.01) is not None
