"""NIfTI-1/2 (``.nii``, ``.nii.gz``) via nibabel, in the LPS frame SimpleITK reports.

NIfTI stores a voxel-to-RAS matrix; volwarp (like ITK, DICOM and 3D Slicer's
files) works in LPS, so x and y of the world are negated on the way in and out.

Which matrix is used follows ITK's NiftiImageIO (so volwarp and SimpleITK place
every file alike):

1. neither form coded (``sform_code == qform_code == 0``, "method 1"): the
   voxel sizes ``pixdim[1:4]`` on the diagonal, origin 0;
2. the sform, when it is coded and orthonormal once its column lengths are
   divided out, and either the qform is not coded, or the sform's code is 1
   (scanner), or both forms agree within 1e-4;
3. else the qform, when it is coded;
4. else the (skewed) sform: ITK refuses such files, volwarp keeps the shear in
   ``direction``.

Written files carry the same matrix as both sform and qform, code 1
(scanner), so every reader finds the same geometry whichever it prefers.
Files with a 4th dimension longer than 1 are refused unless ``volume_index``
picks one volume.
"""

from __future__ import annotations

import contextlib
import gzip
import logging
import os
import threading
from pathlib import Path

import numpy as np

from ..errors import FormatError, VolwarpError
from ..volume import Volume
from .atomic import atomic_output
from .common import check_dtype, ensure_fits_in_memory, make_volume, native, voxel_count

log = logging.getLogger("volwarp")

_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0])


def choose_affine(header) -> tuple[np.ndarray, str]:
    """The voxel-to-RAS 4x4 matrix by ITK's rule (module docstring), and its name."""
    zooms = np.array([float(z) if z > 0 else 1.0 for z in header["pixdim"][1:4]])
    sform, scode = header.get_sform(coded=True)
    qform, qcode = header.get_qform(coded=True)
    scode = int(scode or 0) if sform is not None else 0
    qcode = int(qcode or 0) if qform is not None else 0
    if scode == 0 and qcode == 0:
        aff = np.eye(4)
        aff[:3, :3] = np.diag(zooms)
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


def read_nifti(path: str | os.PathLike, volume_index: int | None = None) -> Volume:
    import nibabel as nib
    from nibabel.filebasedimages import ImageFileError

    where = str(path)
    with _quiet_nibabel():
        try:
            img = nib.load(str(path))
        except (ImageFileError, OSError, EOFError, ValueError) as exc:
            raise FormatError(f"{where}: not a readable NIfTI file ({_one_line(exc)})") from None
        except Exception as exc:  # nibabel's HeaderDataError and others, for damaged headers
            raise FormatError(f"{where}: not a readable NIfTI file "
                              f"({type(exc).__name__}: {_one_line(exc)})") from None
    shape = tuple(int(s) for s in img.shape)
    if not shape or any(s <= 0 for s in shape):
        dims = [int(d) for d in img.header["dim"]]
        raise FormatError(f"{where}: NIfTI sizes must be positive, got {shape} "
                          f"(header dim {dims})")
    if len(shape) < 3:
        shape = shape + (1,) * (3 - len(shape))
    extra = shape[3:]
    if any(s > 1 for s in extra[1:]):
        raise FormatError(f"{where}: NIfTI with shape {shape} has more than 4 dimensions")
    nvol = extra[0] if extra else 1
    if nvol > 1 and volume_index is None:
        raise FormatError(f"{where}: 4-D NIfTI with {nvol} volumes; choose one with "
                          "--volume-index N")
    if volume_index is not None and not 0 <= volume_index < nvol:
        raise VolwarpError(f"{where}: --volume-index {volume_index} is outside 0..{nvol - 1}")
    dtype = img.get_data_dtype()
    slope, inter = img.header.get_slope_inter()
    scaled = slope is not None and not (np.isnan(slope) or (slope == 1 and not inter))
    item = 8 if scaled else np.dtype(dtype).itemsize
    ensure_fits_in_memory(voxel_count(shape[:3]) * item, f"{where} ({shape[:3]})")
    try:
        proxy = img.dataobj
        if len(img.shape) >= 4:
            index = (slice(None),) * 3 + (volume_index or 0,) + (0,) * (len(img.shape) - 4)
            arr = np.asanyarray(proxy[index])
        else:
            arr = np.asanyarray(proxy)
    except (OSError, EOFError, ValueError) as exc:
        raise FormatError(f"{where}: cannot read NIfTI data ({exc})") from None
    arr = arr.reshape(shape[:3], order="A") if arr.ndim != 3 else arr
    if scaled:
        arr = arr.astype(np.float32) if np.dtype(dtype).itemsize <= 2 else arr.astype(np.float64)
    check_dtype(arr.dtype, where)
    data = native(np.ascontiguousarray(arr.transpose(2, 1, 0)))
    aff, _ = choose_affine(img.header)
    lin = _RAS_TO_LPS @ aff[:3, :3]
    spacing = np.linalg.norm(lin, axis=0)
    if np.any(spacing == 0):
        raise FormatError(f"{where}: NIfTI matrix has a zero-length axis")
    meta = {}
    descrip = img.header.get("descrip")
    if descrip is not None:
        text = bytes(np.asarray(descrip).tobytes()).split(b"\0", 1)[0].decode("latin-1").strip()
        if text:
            meta["descrip"] = text
    return make_volume(where, data, spacing=spacing, origin=_RAS_TO_LPS @ aff[:3, 3],
                       direction=lin / spacing[None, :], space="left-posterior-superior",
                       meta=meta)


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())[:200]


class _ThreadFilter(logging.Filter):
    """Drops the records of threads reading a NIfTI file (they go to volwarp's debug log)."""

    def __init__(self):
        super().__init__()
        self.threads: dict[int, int] = {}
        self.lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
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


def write_nifti(vol: Volume, path: str | os.PathLike) -> None:
    import nibabel as nib

    path = Path(path)
    check_dtype(vol.data.dtype, str(path))
    aff = np.eye(4)
    aff[:3, :3] = _RAS_TO_LPS @ (vol.direction * vol.spacing[None, :])
    aff[:3, 3] = _RAS_TO_LPS @ vol.origin
    img = nib.Nifti1Image(vol.data.transpose(2, 1, 0), aff)
    img.header.set_xyzt_units("mm")
    img.set_sform(aff, code=1)
    img.set_qform(aff, code=1)
    descrip = str(vol.meta.get("descrip", ""))[:79]
    if descrip:
        img.header["descrip"] = descrip.encode("latin-1", errors="replace")
    payload = img.to_bytes()
    if path.name.lower().endswith(".gz"):
        payload = gzip.compress(payload, compresslevel=1, mtime=0)
    with atomic_output(path) as tmp:
        tmp.write_bytes(payload)
