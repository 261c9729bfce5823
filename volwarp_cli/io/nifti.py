"""NIfTI-1/2 (``.nii``, ``.nii.gz``), in the LPS frame SimpleITK reports.

Headers are read and written by :mod:`.niftiheader` (nibabel's import is 0.05 s
of a command): a header that needs no repair is read there, as nibabel reads it
(the same fields, and the forms' matrices to the bit); any other (a field nibabel
repairs or refuses, scaled samples, CIFTI-2, a DICOM extension) goes to nibabel,
whose checks and messages apply, as does the scaling of scaled samples.

NIfTI stores a voxel-to-RAS matrix; volwarp (like ITK, DICOM and 3D Slicer's
files) works in LPS, so x and y of the world are negated on the way in and out
(``Volume.space`` is LPS, ``Volume.file_space`` right-anterior-superior).

Which matrix is used follows ITK's NiftiImageIO (so volwarp and SimpleITK place
every file alike, but one: see 3):

1. neither form coded (``sform_code == qform_code == 0``, "method 1"): the
   voxel sizes ``pixdim[1:4]`` along the LPS axes (identity direction, as
   ITK reads such files), origin 0;
2. the sform, when it is coded and orthonormal once its column lengths are
   divided out, and either the qform is not coded, or the sform's code is 1
   (scanner), or both forms agree within 1e-4;
3. else the qform, when it is coded. Where ITK's code checks whether the
   two forms agree, it compares their singular value decompositions' left
   factors and values only: two forms that differ by a turn or a mirror of
   the voxel axes about one origin can pass, and ITK then reads the sform
   (whether they pass depends on the signs its SVD gives). volwarp compares
   the matrices, reads the qform of such a file, and its warning says that
   nibabel, FSL and SPM read the sform (as they do whenever its code is
   above 0);
4. else the (skewed) sform: ITK refuses such files, volwarp keeps the shear in
   ``direction``.

Voxel sizes are the chosen matrix's column lengths. Where an sform is read
whose lengths are not ``pixdim``'s, volwarp says so: it reads the sform's, as
nibabel's affine and SPM do, while ITK takes ``pixdim``'s (its spacing always
comes from there), so the image's extent differs in SimpleITK.

Units: like ITK, a file whose ``xyzt_units`` say metres or microns is read in
millimetres (spacing and origin scaled by 1000 or 1/1000); other space units
(mm, unknown) are taken as millimetres. The units are written back as they
were, with the matrix scaled back to them.

Header fields kept on a round trip, as ``Volume.meta`` strings (each only where
it differs from what the writer does by default: codes 1 and 1, mm):

* ``NIfTI_sform_code``, ``NIfTI_qform_code`` (integers; e.g. 4 for an MNI152
  template, 2 for an aligned space). A code names the world frame of its own
  form's matrix, and volwarp carries one matrix: the one the rule above reads.
  So the rule of the codes is: **a written NIfTI never pairs a form's code
  with a matrix that is not that form's.**

  - Reading: a form keeps its code when its matrix is the one read (the
    form read, and the other form where it places every corner of the grid
    within 0.01 voxel of it, or agrees within ITK's 1e-4 entry by entry:
    the usual file, both forms written from one matrix, the qform's
    quaternion rounded). A coded form whose matrix differs (an MNI sform
    beside a scanner qform that ITK's rule reads, a skewed sform beside its
    qform) gets code 0 in ``meta``, with a warning: volwarp does not carry
    its matrix, so no output can hold it.
  - Writing: volwarp writes its one matrix into both forms, each with its
    code in ``meta``; a form coded 0 is ignored by every reader. The
    geometry volwarp writes is the read matrix moved with the grid (a crop,
    a resample: still in the same world frame, so its code still applies);
    a form whose matrix was not read is not re-created after an operation
    (its relation to the grid would be stale after a warp).
  - Without these keys (an NRRD or TIFF input) both codes are 1 (scanner).
    Two exceptions, so that the written geometry is always the one readers
    use: when both codes are 0 but the geometry is no longer the one
    "method 1" gives (origin 0, identity direction in LPS), both are
    written as 1; when the qform's float32 quaternion cannot hold the
    matrix (:func:`_qform_holds`: a rotation near a half turn, common as an
    LPS grid turned slightly in its plane is one in RAS, lost up to 1.3e-3
    rad, 0.3 mm 230 mm out; a direction from another format's grid, e.g.
    ``apply --reference`` an NRRD or DICOM grid), the qform gets code 0 and
    the sform the code (the qform's where the sform had none), as nibabel
    writes a new image: ITK would read a coded qform beside an sform of code
    2-4 that it does not match, and volwarp too, with a warning. A direction
    read from a quaternion is held: its round trip is unchanged.

  So nibabel, FSL and SPM (the sform whenever its code is above 0), ITK and
  SimpleITK (the rule above) and volwarp read a written file alike.
* ``NIfTI_xyzt_units`` (the byte: space units | time units; default 2, mm);
* ``NIfTI_intent_code``, ``NIfTI_intent_p1`` .. ``p3``, ``NIfTI_intent_name``
  (only when the file has an intent);
* ``descrip`` (at most 79 bytes, latin-1);
* fields true of the samples as read, on their grid: ``NIfTI_cal_min``,
  ``NIfTI_cal_max`` (a display window), ``NIfTI_dim_info`` (the frequency,
  phase and slice axes), ``NIfTI_slice_code``, ``NIfTI_slice_start``,
  ``NIfTI_slice_end``, ``NIfTI_slice_duration`` (slice timing),
  ``NIfTI_toffset``, ``NIfTI_aux_file`` (a lookup table's name, as FSL uses
  it). ``convert`` keeps them (the same samples on the same grid); a command
  that computes new samples drops them (a stale window would hide the new
  values, a slice axis or timing is no longer the acquisition's:
  :func:`volwarp_cli.provenance.stamp`).

volwarp's other key/values (``volwarp_version``, ``volwarp_command``,
``volwarp_input``, ``volwarp_spec_sha256``, key/values carried from an NRRD
input, ...) go into one header extension with code 6 ("comment", the
registered code for free text: nibabel, niftilib-based readers such as ITK
and FSL, and AFNI skip or display it as text, while the codes of other
registered formats, e.g. 4 AFNI or 8 XCEDE XML, promise a content volwarp's
does not have). Its content is ``volwarp-meta-json/1`` and a newline, then
the key/values as ASCII JSON with sorted keys (deterministic bytes), padded
with NULs to a multiple of 16 bytes as the format requires. On reading, only
a code-6 extension starting with that prefix is volwarp's; any other
extension (another program's comment, DICOM, AFNI, ...) is left alone: not
read into ``meta`` and not copied to outputs.

Damaged headers are a one-line :class:`FormatError` naming the file and the
field: a ``vox_offset`` that would make the samples start inside the header
(smaller than 352 bytes for a NIfTI-1 file, 544 for a NIfTI-2 file), a coded
qform whose ``quatern_b, quatern_c, quatern_d`` have a sum of squares above
1. An all-zero or otherwise degenerate matrix is an error, never a numpy
warning on stderr.

Samples: a ``.nii.gz`` is decompressed to the end of its gzip stream (ISA-L
where installed) whatever part of it is read, so that its CRC-32 and length
are checked: a damaged or truncated file is a FormatError naming it ("cannot
read NIfTI data (...)"), never samples silently wrong. An uncompressed file
shorter than its header's samples is refused before any is read (the lazy
reader of :mod:`.lazy` opens files through :func:`open_nifti` too, with the
same checks, geometry and key/values).

Files with a 4th dimension (time) longer than 1 are refused unless
``volume_index`` picks one volume. A 5-D file whose 4th dimension is 1 holds
several components per voxel in its 5th (SimpleITK's vector images, volwarp's
own ``--displacement-to`` fields, any intent): ``volume_index`` picks one
component, as for a multi-component NRRD, read as stored (no change of frame:
SimpleITK and volwarp store LPS components); its intent is not kept (it
describes the 5th axis), and its name goes to ``volwarp_component`` (``x``,
``y``, ``z`` for volwarp's fields). Larger dimensions, or several volumes of
several components, are refused. Files nibabel reads as another image class
than a NIfTI-1/2 volume (CIFTI-2's surface and grayordinate data) are refused.
"""

