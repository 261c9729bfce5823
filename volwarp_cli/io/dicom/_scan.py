"""Finding DICOM files, reading their headers, and grouping the frames into candidates.

Headers are read with ``stop_before_pixels``; the file position pydicom stops
at is the PixelData element, whose offset and length the pixel reader uses
later. One :class:`Frame` per image (a classic file has one, a multi-frame
file one per frame) carries what the grouping and the geometry need.
"""

from __future__ import annotations

import os
import struct
import time
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydicom.multival import MultiValue

from ...errors import FormatError, VolwarpError
from ...progress import log
from ...runscope import first_said
from ..inputs import has_dicom_preamble as _has_preamble

try:  # the command line maps ChoiceNeeded to a usage error (exit 2)
    from ...errors import ChoiceNeeded as _ChoiceBase
except ImportError:  # pragma: no cover - an errors module without it
    _ChoiceBase = VolwarpError


DICOMDIR_SOP = "1.2.840.10008.1.3.10"
RTDOSE_SOP = "1.2.840.10008.5.1.4.1.1.481.2"
_PIXEL_TAG = (0x7FE0, 0x0010)
_FLOAT_PIXEL_TAGS = ((0x7FE0, 0x0008), (0x7FE0, 0x0009))
_BIG_ENDIAN = "1.2.840.10008.1.2.2"
_IMPLICIT = "1.2.840.10008.1.2"
_EXPLICIT = "1.2.840.10008.1.2.1"
#: the VRs PixelData can have in an explicit VR data set
_PIXEL_VRS = (b"OB", b"OW", b"OD", b"OF", b"OL", b"OV", b"UN")
_DEFLATED = "1.2.840.10008.1.2.1.99"

_STUB = "image without pixels: "

#: tags kept in ``meta`` as ``DICOM_<keyword>``
META_TAGS = ("Modality", "SeriesDescription", "SeriesNumber", "PatientPosition",
             "StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID", "SOPClassUID",
             "DoseUnits", "DoseType", "DoseSummationType")
#: identifying tags, kept only with ``keep_phi``
PHI_TAGS = ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "PatientAge",
            "OtherPatientIDs", "AccessionNumber", "StudyDate", "StudyTime", "SeriesDate",
            "AcquisitionDate", "ContentDate", "InstitutionName", "ReferringPhysicianName",
            "StudyID", "StudyDescription")

#: position tolerance (mm) for "same orientation / same pixel spacing"
_ATOL = 1e-4
#: |row . column| of ImageOrientationPatient taken for a right angle (the cosines rounded):
#: :attr:`volwarp_cli.geometry.Geometry.right_angled`'s tolerance
_SQUARE = 1e-4
#: what ``Frame.assumed`` says of an image without PixelSpacing (or ImagerPixelSpacing)
NO_PIXEL_SPACING = "1 mm pixels (no PixelSpacing)"
#: a file's first bytes its stamp hashes (its header, up to the pixel data)
HEADER_STAMP_BYTES = 1 << 16


class DicomSeriesChoiceError(_ChoiceBase):
    """A path holds several candidate volumes and none was chosen (a usage error)."""


@dataclass
class FileInfo:
    """Per-file facts the pixel reader needs."""

    path: str
    label: str
    transfer_syntax: str
    ts_name: str
    rows: int
    columns: int
    bits_allocated: int
    bits_stored: int
    signed: bool
    samples: int
    n_frames: int
    pixel_offset: int | None
    pixel_length: int | None
    dose_scaling: float | None
    meta: dict
    sop_uid: str = ""
    #: :func:`~volwarp_cli.io.mapped.stamp` of the file as its header was read: its
    #: pixels are read later (by offset, or a stack slab by slab as the work goes), from
    #: it only (:func:`._pixels.open_unchanged`)
    stamp: tuple | None = None


@dataclass
class Frame:
    """One 2-D image: where it lies and how its samples map to values."""

    file: FileInfo
    frame: int
    order: int
    position: np.ndarray | None
    row: np.ndarray | None
    col: np.ndarray | None
    pixel_spacing: tuple[float, float]  # (x, y): PixelSpacing[1], PixelSpacing[0]
    slope: float
    intercept: float
    single_spacing: float
    series_uid: str
    keys: dict
    split_keys: dict
    localizer: bool = False
    synthetic: bool = False  # placed by volwarp: the file gives no position per frame
    assumed: str = ""  # what the file does not say and volwarp took (DICOM_geometry)
    problem: str = ""

    @property
    def label(self) -> str:
        if self.file.n_frames > 1:
            return f"{self.file.label} frame {self.frame + 1}"
        return self.file.label


@dataclass(frozen=True)
class Candidate:
    """One volume a DICOM path holds (``index`` is what ``series=`` takes)."""

    index: int
    series_uid: str
    description: str
    modality: str
    shape_xyz: tuple[int, int, int]
    spacing: tuple[float, float, float]
    n_files: int
    n_frames: int
    why: str
    series_number: int | None = None
    frames: tuple = field(default=(), repr=False, compare=False)
    problem: str = ""  # (why it cannot be read: a file of its series cut short)

    def describe(self) -> dict:
        """A JSON-able description (for ``volwarp info --json``)."""
        return {"index": self.index, "series_uid": self.series_uid,
                "description": self.description, "modality": self.modality,
                "series_number": self.series_number, "shape_xyz": list(self.shape_xyz),
                "spacing": [round(float(s), 6) for s in self.spacing],
                "files": self.n_files, "frames": self.n_frames, "why": self.why}

    def one_line(self) -> str:
        x, y, z = self.shape_xyz
        desc = f" {self.description!r}" if self.description else ""
        why = f" ({self.why})" if self.why else ""
        return (f"[{self.index}] {self.series_uid}{desc} {self.modality} {x}x{y}x{z}, "
                f"{self.n_files} file(s), {self.n_frames} frame(s){why}")


# -- finding files -------------------------------------------------------------

