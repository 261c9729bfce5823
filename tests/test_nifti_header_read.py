"""volwarp's NIfTI header reader (no nibabel) against nibabel's: where it reads a header, the
same shape, type, offset, forms (bit for bit), fields and extensions; everything else it leaves
to nibabel.

Headers are made by changing random fields of valid ones (NIfTI-1 and -2, both byte orders,
with and without extensions) to values nibabel repairs, refuses or reads: sizes, magic,
dimensions, types, voxel sizes, qfac, offsets, codes, quaternions, scaling, CIFTI intents,
extension sizes.
"""

from __future__ import annotations

import gzip
import subprocess
import sys
import warnings

import nibabel as nib
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from volwarp_cli.io import read_volume
from volwarp_cli.io.nifti import header_without_nibabel, nibabel
from volwarp_cli.io.niftiheader import HEADER1, HEADER2, NiftiHeader, read_header

FIELD_VALUES = {
    "sizeof_hdr": [348, 540, 0, 1000],
    "dim": [[3, 4, 3, 2, 1, 1, 1, 1], [5, 2, 2, 2, 1, 3, 1, 1], [4, 2, 2, 2, 3, 1, 1, 1],
            [0, 1, 1, 1, 1, 1, 1, 1], [9, 2, 2, 2, 1, 1, 1, 1], [3, -1, 1, 1, 1, 1, 1, 1],
            [3, 0, 2, 2, 1, 1, 1, 1], [2, 5, 4, 1, 1, 1, 1, 1], [3, 27307, 1, 6, 1, 1, 1, 1]],
    "datatype": [2, 4, 8, 16, 64, 256, 512, 768, 1024, 32, 128, 0, 3, 1536],
    "bitpix": [8, 16, 32, 64, 0, 12],
    "pixdim": [[1, 1, 1, 1, 1, 1, 1, 1], [-1, 0.5, 2, 3.5, 0, 0, 0, 0], [0, 1, 1, 1, 1, 1, 1, 1],
               [1, -1, 1, 1, 1, 1, 1, 1], [1, 0, 1, 1, 1, 1, 1, 1], [2, 1, 1, 1, 1, 1, 1, 1],
               [1, np.nan, 1, 1, 1, 1, 1, 1], [1, 1e-3, 7e2, 1, 1, 1, 1, 1]],
    "vox_offset": [352, 368, 544, 560, 0, 100, 360, 352.5, 4096],
    "scl_slope": [0.0, 1.0, 2.0, np.nan, np.inf, -1.0],
    "scl_inter": [0.0, 1.0, np.nan],
    "qform_code": [0, 1, 2, 4, 5, 6, -1],
    "sform_code": [0, 1, 3, 5, 7],
    "quatern_b": [0.0, 0.5, 1.0, -0.7, 0.9],
    "quatern_c": [0.0, 0.5, -0.3, 1e-8],
    "quatern_d": [0.0, 0.5, 0.7071068, 0.1],
    "intent_code": [0, 1007, 1006, 3001, 3006, 2003],
    "xyzt_units": [0, 2, 10, 3],
    "qoffset_x": [0.0, -100.25, 1e6],
    "srow_x": [[1, 0, 0, 0], [0.5, 0.1, 0, -90], [0, 0, 0, 0]],
}


@st.composite
def headers(draw):
    version = draw(st.sampled_from([1, 2]))
    end = draw(st.sampled_from("<>"))
    dtype = (HEADER1 if version == 1 else HEADER2).newbyteorder(end)
    h = np.zeros((), dtype=dtype)
    h["sizeof_hdr"] = dtype.itemsize
    h["magic"] = b"n+1" if version == 1 else b"n+2"
    if version == 2:
        h["eol_check"] = (13, 10, 26, 10)
    h["dim"] = [3, 4, 3, 2, 1, 1, 1, 1]
    h["datatype"], h["bitpix"] = 4, 16
    h["pixdim"] = [1, 0.9, 1.1, 1.3, 1, 1, 1, 1]
    h["vox_offset"] = 352 if version == 1 else 544
    h["scl_slope"] = 1.0
    h["qform_code"], h["sform_code"] = 1, 1
    h["quatern_b"], h["quatern_c"], h["quatern_d"] = 0.1, -0.2, 0.3
    h["qoffset_x"], h["qoffset_y"], h["qoffset_z"] = 10.0, -20.5, 3.25
    h["srow_x"], h["srow_y"], h["srow_z"] = [0.9, 0, 0, 10.0], [0, 1.1, 0, -20.5], [0, 0, 1.3, 3]
    for name in draw(st.lists(st.sampled_from(sorted(FIELD_VALUES)), max_size=4, unique=True)):
        h[name] = draw(st.sampled_from(FIELD_VALUES[name]))
    if draw(st.booleans()):  # (any rotation: the quaternion's w and matrix to the bit)
        unit = st.floats(-0.5, 0.5, width=32 if version == 1 else 64)
        h["quatern_b"], h["quatern_c"], h["quatern_d"] = (draw(unit) for _ in range(3))
        h["pixdim"][0] = draw(st.sampled_from([1, -1]))
    if draw(st.integers(0, 9)) == 0:
        h["magic"] = draw(st.sampled_from([b"ni1", b"n+2", b"n+1", b"xyz"]))
    extensions = b""
    if draw(st.booleans()):
        for _ in range(draw(st.integers(1, 3))):
            content = draw(st.binary(max_size=40))
            size = len(content) + 8
            size += (16 - size % 16) % 16
            size = draw(st.sampled_from([size, size, size, size + 1, 8, 0]))
            code = draw(st.sampled_from([6, 2, 4, 40]))
            extensions += np.array([size, code], dtype=end + "i4").tobytes()
            extensions += content.ljust(max(size - 8, 0), b"\0")
        if draw(st.booleans()):  # the offset past them, as a writer sets it
            h["vox_offset"] = dtype.itemsize + 4 + len(extensions)
    flag = bytes([1 if extensions else draw(st.sampled_from([0, 0, 1])), 0, 0, 0])
    return h.tobytes() + flag + extensions + bytes(4096)