from __future__ import annotations

import contextlib
import gzip
import json
import os
import struct
import sys
import threading
import types
import zlib
from pathlib import Path

import numpy as np

from ..errors import BadUsage, ChoiceNeeded, FormatError, VolwarpError
from ..geometry import check_placement
from ..memory import ensure_fits_in_memory
from ..progress import log
from ..runscope import first_said
from ..samples import check_dtype, voxel_count
from ..volume import Volume, xyz_to_zyx
from .atomic import atomic_output
from .common import (
    make_volume,
    native,
    read_exact,
    write_samples,
)

_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0])

#: NIfTI space units (``xyzt_units & 7``) -> millimetres, as ITK converts them
#: (1 metre, 3 micron; 2 is mm, 0 unknown, taken as mm)
_SPACE_UNIT_TO_MM = {1: 1000.0, 3: 1e-3}
#: the header fields each of the three matrices (choose_affine's names) comes from
_SFORM = "sform (srow_x, srow_y, srow_z)"
_FIELDS = {"sform": {"spacing": _SFORM, "origin": _SFORM, "direction": _SFORM},
           "qform": {"spacing": "pixdim", "origin": "qform (qoffset_x, qoffset_y, qoffset_z)",
                     "direction": "qform (quatern_b, quatern_c, quatern_d, pixdim[0])"},
           "pixdim": {"spacing": "pixdim", "origin": "pixdim", "direction": "pixdim"}}
#: ``xyzt_units`` of a file written from a volume that names none: mm, no time unit
_DEFAULT_XYZT_UNITS = 2

#: volwarp's header extension: code 6 ("comment"), content starting with this prefix
EXTENSION_CODE = 6
EXTENSION_PREFIX = b"volwarp-meta-json/1\n"

#: the meta keys that are NIfTI header fields (everything else goes to the extension)
_INTENT_KEYS = ("NIfTI_intent_code", "NIfTI_intent_p1", "NIfTI_intent_p2", "NIfTI_intent_p3",
                "NIfTI_intent_name")
#: header fields true of the samples as read, on their grid, and their keys: kept by
#: ``convert`` only (:data:`volwarp_cli.provenance.AS_READ_KEYS`); each a type and range
#: (None: text)
AS_READ_FIELDS = {
    "NIfTI_cal_min": ("cal_min", float), "NIfTI_cal_max": ("cal_max", float),
    "NIfTI_dim_info": ("dim_info", (0, 255)), "NIfTI_slice_code": ("slice_code", (0, 255)),
    "NIfTI_slice_start": ("slice_start", (-32768, 32767)),
    "NIfTI_slice_end": ("slice_end", (-32768, 32767)),
    "NIfTI_slice_duration": ("slice_duration", float), "NIfTI_toffset": ("toffset", float),
    "NIfTI_aux_file": ("aux_file", None),
}
HEADER_KEYS = ("descrip", "NIfTI_sform_code", "NIfTI_qform_code", "NIfTI_xyzt_units",
               *_INTENT_KEYS, *AS_READ_FIELDS)


def choose_affine(header, where: str = "") -> tuple[np.ndarray, str]:
    """The voxel-to-RAS 4x4 matrix by ITK's rule (module docstring), and its name."""
    with np.errstate(all="ignore"):
        return _choose_affine(header, where)


def _choose_affine(header, where: str) -> tuple[np.ndarray, str]:
    pixdim = [float(z) for z in header["pixdim"][1:4]]
    bad = [f"pixdim[{i + 1}] = {z}" for i, z in enumerate(pixdim) if not np.isfinite(z)]
    if bad:  # (NaN failed "> 0" and was read as 1 where no form names a matrix)
        prefix = f"{where}: " if where else ""
        raise FormatError(f"{prefix}NIfTI {', '.join(bad)}: voxel sizes must be finite")
    zooms = np.array([z if z > 0 else 1.0 for z in pixdim])  # (0: 1, as ITK and nibabel)
    sform, scode = header.get_sform(coded=True)
    try:
        qform, qcode = header.get_qform(coded=True)
    except ValueError as exc:  # nibabel's "w2 should be positive": an invalid quaternion
        prefix = f"{where}: " if where else ""
        raise FormatError(f"{prefix}NIfTI qform has an invalid quaternion (quatern_b, "
                          f"quatern_c, quatern_d): {_one_line(exc)}") from None
    scode = int(scode or 0) if sform is not None else 0
    qcode = int(qcode or 0) if qform is not None else 0
    if scode == 0 and qcode == 0:  # as ITK: LPS axes (RAS -x, -y, +z), origin 0
        aff = np.eye(4)
        aff[:3, :3] = np.diag(zooms * [-1.0, -1.0, 1.0])
        return aff, "pixdim"
    sform = np.asarray(sform, dtype=np.float64) if scode else None
    qform = np.asarray(qform, dtype=np.float64) if qcode else None
    prefer_sform = (sform is not None and qform is not None
                    and np.allclose(sform[:3, :3], qform[:3, :3], rtol=0, atol=1e-5)
                    and np.abs(sform[:3, 3] - qform[:3, 3]).sum() <= 1e-7)
    if sform is not None:
        lin = sform[:3, :3] / np.linalg.norm(sform[:3, :3], axis=0)[None, :]
        if np.allclose(lin @ lin.T, np.eye(3), atol=1e-4):
            if qform is None or scode == 1:
                prefer_sform = True
            else:
                prefer_sform = bool(np.allclose(sform, qform, rtol=0, atol=1e-4))
    if prefer_sform:
        return sform, "sform"
    if qform is not None:
        return qform, "qform"
    return sform, "sform"


def _read_start(path, count: int) -> bytes | None:
    """The first ``count`` bytes of the (possibly gzipped) file (fewer at its end), or None."""
    try:
        with open(path, "rb") as fh:
            if fh.read(2) == b"\x1f\x8b":
                fh.seek(0)
                with gzip.GzipFile(fileobj=fh) as gz:
                    return gz.read(count)
            fh.seek(0)
            return fh.read(count)
    except (OSError, EOFError, zlib.error):
        return None


