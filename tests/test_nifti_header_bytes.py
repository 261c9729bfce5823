"""volwarp's NIfTI-1 writer (no nibabel) against nibabel's: the same bytes, field by field.

The reference writes what volwarp wrote through nibabel before (``Nifti1Image``,
both forms set from one matrix with their codes, units, intent, description,
volwarp's extension, ``to_bytes``); the files must be equal byte for byte, for
grids of every orientation (left- and right-handed, oblique, sheared ones
refused before), every sample type volwarp writes, 3-D volumes and 5-D vector
fields, plain and gzipped. Then nibabel and SimpleITK read the written files.
"""

from __future__ import annotations

import gzip

import nibabel as nib
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.nifti import EXTENSION_CODE, _extension, ras_affine, write_nifti_file
from volwarp_cli.io.niftiheader import DATATYPE_CODES, rotation_quaternion
from volwarp_cli.volume import Volume

TYPES = sorted(DATATYPE_CODES, key=str)


def nibabel_bytes(data_xyz, aff, *, units, codes, intent=None, descrip="", meta=None):
    """What volwarp's writer wrote through nibabel (the code this writer replaced)."""
    img = nib.Nifti1Image(data_xyz, aff)
    header = img.header
    header["xyzt_units"] = units
    img.set_sform(aff, code=codes[0])
    img.set_qform(aff, code=codes[1])
    if intent is not None:
        code, params, name = intent
        header["intent_code"] = code
        for i, p in enumerate(params, 1):
            header[f"intent_p{i}"] = p
        header["intent_name"] = name[:15].encode("latin-1", errors="replace")
    if descrip:
        header["descrip"] = descrip[:79].encode("latin-1", errors="replace")
    ext = _extension(meta or {})
    if ext is not None:
        header.extensions.append(nib.nifti1.Nifti1Extension(*ext))
    return img.to_bytes()


def ours(tmp_path, name, data_xyz, aff, **kw) -> bytes:
    path = tmp_path / name
    write_nifti_file(path, data_xyz, aff, **kw)
    raw = path.read_bytes()
    return gzip.decompress(raw) if name.endswith(".gz") else raw


def grid_affine(rotvec, spacing, origin, flip: bool) -> np.ndarray:
    direction = Rotation.from_rotvec(rotvec).as_matrix()
    if flip:
        direction[:, 2] *= -1  # left-handed (qfac -1)
    vol = Volume(np.zeros((1, 1, 1)), spacing=np.asarray(spacing), origin=np.asarray(origin),
                 direction=direction)
    return ras_affine(vol)


@settings(max_examples=120, deadline=None)
@given(rotvec=st.lists(st.floats(-3.2, 3.2), min_size=3, max_size=3),
       spacing=st.lists(st.floats(1e-3, 50), min_size=3, max_size=3),
       origin=st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3),
       flip=st.booleans(), kind=st.sampled_from(TYPES),
       shape=st.tuples(st.integers(1, 5), st.integers(1, 5), st.integers(1, 5)),
       codes=st.tuples(st.integers(0, 5), st.integers(0, 5)), units=st.integers(0, 255),
       intent=st.none() | st.tuples(st.integers(-32768, 32767),
                                    st.lists(st.floats(-1e6, 1e6, width=32), min_size=3,
                                             max_size=3),
                                    st.text(max_size=20)),
       descrip=st.text(max_size=90), meta=st.dictionaries(st.text(max_size=8),
                                                           st.text(max_size=30), max_size=3))
def test_the_same_bytes_as_nibabel(tmp_path_factory, rotvec, spacing, origin, flip, kind,
                                   shape, codes, units, intent, descrip, meta):
    tmp = tmp_path_factory.mktemp("n")
    data = np.arange(np.prod(shape)).reshape(shape[::-1]).astype(kind)  # [z, y, x]
    aff = grid_affine(rotvec, spacing, origin, flip)
    kw = dict(units=units, codes=codes, intent=intent, descrip=descrip, meta=meta)
    want = nibabel_bytes(data.transpose(2, 1, 0), aff, **kw)
    assert ours(tmp, "a.nii", data.transpose(2, 1, 0), aff, **kw) == want


