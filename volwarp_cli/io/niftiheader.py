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
                        extensions: tuple[tuple[int, bytes], ...] = (),
                        fields: dict | None = None) -> bytes:
    """The header and extensions of a single NIfTI-1 file, up to its first sample.

    ``shape_xyz``: the samples' sizes (x fastest; up to 7 axes); ``aff``: the
    voxel-to-RAS 4x4 matrix written in both forms, with ``codes`` (sform,
    qform); ``units``: ``xyzt_units``; ``intent``: ``(code, (p1, p2, p3),
    name bytes)`` or None; ``descrip``: at most 80 bytes; ``extensions``:
    ``(code, content)`` pairs; ``fields``: other fields' values by name
    (``cal_min``, ``dim_info``, ...). A ValueError for a type or a size NIfTI-1
    cannot hold: more than 32767 samples along an axis is refused (nibabel
    wrote a line of them with FreeSurfer's ``dim[1] = -1``, which ITK and
    SimpleITK do not read as such).
    """
    dtype = np.dtype(dtype)
    if dtype.newbyteorder("=") not in DATATYPE_CODES:
        raise ValueError(f"NIfTI-1 has no type for {dtype.name} samples")
    if not 1 <= len(shape_xyz) <= 7 or any(not 0 < n <= _DIM_MAX for n in shape_xyz):
        raise ValueError(f"NIfTI-1 cannot hold {len(shape_xyz)}-D samples of sizes "
                         f"{tuple(shape_xyz)} (1 to 7 axes, each at most {_DIM_MAX}; "
                         "write .nrrd or .mha)")
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
    for name, value in (fields or {}).items():
        hdr[name] = value
    hdr["magic"] = b"n+1"
    tail = b"".join(extension_bytes(code, content) for code, content in extensions)
    hdr["vox_offset"] = 352 + len(tail)
    flag = bytes([1 if extensions else 0, 0, 0, 0])
    return hdr.tobytes() + flag + tail


# -- reading ---------------------------------------------------------------------------

#: NIfTI-2's header fields, in order (540 bytes)
HEADER2 = np.dtype([
    ("sizeof_hdr", "i4"), ("magic", "S4"), ("eol_check", "i1", (4,)), ("datatype", "i2"),
    ("bitpix", "i2"), ("dim", "i8", (8,)), ("intent_p1", "f8"), ("intent_p2", "f8"),
    ("intent_p3", "f8"), ("pixdim", "f8", (8,)), ("vox_offset", "i8"), ("scl_slope", "f8"),
    ("scl_inter", "f8"), ("cal_max", "f8"), ("cal_min", "f8"), ("slice_duration", "f8"),
    ("toffset", "f8"), ("slice_start", "i8"), ("slice_end", "i8"), ("descrip", "S80"),
    ("aux_file", "S24"), ("qform_code", "i4"), ("sform_code", "i4"), ("quatern_b", "f8"),
    ("quatern_c", "f8"), ("quatern_d", "f8"), ("qoffset_x", "f8"), ("qoffset_y", "f8"),
    ("qoffset_z", "f8"), ("srow_x", "f8", (4,)), ("srow_y", "f8", (4,)), ("srow_z", "f8", (4,)),
    ("slice_code", "i4"), ("xyzt_units", "i4"), ("intent_code", "i4"), ("intent_name", "S16"),
    ("dim_info", "u1"), ("unused_str", "S15"),
])
assert HEADER2.itemsize == 540

_SAMPLE_TYPES = {code: dt for dt, code in DATATYPE_CODES.items()}
#: the most header bytes (header, extensions) read here; beyond, nibabel reads the file
MAX_HEADER_BYTES = 1 << 20
#: the code of a DICOM header extension (nibabel reads it with pydicom where it can)
_DICOM_EXTENSION = 2
#: NIfTI-2 intent codes of CIFTI-2 files (data on surfaces: nibabel reads them as such)
_CIFTI_INTENTS = range(3000, 3100)


class _Extension:
    """A header extension: its code and content (trailing NULs removed)."""

    def __init__(self, code: int, content: bytes):
        self.code, self.content = code, content

    def get_code(self) -> int:
        return self.code