def _gzipped(path) -> bool:
    """True where the file starts with gzip's magic bytes (False where it cannot be read)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(2) == b"\x1f\x8b"
    except OSError:
        return False


def _check_raw_header(block: bytes | None, where: str) -> None:
    """Refuse, before nibabel reads them, a vox_offset inside the header and an invalid quaternion.

    ``block``: the file's first (decompressed) bytes, None where they cannot be
    read (nibabel then says why). nibabel would read header bytes as samples, or
    fail with a traceback-like message that names no field.
    """
    if not block or len(block) < 348:
        return
    for end in "<>":
        size = struct.unpack_from(end + "i", block, 0)[0]
        if size in (348, 540):
            break
    else:
        return
    if size == 348:
        single = block[344:348] == b"n+1\0"
        vox = struct.unpack_from(end + "f", block, 108)[0]
        qcode = struct.unpack_from(end + "h", block, 252)[0]
        quat = struct.unpack_from(end + "3f", block, 256)
        pixdim = struct.unpack_from(end + "3f", block, 80)
        minimum, eps = 352, float(np.finfo(np.float32).eps)
    else:
        if len(block) < 376:
            return
        single = block[4:8] == b"n+2\0"
        vox = struct.unpack_from(end + "q", block, 168)[0]
        qcode = struct.unpack_from(end + "i", block, 344)[0]
        quat = struct.unpack_from(end + "3d", block, 352)
        pixdim = struct.unpack_from(end + "3d", block, 112)
        minimum, eps = 544, float(np.finfo(np.float64).eps)
    if single and not vox >= minimum:  # also NaN
        raise FormatError(f"{where}: NIfTI header field vox_offset is {vox:g}, but the samples "
                          f"of a single-file NIfTI-{1 if size == 348 else 2} file start after "
                          f"its {minimum}-byte header (vox_offset >= {minimum})")
    if qcode != 0:
        with np.errstate(all="ignore"):
            norm2 = float(np.dot(np.asarray(quat, np.float64), np.asarray(quat, np.float64)))
        if not norm2 <= 1.0 + 3 * eps:
            b, c, d = (f"{v:.6g}" for v in quat)
            raise FormatError(f"{where}: NIfTI qform (qform_code {qcode}) has an invalid "
                              f"quaternion: quatern_b, quatern_c, quatern_d = {b}, {c}, {d} "
                              f"give b^2+c^2+d^2 = {norm2:.6g}, more than 1")
    _say_negative_pixdim(pixdim, where)


def _say_negative_pixdim(pixdim, where: str) -> None:
    """Say voxel sizes the header gives negative (the standard has them positive).

    nibabel takes their sizes ("setting to abs") before volwarp sees the header,
    and so volwarp does, while ITK and SimpleITK mirror the axis: the same voxel
    lies elsewhere in the two. Said once a run for the file.
    """
    from ..runscope import first_said

    negative = [f"pixdim[{i + 1}] = {z:g}" for i, z in enumerate(pixdim) if z < 0]
    if negative and first_said(("negative pixdim", os.path.abspath(where))):
        log.warning("%s: NIfTI %s: a voxel size given negative; volwarp takes its size, as "
                    "nibabel does, while ITK and SimpleITK mirror that axis (the image lies "
                    "elsewhere in them): write the file again with positive pixdim", where,
                    ", ".join(negative))


_LPS = "left-posterior-superior"
_RAS = "right-anterior-superior"
#: decompressed bytes per inflate call, and compressed bytes per read
#: a form whose matrix places every corner of the grid within this fraction of a voxel of
#: the matrix volwarp reads holds the same geometry (float32 storage, a quaternion's rounding)
_SAME_FORM_VOXELS = 1e-2


class NiftiFile:
    """A NIfTI file opened and checked by :func:`open_nifti`; its samples are not read yet.

    ``shape`` is the file's (x, y, z, ...) sizes (at least 3), ``volumes`` the
    size of the 4th axis (time), ``components`` that of the 5th (the values of
    a vector per voxel). ``file_dtype`` keeps the file's byte order; ``offset``
    is where the samples start (in the decompressed stream of a ``.nii.gz``).
    """

    def __init__(self, path: Path, where: str, header, file_dtype, offset: int, scaling,
                 shape: tuple[int, ...]):
        self.path = path
        self.where = where
        self.header = header  # (nibabel's, or a NiftiHeader: the same fields and forms)
        self.file_dtype = np.dtype(file_dtype)
        self.offset = int(offset)
        self.slope, self.inter = scaling  # (as nibabel's data proxy has them)
        self.scaled = (float(self.slope), float(self.inter)) != (1.0, 0.0)
        shape = tuple(int(s) for s in shape)
        if not shape or any(s <= 0 for s in shape):
            dims = [int(d) for d in header["dim"]]
            raise FormatError(f"{where}: NIfTI sizes must be positive, got {shape} "
                              f"(header dim {dims})")
        self.shape = shape + (1,) * (3 - len(shape))
        extra = self.shape[3:]
        self.volumes = extra[0] if extra else 1
        self.components = extra[1] if len(extra) > 1 else 1
        if any(s > 1 for s in extra[2:]):
            raise FormatError(f"{where}: NIfTI with shape {self.shape} has more than 5 "
                              "dimensions")
        if self.volumes > 1 and self.components > 1:
            raise FormatError(f"{where}: NIfTI with shape {self.shape} has {self.volumes} "
                              f"volumes of {self.components} components each; volwarp reads "
                              "one volume of a 4-D file or one component of a 5-D file with "
                              "one volume")
        self.block_bytes = voxel_count(self.shape[:3]) * self.file_dtype.itemsize
        self.data_bytes = voxel_count(self.shape) * self.file_dtype.itemsize
        with open(path, "rb") as fh:
            self.gzipped = fh.read(2) == b"\x1f\x8b"
            size = os.fstat(fh.fileno()).st_size
        if not self.gzipped and size - self.offset < self.data_bytes:
            raise FormatError(f"{where}: cannot read NIfTI data (truncated: "
                              f"{self.layout()} need {self.data_bytes} bytes from byte "
                              f"{self.offset}, the file has {max(size - self.offset, 0)})")

    def layout(self) -> str:
        """``"XxYxZ TYPE samples"``, for messages."""
        return f"{'x'.join(map(str, self.shape))} {self.file_dtype.name} samples"

    def sample_dtype(self) -> np.dtype:
        """The (native) type of the samples read: float for scaled ones, else the file's.

        Scaled 8- and 16-bit samples are float32 (as ITK reads them), unless a
        whole slope and intercept take the type's range past 2**24, where
        float32 stops holding every integer: then float64, as nibabel reads
        them. A label map of int16 ids with ``scl_inter`` 16777216 read its
        ids 0 and 1 as one id (and 3 as 16777220) in float32.
        """
        dt = self.file_dtype
        if self.scaled and dt.kind in "iuf":
            return np.dtype(np.float32 if dt.itemsize <= 2 and not self._whole_past_float32()
                            else np.float64)
        return check_dtype(dt, self.where)

    def _whole_past_float32(self) -> bool:
        """Whether integer samples scaled by a whole slope and intercept can pass 2**24."""
        slope, inter = float(self.slope), float(self.inter)
        if self.file_dtype.kind not in "iu" or not (slope.is_integer() and inter.is_integer()):
            return False
        info = np.iinfo(self.file_dtype)
        reach = max(abs(slope * info.min + inter), abs(slope * info.max + inter))
        return reach > 2.0 ** (np.finfo(np.float32).nmant + 1)

    def select(self, volume_index: int | None) -> tuple[int, int | None]:
        """The sample block to read for ``volume_index``, and the component it is (or None)."""
        where = self.where
        count = max(self.volumes, self.components)
        if count > 1 and volume_index is None:
            if self.components > 1:
                intent = int(self.header["intent_code"])
                raise ChoiceNeeded(f"{where}: NIfTI with {self.components} components per voxel "
                                  f"(intent code {intent}, shape {self.shape}); choose one with "
                                  f"--volume-index 0..{self.components - 1}")
            raise ChoiceNeeded(f"{where}: 4-D NIfTI with {self.volumes} volumes; choose one with "
                              "--volume-index N")
        if volume_index is not None and not 0 <= volume_index < count:
            raise BadUsage(f"{where}: --volume-index {volume_index} is outside "
                           f"0..{count - 1}")
        k = volume_index or 0
        return k, (k if self.components > 1 else None)

    def read_block(self, k: int) -> np.ndarray:
        """The raw bytes of sample block ``k`` (a 3-D volume: x fastest), as uint8.

        A ``.nii.gz`` is decompressed to its end whatever the block, so that gzip
        checks the stream's CRC-32 and length: a damaged or truncated file is a
        FormatError, never samples read silently wrong.
        """
        start = self.offset + k * self.block_bytes
        if self.gzipped:
            return _gunzip_range(self.path, start, self.block_bytes,
                                 self.offset + self.data_bytes, self.where, self.layout())
        with open(self.path, "rb") as fh:
            fh.seek(start)
            try:
                return read_exact(fh, self.block_bytes, self.where)
            except FormatError as exc:  # shortened since it was opened
                raise FormatError(f"{self.where}: cannot read NIfTI data "
                                  f"({str(exc).removeprefix(self.where + ': ')})") from None


def _gunzip_range(path: Path, start: int, count: int, need: int, where: str,
                  layout: str) -> np.ndarray:
    """Bytes ``[start, start + count)`` of a gzip file's decompressed stream, as uint8."""
    out = np.empty(count, dtype=np.uint8)
    dest = memoryview(out)

    def sink(at: int, piece: memoryview) -> None:
        dest[at:at + len(piece)] = piece

    gunzip_range_into(path, start, count, need, where, layout, sink)
    return out


