"""NIfTI-1 header bytes, written without nibabel (its import is 0.05 s of every NIfTI write).

The single-file layout (``n+1``): the 348-byte header, the 4-byte extension flag,
the extensions (each ``esize``, ``ecode``, the content padded with NULs to a
multiple of 16 bytes), then the samples from ``vox_offset`` = 352 + the
extensions' sizes, x fastest. Fields as nibabel's ``Nifti1Image.to_bytes`` sets
them for the same image (``tests/test_nifti_header_bytes.py`` compares the bytes
of both for many grids, types and key/values): ``scl_slope`` 1 and ``scl_inter``
0 (the samples as they are), ``pixdim`` 1 beyond the voxel sizes, every other
field zero or empty but those given.

The qform holds a rotation, a handedness ``qfac`` (``pixdim[0]``) and the voxel
sizes (``pixdim[1:4]``): the columns' lengths are the sizes; the nearest rotation
to the normalised columns (polar decomposition by SVD, the last column flipped
first where the determinant is negative) is stored as the quaternion of largest
eigenvalue of Bar-Itzhack's symmetric matrix, with a positive real part.

Reference: the NIfTI-1 header, ``nifti1.h`` (NIfTI Data Format Working Group,
2004); I. Y. Bar-Itzhack, "New method for extracting the quaternion from a
rotation matrix", J. Guidance, Control and Dynamics 23(6), 2000.
"""

from __future__ import annotations

import numpy as np

#: NIfTI-1's header fields, in order (348 bytes, native byte order)
HEADER1 = np.dtype([
    ("sizeof_hdr", "i4"), ("data_type", "S10"), ("db_name", "S18"), ("extents", "i4"),
    ("session_error", "i2"), ("regular", "S1"), ("dim_info", "u1"), ("dim", "i2", (8,)),
    ("intent_p1", "f4"), ("intent_p2", "f4"), ("intent_p3", "f4"), ("intent_code", "i2"),
    ("datatype", "i2"), ("bitpix", "i2"), ("slice_start", "i2"), ("pixdim", "f4", (8,)),
    ("vox_offset", "f4"), ("scl_slope", "f4"), ("scl_inter", "f4"), ("slice_end", "i2"),
    ("slice_code", "u1"), ("xyzt_units", "u1"), ("cal_max", "f4"), ("cal_min", "f4"),
    ("slice_duration", "f4"), ("toffset", "f4"), ("glmax", "i4"), ("glmin", "i4"),
    ("descrip", "S80"), ("aux_file", "S24"), ("qform_code", "i2"), ("sform_code", "i2"),
    ("quatern_b", "f4"), ("quatern_c", "f4"), ("quatern_d", "f4"), ("qoffset_x", "f4"),
    ("qoffset_y", "f4"), ("qoffset_z", "f4"), ("srow_x", "f4", (4,)), ("srow_y", "f4", (4,)),
    ("srow_z", "f4", (4,)), ("intent_name", "S16"), ("magic", "S4"),
])
assert HEADER1.itemsize == 348

#: numpy sample types -> NIfTI ``datatype`` codes (the types volwarp writes)
DATATYPE_CODES = {
    np.dtype(np.uint8): 2, np.dtype(np.int16): 4, np.dtype(np.int32): 8,
    np.dtype(np.float32): 16, np.dtype(np.float64): 64, np.dtype(np.int8): 256,
    np.dtype(np.uint16): 512, np.dtype(np.uint32): 768,
}

_DIM_MAX = np.iinfo(np.int16).max