class NiftiHeader:
    """A NIfTI-1 or NIfTI-2 header that needs no repair, read as nibabel reads it.

    ``fields``: the header's fields (``header["pixdim"]``, ``header.get(name)``);
    ``shape`` (x, y, z, ...), ``dtype`` (the file's byte order), ``offset``
    (where the samples start); ``extensions``. The forms' matrices are
    nibabel's to the bit: the sform's rows; the qform's quaternion completed
    and turned into a matrix in extended precision, times the voxel sizes
    (the last one times ``qfac``).
    """

    def __init__(self, fields: np.void, version: int, extensions: list):
        self.fields, self.version, self.extensions = fields, version, extensions
        self.shape = tuple(int(d) for d in fields["dim"][1:int(fields["dim"][0]) + 1])
        self.dtype = _SAMPLE_TYPES[int(fields["datatype"])].newbyteorder(
            fields.dtype["sizeof_hdr"].byteorder)
        self.offset = int(fields["vox_offset"])

    def __getitem__(self, name: str):
        return self.fields[name]

    def get(self, name: str, default=None):
        """Field ``name``, or ``default`` where this version has none."""
        return self.fields[name] if name in self.fields.dtype.names else default

    def get_data_shape(self) -> tuple[int, ...]:
        """The samples' sizes (x, y, z, ...)."""
        return self.shape

    def get_sform(self, coded: bool = False):
        """The sform's 4x4 matrix (``coded``: and its code; None for code 0)."""
        code = int(self.fields["sform_code"])
        if coded and code == 0:
            return None, 0
        out = np.eye(4)
        out[0, :], out[1, :], out[2, :] = (self.fields[r] for r in ("srow_x", "srow_y",
                                                                       "srow_z"))
        return (out, code) if coded else out

    def get_qform(self, coded: bool = False):
        """The qform's 4x4 matrix (``coded``: and its code; None for code 0)."""
        code = int(self.fields["qform_code"])
        if coded and code == 0:
            return None, 0
        out = _qform_matrix(self.fields, self.version)
        return (out, code) if coded else out


#: niftilib's bound (``nifti_quatern_to_mat44``, read by ITK, SimpleITK and FSL): where
#: 1 - b^2 - c^2 - d^2 is below it, w is 0 (nibabel's bound is 3 epsilons, 3.6e-7 for
#: NIfTI-1: near a half turn the two read one quaternion up to 1.3e-3 rad apart)
NIFTILIB_W2_ZERO = 1e-7


def _qform_matrix(f, version: int, w2_zero=None) -> np.ndarray:
    """The qform's 4x4 matrix of header fields ``f``, w completed as nibabel (or below ``w2_zero``: 0)."""
    rot = _quaternion_matrix(_completed_quaternion(
        [f["quatern_b"], f["quatern_c"], f["quatern_d"]], version, w2_zero))
    vox = f["pixdim"][1:4].copy()
    vox[-1] *= f["pixdim"][0]
    out = np.eye(4)
    out[0:3, 0:3] = np.dot(rot, np.diag(vox))
    out[0:3, 3] = [f["qoffset_x"], f["qoffset_y"], f["qoffset_z"]]
    return out


