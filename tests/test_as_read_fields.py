"""Header fields true of the samples as read: kept by convert, dropped by what computes samples.

`convert` promises to keep a file's geometry and key/values, but dropped without a
word a NIfTI's display window (cal_min/cal_max), its frequency/phase/slice axes
(dim_info), its slice timing (slice_code/start/end/duration), toffset and aux_file
(FSL's lookup table name), and an NRRD's `sample units`, `thicknesses` and `labels`.
They are kept now, through every format (checked with nibabel and pynrrd), and a
command that computes new samples (warp, apply, distance) drops them: a stale window
would hide the new values, a slice timing or thickness is no longer the
acquisition's, a distance map's units are millimetres.
"""

from __future__ import annotations

import nibabel as nib
import nrrd
import numpy as np
import pytest

from volwarp_cli import provenance
from volwarp_cli.io import metaimage as metaimage_io
from volwarp_cli.io import nifti as nifti_io
from volwarp_cli.io import nrrd as nrrd_io

FIELDS = {"cal_min": 0.125, "cal_max": 0.875, "toffset": 2.5, "slice_duration": 0.0625,
          "slice_start": 1, "slice_end": 8, "slice_code": 3, "aux_file": b"lut.txt"}
SAMPLES = np.random.default_rng(0).random((8, 9, 10)).astype(np.float32)  # (x, y, z)
WARP = ("version: 1\ncapture: {lattice: 5, oversample: 1}\npushforward: box\nsteps:\n"
        "  - move:\n      - {index: [2, 2, 2], by: [1.0, 0.5, 0.2]}\n")


@pytest.fixture
def nii(tmp_path):
    img = nib.Nifti1Image(SAMPLES, np.diag([0.8, 0.9, 1.1, 1.0]))
    header = img.header
    header["descrip"] = b"T1 from scanner X"
    header.set_dim_info(freq=0, phase=1, slice=2)
    for name, value in FIELDS.items():
        header[name] = value
    path = tmp_path / "in.nii"
    nib.save(img, str(path))
    return path


def _fields(path) -> dict:
    header = nib.load(str(path)).header
    got = {name: header[name].item() for name in FIELDS}
    got["dim_info"] = header.get_dim_info()
    return got


def _want() -> dict:
    return {**FIELDS, "dim_info": (0, 1, 2)}


@pytest.mark.parametrize("route", [[".nii"], [".nii.gz"], [".nrrd", ".nii"], [".nhdr", ".nii"],
                                   [".mha", ".nii"], [".ome.zarr", ".nii"]],
                         ids=lambda r: "->".join(r))
def test_convert_keeps_a_niftis_fields_through_every_format(run, nii, tmp_path, route):
    """Before: every one of them 0 or empty in the output."""
    src = nii
    for k, ext in enumerate(route):
        out = tmp_path / f"out{k}{ext}"
        r = run("convert", src, "-o", out)
        assert r.code == 0, r
        src = out
    want = _want()
    samples = np.asarray(nib.load(str(src)).dataobj)
    if ".ome.zarr" in route:  # (stored flipped to the identity direction: the slice axis
        # and numbers of the file's index order are not the store's, and go)
        want.update(dim_info=(None, None, None), slice_start=0, slice_end=0, slice_code=0)
        samples = samples[::-1, ::-1, :]  # (the geometry follows: the same image)
    assert _fields(src) == want
    assert nib.load(str(src)).header["descrip"].item() == b"T1 from scanner X"
    assert np.array_equal(samples, SAMPLES)


@pytest.mark.parametrize("command", ["warp", "distance"])
def test_computed_samples_carry_none_of_them(run, nii, tmp_path, command):
    """A warp's or a distance's new samples: no stale window, timing or slice axis; the
    description stays."""
    out = tmp_path / "out.nii"
    if command == "warp":
        spec = tmp_path / "w.yaml"
        spec.write_text(WARP)
        r = run("warp", nii, "--spec", spec, "-o", out)
    else:
        r = run("distance", nii, "--iso", "0.5", "--values", "intensity", "-o", out)
    assert r.code == 0, r
    got = _fields(out)
    assert got["dim_info"] == (None, None, None)
    assert all(not got[name] for name in FIELDS), got
    assert nib.load(str(out)).header["descrip"].item() == b"T1 from scanner X"


NRRD_HEADER = """NRRD0005
type: float
dimension: 3
space: left-posterior-superior
sizes: 8 9 10
space directions: (0.8,0,0) (0,0.9,0) (0,0,1.1)
kinds: domain domain domain
labels: "left right" "y" "z"
sample units: HU
thicknesses: nan nan 2.5
endian: little
encoding: raw
space origin: (1,2,3)

"""


@pytest.fixture
def nrrd_in(tmp_path):
    path = tmp_path / "in.nrrd"
    path.write_bytes(NRRD_HEADER.encode() + SAMPLES.tobytes(order="F"))
    return path


@pytest.mark.parametrize("route", [[".nrrd"], [".nhdr"], [".nii", ".nrrd"], [".mha", ".nrrd"]],
                         ids=lambda r: "->".join(r))
def test_convert_keeps_an_nrrds_sample_units_thicknesses_and_labels(run, nrrd_in, tmp_path,
                                                                    route):
    """Before: the three fields were not written back (pynrrd read none of them)."""
    src = nrrd_in
    for k, ext in enumerate(route):
        out = tmp_path / f"out{k}{ext}"
        assert run("convert", src, "-o", out).code == 0
        src = out
    data, header = nrrd.read(str(src))
    assert header["sample units"] == "HU"
    assert header["labels"] == ["left right", "y", "z"]
    assert np.isnan(header["thicknesses"][:2]).all() and header["thicknesses"][2] == 2.5
    assert np.array_equal(data, SAMPLES)


