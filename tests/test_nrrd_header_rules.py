"""NRRD space and kinds fields read as teem and ITK (SimpleITK) read them, or refused.

Reference: SimpleITK reads each file (teem's NrrdIO inside ITK's NrrdImageIO). Where it
places the samples, volwarp places them at the same physical points; where teem refuses
the header, volwarp refuses it with one line naming the file and the field (exit 1,
nothing written): before, each of these was read, some with the origin dropped or an
axis mirrored, exit 0.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume
from volwarp_cli.io.lazy import open_volume_lazy

DATA = np.arange(2 * 3 * 4, dtype=np.uint8).reshape(4, 3, 2)
HEAD = "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 3 4\nencoding: raw\n"
INDICES = [(0, 0, 0), (1, 2, 3), (1, 0, 2)]


def _file(tmp_path, fields: str, head: str = HEAD, data: bytes = DATA.tobytes()):
    path = tmp_path / "v.nrrd"
    path.write_bytes(f"{head}{fields}\n".encode() + data)
    return path


def _refused(path, run, match: str) -> None:
    """SimpleITK refuses the file; so do volwarp's readers, whole and by box, and convert."""
    with pytest.raises(RuntimeError):
        sitk.ReadImage(str(path))
    for read in (read_volume, open_volume_lazy):
        with pytest.raises(FormatError, match=match):
            read(path)
    out = path.parent / "out.nii.gz"
    res = run("convert", path, "-o", out)
    assert res.code == 1 and res.stderr.strip().count("\n") == 0, res.stderr
    assert str(path) in res.stderr and not out.exists()


def test_space_origin_of_a_space_without_directions_is_itks_origin(tmp_path):
    """``space: LPS`` and ``space origin`` without ``space directions``: ITK places the first
    voxel at the origin (spacing 1); volwarp dropped the origin (0, 0, 0), exit 0."""
    path = _file(tmp_path, "space: left-posterior-superior\nspace origin: (10,-20,30.5)\n")
    itk = sitk.ReadImage(str(path))
    for vol in (read_volume(path), open_volume_lazy(path)[0]):
        for index in INDICES:
            world = vol.origin + vol.direction @ (vol.spacing * np.array(index))
            np.testing.assert_allclose(world, itk.TransformIndexToPhysicalPoint(index))
    assert np.array_equal(read_volume(path).data, sitk.GetArrayFromImage(itk))


@pytest.mark.parametrize("fields, name", [
    ("space directions: (0,2,0) (-1,0,0) (0,0,3)\nspace origin: (10,20,30)\n",
     "space directions"),
    ("spacings: 1 2 3\nspace origin: (10,20,30)\n", "space origin"),
    ("spacings: 1 2 3\nspace units: \"cm\" \"cm\" \"cm\"\n", "space units"),
    ("spacings: 1 2 3\nmeasurement frame: (1,0,0) (0,1,0) (0,0,1)\n", "measurement frame"),
], ids=["directions", "origin", "space-units", "measurement-frame"])
def test_space_fields_without_a_space_are_refused_as_teem_refuses_them(tmp_path, run, fields,
                                                                       name):
    """teem needs ``space`` or ``space dimension`` before any of these; volwarp read the
    directions as frameless, dropped the origin and the centimetres, exit 0."""
    _refused(_file(tmp_path, fields), run, f"'{name}' without 'space' or 'space dimension'")


@pytest.mark.parametrize("fields, match", [
    ("space dimension: 4\nspace directions: (0,2,0) (-1,0,0) (0,0,3)\n",
     "'space dimension' must be 3"),
    ("space dimension: three\nspace directions: (0,2,0) (-1,0,0) (0,0,3)\n",
     "'space dimension' must be 3"),
    ("space: RAS\nspace dimension: 3\nspace directions: (0,2,0) (-1,0,0) (0,0,3)\n",
     "'space' and 'space dimension' are both given"),
], ids=["four", "word", "both"])
def test_a_space_dimension_teem_refuses_is_refused(tmp_path, run, fields, match):
    """``space dimension`` was never read: a 4-D space of 3-vectors, or one beside a
    ``space``, gave a volume."""
    _refused(_file(tmp_path, fields), run, match)