def is_dicom_path(path) -> bool:
    """True for a folder holding DICOM files (recursively), a DICOMDIR, or a DICOM file."""
    p = Path(path)
    if p.is_dir():  # (by content, as the folder's files are read: the preamble or not)
        for root, dirs, files in os.walk(p):
            dirs.sort()
            for name in sorted(files):  # (a copy under way too: its reader says so)
                if _folder_file(os.path.join(root, name), name) in ("dicom", _HIDDEN_COPY):
                    return True
        return False
    if not p.is_file():
        return False
    if _has_preamble(str(p)):
        return True
    if p.suffix.lower() == ".dcm" or p.name.upper() == "DICOMDIR":
        try:
            _read_dataset(str(p), force=True)
            return True
        except FormatError:
            return False
    return False


def _read_dataset(path: str, *, force: bool = False, stop: bool = True):
    """``(dataset, position, tail, stamp)`` of the file, or a FormatError naming it.

    ``position``: where pydicom stopped; ``tail``: the 12 bytes from there;
    ``stamp``: what tells this file from another put in its place or
    rewritten before its pixels are read (:func:`~volwarp_cli.io.mapped.stamp`
    of the header read).
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    from ..mapped import stamp as file_stamp

    try:
        with warnings.catch_warnings(record=True) as caught, open(path, "rb") as fh:
            warnings.simplefilter("always")
            before = os.fstat(fh.fileno())
            ds = pydicom.dcmread(fh, stop_before_pixels=stop, force=force)
            pos = fh.tell()
            fh.seek(pos)
            tail = fh.read(12)
            stamped = file_stamp(fh.fileno(), min(pos, HEADER_STAMP_BYTES))
            if stamped[1][:2] != ((before.st_size, before.st_mtime_ns, before.st_ino),
                                  before.st_ctime_ns):
                raise FormatError(f"{path}: the file changed while its header was being read "
                                  "(rewritten by another program?)")
        for w in caught:
            log.debug("pydicom: %s: %s", path, w.message)
    except FormatError:
        raise
    except InvalidDicomError as exc:
        raise FormatError(f"{path}: not a DICOM file ({_one_line(exc)})") from None
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except zlib.error as exc:  # a Deflated Explicit VR Little Endian body
        raise FormatError(f"{path}: the deflated data set is truncated or damaged "
                          f"({_one_line(exc)})") from None
    except Exception as exc:  # truncated or damaged headers raise many types in pydicom
        raise FormatError(f"{path}: damaged DICOM header ({type(exc).__name__}: "
                          f"{_one_line(exc)})") from None
    if force and "TransferSyntaxUID" not in getattr(ds, "file_meta", {}):
        if len(ds) == 0:
            raise FormatError(f"{path}: not a DICOM file (no data elements)")
    return ds, pos, tail, stamped


#: file names that say "DICOM" (an empty or foreign one of them in a series folder is refused)
_DICOM_SUFFIXES = (".dcm", ".dicom", ".dic", ".ima")


def _looks_like_dicom_body(head: bytes) -> bool:
    """True where a file without the preamble starts as a DICOM data set does.

    Its first element is of group 0002 (file meta) or 0008 (identification),
    little-endian, implicit or explicit VR: GDCM and pydicom read such files,
    and a series folder copied by older tools holds them.
    """
    if len(head) < 8:
        return False
    group, elem = struct.unpack("<HH", head[:4])
    if group not in (0x0002, 0x0008) or elem > 0x0100:
        return False
    if head[4:6].isalpha() and head[4:6].isupper():  # an explicit VR
        return True
    (length,) = struct.unpack("<I", head[4:8])  # implicit: a sane length
    return length < 1 << 16


#: a hidden file of a series folder holding a DICOM data set (:func:`_folder_file`)
_HIDDEN_COPY = ("a hidden DICOM file (a copy under way? rsync writes .NAME.XXXXXX until the "
                "file is whole: let it end, or move it out)")


def _folder_file(full: str, name: str) -> str:
    """"dicom", "" (skip: not DICOM) or a reason to refuse, for one file of a series folder.

    A file volwarp cannot open, or an empty or foreign one named like a DICOM
    file, may be a slice: skipped, it left a volume a slice short (the first or
    last: nothing else shows it) with exit 0. A hidden file (macOS's ``._*``
    companions, ``.DS_Store``, locks, links) is skipped whatever it is, unless
    it holds a DICOM data set: that is a copy under way (rsync writes each file
    as ``.NAME.XXXXXX`` and renames it when whole), its slice not there yet.
    A hidden link is no copy (rsync writes files): skipped, as it always was.
    """
    hidden = name.startswith(".")
    if hidden and os.path.islink(full):
        return ""
    try:
        st = os.stat(full)
    except OSError as exc:
        return "" if hidden else f"cannot read ({exc.strerror or exc})"
    import stat

    if not stat.S_ISREG(st.st_mode):
        return ""  # (a FIFO or socket: opening it could block)
    try:
        with open(full, "rb") as fh:
            head = fh.read(132)
    except OSError as exc:
        return "" if hidden else f"cannot read ({exc.strerror or exc})"
    dicom = (len(head) == 132 and head[128:132] == b"DICM") or _looks_like_dicom_body(head)
    if hidden:
        return _HIDDEN_COPY if dicom else ""
    if dicom:
        return "dicom"
    if name.lower().endswith(_DICOM_SUFFIXES):
        return "empty file" if not head else "not a DICOM file (no DICM preamble, no DICOM header)"
    return ""


def _files_of(path: Path) -> tuple[list[tuple[str, str]], int]:
    """(file path, label) of the DICOM files under ``path``, and how many files were looked at.

    In a folder: files with DICOM's preamble, and those starting as a DICOM data
    set without it. A file that cannot be read, or an empty or foreign one named
    ``*.dcm`` (``.dicom``, ``.dic``, ``.ima``), is refused; other files are
    skipped, and a warning says how many.
    """
    if path.is_dir():
        out, seen, skipped = [], 0, []
        for root, dirs, files in os.walk(path):
            dirs.sort()
            for name in sorted(files):
                seen += 1
                full = os.path.join(root, name)
                kind = _folder_file(full, name)
                if kind == "dicom":
                    out.append((full, os.path.relpath(full, path)))
                elif kind:
                    raise FormatError(f"{full}: {kind}: a file of the DICOM folder {path} "
                                      "(a slice lost would leave the volume short)")
                elif not name.startswith("."):
                    skipped.append(os.path.relpath(full, path))
        if out and skipped:
            more = f" and {len(skipped) - 1} more" if len(skipped) > 1 else ""
            log.warning("warning: %s: %s%s skipped (not DICOM)", path, skipped[0], more)
        _say_young(path, [f for f, _ in out])
        return out, seen
    if not path.exists():
        raise FormatError(f"{path}: no such file or folder")
    ds = _read_dataset(str(path), force=not _has_preamble(str(path)))[0]
    if _sop_class(ds) == DICOMDIR_SOP or "DirectoryRecordSequence" in ds:
        return _dicomdir_files(path, ds), 1
    return [(str(path), path.name)], 1


#: seconds: a series folder whose newest file is younger is said to be (:func:`_say_young`)
YOUNG_SECONDS = 5.0


def _say_young(path: Path, files: list[str]) -> None:
    """Warn, once a run, where the newest of a series folder's files is seconds old.

    No tag says how many slices a classic series has: a folder read while a
    PACS or rsync is still storing slices gives a volume short of them, and
    nothing else shows it. A command is not refused (a folder just written
    whole is as young); ``volwarp batch`` leaves such a folder to its next run
    (``inputs.settle``).
    """
    from ...batch.content import age_words, last_change

    now = time.time()
    newest = last_change(files, now)
    if newest is None:
        return
    age = now - newest
    if age < YOUNG_SECONDS and first_said(("young series", os.path.realpath(path))):
        log.warning("warning: the newest file of %s is %s: a series still being copied "
                    "would be read short", path, age_words(age))


def _dicomdir_files(path: Path, ds) -> list[tuple[str, str]]:
    base = path.parent
    out, missing = [], []
    for rec in ds.get("DirectoryRecordSequence", []):
        ref = rec.get("ReferencedFileID")
        if ref is None:
            continue
        parts = [str(p) for p in (ref if isinstance(ref, list | tuple) or
                                  type(ref).__name__ == "MultiValue" else [ref])]
        full = base.joinpath(*parts)
        if not full.is_file():
            missing.append(str(full))
            continue
        out.append((str(full), os.path.relpath(full, base)))
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise FormatError(f"{path}: DICOMDIR references missing file {missing[0]}{more}")
    if not out:
        raise FormatError(f"{path}: DICOMDIR references no files")
    return sorted(set(out))


def _sop_class(ds) -> str:
    uid = ds.get("SOPClassUID")
    if uid is None:
        uid = getattr(ds, "file_meta", {}).get("MediaStorageSOPClassUID")
    return str(uid) if uid is not None else ""


# -- headers -> frames -------------------------------------------------------------

def _one_line(exc) -> str:
    return " ".join(str(exc).split())[:200]


def _floats(ds, keyword: str, n: int, where: str):
    elem = ds.get(keyword)
    if elem is None or elem == "":
        return None
    try:
        vals = [float(v) for v in (elem if hasattr(elem, "__len__") and not isinstance(elem, str)
                                   else [elem])]
    except (TypeError, ValueError):
        raise FormatError(f"{where}: {keyword} is not numeric ({elem!r})") from None
    if len(vals) != n or not all(np.isfinite(vals)):
        raise FormatError(f"{where}: {keyword} must have {n} finite values, got {elem!r}")
    return np.array(vals)


def _float(ds, keyword: str, default, where: str):
    v = _floats(ds, keyword, 1, where) if ds is not None else None
    return default if v is None else float(v[0])


def _text(ds, keyword: str) -> str:
    v = ds.get(keyword) if ds is not None else None
    if v is None:
        return ""
    if isinstance(v, list | tuple | MultiValue):
        return "\\".join(str(x) for x in v)
    return str(v).strip()


def _int(ds, keyword: str, where: str, default=None):
    v = ds.get(keyword)
    if v is None or v == "":
        if default is None:
            raise FormatError(f"{where}: {keyword} is missing")
        return default
    try:
        return int(v)
    except (TypeError, ValueError):
        raise FormatError(f"{where}: {keyword} is not an integer ({v!r})") from None


def _cosines(iop, where: str):
    row, col = iop[:3], iop[3:]
    nr, nc = np.linalg.norm(row), np.linalg.norm(col)
    if nr < 1e-6 or nc < 1e-6:
        raise FormatError(f"{where}: ImageOrientationPatient has a zero vector ({iop.tolist()})")
    row, col = row / nr, col / nc
    if np.linalg.norm(np.cross(row, col)) < 1e-3:
        raise FormatError(f"{where}: ImageOrientationPatient row and column are parallel "
                          f"({iop.tolist()})")
    dot = float(row @ col)
    if 0 < abs(dot) <= _SQUARE:
        # cosines rounded by the scanner, a hair off a right angle: the row made square to
        # the column as ITK does (SimpleITK's direction); kept, the grid was sheared by
        # that hair and NIfTI outputs refused it
        row = row - dot * col
        row /= np.linalg.norm(row)
    return row, col


def _pixel_element(tail: bytes, ts: str, pos: int, size: int, where: str = ""):
    """(offset, length) of a raw PixelData value from the 12 bytes after the header, or Nones.

    The element is parsed as it is written, not as the transfer syntax says: a
    file's meta can name Implicit VR over an Explicit VR body or the other way
    round (pydicom reads such bodies right). Taken by the meta, the value
    started 4 bytes early or late: samples shifted, exit 0. The two are told
    apart by the bytes after the tag: an explicit VR's two letters and two
    zero bytes, which as an implicit length would be odd (``OW``: 22351), and
    DICOM values have even lengths. Encapsulated (compressed) pixel data under
    an uncompressed transfer syntax is refused: read as raw, the fragments'
    bytes were taken for samples.
    """
    if len(tail) < 8:
        return None, None, False
    endian = ">" if ts == _BIG_ENDIAN else "<"
    group, elem = struct.unpack(endian + "HH", tail[:4])
    if (group, elem) in _FLOAT_PIXEL_TAGS:
        return None, None, "float"
    if (group, elem) != _PIXEL_TAG:
        return None, None, False
    if tail[4:6] not in _PIXEL_VRS or tail[6:8] != b"\0\0":  # implicit VR
        (length,) = struct.unpack("<I", tail[4:8])
        offset = pos + 8
    else:
        if len(tail) < 12:
            return None, None, True
        (length,) = struct.unpack(endian + "I", tail[8:12])
        offset = pos + 12
    if length == 0xFFFFFFFF:  # encapsulated
        if ts in (_IMPLICIT, _EXPLICIT, _BIG_ENDIAN):
            raise FormatError(f"{where}: encapsulated (compressed) pixel data under the "
                              f"uncompressed transfer syntax {ts}: the file's transfer "
                              "syntax is wrong")
        return None, None, True
    return offset, min(length, max(0, size - offset)), True


def _file_frames(full: str, label: str, order: int) -> tuple[list[Frame], str]:
    """The frames of one file, or ([], reason) for a DICOM file without an image."""
    force = not _has_preamble(full)
    ds, pos, tail, stamped = _read_dataset(full, force=force)
    sop = _sop_class(ds)
    if sop == DICOMDIR_SOP or "DirectoryRecordSequence" in ds:
        return [], "DICOMDIR"
    meta_ds = getattr(ds, "file_meta", None)
    ts = str(meta_ds.get("TransferSyntaxUID", _IMPLICIT)) if meta_ds is not None else _IMPLICIT
    if ts == _DEFLATED:
        ds, pos, tail, stamped = _read_dataset(full, force=force, stop=False)
        has_pixels = "PixelData" in ds
        float_pixels = "FloatPixelData" in ds or "DoubleFloatPixelData" in ds
        offset = length = None
    else:
        size = os.path.getsize(full)
        offset, length, has_pixels = _pixel_element(tail, ts, pos, size, full)
        float_pixels = has_pixels == "float"
    modality = _text(ds, "Modality")
    if float_pixels:
        return [], f"{modality or 'image'} with float pixel data (not supported)"
    if not has_pixels:
        from pydicom.uid import UID as _UID

        kind = _UID(sop).name if sop else ""
        if "Image Storage" in kind or "Rows" in ds:
            return [], f"{_STUB}{kind or 'image'}"
        return [], modality or "no PixelData"
    from pydicom.uid import UID

    where = full
    rows, cols = _int(ds, "Rows", where), _int(ds, "Columns", where)
    bits_alloc = _int(ds, "BitsAllocated", where)
    bits_stored = _int(ds, "BitsStored", where, bits_alloc)
    signed = _int(ds, "PixelRepresentation", where, 0) == 1
    samples = _int(ds, "SamplesPerPixel", where, 1)
    n_frames = _int(ds, "NumberOfFrames", where, 1) or 1
    if rows <= 0 or cols <= 0:
        raise FormatError(f"{where}: image size must be positive, got Rows {rows} Columns {cols}")
    if bits_alloc not in (1, 8, 16, 32):
        raise FormatError(f"{where}: BitsAllocated {bits_alloc} is not supported (1, 8, 16, 32)")
    if not 0 < bits_stored <= bits_alloc:
        raise FormatError(f"{where}: BitsStored {bits_stored} does not fit BitsAllocated "
                          f"{bits_alloc}")
    is_dose = sop == RTDOSE_SOP or modality == "RTDOSE"
    meta = {}
    for kw in META_TAGS + PHI_TAGS:
        v = _text(ds, kw)
        if v:
            meta[kw] = v
    info = FileInfo(path=full, label=label, transfer_syntax=ts, ts_name=UID(ts).name,
                    rows=rows, columns=cols, bits_allocated=bits_alloc, bits_stored=bits_stored,
                    signed=signed, samples=samples, n_frames=n_frames, pixel_offset=offset,
                    pixel_length=length,
                    dose_scaling=_float(ds, "DoseGridScaling", 1.0, where) if is_dose else None,
                    meta=meta, sop_uid=_text(ds, "SOPInstanceUID"), stamp=stamped)
    series_uid = _text(ds, "SeriesInstanceUID") or "(no SeriesInstanceUID)"
    common = {"FrameOfReferenceUID": _text(ds, "FrameOfReferenceUID"),
              "Rows/Columns": (rows, cols)}
    problem = ""
    photometric = _text(ds, "PhotometricInterpretation")
    if samples != 1 or photometric.upper() == "PALETTE COLOR":  # (indices into colour tables)
        problem = (f"colour image (SamplesPerPixel {samples}, {photometric}): volwarp reads "
                   "greyscale volumes")
    image_type = _text(ds, "ImageType").upper().split("\\")
    localizer = "LOCALIZER" in image_type
    top_spacing = _floats(ds, "PixelSpacing", 2, where)
    if top_spacing is None:  # projection images (CR, DX) give the detector's, as GDCM reads it
        top_spacing = _floats(ds, "ImagerPixelSpacing", 2, where)
    top_slope = _float(ds, "RescaleSlope", 1.0, where)
    top_inter = _float(ds, "RescaleIntercept", 0.0, where)
    if top_slope == 0:
        raise FormatError(f"{where}: RescaleSlope is 0")
    if any("LUTData" in item for item in ds.get("ModalityLUTSequence") or ()):
        # (its values come through a table, not slope/intercept; an empty sequence is none)
        raise FormatError(f"{where}: ModalityLUTSequence (stored values mapped through a lookup "
                          "table) is not supported: the stored values are not the image's")
    frames: list[Frame] = []

    def add(position, row, col, spacing, slope, inter, single, keys, split, synthetic=False,
            frame=0, assumed=""):
        if spacing is None:  # (1 mm pixels, as ITK takes them: said, not silent)
            assumed = ", ".join(filter(None, (assumed, NO_PIXEL_SPACING)))
        spacing = (1.0, 1.0) if spacing is None else (float(spacing[1]), float(spacing[0]))
        if spacing[0] <= 0 or spacing[1] <= 0:
            raise FormatError(f"{where}: PixelSpacing must be positive, got "
                              f"{[spacing[1], spacing[0]]}")
        frames.append(Frame(file=info, frame=frame, order=order, position=position, row=row,
                            col=col, pixel_spacing=spacing, slope=slope, intercept=inter,
                            single_spacing=single, series_uid=series_uid,
                            keys={**common, **keys}, split_keys=split, localizer=localizer,
                            synthetic=synthetic, assumed=assumed, problem=problem))

    sbs = _float(ds, "SpacingBetweenSlices", 0.0, where)
    single = abs(sbs) or 1.0
    pffg = ds.get("PerFrameFunctionalGroupsSequence")
    offsets = _offsets(ds, n_frames, where) if is_dose else None
    if is_dose and n_frames > 1 and offsets is None:
        raise FormatError(f"{where}: RT Dose with {n_frames} frames has no GridFrameOffsetVector "
                          f"of {n_frames} values")
    if offsets is not None:
        ipp = _floats(ds, "ImagePositionPatient", 3, where)
        iop = _floats(ds, "ImageOrientationPatient", 6, where)
        if ipp is None or iop is None:
            raise FormatError(f"{where}: RT Dose without ImagePositionPatient / "
                              "ImageOrientationPatient")
        row, col = _cosines(iop, where)
        normal = np.cross(row, col)
        normal /= np.linalg.norm(normal)
        steps = offsets if offsets[0] == 0 else _absolute_steps(offsets, ipp, normal, where)
        positions = ipp[None, :] + steps[:, None] * normal[None, :]
        keys = {"ImageOrientationPatient": tuple(iop), "PixelSpacing": _tup(top_spacing)}
        for k in range(n_frames):
            add(positions[k], row, col, top_spacing, 1.0, 0.0, single, keys, {}, frame=k)
    elif pffg is not None:  # (one frame too, whatever the SOP class: a Legacy Converted
        # Enhanced MR or PET of one frame has its geometry and rescale only there)
        _enhanced_frames(ds, pffg, n_frames, where, add, top_spacing, top_slope, top_inter,
                         single)
    else:
        ipp, iop = _plane(ds, where)
        if n_frames > 1 or ipp is None or iop is None:
            # no per-frame geometry: frames in file order SpacingBetweenSlices apart, as ITK
            # (GDCM) reads them: a negative one steps against the normal, SliceThickness is
            # no spacing, and without either unit spacing, which the warning and key say
            row, col = _cosines(iop, where) if iop is not None else (np.eye(3)[0], np.eye(3)[1])
            normal = np.cross(row, col)
            normal /= np.linalg.norm(normal)
            origin = ipp if ipp is not None else np.zeros(3)
            missing = [what for gone, what in (
                (ipp is None, "origin 0 (no ImagePositionPatient)"),
                (iop is None, "identity orientation (no ImageOrientationPatient)"),
                (n_frames > 1 and not sbs, "unit slice spacing (no SpacingBetweenSlices)"))
                if gone]
            keys = {"file": full, "ImageOrientationPatient": tuple(np.r_[row, col]),
                    "PixelSpacing": _tup(top_spacing)}
            for k in range(n_frames):
                add(origin + k * (sbs or 1.0) * normal, row, col, top_spacing, top_slope,
                    top_inter, single, keys, {}, synthetic=True, frame=k,
                    assumed=", ".join(missing))
        else:
            row, col = _cosines(iop, where)
            keys = {"ImageOrientationPatient": tuple(iop), "PixelSpacing": _tup(top_spacing),
                    "EchoNumbers": _text(ds, "EchoNumbers")}
            split = {"TemporalPositionIdentifier": _text(ds, "TemporalPositionIdentifier"),
                     "AcquisitionNumber": _text(ds, "AcquisitionNumber")}
            add(ipp, row, col, top_spacing, top_slope, top_inter, single, keys, split)
    return frames, ""


def _plane(ds, where: str):
    """ImagePositionPatient and ImageOrientationPatient of an image without functional groups.

    An NM image keeps them in DetectorInformationSequence (PS3.3 C.8.4.10), where
    GDCM reads them first; the top-level ones are the fallback (GDCM leaves an NM
    origin at 0 then). Detectors placed differently are no one stack: refused.
    """
    ipp = _floats(ds, "ImagePositionPatient", 3, where)
    iop = _floats(ds, "ImageOrientationPatient", 6, where)
    found = []
    for k, item in enumerate(ds.get("DetectorInformationSequence") or []):
        fw = f"{where}: DetectorInformationSequence item {k + 1}"
        det = (_floats(item, "ImagePositionPatient", 3, fw),
               _floats(item, "ImageOrientationPatient", 6, fw))
        if any(v is not None for v in det):
            found.append(det)
    if not found:
        return ipp, iop
    if any(not all(_same(_tup(a), _tup(b)) for a, b in zip(det, found[0], strict=True))
           for det in found[1:]):
        raise FormatError(f"{where}: DetectorInformationSequence places its {len(found)} "
                          "detectors' frames differently (ImagePositionPatient / "
                          "ImageOrientationPatient): not one stack")
    det_ipp, det_iop = found[0]
    return (ipp if det_ipp is None else det_ipp), (iop if det_iop is None else det_iop)


def _offsets(ds, n_frames: int, where: str):
    """GridFrameOffsetVector, its first NumberOfFrames values (some files carry more)."""
    elem = ds.get("GridFrameOffsetVector")
    if elem is None or elem == "":
        return None
    vals = elem if hasattr(elem, "__len__") and not isinstance(elem, str) else [elem]
    try:
        vals = np.array([float(v) for v in vals])
    except (TypeError, ValueError):
        raise FormatError(f"{where}: GridFrameOffsetVector is not numeric") from None
    if len(vals) < n_frames or not np.all(np.isfinite(vals)):
        raise FormatError(f"{where}: GridFrameOffsetVector has {len(vals)} values for "
                          f"{n_frames} frames")
    return vals[:n_frames]


def _absolute_steps(offsets, ipp, normal, where: str) -> np.ndarray:
    """Distances along the normal of frames whose GridFrameOffsetVector gives their z.

    PS3.3 C.8.8.3.2: a first offset other than 0 makes the offsets the frames'
    z coordinates (allowed with ImageOrientationPatient (1, 0, 0, 0, 1, 0) only).
    Frame 0 stays at ImagePositionPatient, so its z must be the first offset.
    """
    if abs(normal[2]) < _ATOL:
        raise FormatError(f"{where}: GridFrameOffsetVector starts at {offsets[0]:g}, not 0: "
                          "absolute z positions, but the slice normal of ImageOrientationPatient "
                          "has no z component")
    if abs(offsets[0] - ipp[2]) > 0.01:
        raise FormatError(f"{where}: GridFrameOffsetVector starts at {offsets[0]:g}, not 0: "
                          f"an absolute z position, but ImagePositionPatient's z is {ipp[2]:g} "
                          "(they must agree within 0.01 mm)")
    return (offsets - offsets[0]) / normal[2]


def _tup(v):
    return None if v is None else tuple(float(x) for x in v)


def _item(fg, shared, name):
    for src in (fg, shared):
        if src is not None and name in src:
            seq = src[name].value
            if seq:
                return seq[0]
    return None


def _enhanced_frames(ds, pffg, n_frames, where, add, top_spacing, top_slope, top_inter, single):
    if len(pffg) != n_frames:
        raise FormatError(f"{where}: PerFrameFunctionalGroupsSequence has {len(pffg)} items "
                          f"for {n_frames} frames")
    sfg = ds.get("SharedFunctionalGroupsSequence")
    shared = sfg[0] if sfg else None
    top_ipp = _floats(ds, "ImagePositionPatient", 3, where)
    top_iop = _floats(ds, "ImageOrientationPatient", 6, where)
    rows = []
    for k, fg in enumerate(pffg):
        fw = f"{where} frame {k + 1}"
        pos_item = _item(fg, shared, "PlanePositionSequence")
        ori_item = _item(fg, shared, "PlaneOrientationSequence")
        pm = _item(fg, shared, "PixelMeasuresSequence")
        pvt = _item(fg, shared, "PixelValueTransformationSequence")
        content = _item(fg, None, "FrameContentSequence")
        seg = _item(fg, shared, "SegmentIdentificationSequence")
        echo = _item(fg, shared, "MREchoSequence")
        ipp = _floats(pos_item, "ImagePositionPatient", 3, fw) if pos_item is not None else top_ipp
        iop = _floats(ori_item, "ImageOrientationPatient", 6, fw) if ori_item is not None \
            else top_iop
        spacing = _floats(pm, "PixelSpacing", 2, fw) if pm is not None else None
        spacing = top_spacing if spacing is None else spacing
        sbs = _float(pm, "SpacingBetweenSlices", 0.0, fw) if pm is not None else 0.0
        slope = _float(pvt, "RescaleSlope", top_slope, fw) if pvt is not None else top_slope
        inter = _float(pvt, "RescaleIntercept", top_inter, fw) if pvt is not None else top_inter
        if slope == 0:
            raise FormatError(f"{fw}: RescaleSlope is 0")
        keys = {"StackID": _text(content, "StackID"),
                "TemporalPositionIndex": _text(content, "TemporalPositionIndex"),
                "SegmentNumber": _text(seg, "ReferencedSegmentNumber"),
                "EffectiveEchoTime": _text(echo, "EffectiveEchoTime")}
        rows.append((ipp, iop, spacing, slope, inter, sbs if sbs > 0 else single, keys))
    have = [r[0] is not None and r[1] is not None for r in rows]
    if not any(have):
        ident = np.eye(3)
        for k, r in enumerate(rows):
            add(np.array([0.0, 0.0, float(k)]), ident[0], ident[1], r[2], r[3], r[4], 1.0,
                {"file": where, **r[6]}, {}, synthetic=True, frame=k,
                assumed="origin 0, identity orientation, unit slice spacing (no "
                        "PlanePositionSequence / PlaneOrientationSequence in the functional "
                        "groups)")
        return
    if not all(have):
        k = have.index(False)
        raise FormatError(f"{where} frame {k + 1}: no ImagePositionPatient / "
                          "ImageOrientationPatient in its functional groups (other frames have)")
    for k, (ipp, iop, spacing, slope, inter, sgl, keys) in enumerate(rows):
        row, col = _cosines(iop, f"{where} frame {k + 1}")
        add(ipp, row, col, spacing, slope, inter, sgl,
            {"ImageOrientationPatient": tuple(iop), "PixelSpacing": _tup(spacing), **keys},
            {}, frame=k)


# -- grouping -------------------------------------------------------------------

def _same(a, b) -> bool:
    if isinstance(a, tuple) and isinstance(b, tuple) and len(a) == len(b) \
            and all(isinstance(x, float) for x in a + b):
        return bool(np.allclose(a, b, rtol=0, atol=_ATOL))
    return a == b


def _show(v) -> str:
    if isinstance(v, tuple):
        return "[" + ", ".join(f"{x:.6g}" if isinstance(x, float) else str(x) for x in v) + "]"
    return repr(v) if v != "" else "(none)"


def _has_duplicates(frames: list[Frame]) -> bool:
    if len(frames) < 2 or frames[0].synthetic:
        return False
    normal = np.cross(frames[0].row, frames[0].col)
    d = np.sort(np.array([f.position @ normal for f in frames]))
    return bool(np.any(np.diff(d) <= 0.01))


def _whole_stacks(members: list[Frame]) -> list[tuple[list[Frame], str]] | None:
    """Parts by TemporalPositionIdentifier or AcquisitionNumber, when they are whole stacks.

    Time points and repeated acquisitions are whole stacks at the same positions,
    each with one image per position: candidates of their own. Any other split
    (a re-acquired slice, scanners giving every slice its own AcquisitionNumber)
    would cut one volume into partial ones: None, and the images sharing a
    position are duplicates, which ``duplicates="first"|"last"`` resolves.
    """
    for name in ("TemporalPositionIdentifier", "AcquisitionNumber"):
        values = sorted({m.split_keys.get(name, "") for m in members})
        if len(values) < 2:
            continue
        parts = [[m for m in members if m.split_keys.get(name, "") == v] for v in values]
        if not any(_has_duplicates(p) for p in parts) and _same_positions(parts):
            return [(p, f"{name} {v or '(none)'} of {len(values)} at the same positions")
                    for p, v in zip(parts, values, strict=True)]
    return None


def _same_positions(parts: list[list[Frame]]) -> bool:
    """True when every part has its images at the same positions along the normal (0.01 mm)."""
    normal = np.cross(parts[0][0].row, parts[0][0].col)
    ds = [np.sort(np.array([f.position @ normal for f in p])) for p in parts]
    return all(len(d) == len(ds[0]) and np.allclose(d, ds[0], rtol=0, atol=0.01) for d in ds)


def _split(frames: list[Frame]) -> list[tuple[list[Frame], str]]:
    """Geometry groups of one series' frames, each with why it was split (or "")."""
    groups: list[tuple[dict, list[Frame]]] = []
    for f in frames:
        for keys, members in groups:
            if all(_same(keys.get(k), v) for k, v in f.keys.items()) and len(keys) == len(f.keys):
                members.append(f)
                break
        else:
            groups.append((f.keys, [f]))
    out = []
    for keys, members in groups:
        parts = (_has_duplicates(members) and _whole_stacks(members)) or [(members, "")]
        out.extend((keys, p, why) for p, why in parts)
    if len(out) == 1:
        return [(out[0][1], out[0][2])]
    main_keys = max(out, key=lambda t: len(t[1]))[0]
    result = []
    for keys, members, why in out:
        diffs = [k for k in keys if k != "file" and not _same(keys.get(k), main_keys.get(k))]
        if diffs:
            k = diffs[0]
            why2 = f"{k} {_show(keys.get(k))} differs from the series' main stack " \
                   f"({_show(main_keys.get(k))})"
            why = f"{why}; {why2}" if why else why2
        elif "file" in keys and not why:
            why = "own file without per-frame positions"
        result.append((members, why))
    return result