def test_a_warp_of_an_nrrd_drops_them(run, nrrd_in, tmp_path):
    spec = tmp_path / "w.yaml"
    spec.write_text(WARP)
    out = tmp_path / "w.nrrd"
    assert run("warp", nrrd_in, "--spec", spec, "-o", out).code == 0
    header = nrrd.read_header(str(out))
    assert not {"sample units", "thicknesses", "labels"} & set(header)


def test_the_per_axis_fields_of_a_4d_file_are_not_given_to_one_of_its_volumes(run, tmp_path):
    """A component read from a 4-D NRRD: its thicknesses name four axes, the output has three."""
    path = tmp_path / "v.nrrd"
    header = NRRD_HEADER.replace("dimension: 3", "dimension: 4").replace(
        "sizes: 8 9 10", "sizes: 2 8 9 10").replace(
        "space directions: (", "space directions: none (").replace(
        "kinds: domain", "kinds: vector domain").replace(
        'labels: "left right"', 'labels: "c" "left right"').replace(
        "thicknesses: nan", "thicknesses: nan nan")
    both = np.stack([SAMPLES, SAMPLES + 1])  # (component first: fastest in the file)
    path.write_bytes(header.encode() + both.transpose(3, 2, 1, 0).tobytes())
    out = tmp_path / "c1.nrrd"
    r = run("convert", path, "--volume-index", "1", "-o", out)
    assert r.code == 0, r
    data, got = nrrd.read(str(out))
    assert got["sample units"] == "HU"  # (of every component's samples)
    assert "thicknesses" not in got and "labels" not in got
    assert np.array_equal(data, SAMPLES + 1)


def test_the_keys_commands_drop_are_the_readers_fields():
    readers = (set(nifti_io.AS_READ_FIELDS) | {f"NRRD_{n}" for n in nrrd_io.AS_READ_FIELDS}
               | {metaimage_io.PREFIX + n for n in metaimage_io.AS_READ_FIELDS})
    assert provenance.AS_READ_KEYS == readers
    assert provenance.AS_READ_AXIS_KEYS < provenance.AS_READ_KEYS


def test_a_store_of_an_unflipped_grid_keeps_the_slice_fields(run, tmp_path):
    """Only a reindexed store drops them: one whose direction is the identity stores the
    file's own index order."""
    img = nib.Nifti1Image(SAMPLES, np.diag([-0.8, -0.9, 1.1, 1.0]))  # (LPS identity)
    img.header.set_dim_info(freq=0, phase=1, slice=2)
    img.header["slice_start"], img.header["slice_end"], img.header["slice_code"] = 1, 8, 3
    src = tmp_path / "lps.nii"
    nib.save(img, str(src))
    assert run("convert", src, "-o", tmp_path / "s.ome.zarr").code == 0
    assert run("convert", tmp_path / "s.ome.zarr", "-o", tmp_path / "b.nii").code == 0
    header = nib.load(str(tmp_path / "b.nii")).header
    assert header.get_dim_info() == (0, 1, 2)
    assert (header["slice_start"], header["slice_end"], header["slice_code"]) == (1, 8, 3)


def test_a_distance_of_a_metaimage_drops_its_samples_range(run, tmp_path):
    """ElementMin/ElementMax say the samples' range: a distance map's is another (it kept
    the input's 0..1); convert keeps them, with the rest of the header."""
    header = ("ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
              "TransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = 1 2 3\nElementSpacing = 0.8 0.9 1.1\n"
              "Modality = MET_MOD_MR\nElementMin = 0\nElementMax = 1\nDimSize = 8 9 10\n"
              "ElementType = MET_FLOAT\nElementDataFile = LOCAL\n")
    src = tmp_path / "in.mha"
    src.write_bytes(header.encode() + SAMPLES.tobytes(order="F"))
    assert run("convert", src, "-o", tmp_path / "c.mha").code == 0
    assert run("distance", src, "--iso", "0.5", "--values", "intensity",
               "-o", tmp_path / "d.mha").code == 0

    def fields(path):
        head = path.read_bytes().split(b"ElementDataFile")[0].decode()
        return dict(line.split(" = ", 1) for line in head.splitlines())

    assert fields(tmp_path / "c.mha")["ElementMax"] == "1"
    got = fields(tmp_path / "d.mha")
    assert "ElementMin" not in got and "ElementMax" not in got
    assert got["Modality"] == "MET_MOD_MR"


@pytest.mark.parametrize("line, said", [
    ("thicknesses: a b c", "'thicknesses' must be numbers"),
    ("thicknesses: 1 2", "'thicknesses' has 2 entries, 'dimension' is 3"),
    ("labels: x y z", "'labels' must be 3 quoted strings"),
    ('labels: "x" "y"', "'labels' must be 3 quoted strings")])
def test_a_malformed_per_axis_field_is_one_line_naming_it(run, tmp_path, line, said):
    """Kept and written back as read, a malformed thicknesses or labels made an output
    pynrrd (and teem) refuse: refused when read, as every malformed field is."""
    src = tmp_path / "in.nrrd"
    text = NRRD_HEADER.replace('labels: "left right" "y" "z"\n', "").replace(
        "thicknesses: nan nan 2.5\n", line + "\n")
    src.write_bytes(text.encode() + SAMPLES.tobytes(order="F"))
    out = tmp_path / "out.nrrd"
    r = run("convert", src, "-o", out)
    assert r.code == 1 and r.stderr.splitlines() == [r.stderr.strip()], r.stderr
    assert str(src) in r.stderr and said in r.stderr, r.stderr
    assert not out.exists()