@pytest.mark.parametrize("fields, name", [
    ("space: LPS\nspacings: 1 2 3\nspace origin: (10,20,30)\n", "spacings"),
    ("space: LPS\naxis mins: 10 20 30\naxis maxs: 12 26 42\n", "axis mins"),
    ("space dimension: 3\naxis maxs: 12 26 42\nspacings: nan nan nan\naxis mins: 10 20 30\n",
     "axis mins"),
    ("space: RAS\nspace origin: (10,20,30)\n", "space: RAS"),
], ids=["spacings", "mins-maxs", "space-dimension-mins", "ras"])
def test_axis_placement_in_a_space_without_directions_is_refused(tmp_path, run, fields, name):
    """A space without ``space directions`` gives its axes no direction. ITK refuses
    ``spacings`` there (nrrdSpacingStatusScalarWithSpace) and ignores ``axis mins`` (origin
    0 where volwarp took (10.5, 21, 31.5)); a RAS space is mirrored by volwarp and not by ITK
    (its voxel (1, 2, 3) at (-1, -2, 3) against ITK's (-9, -18, 33)). One line, naming the
    field: where ITK reads such a file, its placement is not the header's."""
    path = _file(tmp_path, fields)
    for read in (read_volume, open_volume_lazy):
        with pytest.raises(FormatError, match=f"'{name}'.* without 'space directions'"):
            read(path)
    res = run("convert", path, "-o", tmp_path / "out.nrrd")
    assert res.code == 1 and name in res.stderr and not (tmp_path / "out.nrrd").exists()


def test_units_beside_space_directions_are_refused_as_teem_refuses_them(tmp_path, run):
    """``units: "cm" "cm" "cm"`` beside ``space directions`` (teem: an axis with a direction
    takes no units) was dropped: the numbers read as millimetres, exit 0."""
    fields = ("space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n"
              'units: "cm" "cm" "cm"\n')
    _refused(_file(tmp_path, fields), run, "'units' beside 'space directions'")


FOUR = ("NRRD0004\ntype: uint8\ndimension: 4\nsizes: {n} 2 3 4\nencoding: raw\n"
        "space: left-posterior-superior\n"
        "space directions: none (1,0,0) (0,1,0) (0,0,1)\n")


@pytest.mark.parametrize("kind, n, match", [
    ("3-vector", 4, "a 3-vector axis has 3 samples, axis 0 has 4"),
    ("RGB-color", 2, "a RGB-color axis has 3 samples, axis 0 has 2"),
    ("quaternion", 3, "a quaternion axis has 4 samples, axis 0 has 3"),
    ("3D-symmetric-matrix", 5, "a 3D-symmetric-matrix axis has 6 samples, axis 0 has 5"),
    ("complex", 3, "a complex axis has 2 samples, axis 0 has 3"),
    ("vektor", 3, "'vektor' .axis 0. is not a NRRD kind"),
], ids=["3-vector", "rgb", "quaternion", "sym-matrix", "complex", "unknown"])
def test_a_kind_whose_axis_has_another_size_is_refused(tmp_path, run, kind, n, match):
    """teem refuses a kind whose axis is not its size (nrrdKindSize) and a kind it does not
    know; volwarp read the axis as that many components, exit 0."""
    data = np.arange(n * 24, dtype=np.uint8).tobytes()
    path = _file(tmp_path, f"kinds: {kind} domain domain domain\n", FOUR.format(n=n), data)
    with pytest.raises(RuntimeError):
        sitk.ReadImage(str(path))
    with pytest.raises(FormatError, match=f"'kinds': {match}"):
        read_volume(path, volume_index=0)
    res = run("convert", path, "-o", tmp_path / "out.nrrd", "--volume-index", "0")
    assert res.code == 1 and "'kinds'" in res.stderr and not (tmp_path / "out.nrrd").exists()