# -- exact copies ---------------------------------------------------------------------

def _drop_exact_copies(frames: list[Frame], where: str) -> list[Frame]:
    """The frames without those of files that are exact copies of another (``cp`` leaves them).

    A copy has the SOPInstanceUID of its original, the same frames (positions,
    orientation, spacing, rescale) and the same pixel data: one image stored
    twice, not a second image at its position. The first file (path order) is
    kept and one warning says how many were dropped; a file with another's
    SOPInstanceUID but other pixels or geometry stays (then a duplicate position,
    or a slice of its own).
    """
    by_uid: dict[str, list[FileInfo]] = {}
    signatures: dict[int, list[tuple]] = {}
    for f in frames:
        if f.file.sop_uid and id(f.file) not in signatures:
            by_uid.setdefault(f.file.sop_uid, []).append(f.file)
        signatures.setdefault(id(f.file), []).append(_frame_signature(f))
    copies: dict[int, tuple[FileInfo, FileInfo]] = {}
    for files in by_uid.values():
        kept: list[FileInfo] = []
        for info in files:
            original = next((k for k in kept if signatures[id(k)] == signatures[id(info)]
                             and _same_pixels(k, info)), None)
            if original is None:
                kept.append(info)
            else:
                copies[id(info)] = (info, original)
    if not copies:
        return frames
    copy, original = next(iter(copies.values()))
    more = f" (and {len(copies) - 1} more)" if len(copies) > 1 else ""
    log.warning("warning: %s: %d exact duplicate file(s) dropped (the same SOPInstanceUID and "
                "pixel data as another file): %s and %s are the same, the first kept%s", where,
                len(copies), original.label, copy.label, more)
    return [f for f in frames if id(f.file) not in copies]