def rotation_quaternion(rotation: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z), w >= 0, nearest to a 3x3 rotation matrix.

    Bar-Itzhack's method: the eigenvector of the largest eigenvalue of a
    symmetric 4x4 matrix made from the entries (robust to a matrix that is
    not quite orthogonal).
    """
    xx, yx, zx, xy, yy, zy, xz, yz, zz = rotation.flat
    k = np.array([[xx - yy - zz, 0, 0, 0],
                  [yx + xy, yy - xx - zz, 0, 0],
                  [zx + xz, zy + yz, zz - xx - yy, 0],
                  [yz - zy, zx - xz, xy - yx, xx + yy + zz]]) / 3.0
    values, vectors = np.linalg.eigh(k)  # (the lower triangle is read)
    q = vectors[[3, 0, 1, 2], np.argmax(values)]
    if q[0] < 0:
        q *= -1
    return q


def _set_qform(hdr: np.ndarray, aff: np.ndarray) -> None:
    """The qform fields (quaternion, qfac, voxel sizes, offset) of ``aff``'s matrix."""
    lin = aff[:3, :3]
    zooms = np.sqrt(np.sum(lin * lin, axis=0))
    rot = lin / zooms
    if np.linalg.det(rot) > 0:
        qfac = 1
    else:
        qfac = -1
        rot[:, -1] *= -1
    u, _, vt = np.linalg.svd(rot)
    quat = rotation_quaternion(np.dot(u, vt))
    hdr["qoffset_x"], hdr["qoffset_y"], hdr["qoffset_z"] = aff[:3, 3]
    hdr["pixdim"][0] = qfac
    hdr["pixdim"][1:4] = zooms
    hdr["quatern_b"], hdr["quatern_c"], hdr["quatern_d"] = quat[1:]


def extension_bytes(code: int, content: bytes) -> bytes:
    """A header extension: its size (a multiple of 16), code and NUL-padded content."""
    size = len(content) + 8
    size += (16 - size % 16) % 16
    return np.array([size, code], dtype=np.int32).tobytes() + content.ljust(size - 8, b"\0")


def nifti1_header_bytes(shape_xyz: tuple[int, ...], dtype, aff: np.ndarray, *,
                        codes: tuple[int, int], units: int, intent=None, descrip: bytes = b"",
                        extensions: tuple[tuple[int, bytes], ...] = ()) -> bytes:
    """The header and extensions of a single NIfTI-1 file, up to its first sample.

    ``shape_xyz``: the samples' sizes (x fastest; up to 7 axes); ``aff``: the
    voxel-to-RAS 4x4 matrix written in both forms, with ``codes`` (sform,
    qform); ``units``: ``xyzt_units``; ``intent``: ``(code, (p1, p2, p3),
    name bytes)`` or None; ``descrip``: at most 80 bytes; ``extensions``:
    ``(code, content)`` pairs. A ValueError for a type or a size NIfTI-1
    cannot hold.
    """
    dtype = np.dtype(dtype)
    if dtype.newbyteorder("=") not in DATATYPE_CODES:
        raise ValueError(f"NIfTI-1 has no type for {dtype.name} samples")
    if not 1 <= len(shape_xyz) <= 7 or any(not 0 < n <= _DIM_MAX for n in shape_xyz):
        raise ValueError(f"NIfTI-1 cannot hold {len(shape_xyz)}-D samples of sizes "
                         f"{tuple(shape_xyz)} (1 to 7 axes, each at most {_DIM_MAX})")
    hdr = np.zeros((), dtype=HEADER1)
    hdr["sizeof_hdr"] = 348
    hdr["dim"] = 1
    hdr["dim"][0] = len(shape_xyz)
    hdr["dim"][1:len(shape_xyz) + 1] = shape_xyz
    hdr["datatype"] = DATATYPE_CODES[dtype.newbyteorder("=")]
    hdr["bitpix"] = dtype.itemsize * 8
    hdr["pixdim"] = 1
    hdr["scl_slope"] = 1
    hdr["xyzt_units"] = units
    aff = np.array(aff, dtype=np.float64)
    hdr["sform_code"], hdr["qform_code"] = codes
    hdr["srow_x"], hdr["srow_y"], hdr["srow_z"] = aff[0], aff[1], aff[2]
    _set_qform(hdr, aff)
    if intent is not None:
        code, params, name = intent
        hdr["intent_code"] = code
        hdr["intent_p1"], hdr["intent_p2"], hdr["intent_p3"] = params
        hdr["intent_name"] = name[:16]
    hdr["descrip"] = descrip[:80]
    hdr["magic"] = b"n+1"
    tail = b"".join(extension_bytes(code, content) for code, content in extensions)
    hdr["vox_offset"] = 352 + len(tail)
    flag = bytes([1 if extensions else 0, 0, 0, 0])
    return hdr.tobytes() + flag + tail