def gunzip_range_into(path: Path, start: int, count: int, need: int, where: str,
                      layout: str, sink, *, beside: bool = False) -> None:
    """Bytes ``[start, start + count)`` of a gzip file's decompressed stream, to ``sink``.

    ``sink(at, piece)`` takes each decompressed piece in order, ``at`` its
    position from ``start`` (a caller may place them without a buffer of
    the whole range); with ``beside`` (a sink that is more than a copy),
    on a thread of its own while the stream inflates
    (:func:`.deflate.sink_beside`). The whole stream is decompressed (other bytes dropped
    as they come): zlib then checks every member's CRC-32 and length.
    ``need``: the decompressed bytes the header asks for. Members may follow
    one another (as gzip allows), and NUL padding may end the file; anything
    else after a member is corrupt.
    """
    from .deflate import ERRORS, Truncated, inflate_pieces, sink_beside

    end = start + count
    pos = 0  # decompressed bytes so far

    def fail(why: str):
        return FormatError(f"{where}: cannot read NIfTI data ({why})")

    try:
        with open(path, "rb") as fh, sink_beside(sink, count if beside else 0) as place:
            for piece in inflate_pieces(fh):
                lo, hi = max(pos, start), min(pos + len(piece), end)
                if hi > lo:
                    place(lo - start, memoryview(piece)[lo - pos:hi - pos])
                pos += len(piece)
    except ERRORS as exc:
        raise fail(f"the gzip stream is corrupt: {_one_line(exc)}") from None
    except OSError as exc:
        raise fail(f"cannot read the file: {exc.strerror or exc}") from None
    except Truncated:
        raise fail(f"the gzip stream is truncated: it ends after {pos} decompressed bytes, "
                   "before its end-of-stream marker") from None
    if pos < need:
        raise fail(f"truncated: {layout} end at decompressed byte {need}, the stream "
                   f"holds {pos}")


class _NoPydicomForNibabel:
    """A finder refusing ``pydicom`` and ``scipy`` to nibabel's optional imports, and to nobody else.

    ``import nibabel`` imports pydicom (0.12 s on a quiet machine, 0.3 s on a busy
    one: most of nibabel's import) only to show a NIfTI's DICOM header extension
    (code 2) as a pydicom Dataset. volwarp never reads other programs'
    extensions (module notes); without pydicom nibabel keeps such an extension
    as its bytes. scipy (7-9 ms where no command imported it before) serves the
    ``.mat`` sidecar of SPM's Analyze images only: :func:`nibabel` gives those
    back their scipy after the import (:func:`_spm_reads_mat_again`). Only an
    import made from ``nibabel.optpkg`` is refused, so another thread
    importing either meanwhile (a DICOM input) is not.
    """

    REFUSED = ("pydicom", "scipy")

    @staticmethod
    def find_spec(name, path=None, target=None):
        if name not in _NoPydicomForNibabel.REFUSED:
            return None
        frame = sys._getframe(1)
        while frame is not None:
            if frame.f_globals.get("__name__") == "nibabel.optpkg":
                raise ModuleNotFoundError(f"{name}: not for nibabel's import (volwarp reads "
                                          "no DICOM extension of a NIfTI, no SPM .mat)",
                                          name=name)
            frame = frame.f_back
        return None


def _spm_reads_mat_again(module) -> None:
    """SPM99/SPM2 Analyze images read their ``.mat`` again where scipy is installed.

    nibabel noted at import, without scipy (:class:`_NoPydicomForNibabel`), that
    they cannot (``spm99analyze.have_scipy``, the image classes' ``rw``). It reads
    a ``.mat`` by importing ``scipy.io`` whatever these say (nibabel 5), but a
    program beside volwarp may ask them: where scipy can be imported, they are
    set as an import with scipy sets them.
    """
    import importlib.util

    spm = getattr(module, "spm99analyze", None)
    if spm is None or spm.have_scipy or importlib.util.find_spec("scipy") is None:
        return
    spm.have_scipy = True
    spm.Spm99AnalyzeImage.rw = True


class _RequestOnUse(types.ModuleType):
    """What nibabel's ``from urllib import request`` binds: the real module at first use.

    ``urllib.request`` (with ``http.client``, ``ssl`` and ``email``: 17-47 ms)
    serves nibabel's ``from_url`` only. This stand-in is set as the ``urllib``
    package's attribute while nibabel imports, never in ``sys.modules``: any
    other ``import urllib.request`` is the real, locked import, and the stand-in's
    first attribute makes one.
    """

    def __getattr__(self, attr):
        import importlib

        return getattr(importlib.import_module("urllib.request"), attr)


def nibabel():
    """The nibabel module, imported without pydicom and scipy (:class:`_NoPydicomForNibabel`).

    And without running ``urllib.request`` (:class:`_RequestOnUse`).
    """
    if _nibabel:
        return _nibabel[0]
    with _NIBABEL_LOCK:  # (a second thread finds nibabel in sys.modules half made)
        if not _nibabel:
            import urllib

            stand_in = None
            if "urllib.request" not in sys.modules and not hasattr(urllib, "request"):
                stand_in = _RequestOnUse("urllib.request")
                urllib.request = stand_in
            finder = _NoPydicomForNibabel()
            sys.meta_path.insert(0, finder)
            try:
                import nibabel as module
            finally:
                sys.meta_path.remove(finder)
                if stand_in is not None and getattr(urllib, "request", None) is stand_in:
                    del urllib.request
            _spm_reads_mat_again(module)
            _nibabel.append(module)
    return _nibabel[0]


#: the nibabel module once :func:`nibabel` has imported it whole (``sys.modules`` holds
#: it from the start of its import: another thread would find it half made there)
_nibabel: list = []
_NIBABEL_LOCK = threading.Lock()


