"""NRRD fields other tools write, read as SimpleITK (and teem's documented meaning) read them.

A displacement field's ``measurement frame`` says along which axes its
vector components were measured (teem: the world vector is ``frame @ v``). A
RAS file whose frame is ``(-1,0,0) (0,-1,0) (0,0,1)`` holds LPS vectors: volwarp
turned them by the space's signs alone and moved every point mirrored in x
and y, where SimpleITK (which reads the components unchanged, as LPS) and
teem agree on the LPS vector. A field in microns (``space units: "um"``,
microscopy) had its grid read in millimetres and its vectors not: every
point moved 1000 times too far (SimpleITK reads every number of the three
files in microns alike, and warps as a consistent reading does).
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from volwarp_cli.transforms.fields import read_field

VECTOR = (2.0, 4.0, 6.0)  # LPS mm


def _ras_field(path, frame: str, vector=VECTOR, n: int = 12) -> None:
    """A RAS-space NRRD field of one vector everywhere, its components in ``frame``."""
    vec = np.zeros((n, n, n, 3), np.float32)
    vec[...] = vector
    header = (f"NRRD0004\ntype: float\ndimension: 4\nspace: right-anterior-superior\n"
              f"sizes: 3 {n} {n} {n}\n"
              "space directions: none (-2,0,0) (0,-2,0) (0,0,2)\n"
              "kinds: vector domain domain domain\nendian: little\nencoding: raw\n"
              "space origin: (12,12,-12)\n"
              f"measurement frame: {frame}\n\n")
    path.write_bytes(header.encode() + vec.tobytes())


def _moving(path) -> sitk.Image:
    z, y, x = np.indices((20, 20, 20)).astype(np.float32)
    img = sitk.GetImageFromArray(x + 10 * y + 100 * z)
    img.SetSpacing((2, 2, 2))
    img.SetOrigin((-20, -20, -20))
    sitk.WriteImage(img, str(path))
    return img


def test_a_ras_field_of_lps_components_moves_points_as_simpleitk(run, tmp_path):
    """`apply -t` a RAS field whose measurement frame makes its components LPS: SimpleITK's warp."""
    _ras_field(tmp_path / "f.nrrd", "(-1,0,0) (0,-1,0) (0,0,1)")
    moving = _moving(tmp_path / "m.nrrd")
    ref = sitk.Image(8, 8, 8, sitk.sitkFloat32)
    ref.SetSpacing((2, 2, 2))
    ref.SetOrigin((-8, -8, -8))
    sitk.WriteImage(ref, str(tmp_path / "ref.nrrd"))
    field = sitk.ReadImage(str(tmp_path / "f.nrrd"), sitk.sitkVectorFloat64)
    tx = sitk.DisplacementFieldTransform(field)
    assert tx.TransformPoint((0, 0, 0)) == pytest.approx(VECTOR)
    expected = sitk.GetArrayFromImage(sitk.Resample(moving, ref, tx, sitk.sitkLinear, 0.0))
    res = run("apply", tmp_path / "m.nrrd", "-t", tmp_path / "f.nrrd", "--reference",
              tmp_path / "ref.nrrd", "-o", tmp_path / "out.nrrd", "--interpolation", "linear")
    assert res.code == 0, res.stderr
    got = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "out.nrrd")))
    np.testing.assert_allclose(got, expected, atol=1e-3)


@pytest.mark.parametrize("by_windows", [False, True])
@pytest.mark.parametrize("frame, lps", [
    ("(-1,0,0) (0,-1,0) (0,0,1)", VECTOR),  # LPS components: SimpleITK's reading too
    ("(1,0,0) (0,1,0) (0,0,1)", (-2.0, -4.0, 6.0)),  # RAS components (no frame alike)
    ("(0,1,0) (-1,0,0) (0,0,1)", (4.0, -2.0, 6.0)),  # turned 90 degrees about z in RAS
])
def test_field_vectors_are_the_measurement_frame_times_the_components(tmp_path, monkeypatch,
                                                                      by_windows, frame, lps):
    """teem's meaning, RAS world ``frame @ v``, then to LPS; read whole and by windows alike."""
    from volwarp_cli import memory
    from volwarp_cli.io.inputs import claim_output
    from volwarp_cli.runscope import run_scope

    _ras_field(tmp_path / "f.nrrd", frame)
    if by_windows:
        monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    with run_scope():
        claim_output(tmp_path / "o.nrrd", "-o")
        field = read_field(str(tmp_path / "f.nrrd"), "nrrd")
        vectors = field.vectors if not by_windows else field.source.read((0, 0, 0), (12, 12, 12))
    assert (field.vectors is None) == by_windows
    np.testing.assert_allclose(vectors[3, 4, 5], lps, atol=1e-6)
    np.testing.assert_allclose(field.map(np.array([[0.0, 0.0, 0.0]]))[0], lps, atol=1e-5)