def _frame_signature(f: Frame) -> tuple:
    """What places a frame and maps its values: equal for a frame and its copy."""
    def tup(v):
        return None if v is None else tuple(np.round(np.asarray(v, dtype=float), 6).tolist())

    return (f.frame, tup(f.position), tup(f.row), tup(f.col), f.pixel_spacing, f.slope,
            f.intercept, f.single_spacing, f.series_uid)


def _same_pixels(a: FileInfo, b: FileInfo) -> bool:
    """True when two files hold the same pixel data (the stored bytes, or decoded values)."""
    layout = ("rows", "columns", "n_frames", "bits_allocated", "bits_stored", "signed", "samples")
    if any(getattr(a, k) != getattr(b, k) for k in layout):
        return False
    if a.pixel_offset is not None and b.pixel_offset is not None:
        return a.transfer_syntax == b.transfer_syntax and _same_stored(a, b)
    try:
        if a.transfer_syntax == b.transfer_syntax:
            return _dataset(a).PixelData == _dataset(b).PixelData
        return bool(np.array_equal(_dataset(a).pixel_array, _dataset(b).pixel_array))
    except Exception:  # an unreadable file is not shown to be a copy: kept, read as usual
        return False


def _same_stored(a: FileInfo, b: FileInfo, chunk: int = 1 << 22) -> bool:
    """Byte-for-byte equal raw PixelData values, compared a chunk at a time."""
    if a.pixel_length != b.pixel_length:
        return False
    from ._pixels import open_unchanged

    with open_unchanged(a) as fa, open_unchanged(b) as fb:
        fa.seek(a.pixel_offset)
        fb.seek(b.pixel_offset)
        left = a.pixel_length or 0
        while left > 0:
            n = min(chunk, left)
            if fa.read(n) != fb.read(n):
                return False
            left -= n
    return True