def open_nifti(path: str | os.PathLike) -> NiftiFile:
    """Open a NIfTI-1/2 file and check its header (the samples are read later).

    A FormatError naming the file for anything volwarp cannot read as a volume:
    a damaged header (:func:`_check_raw_header`, nibabel's checks), a file nibabel
    reads as another image class (CIFTI-2: data on surfaces and grayordinates),
    empty axes, axes beyond the 5th, an uncompressed file shorter than its samples.
    """
    where = str(path)
    if not where.lower().endswith(".gz") and _gzipped(path):
        # (nibabel's "Cannot work out file type" reached the user; ITK refuses it too)
        raise FormatError(f"{where}: is gzip-compressed but named .nii: rename it .nii.gz "
                          "(nibabel and ITK read a .nii as uncompressed)")
    start = _read_start(path, _SNIFF_BYTES)  # (read once for both: a .nii.gz inflates it)
    _check_raw_header(start if start is not None else _read_start(path, _HEADER_BYTES), where)
    header = header_without_nibabel(path, start, read=False)
    if header is not None:  # (a header nibabel reads as it is: no nibabel import, 0.05 s)
        return NiftiFile(Path(path), where, header, header.dtype, header.offset, (1.0, 0.0),
                         header.shape)
    nib = nibabel()
    ImageFileError = nib.filebasedimages.ImageFileError  # noqa: N806
    with _quiet_nibabel():
        try:
            img = nib.load(str(path), mmap=False)
        except (ImageFileError, OSError, EOFError, ValueError) as exc:
            raise FormatError(f"{where}: not a readable NIfTI file ({_one_line(exc)})") from None
        except Exception as exc:  # nibabel's HeaderDataError and others, for damaged headers
            raise FormatError(f"{where}: not a readable NIfTI file "
                              f"({type(exc).__name__}: {_one_line(exc)})") from None
    if type(img) not in (nib.Nifti1Image, nib.Nifti2Image):
        kind = type(img).__name__
        what = (f"a CIFTI-2 file ({kind}: data on surface vertices and grayordinates)"
                if "cifti" in kind.lower() else f"read by nibabel as a {kind}")
        raise FormatError(f"{where}: is {what}, not a NIfTI-1/2 volume; volwarp reads "
                          "NIfTI volumes only")
    proxy = img.dataobj  # (nibabel moves scl_slope/scl_inter from the header to it)
    return NiftiFile(Path(path), where, img.header, proxy.dtype, proxy.offset,
                     (proxy.slope, proxy.inter), img.shape)


def header_without_nibabel(path, start=None, *, read: bool = True):
    """The header of a NIfTI file as nibabel would read it, or None to let nibabel read it.

    Only where nibabel would take the file for a NIfTI by its name and read it
    as it is: a ``.nii`` that is not gzipped, a ``.nii.gz`` that is (nibabel
    goes by the name: another name, or the other content, it refuses or reads
    as another format), whose first 1024 bytes inflate (nibabel reads as many
    to find the format: a short stream with a damaged end is refused there), and
    whose header needs no repair (:func:`.niftiheader.read_header`). ``start``:
    the file's first 1024 bytes where the caller read them (``read=False``;
    None: they could not be read).
    """
    from .niftiheader import read_header

    name = str(path).lower()
    if not name.endswith((".nii", ".nii.gz")):
        return None
    if _gzipped(path) != name.endswith(".gz"):
        return None
    first = _read_start(path, _SNIFF_BYTES) if read else start
    if first is None:
        return None
    return read_header(lambda n: first[:n] if n <= len(first) else _read_start(path, n))


#: the decompressed bytes nibabel reads of a file to find its format
_SNIFF_BYTES = 1024
#: the bytes :func:`_check_raw_header` needs (a NIfTI-2 header and its extension flag)
_HEADER_BYTES = 560


def nifti_geometry(header, where: str) -> tuple[dict, tuple[np.ndarray, str]]:
    """The Volume geometry (LPS, mm) of a NIfTI header, and the matrix chosen and its name.

    The keyword arguments of :class:`~volwarp_cli.volume.Volume` but ``data`` and
    ``meta``; the matrix is :func:`choose_affine`'s (the file's units, RAS).
    """
    with np.errstate(all="ignore"):  # an all-zero matrix: an error below, not a warning
        chosen = choose_affine(header, where)
        aff = np.array(chosen[0], dtype=np.float64)
        if not np.all(np.isfinite(aff[:3])):  # the numbers as the file has them, not derived
            rows = "; ".join(" ".join(f"{v:g}" for v in row) for row in aff[:3])
            raise FormatError(f"{where}: NIfTI {_FIELDS[chosen[1]]['origin'].split(' (')[0]}"
                              f" matrix has non-finite numbers ({rows})")
        aff[:3, :] *= _SPACE_UNIT_TO_MM.get(int(header["xyzt_units"]) & 7, 1.0)  # as ITK: mm
        lin = _RAS_TO_LPS @ aff[:3, :3]
        spacing = np.linalg.norm(lin, axis=0)
        direction = lin / np.where(spacing > 0, spacing, 1.0)[None, :]
        spacing, origin, direction = check_placement(
            spacing, _RAS_TO_LPS @ aff[:3, 3], direction, _space_sizes(header),
            where=where, fields=_FIELDS[chosen[1]])
        if chosen[1] == "sform":  # (a placement that holds: one that does not is an error)
            _say_sform_sizes(header, chosen[0], where)
        return dict(spacing=spacing, origin=origin, direction=direction, space=_LPS,
                    file_space=_RAS), chosen


#: how far, relatively, an sform's column length may be from its pixdim (float32 rounding;
#: ITK's own warning takes 1e-3 in the file's units, which hides a metre file's mismatch)
_SFORM_SIZE_TOLERANCE = 1e-4


def _say_sform_sizes(header, sform, where: str) -> None:
    """Warn where the sform read has voxel sizes other than ``pixdim``'s.

    volwarp takes the sform's (the matrix places every voxel, as nibabel's affine
    and SPM take it); ITK warns "unexpected scales in sform" and takes
    ``pixdim``'s, so the image has another extent there.
    """
    sizes = np.linalg.norm(np.asarray(sform, dtype=np.float64)[:3, :3], axis=0)
    pixdim = np.array([z if z > 0 else 1.0 for z in map(float, header["pixdim"][1:4])])
    if np.allclose(sizes, pixdim, rtol=_SFORM_SIZE_TOLERANCE, atol=0):
        return
    key = ("nifti-sizes", os.path.abspath(where))
    if not first_said(key):
        return
    log.warning("%s: the NIfTI sform's voxel sizes (%s) are not pixdim's (%s); volwarp reads "
                "the sform's, as nibabel's affine and SPM do (ITK and SimpleITK take pixdim's)",
                where, ", ".join(f"{v:.6g}" for v in sizes),
                ", ".join(f"{v:.6g}" for v in pixdim), extra={"once": key})


def _space_sizes(header) -> tuple[int, ...]:
    """The sizes of the three space axes (a 2-D image has one slice)."""
    shape = tuple(int(n) for n in header.get_data_shape()[:3])
    return shape + (1,) * (3 - len(shape))