@pytest.mark.parametrize("kind", TYPES, ids=str)
def test_every_type_and_a_gzipped_vector_field(tmp_path, kind):
    rng = np.random.default_rng(1)
    field = rng.normal(size=(4, 5, 6, 3)).astype(np.float32)  # (z, y, x, 3)
    data5 = np.ascontiguousarray(field.transpose(2, 1, 0, 3))[:, :, :, None, :]
    aff = grid_affine([0.3, -0.2, 1.1], [0.9, 1.0, 1.25], [10.0, -20.0, 5.0], True)
    kw = dict(units=2, codes=(1, 1), intent=(1007, (0.0, 0.0, 0.0), ""),
              descrip="volwarp forward displacement field, LPS mm",
              meta={"volwarp_field": "forward"})
    assert ours(tmp_path, "f.nii.gz", data5, aff, **kw) == nibabel_bytes(data5, aff, **kw)
    info = np.iinfo(kind) if np.dtype(kind).kind in "iu" else np.finfo(kind)
    data = np.array([info.min, info.max, 0, 1], dtype=kind).reshape(1, 2, 2)
    big = data.astype(np.dtype(kind).newbyteorder(">"))  # (samples of the other byte order)
    kw = dict(units=10, codes=(2, 0))
    want = nibabel_bytes(data.transpose(2, 1, 0), aff, **kw)
    assert ours(tmp_path, "v.nii.gz", big.transpose(2, 1, 0), aff, **kw) == want


def test_readers_read_what_it_writes(tmp_path):
    """nibabel and SimpleITK (an independent NIfTI reader, ITK's) place the grid and read the
    samples and volwarp's key/values, left-handed and oblique."""
    import SimpleITK as sitk

    direction = Rotation.from_rotvec([0.2, -0.5, 0.7]).as_matrix()
    direction[:, 1] *= -1
    rng = np.random.default_rng(2)
    vol = Volume(rng.integers(-500, 500, size=(7, 6, 5)).astype(np.int16),
                 spacing=np.array([0.8, 1.1, 2.5]), origin=np.array([-90.0, 120.0, 33.0]),
                 direction=direction, meta={"volwarp_input": "scan.nrrd", "descrip": "a scan"})
    write_volume(vol, tmp_path / "v.nii.gz")
    img = sitk.ReadImage(str(tmp_path / "v.nii.gz"))
    np.testing.assert_array_equal(sitk.GetArrayFromImage(img), vol.data)
    np.testing.assert_allclose(img.GetSpacing(), vol.spacing, rtol=1e-6)
    np.testing.assert_allclose(img.GetOrigin(), vol.origin, atol=1e-4)
    np.testing.assert_allclose(np.reshape(img.GetDirection(), (3, 3)), vol.direction,
                               atol=1e-6)
    n = nib.load(tmp_path / "v.nii.gz")
    assert n.header.extensions[0].get_code() == EXTENSION_CODE
    assert n.header["descrip"].item() == b"a scan"
    back = read_volume(tmp_path / "v.nii.gz")
    np.testing.assert_array_equal(back.data, vol.data)
    assert back.meta["volwarp_input"] == "scan.nrrd" and back.meta["descrip"] == "a scan"


def test_the_quaternion_of_a_rotation():
    """A quarter turn about z is (cos 45, 0, 0, sin 45); the real part is never negative."""
    q = rotation_quaternion(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(q, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-12)
    for rotvec in ([3.1, 0, 0], [0, -3.0, 0.5], [1, 1, 1]):
        r = Rotation.from_rotvec(rotvec)
        q = rotation_quaternion(r.as_matrix())
        x, y, z, w = r.as_quat()
        assert q[0] >= 0
        np.testing.assert_allclose(q, np.sign(w or 1) * np.array([w, x, y, z]), atol=1e-12)


def test_a_size_nifti1_cannot_hold_is_refused_and_nothing_written(tmp_path):
    """Over 32767 samples along an axis: refused (nibabel wrote a line of them with
    FreeSurfer's dim[1] = -1, which ITK does not read as such)."""
    from volwarp_cli.errors import VolwarpError

    path = tmp_path / "long.nii"
    with pytest.raises(VolwarpError, match=r"at most 32767; write \.nrrd or \.mha"):
        write_nifti_file(path, np.zeros((40000, 1, 1), np.uint8), np.eye(4), units=2,
                         codes=(1, 1))
    assert not path.exists()


def test_writing_nifti_imports_no_nibabel(tmp_path):
    """A NIfTI output of another format's input costs no nibabel import (0.05 s a command)."""
    import subprocess
    import sys

    write_volume(Volume(np.arange(24, dtype=np.int16).reshape(2, 3, 4)), tmp_path / "v.nrrd")
    code = ("import sys\n"
            "from volwarp_cli.cli.main import main\n"
            f"assert main(['convert', r'{tmp_path / 'v.nrrd'}', '-o', r'{tmp_path / 'v.nii.gz'}'"
            "]) == 0\n"
            "assert 'nibabel' not in sys.modules, 'nibabel imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    np.testing.assert_array_equal(read_volume(tmp_path / "v.nii.gz").data,
                                  np.arange(24, dtype=np.int16).reshape(2, 3, 4))