def written_qforms(aff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The qform written of ``aff`` as nibabel and as niftilib read it back (4x4 matrices).

    Its quaternion is float32 and readers complete w from b, c, d: near a half
    turn (w near 0: an LPS grid turned slightly in its plane, written in RAS)
    that loses up to 1.3e-3 rad, and the two readers' bounds for a w of 0
    differ (:data:`NIFTILIB_W2_ZERO`).
    """
    hdr = np.zeros((), dtype=HEADER1)
    hdr["pixdim"] = 1
    _set_qform(hdr, np.asarray(aff, dtype=np.float64))
    return _qform_matrix(hdr, 1), _qform_matrix(hdr, 1, NIFTILIB_W2_ZERO)


def _completed_quaternion(bcd, version: int, w2_zero=None) -> np.ndarray:
    """(w, b, c, d), w = sqrt(1 - b^2 - c^2 - d^2) in extended precision, 0 within rounding.

    Within 3 float32 epsilons (NIfTI-1) or 3 float64 ones (NIfTI-2) of a
    unit vector, or below ``w2_zero`` where given (niftilib's rule), w is 0;
    beyond, a ValueError (the caller checked before).
    """
    eps = np.finfo(np.float32 if version == 1 else np.float64).eps * 3
    xyz = np.asarray(bcd, dtype=np.longdouble)
    w2 = 1.0 - xyz @ xyz
    if np.abs(w2) < eps or (w2_zero is not None and w2 < w2_zero):
        w = 0
    elif w2 < 0:
        raise ValueError(f"w2 should be positive, but is {w2:e}")
    else:
        w = np.sqrt(w2)
    return np.r_[w, xyz]


def _quaternion_matrix(q) -> np.ndarray:
    """The rotation matrix of a quaternion (w, x, y, z), scaled to unit length."""
    w, x, y, z = q
    nq = w * w + x * x + y * y + z * z
    if nq < np.finfo(float).eps:
        return np.eye(3)
    s = 2.0 / nq
    xs, ys, zs = x * s, y * s, z * s
    wx, wy, wz = w * xs, w * ys, w * zs
    xx, xy, xz = x * xs, x * ys, x * zs
    yy, yz, zz = y * ys, y * zs, z * zs
    return np.array([[1.0 - (yy + zz), xy - wz, xz + wy],
                     [xy + wz, 1.0 - (xx + zz), yz - wx],
                     [xz - wy, yz + wx, 1.0 - (xx + yy)]])


def _fields(block: bytes) -> tuple[np.void, int] | None:
    """The header fields of a single-file NIfTI-1 or NIfTI-2 header, and its version."""
    for version, dtype, magic in ((1, HEADER1, b"n+1\0"), (2, HEADER2, b"n+2\0")):
        size = dtype.itemsize
        if len(block) < size + 4:
            continue
        for end in "<>":
            if int(np.frombuffer(block, end + "i4", 1)[0]) != size:
                continue
            at = 344 if version == 1 else 4
            if block[at:at + 4] != magic:
                return None
            if version == 2 and (block[8:12] != b"\r\n\x1a\n"
                                 or block[344:348].rstrip(b"\0") in (b"ni1", b"n+1")):
                return None  # (nibabel would read the second as NIfTI-1)
            return np.frombuffer(block, dtype.newbyteorder(end), 1)[0], version
    return None


def _needs_nibabel(f: np.void, version: int) -> bool:
    """Whether nibabel would repair, refuse, scale or read otherwise: left to it."""
    dims = f["dim"]
    if not 1 <= dims[0] <= 7 or np.any(dims[1:int(dims[0]) + 1] < 1):
        return True
    if tuple(dims[1:4]) == (27307, 1, 6):  # (FreeSurfer's icosahedron, reshaped by nibabel)
        return True
    kind = _SAMPLE_TYPES.get(int(f["datatype"]))
    if kind is None or int(f["bitpix"]) != kind.itemsize * 8:
        return True
    pixdim = f["pixdim"]
    if np.any(pixdim[1:4] <= 0) or pixdim[0] not in (-1, 1):
        return True
    offset = float(f["vox_offset"])
    if not (offset >= (352 if version == 1 else 544) and offset % 16 == 0
            and offset <= MAX_HEADER_BYTES):
        return True
    if int(f["qform_code"]) not in range(6) or int(f["sform_code"]) not in range(6):
        return True
    if version == 2 and int(f["intent_code"]) in _CIFTI_INTENTS:
        return True
    slope, inter = float(f["scl_slope"]), float(f["scl_inter"])
    if slope != 0 and np.isfinite(slope) and (slope, inter) != (1.0, 0.0):
        return True  # (scaled samples, or an intercept that is not a number)
    try:
        _completed_quaternion([f["quatern_b"], f["quatern_c"], f["quatern_d"]], version)
    except ValueError:
        return True
    return False


def read_header(read) -> NiftiHeader | None:
    """The header of a single NIfTI-1/2 file as nibabel reads it, or None to leave it to nibabel.

    ``read(n)``: the file's first ``n`` bytes (decompressed; fewer at its end).
    None for anything that is not a clean single-file NIfTI header: another
    format, a field nibabel would repair or refuse (a size, a type, the voxel
    sizes, ``qfac``, the codes, the offset), scaled samples, CIFTI-2, an
    extension whose size is not a multiple of 16 or runs past the samples, a
    DICOM extension.
    """
    first = read(548) or b""
    parsed = _fields(first)
    if parsed is None or _needs_nibabel(*parsed):
        return None
    fields, version = parsed
    size = fields.dtype.itemsize
    offset = int(fields["vox_offset"])
    block = (read(offset) or b"") if offset > len(first) else first
    if len(block) < offset:
        return None
    extensions = []
    if block[size:size + 1] != b"\0":
        byteorder = fields.dtype["sizeof_hdr"].byteorder
        at, left = size + 4, offset - size - 4
        while left >= 16:
            esize, ecode = (int(v) for v in np.frombuffer(block, byteorder + "i4", 2, at))
            if esize < 16 or esize % 16 or esize > left or ecode == _DICOM_EXTENSION:
                return None
            extensions.append(_Extension(ecode, block[at + 8:at + esize].rstrip(b"\0")))
            at, left = at + esize, left - esize
    return NiftiHeader(fields, version, extensions)