def _dataset(info: FileInfo):
    """The whole data set of a file (compressed or deflated pixel data)."""
    return _read_dataset(info.path, force=not _has_preamble(info.path), stop=False)[0]


def _drop_localizers(parts):
    locs = [p for p in parts if all(f.localizer for f in p[0])]
    rest = [p for p in parts if not all(f.localizer for f in p[0])]
    if not locs or not rest:
        return parts
    n = sum(len(p[0]) for p in locs)
    note = f"{n} localizer image(s) in another orientation dropped"
    return [(m, f"{why}; {note}" if why else note) for m, why in rest]


def estimate_geometry(frames: list[Frame]) -> tuple[tuple[int, int, int], tuple[float, ...]]:
    """Shape and spacing for the candidate list (the reader checks them strictly)."""
    f0 = frames[0]
    sx, sy = f0.pixel_spacing
    if len(frames) == 1:
        return (f0.file.columns, f0.file.rows, 1), (sx, sy, f0.single_spacing)
    normal = np.cross(f0.row, f0.col)
    normal /= np.linalg.norm(normal)
    d = np.unique(np.round(np.array([f.position @ normal for f in frames]), 2))
    gaps = np.diff(d)
    sz = float(np.median(gaps)) if len(gaps) else f0.single_spacing
    return (f0.file.columns, f0.file.rows, len(d)), (sx, sy, sz)