def fields_of(h):
    """What volwarp reads of a header (nibabel's or its own) and its image."""
    out = {}
    for coded in (True, False):
        for name in ("sform", "qform"):
            try:
                got = getattr(h, f"get_{name}")(coded=coded)
            except Exception as exc:  # (nibabel refuses a bad qfac, negative sizes)
                got = type(exc).__name__
            if isinstance(got, tuple):
                got = (None if got[0] is None else got[0].tolist(), got[1])
            elif isinstance(got, np.ndarray):
                got = got.tolist()
            out[name, coded] = repr(got)  # (every float in full: the matrices to the bit)
    for name in ("pixdim", "xyzt_units", "sform_code", "qform_code", "intent_code", "intent_p1",
                 "intent_p2", "intent_p3", "intent_name", "descrip", "dim"):
        out[name] = repr(np.asarray(h[name]).tolist())  # (NaN as text: equal to itself)
    out["extensions"] = [(int(e.get_code()), bytes(e.content)) for e in h.extensions]
    return out


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(block=headers(), name=st.sampled_from(["h.nii", "h.nii", "h.nii.gz", "h.nii.gz",
                                              "H.NII.GZ", "gz.nii", "plain.nii.gz", "h.hdr",
                                              "h", "cut.nii.gz"]))
def test_where_it_reads_a_header_nibabel_reads_the_same(tmp_path_factory, block, name):
    """Files named and compressed as nibabel finds them, or not (a gzip .nii, a plain .nii.gz,
    other names, a gzip stream whose end is cut)."""
    path = tmp_path_factory.mktemp("h") / name
    gzipped = name.lower().endswith(".gz") != name.startswith(("gz", "plain"))
    raw = gzip.compress(block[:700] if name.startswith("cut") else block) if gzipped else block
    path.write_bytes(raw[:-8] if name.startswith("cut") else raw)
    ours = header_without_nibabel(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            img = nibabel().load(path, mmap=False)
        except Exception:
            img = None
    if ours is None:
        return  # (left to nibabel: the reader as before)
    assert isinstance(ours, NiftiHeader)
    assert img is not None and type(img) in (nib.Nifti1Image, nib.Nifti2Image)
    proxy = img.dataobj
    assert (float(proxy.slope), float(proxy.inter)) == (1.0, 0.0)
    assert (ours.shape, ours.dtype, ours.offset) == (img.shape, np.dtype(proxy.dtype),
                                                     int(proxy.offset))
    assert fields_of(ours) == fields_of(img.header)


def test_it_reads_the_files_volwarp_simpleitk_and_nibabel_write(tmp_path):
    """The usual files are read without nibabel: NIfTI-1 and -2, gzipped, both byte orders,
    5-D vector fields, extensions."""
    import SimpleITK as sitk

    data = np.arange(60, dtype=np.int16).reshape(5, 4, 3)
    made = []
    img = sitk.GetImageFromArray(data)
    img.SetSpacing((0.5, 0.7, 1.2))
    sitk.WriteImage(img, str(tmp_path / "s.nii.gz"))
    made.append(tmp_path / "s.nii.gz")
    field = sitk.GetImageFromArray(np.ones((5, 4, 3, 3)), isVector=True)
    sitk.WriteImage(field, str(tmp_path / "f.nii.gz"))
    made.append(tmp_path / "f.nii.gz")
    for klass, name in ((nib.Nifti1Image, "n1.nii"), (nib.Nifti2Image, "n2.nii")):
        for end in "<>":
            image = klass(data.transpose(2, 1, 0).astype(end + "i2"), np.diag([2, 3, 4, 1.0]))
            image.header.extensions.append(nib.nifti1.Nifti1Extension(6, b"a comment"))
            nib.save(image, tmp_path / f"{end == '>'}{name}")
            made.append(tmp_path / f"{end == '>'}{name}")
    for path in made:
        raw = path.read_bytes()
        if raw[:2] == b"\x1f\x8b":
            import gzip

            raw = gzip.decompress(raw)
        ours = read_header(lambda n, raw=raw: raw[:n])
        assert ours is not None, path
        assert fields_of(ours) == fields_of(nib.load(path).header)
    code = ("import sys\n"
            "from volwarp_cli.io import read_volume\n"
            f"paths = {[str(p) for p in made if 'f.nii' not in str(p)]}\n"
            "for p in paths:\n"
            "    read_volume(p)\n"
            "assert 'nibabel' not in sys.modules, 'nibabel imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    np.testing.assert_array_equal(read_volume(tmp_path / "s.nii.gz").data, data)
    np.testing.assert_array_equal(read_volume(tmp_path / "True" "n2.nii").data, data)