def nifti_meta(nf: NiftiFile, chosen: tuple[np.ndarray, str],
               component: int | None = None) -> dict:
    """``Volume.meta`` of a NIfTI file (module docstring), ``chosen`` its matrix and name.

    ``component``: the component of a 5-D file that is read; its intent (vector,
    displacement, ...) describes the 5th axis, so it is not kept, and the
    component's name is ``volwarp_component`` as for a NRRD component.
    """
    header = nf.header
    meta = {**_extension_meta(header, nf.where), **_header_meta(header, nf.where, chosen,
                                                                 nf.shape[:3])}
    if component is not None:
        for key in _INTENT_KEYS:
            meta.pop(key, None)
        names = str(meta.pop("volwarp_components", "")).split()
        if len(names) == nf.components:
            meta["volwarp_component"] = names[component]
        elif "volwarp_field" in meta and nf.components == 3:  # write_field's x, y, z (LPS)
            meta["volwarp_component"] = "xyz"[component]
    return meta


def read_nifti(path: str | os.PathLike, volume_index: int | None = None) -> Volume:
    """Read a NIfTI file into LPS (module notes).

    ``volume_index`` picks a volume of a 4-D file or a component of a 5-D file.
    """
    nf = open_nifti(path)
    geometry, chosen = nifti_geometry(nf.header, nf.where)
    k, component = nf.select(volume_index)
    with np.errstate(all="ignore"):  # a degenerate matrix: an error below, not a warning
        return _read_samples(nf, k, geometry, nifti_meta(nf, chosen, component))


def _read_samples(nf: NiftiFile, k: int, geometry: dict, meta: dict) -> Volume:
    dtype = nf.sample_dtype()
    nvox = voxel_count(nf.shape[:3])
    ensure_fits_in_memory(nf.block_bytes + (nvox * 8 if nf.scaled else 0),
                          f"{nf.where} ({nf.shape[:3]})")
    data = np.frombuffer(nf.read_block(k), dtype=nf.file_dtype).reshape(xyz_to_zyx(nf.shape[:3]))
    if nf.scaled:  # as nibabel's data proxy scales, then in float32 or float64
        apply_read_scaling = nibabel().volumeutils.apply_read_scaling

        data = apply_read_scaling(data, np.asanyarray(nf.slope), np.asanyarray(nf.inter))
        data = data.astype(dtype)
    data = native(np.ascontiguousarray(data))  # [z, y, x]: the file's x-fastest order
    check_dtype(data.dtype, nf.where)
    return make_volume(nf.where, data, meta=meta, **geometry)


def _text_field(header, name: str) -> str:
    value = header.get(name)
    if value is None:
        return ""
    return bytes(np.asarray(value).tobytes()).split(b"\0", 1)[0].decode("latin-1").strip()


def _same_form(other: np.ndarray, chosen: np.ndarray, shape_xyz) -> bool:
    """True when ``other`` places every corner of the grid where ``chosen`` does.

    Within :data:`_SAME_FORM_VOXELS` of the smallest voxel size, or within ITK's
    1e-4 for every matrix entry.
    """
    other = np.asarray(other, dtype=np.float64)
    if np.allclose(other, chosen, rtol=0, atol=1e-4):
        return True
    corners = np.array([[i, j, k, 1.0] for i in (0, shape_xyz[0] - 1)
                        for j in (0, shape_xyz[1] - 1) for k in (0, shape_xyz[2] - 1)])
    gap = np.abs(corners @ (other - chosen)[:3].T).max()
    voxel = np.linalg.norm(chosen[:3, :3], axis=0).min()
    return bool(gap <= _SAME_FORM_VOXELS * voxel)


def _form_codes_read(header, where: str, chosen: tuple[np.ndarray, str],
                     shape_xyz) -> tuple[int, int]:
    """The sform and qform codes kept: a coded form whose matrix is not the one read is 0.

    volwarp carries one geometry, the matrix ITK's rule chose (module docstring);
    a code labels the world frame of its form's matrix, so only the forms holding
    that matrix keep theirs.
    """
    scode, qcode = int(header["sform_code"]), int(header["qform_code"])
    aff, name = chosen
    if name not in ("sform", "qform") or not (scode and qcode):
        return scode, qcode
    other = header.get_qform() if name == "sform" else header.get_sform()
    with np.errstate(all="ignore"):
        if _same_form(other, np.asarray(aff, dtype=np.float64), shape_xyz):
            return scode, qcode
    dropped = "qform" if name == "sform" else "sform"
    key = ("nifti-forms", os.path.abspath(where))
    if not first_said(key):
        return (scode, 0) if name == "sform" else (0, qcode)
    # (the qform read beside a coded sform: the readers that take the sform whenever it is
    # coded read another place, and so may ITK where its check of the two can pass)
    others = ""
    if name == "qform":
        itk = (", and so may SimpleITK (its check of the two forms misses a turn or a mirror "
               "of the voxel axes about one origin)") if _itk_may_read_sform(other, aff) else ""
        others = (f"; nibabel, FSL and SPM read the sform of this file{itk}: if the sform is "
                  "meant, set the qform code to 0")
    log.warning("%s: the NIfTI %s (code %d) places the image elsewhere than the %s "
                "(code %d) volwarp reads (ITK's rule); volwarp keeps the %s only (a NIfTI "
                "output gets %s code 0)%s", where, dropped,
                qcode if dropped == "qform" else scode, name,
                scode if name == "sform" else qcode, name, dropped, others,
                extra={"once": key})  # (a worker process's, said once with the run's)
    return (scode, 0) if name == "sform" else (0, qcode)


def _itk_may_read_sform(sform, qform) -> bool:
    """Whether ITK's check of a differing sform and qform can pass (it then reads the sform).

    ITK (NiftiImageIO) takes an orthonormal sform of code 2-4 beside a coded
    qform where their offsets and the singular values of their 3x3 parts agree
    within 1e-4 and the SVDs' left factors match: blind to a turn or a mirror
    on the voxel side, and to the signs its SVD happens to give. Where the
    offsets or the values differ, it reads the qform for certain.
    """
    s, q = np.asarray(sform, dtype=np.float64), np.asarray(qform, dtype=np.float64)
    with np.errstate(all="ignore"):  # (a column of zeros: NaN, and no orthonormal sform)
        lin = s[:3, :3] / np.linalg.norm(s[:3, :3], axis=0)[None, :]
    if not np.all(np.isfinite(lin)) or not np.allclose(lin @ lin.T, np.eye(3), atol=1e-4):
        return False
    if np.abs(s[:3, 3] - q[:3, 3]).max() > 1e-4:
        return False
    values = [np.linalg.svd(m[:3, :3], compute_uv=False) for m in (s, q)]
    return bool(np.abs(values[0] - values[1]).max() <= 1e-4)


def _header_meta(header, where: str, chosen: tuple[np.ndarray, str],
                 shape_xyz) -> dict[str, str]:
    """The header fields volwarp keeps (module docstring), as meta strings."""
    # only what differs from what the writer does anyway (codes 1 and 1, mm): a plain
    # scanner-coded file's key/values stay empty through NIfTI -> NRRD -> NIfTI
    meta = {}
    codes = _form_codes_read(header, where, chosen, shape_xyz)
    if codes != (1, 1):
        meta["NIfTI_sform_code"], meta["NIfTI_qform_code"] = (str(c) for c in codes)
    if int(header["xyzt_units"]) != _DEFAULT_XYZT_UNITS:
        meta["NIfTI_xyzt_units"] = str(int(header["xyzt_units"]))
    params = [float(header[f"intent_p{i}"]) for i in (1, 2, 3)]
    name = _text_field(header, "intent_name")
    if int(header["intent_code"]) or any(params) or name:
        meta["NIfTI_intent_code"] = str(int(header["intent_code"]))
        for i, p in enumerate(params, 1):
            meta[f"NIfTI_intent_p{i}"] = repr(p)
        meta["NIfTI_intent_name"] = name
    descrip = _text_field(header, "descrip")
    if descrip:
        meta["descrip"] = descrip
    for key, (name, kind) in AS_READ_FIELDS.items():  # (where set: not 0, not empty)
        if kind is None:
            text = _text_field(header, name)
            if text:
                meta[key] = text
            continue
        value = header.get(name)
        if value is None:
            continue
        value = float(np.asarray(value)) if kind is float else int(np.asarray(value))
        if value and (kind is not float or np.isfinite(value)):
            meta[key] = repr(value) if kind is float else str(value)
    return meta