def _stub_problems(stubs: dict[str, list[str]], series: set[str]) -> dict[str, str]:
    """Per series, why it cannot be read whole: an image of it without pixel data.

    Such a file is a slice cut before its pixels (a transfer stopped short):
    skipped, it left its series a slice short, the first or last without a
    word. A file cut inside its header names no series: every series gets it
    (key ``""``). The series' candidates are listed with the problem, and
    refused when read; other series read as they are. An image object of a
    series with no image at all (a DICOMDIR's stripped examples) is no slice
    of any candidate: skipped with a warning.
    """
    problems: dict[str, str] = {}
    for kind, names in stubs.items():
        lost, skipped = {}, []
        for n in names:
            uid = _series_of(n)
            if uid in series or not uid:
                lost.setdefault(uid, []).append(n)
            else:
                skipped.append(n)
        if skipped:  # (one line a kind: a DICOMDIR's tree may hold hundreds)
            more = f" and {len(skipped) - 1} more" if len(skipped) > 1 else ""
            log.warning("warning: %s%s: %s without PixelData: skipped", skipped[0], more, kind)
        for uid, files in lost.items():
            more = f" (and {len(files) - 1} more)" if len(files) > 1 else ""
            problems.setdefault(uid, f"{files[0]}: {kind} without PixelData (truncated "
                                     f"file?){more}")
    return problems