@pytest.mark.parametrize("kinds, match", [
    ("domain domain", "'kinds' has 2 entries, 'dimension' is 3"),
    ("domain domain domain domain", "'kinds' has 4 entries, 'dimension' is 3"),
    ("stub domain domain", "a stub axis has 1 sample, axis 0 has 2"),
])
def test_kinds_teem_refuses_in_a_3d_file_are_refused(tmp_path, run, kinds, match):
    """A ``kinds`` of the wrong count was ignored (the volume read), as teem refuses it."""
    fields = f"space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\nkinds: {kinds}\n"
    _refused(_file(tmp_path, fields), run, match)


@pytest.mark.parametrize("kind, n", [("3-vector", 3), ("RGB", 3), ("vector", 5),
                                     ("2-vector", 2), ("quaternion", 4)])
def test_kinds_of_their_size_still_read_as_simpleitk_reads_them(tmp_path, kind, n):
    data = np.arange(n * 24, dtype=np.uint8)
    path = _file(tmp_path, f"kinds: {kind} domain domain domain\n", FOUR.format(n=n),
                 data.tobytes())
    itk = sitk.GetArrayFromImage(sitk.ReadImage(str(path))).reshape(4, 3, 2, n)
    for c in range(n):
        assert np.array_equal(read_volume(path, volume_index=c).data, itk[..., c])


@pytest.mark.parametrize("encoding, body", [
    ("ascii", b"1500 " + " ".join(map(str, range(1, 24))).encode()),
    ("hex", b"ffee" + np.arange(24, dtype="<i2").tobytes().hex().encode()),
], ids=["ascii", "hex"])
def test_a_byte_skip_of_ascii_and_hex_data_is_skipped_as_teem_skips_it(tmp_path, encoding,
                                                                       body):
    """teem skips ``byte skip`` bytes before ascii and hex samples too; volwarp ignored it:
    ``1500 1 2 ...`` with a skip of 2 was read 1500, 1, 2 (SimpleITK: 0, 1, 2), exit 0."""
    head = HEAD.replace("uint8", "short").replace("encoding: raw", f"encoding: {encoding}")
    fields = ("endian: little\nspace: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n"
              f"byte skip: {2 if encoding == 'ascii' else 4}\n")
    path = _file(tmp_path, fields, head, body)
    itk = sitk.GetArrayFromImage(sitk.ReadImage(str(path)))
    assert np.array_equal(read_volume(path).data, itk)
    assert np.array_equal(itk.ravel(), np.arange(24))


def test_a_byte_skip_of_minus_one_in_ascii_is_refused_as_teem_refuses_it(tmp_path, run):
    """-1 (the samples are the file's last bytes) is raw data's: teem refuses it for ascii."""
    head = HEAD.replace("encoding: raw", "encoding: ascii")
    _refused(_file(tmp_path, "byte skip: -1\n", head, " ".join(map(str, range(24))).encode()),
             run, "'byte skip: -1'.*needs raw encoding")


def test_integer_ascii_samples_written_as_decimals_are_their_numbers_and_said(tmp_path, run):
    """``numpy.savetxt``'s ``-5.000e+01`` in a ``short`` file: volwarp reads -50 (MetaIO
    reads its ascii so), teem and SimpleITK -5 (the digits before the '.'): the two
    differed without a word; now a warning names the file."""
    import io

    text = io.StringIO()
    np.savetxt(text, np.arange(24.0) * 10 - 50)
    head = HEAD.replace("uint8", "short").replace("encoding: raw", "encoding: ascii")
    path = _file(tmp_path, "space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n", head,
                 text.getvalue().encode())
    assert sitk.GetArrayFromImage(sitk.ReadImage(str(path))).ravel()[0] == -5  # (documented)
    res = run("convert", path, "-o", tmp_path / "o.nrrd")
    assert res.code == 0 and "integer samples written as decimals" in res.stderr
    assert np.array_equal(read_volume(tmp_path / "o.nrrd").data.ravel(), np.arange(24) * 10 - 50)