def _as_read_fields(meta: dict) -> dict:
    """The :data:`AS_READ_FIELDS` of ``meta`` as header field values (invalid ones left out)."""
    fields = {}
    for key, (name, kind) in AS_READ_FIELDS.items():
        if key not in meta:
            continue
        if kind is None:
            fields[name] = str(meta[key]).encode("latin-1", errors="replace")[:23]
        elif kind is float:
            value = _meta_float(meta, key)
            if value and abs(value) <= np.finfo(np.float32).max:
                fields[name] = value
        else:
            value = _meta_int(meta, key, 0, *kind)
            if value:
                fields[name] = value
    return fields


def _extension_content(ext) -> bytes:
    content = getattr(ext, "content", None)
    if not isinstance(content, bytes):
        content = ext.get_content()
    return content if isinstance(content, bytes) else b""


def _extension_meta(header, where: str) -> dict:
    """The key/values of volwarp's own extension (module docstring); others are ignored."""
    meta: dict = {}
    for ext in header.extensions:
        if ext.get_code() != EXTENSION_CODE:
            continue
        content = _extension_content(ext)
        if not content.startswith(EXTENSION_PREFIX):
            continue  # another program's comment: not volwarp's to read
        text = content[len(EXTENSION_PREFIX):].rstrip(b"\0")
        try:
            values = json.loads(text.decode("utf-8"))
        except (UnicodeDecodeError, ValueError):
            raise FormatError(f"{where}: volwarp's NIfTI extension (code 6, "
                              f"{EXTENSION_PREFIX.decode().strip()}) is not valid JSON") from None
        if not isinstance(values, dict):
            raise FormatError(f"{where}: volwarp's NIfTI extension (code 6, "
                              f"{EXTENSION_PREFIX.decode().strip()}) is not a JSON object")
        meta.update(values)
    return meta


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())[:200]


class _ThreadFilter:
    """Drops the records of threads reading a NIfTI file (they go to volwarp's debug log).

    (A logging filter is any object with this method: no logging.Filter, so that
    this module does not import logging; nibabel, which logs, does.)
    """

    def __init__(self):
        self.threads: dict[int, int] = {}
        self.lock = threading.Lock()

    def filter(self, record) -> bool:
        if record.thread in self.threads:
            log.debug("nibabel: %s", record.getMessage())
            return False
        return True


_FILTER = _ThreadFilter()


@contextlib.contextmanager
def _quiet_nibabel():
    """Keep nibabel's header-fix messages ("sizeof_hdr should be 348; ...") off stderr.

    nibabel logs them through its own stderr handler; the contract is one
    line on stderr per failure, so they go to volwarp's debug log instead.
    """
    import logging

    logger = logging.getLogger("nibabel.global")
    ident = threading.get_ident()
    with _FILTER.lock:
        if _FILTER not in logger.filters:
            logger.addFilter(_FILTER)
        _FILTER.threads[ident] = _FILTER.threads.get(ident, 0) + 1
    try:
        yield
    finally:
        with _FILTER.lock:
            _FILTER.threads[ident] -= 1
            if not _FILTER.threads[ident]:
                del _FILTER.threads[ident]


def _meta_int(meta: dict, key: str, default: int, lo: int, hi: int) -> int:
    """``meta[key]`` as an integer in lo..hi, else ``default`` (a hand-edited NRRD key)."""
    if key not in meta:
        return default
    try:
        value = int(str(meta[key]).strip())
    except ValueError:
        value = None
    if value is None or not lo <= value <= hi:
        log.debug("%s = %r is not an integer in %d..%d: writing %d", key, meta[key], lo, hi,
                  default)
        return default
    return value


def _meta_float(meta: dict, key: str) -> float:
    try:
        value = float(str(meta.get(key, 0.0)))
    except ValueError:
        value = 0.0
    return value if np.isfinite(value) else 0.0


def form_codes(meta: dict, ras: np.ndarray, spacing: np.ndarray,
                shape_xyz) -> tuple[int, int]:
    """The sform and qform codes to write (module docstring: the codes rule)."""
    scode = _meta_int(meta, "NIfTI_sform_code", 1, 0, 5)
    qcode = _meta_int(meta, "NIfTI_qform_code", 1, 0, 5)
    lin = ras[:3, :3] / spacing[None, :]
    if scode == 0 and qcode == 0:
        method1 = (np.allclose(lin, np.diag([-1.0, -1.0, 1.0]), rtol=0, atol=1e-6)
                   and np.allclose(ras[:3, 3], 0, rtol=0, atol=1e-6 * max(1.0, spacing.max())))
        if not method1:  # the geometry needs a coded matrix to be read back
            scode = qcode = 1
    if qcode and not _qform_holds(ras, shape_xyz):
        # (the sform carries the matrix in the same frame; a coded qform beside it would be
        # read instead by ITK for codes 2-4, and by volwarp, with a warning)
        scode, qcode = scode or qcode, 0
    return scode, qcode


def _qform_holds(ras: np.ndarray, shape_xyz) -> bool:
    """Whether the qform written of ``ras`` places the grid where ``ras`` does, as readers read it.

    Its quaternion is float32 and nibabel and niftilib (ITK, FSL) complete w
    from it: a rotation near a half turn (an LPS grid turned slightly in its
    plane, in RAS) loses up to 1.3e-3 rad (0.3 mm 230 mm out), a shear is
    lost. Held: its rotation within :data:`ORTHONORMAL_TOLERANCE` of the
    matrix's normalised columns (what the writer allows of a direction that is
    not quite orthonormal, whose qform is its nearest rotation), and the same
    form by the reading rule (:func:`_same_form`, so a file read back keeps its
    codes). A direction read from a quaternion is held to 1e-7 (9e-8 measured
    on 1e5 quaternions near a half turn, read and written again).
    """
    from .niftiheader import written_qforms

    lin = ras[:3, :3] / np.linalg.norm(ras[:3, :3], axis=0)[None, :]
    for qform in written_qforms(ras):
        rot = qform[:3, :3] / np.linalg.norm(qform[:3, :3], axis=0)[None, :]
        if not (np.abs(rot - lin).max() <= ORTHONORMAL_TOLERANCE
                and _same_form(qform, ras, shape_xyz)):
            return False
    return True


def _extension(meta: dict) -> tuple[int, bytes] | None:
    """The header extension ``(code, content)`` of the meta that is no header field (volwarp's)."""
    rest = {str(k): v for k, v in meta.items() if k not in HEADER_KEYS}
    if not rest:
        return None
    text = json.dumps(rest, sort_keys=True, ensure_ascii=True, separators=(",", ":"),
                      default=str)
    return EXTENSION_CODE, EXTENSION_PREFIX + text.encode("ascii")