def _um_file(path, data: np.ndarray, sizes, dirs: str, kinds: str) -> None:
    """A LPS NRRD whose numbers are microns (``space units``), origin (-n, -n, -n)."""
    n = sizes[-1]
    header = (f"NRRD0004\ntype: float\ndimension: {len(sizes)}\nspace: left-posterior-superior\n"
              f"sizes: {' '.join(map(str, sizes))}\nspace directions: {dirs}\nkinds: {kinds}\n"
              f"endian: little\nencoding: raw\nspace origin: ({-n},{-n},{-n})\n"
              'space units: "um" "um" "um"\n\n')
    path.write_bytes(header.encode() + data.astype(np.float32).tobytes())


@pytest.mark.parametrize("by_windows", [False, True])
def test_a_field_in_microns_moves_points_by_microns(run, tmp_path, monkeypatch, by_windows):
    """`apply` of image, field and reference all in microns: SimpleITK's samples."""
    from volwarp_cli import memory

    z, y, x = np.indices((20, 20, 20)).astype(np.float32)
    axes = "(2,0,0) (0,2,0) (0,0,2)"
    _um_file(tmp_path / "m.nrrd", x + 10 * y + 100 * z, (20, 20, 20), axes, "domain domain domain")
    vec = np.zeros((12, 12, 12, 3), np.float32)
    vec[...] = VECTOR  # microns
    _um_file(tmp_path / "f.nrrd", vec, (3, 12, 12, 12), "none " + axes,
             "vector domain domain domain")
    _um_file(tmp_path / "ref.nrrd", np.zeros((8, 8, 8)), (8, 8, 8), axes, "domain domain domain")
    tx = sitk.DisplacementFieldTransform(sitk.ReadImage(str(tmp_path / "f.nrrd"),
                                                        sitk.sitkVectorFloat64))
    expected = sitk.GetArrayFromImage(sitk.Resample(
        sitk.ReadImage(str(tmp_path / "m.nrrd")), sitk.ReadImage(str(tmp_path / "ref.nrrd")),
        tx, sitk.sitkLinear, 0.0))
    args = ["apply", tmp_path / "m.nrrd", "-t", tmp_path / "f.nrrd", "--reference",
            tmp_path / "ref.nrrd", "-o", tmp_path / "out.nrrd", "--interpolation", "linear"]
    if by_windows:
        monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
        args += ["--chunked", "--block", "4,4,4"]
    res = run(*args)
    assert res.code == 0, res.stderr
    got = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "out.nrrd")))
    np.testing.assert_allclose(got, expected, atol=1e-3)


def test_kinds_and_space_directions_naming_different_component_axes_are_refused(tmp_path):
    """The component axis is the ``none`` direction's and the kinds' one, never a guess between.

    ``kinds: vector domain domain domain`` beside a last ``none`` direction:
    volwarp read the last axis (size 4) as the components, silently; ITK
    refuses the file (its direction comes out singular).
    """
    from volwarp_cli.errors import FormatError
    from volwarp_cli.io import read_components

    path = tmp_path / "f.nrrd"
    path.write_bytes(b"NRRD0004\ntype: float\ndimension: 4\nspace: left-posterior-superior\n"
                     b"sizes: 3 2 3 4\nspace directions: (1.5,0,0) (0,2,0) (0,0,3) none\n"
                     b"kinds: vector domain domain domain\nendian: little\nencoding: raw\n\n"
                     + np.zeros(72, np.float32).tobytes())
    with pytest.raises(RuntimeError):
        sitk.ReadImage(str(path))
    with pytest.raises(FormatError, match="'kinds'.*disagree"):
        read_components(path)