def _series_of(path: str) -> str:
    ds = _read_dataset(path, force=not _has_preamble(path))[0]
    return _text(ds, "SeriesInstanceUID")


def scan_dicom(path) -> list[Candidate]:
    """The candidate volumes under ``path`` (a folder, a DICOMDIR or a file), in a fixed order."""
    path = Path(path)
    files, seen = _files_of(path)
    frames: list[Frame] = []
    skipped: dict[str, int] = {}
    stubs: dict[str, list[str]] = {}  # image kind -> files without pixel data
    for order, (full, label) in enumerate(files):
        got, reason = _file_frames(full, label, order)
        if not got:
            skipped[reason] = skipped.get(reason, 0) + 1
            if reason.startswith(_STUB):
                if not path.is_dir() and len(files) == 1:
                    raise FormatError(f"{full}: {reason[len(_STUB):]} without PixelData "
                                      "(truncated file?)")
                stubs.setdefault(reason[len(_STUB):], []).append(str(full))
            else:
                log.debug("%s: skipped (%s)", full, reason)
        frames.extend(got)
    frames = _drop_exact_copies(frames, str(path))
    stub_problems = _stub_problems(stubs, {f.series_uid for f in frames})
    if not frames:
        if not files:
            what = "is a folder with no DICOM files" if path.is_dir() else "no DICOM files found"
            raise FormatError(f"{path}: {what} ({seen} file(s) looked at)")
        kinds = ", ".join(f"{k} x{v}" for k, v in sorted(skipped.items()))
        if path.is_dir() or len(files) > 1:
            raise FormatError(f"{path}: no DICOM image among {len(files)} DICOM file(s) "
                              f"({kinds}: no PixelData)")
        raise FormatError(f"{path}: not a DICOM image ({kinds}: no PixelData)")
    by_series: dict[str, list[Frame]] = {}
    for f in frames:
        by_series.setdefault(f.series_uid, []).append(f)
    entries = []
    for uid, members in by_series.items():
        meta = members[0].file.meta
        try:
            number = int(float(meta.get("SeriesNumber", "")))
        except ValueError:
            number = None
        for sub, (part, why) in enumerate(_drop_localizers(_split(members))):
            entries.append(((number if number is not None else 1 << 60, uid, sub), uid, number,
                            part, why))
    entries.sort(key=lambda e: e[0])
    out = []
    for index, (_, uid, number, part, why) in enumerate(entries):
        meta = part[0].file.meta
        bad = next((f for f in part if f.problem), None)
        problem = stub_problems.get(uid) or stub_problems.get("")
        if bad is not None:
            shown = bad.problem if bad is part[0] else f"{bad.label}: {bad.problem}"
            why = f"{why}; {shown}" if why else shown
        elif problem:
            why = f"{why}; {problem}" if why else problem
        shape, spacing = estimate_geometry(part)
        out.append(Candidate(index=index, series_uid=uid,
                             description=meta.get("SeriesDescription", ""),
                             modality=meta.get("Modality", ""), shape_xyz=shape,
                             spacing=tuple(float(s) for s in spacing),
                             n_files=len({id(f.file) for f in part}), n_frames=len(part),
                             why=why, series_number=number, frames=tuple(part),
                             problem=problem or ""))
    return out