#: the largest entry of ``D'D - I`` of a direction the NIfTI writer takes (written as it
#: is into the sform, its nearest rotation into the qform). A rotation rounded to d
#: decimals (a DICOM orientation, an NRRD's space directions) is off by up to 3e-d (1.7e-d
#: measured on 200000 random ones): 1e-6 refused 2.7% of those rounded to 6 decimals and
#: nearly all of those rounded to 5. Within 3e-5, ITK (its reader: the sform's normalised
#: columns, in float32, orthonormal within 1e-4 entry by entry; at most 5.1e-5 measured)
#: and volwarp read the sform, as nibabel always does, so the grid lands where it lay; a
#: reader of the qform (an sform coded 0, ITK's SVD test of codes 2-4) is off by at most
#: about half of it times the grid's extent. A real shear (a gantry tilt) is refused.
ORTHONORMAL_TOLERANCE = 3e-5


def write_nifti(vol: Volume, path: str | os.PathLike, *, dtype=None) -> None:
    """Write ``vol`` as NIfTI-1 (gzipped for ``.gz``), atomically, keeping the meta it can.

    ``dtype``: the samples cast to it as they are written (``.nii`` only:
    :func:`~volwarp_cli.io.write_volume` casts a ``.nii.gz`` output's first).
    """
    path = Path(path)
    check_dtype(vol.data.dtype if dtype is None else dtype, str(path))
    d = np.asarray(vol.direction, dtype=np.float64)
    off = float(np.abs(d.T @ d - np.eye(3)).max())
    if not off <= ORTHONORMAL_TOLERANCE:
        # ITK, SimpleITK and volwarp's reader would take the qform, which has no shear:
        # the grid would land elsewhere (a gantry tilt kept with --keep-shear, say)
        raise VolwarpError(f"{path}: the grid is sheared (its axes are not orthogonal: "
                           f"its direction's columns are {off:.2g} off orthonormal), "
                           "which NIfTI readers do not keep; write .nrrd or .mha")
    meta = dict(vol.meta)
    units = _meta_int(meta, "NIfTI_xyzt_units", _DEFAULT_XYZT_UNITS, 0, 255)
    to_file_units = 1.0 / _SPACE_UNIT_TO_MM.get(units & 7, 1.0)  # the file's own units
    aff = ras_affine(vol, to_file_units)
    if not np.all(np.abs(aff) <= np.finfo(np.float32).max):
        raise VolwarpError(f"{path}: the geometry (spacing or origin up to "
                           f"{np.abs(aff).max():.3g}) is beyond NIfTI's float32 matrices; "
                           "write .nrrd or .mha")
    codes = form_codes(meta, aff, vol.spacing * to_file_units, vol.data.shape[::-1])
    intent = None
    if any(k in meta for k in _INTENT_KEYS):
        intent = (_meta_int(meta, "NIfTI_intent_code", 0, -32768, 32767),
                  [_meta_float(meta, f"NIfTI_intent_p{i}") for i in (1, 2, 3)],
                  str(meta.get("NIfTI_intent_name", "")))
    write_nifti_file(path, vol.data.transpose(2, 1, 0), aff, units=units, codes=codes,
                     intent=intent, descrip=str(meta.get("descrip", "")), meta=meta,
                     dtype=dtype, fields=_as_read_fields(meta))


#: voxels: a move of the grid by NIfTI's float32 matrices that is said
FLOAT32_SHIFT_SAID = 0.01


def _say_float32_shift(aff: np.ndarray, shape_xyz, path) -> None:
    """Say where NIfTI's float32 matrices move the grid by :data:`FLOAT32_SHIFT_SAID` voxel or more.

    The sform's rows are float32: a grid far from the origin with small voxels
    (1e-3 mm voxels 1e5 mm out, where float32's step is 0.008 mm) moved by a
    voxel or more without a word, within the format's precision. The
    corners' shift in voxels of the smallest size.
    """
    aff = np.asarray(aff, dtype=np.float64)
    corners = np.array([[x, y, z, 1.0] for x in (0, shape_xyz[0] - 1)
                        for y in (0, shape_xyz[1] - 1) for z in (0, shape_xyz[2] - 1)]).T
    with np.errstate(all="ignore"):
        moved = np.abs((aff.astype(np.float32).astype(np.float64) - aff) @ corners)[:3].max()
        voxel = float(np.linalg.norm(aff[:3, :3], axis=0).min())
    if voxel > 0 and moved >= FLOAT32_SHIFT_SAID * voxel:
        log.warning("warning: %s: NIfTI keeps its matrix in float32, which moves the grid's "
                    "corners by up to %.3g voxels here (write .nrrd or .mha to keep the "
                    "geometry exact)", path, moved / voxel)


def ras_affine(grid, scale: float = 1.0) -> np.ndarray:
    """The voxel-to-RAS 4x4 matrix of an LPS grid (a Volume, a Header), ``scale`` per mm."""
    aff = np.eye(4)
    aff[:3, :3] = _RAS_TO_LPS @ (grid.direction * grid.spacing[None, :]) * scale
    aff[:3, 3] = _RAS_TO_LPS @ grid.origin * scale
    return aff


def write_nifti_file(path: str | os.PathLike, data_xyz: np.ndarray, aff: np.ndarray, *,
                     units: int, codes: tuple[int, int], intent=None, descrip: str = "",
                     meta: dict | None = None, dtype=None, fields: dict | None = None) -> None:
    """``data_xyz`` (x fastest: 3-D, or 5-D with vectors) as a NIfTI-1 file, atomically.

    Gzipped for a ``.gz`` path. ``aff``: the voxel-to-RAS matrix written in
    both forms with ``codes`` (sform, qform); ``units``: ``xyzt_units``;
    ``intent``: ``(code, (p1, p2, p3), name)`` or None (none); ``descrip``
    (at most 79 bytes, latin-1); ``meta``: the key/values that are no header
    field go into volwarp's extension (module notes). ``dtype``: the samples
    cast to it as they are written (``.nii`` only: a ``.gz`` file's samples are
    cast before). ``fields``: other header fields, by name (:func:`_as_read_fields`).
    """
    import sys

    from .niftiheader import nifti1_header_bytes

    samples = np.asarray(data_xyz).T  # [.., z, y, x]: x fastest in memory, as the file has it
    gz = str(path).lower().endswith(".gz")
    if dtype is not None and gz:
        raise ValueError("write_nifti_file: a .gz output's samples are cast before")
    if gz:
        samples = np.ascontiguousarray(samples, dtype=samples.dtype.newbyteorder("="))
    out_dtype = check_dtype(samples.dtype if dtype is None else dtype, str(path))
    if intent is not None:
        code, params, name = intent
        intent = (code, params, name[:15].encode("latin-1", errors="replace"))
    ext = _extension(meta or {})
    _say_float32_shift(aff, samples.shape[::-1][:3], path)
    try:
        head = nifti1_header_bytes(samples.shape[::-1], out_dtype, aff, codes=codes,
                                   units=units, intent=intent, fields=fields,
                                   descrip=descrip[:79].encode("latin-1", errors="replace"),
                                   extensions=() if ext is None else (ext,))
    except ValueError as exc:
        raise VolwarpError(f"{path}: {exc}") from None
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:
        if gz:  # (the stream written as it is made; ISA-L loaded for a .nii.gz only)
            from .deflate import gzip_to

            gzip_to(fh, head, memoryview(samples).cast("B"))
        else:  # (in the machine's order, cast by slabs where it must be)
            fh.write(head)
            write_samples(fh, samples, sys.byteorder, dtype, what=str(path))
