"""Pixel data: the output sample type, and every frame read once into one array.

Uncompressed little-endian files are read straight from disk at the offset
the header scan found (``readinto`` the output slice when no rescale is
needed); every other transfer syntax goes through pydicom's decoders
(deflated files from the dataset ``dcmread`` inflates). The
modality rescale is computed in int64 or float64 and then cast, so that
``uint16 + (-1024)`` cannot wrap.
"""

from __future__ import annotations

import os
import warnings
from collections import defaultdict
from contextlib import closing, contextmanager, nullcontext

import numpy as np

from ...errors import FormatError
from ...progress import log

#: transfer syntaxes whose pixel data lies raw in the file, little-endian
NATIVE_LE = frozenset(("1.2.840.10008.1.2", "1.2.840.10008.1.2.1"))
#: Deflated Explicit VR Little Endian: the whole data set after the file meta is deflated
DEFLATED = "1.2.840.10008.1.2.1.99"

#: who decodes what, for the error naming a missing decoder
_DECODER_PACKAGES = {
    "1.2.840.10008.1.2.4.50": "python-gdcm or pylibjpeg-libjpeg",
    "1.2.840.10008.1.2.4.51": "python-gdcm or pylibjpeg-libjpeg",
    "1.2.840.10008.1.2.4.57": "python-gdcm or pylibjpeg-libjpeg",
    "1.2.840.10008.1.2.4.70": "python-gdcm or pylibjpeg-libjpeg",
    "1.2.840.10008.1.2.4.80": "python-gdcm or pyjpegls",
    "1.2.840.10008.1.2.4.81": "python-gdcm or pyjpegls",
    "1.2.840.10008.1.2.4.90": "pylibjpeg-openjpeg or python-gdcm",
    "1.2.840.10008.1.2.4.91": "pylibjpeg-openjpeg or python-gdcm",
    "1.2.840.10008.1.2.4.201": "pylibjpeg-openjpeg>=2.4",
    "1.2.840.10008.1.2.4.202": "pylibjpeg-openjpeg>=2.4",
    "1.2.840.10008.1.2.4.203": "pylibjpeg-openjpeg>=2.4",
    "1.2.840.10008.1.2.5": "pylibjpeg-rle or python-gdcm",
}


def stored_dtype(bits_allocated: int, signed: bool) -> np.dtype:
    """The numpy type of stored samples (BitsAllocated 1 unpacks to uint8)."""
    if bits_allocated == 1:
        return np.dtype(np.uint8)
    if bits_allocated not in (8, 16, 32):
        raise ValueError(bits_allocated)
    return np.dtype(f"{'i' if signed else 'u'}{bits_allocated // 8}")


def stored_range(bits_stored: int, signed: bool) -> tuple[int, int]:
    if signed:
        return -(1 << (bits_stored - 1)), (1 << (bits_stored - 1)) - 1
    return 0, (1 << bits_stored) - 1


def output_dtype(frames) -> np.dtype:
    """The sample type of the volume: see the module docstring of the package."""
    if any(f.file.dose_scaling is not None for f in frames):
        return np.dtype(np.float32)
    identity = all(f.slope == 1 and f.intercept == 0 for f in frames)
    files = {id(f.file): f.file for f in frames}.values()
    if identity:
        types = {stored_dtype(fi.bits_allocated, fi.signed) for fi in files}
        if len(types) == 1:
            return types.pop()
    integral = all(float(f.slope).is_integer() and float(f.intercept).is_integer() for f in frames)
    if not integral:
        return np.dtype(np.float32)
    lo, hi = 0, 0
    ranges = {}
    for f in frames:
        r = ranges.get(id(f.file))
        if r is None:
            r = ranges[id(f.file)] = stored_range(f.file.bits_stored, f.file.signed)
        a, b = r[0] * int(f.slope) + int(f.intercept), r[1] * int(f.slope) + int(f.intercept)
        lo, hi = min(lo, a, b), max(hi, a, b)
    for dt in (np.int16, np.int32):
        info = np.iinfo(dt)
        if info.min <= lo and hi <= info.max:
            return np.dtype(dt)
    return np.dtype(np.float32)


def check_decodable(fi, where: str) -> None:
    """Raise a one-line FormatError when no installed plugin decodes the transfer syntax."""
    from pydicom.pixels import get_decoder
    from pydicom.uid import UID

    uid = UID(fi.transfer_syntax)
    try:
        decoder = get_decoder(uid)
    except NotImplementedError:
        raise FormatError(f"{where}: pixel data in transfer syntax {uid} ({uid.name}) cannot be "
                          "decoded: pydicom has no decoder for it") from None
    if not decoder.is_available:
        package = _DECODER_PACKAGES.get(str(uid))
        if package is None:
            missing = "; ".join(" ".join(str(m).split()) for m in decoder.missing_dependencies)
            package = missing or "a pydicom decoding plugin"
        raise FormatError(f"{where}: pixel data in transfer syntax {uid} ({uid.name}) cannot be "
                          f"decoded: install {package}")


def read_frames(frames, dtype: np.dtype, out: np.ndarray) -> None:
    """Fill ``out[k]`` (rows x columns) with the rescaled samples of ``frames[k]``."""
    by_file = defaultdict(list)
    for slot, fr in enumerate(frames):
        by_file[id(fr.file)].append((fr.frame, slot, fr))
    for items in by_file.values():
        fi = items[0][2].file
        if fi.transfer_syntax not in NATIVE_LE or fi.pixel_offset is None \
                or fi.bits_allocated not in (8, 16, 32):
            check_decodable(fi, fi.path)
            _read_decoded(fi, items, dtype, out)
        else:
            _read_native(fi, items, dtype, out)


def _store(raw: np.ndarray, fi, fr, dtype: np.dtype, dst: np.ndarray) -> None:
    """``dst = raw * slope + intercept`` (dose: ``raw * DoseGridScaling``), in 64 bits first."""
    if fi.bits_stored < fi.bits_allocated and fi.bits_allocated in (8, 16, 32):
        raw = _fix_high_bits(raw, fi)
    if fi.dose_scaling is not None:
        np.multiply(raw, fi.dose_scaling, out=dst, dtype=np.float64, casting="unsafe")
        return
    slope, inter = fr.slope, fr.intercept
    if dtype.kind == "f":
        if slope == 1 and inter == 0:
            dst[...] = raw
        else:
            tmp = raw.astype(np.float64)
            tmp *= slope
            tmp += inter
            dst[...] = tmp
        return
    if slope == 1 and inter == 0:
        dst[...] = raw
        return
    info, src = np.iinfo(dtype), np.iinfo(raw.dtype)
    if slope == 1 and info.min <= src.min and src.max <= info.max:
        dst[...] = raw
        dst += int(inter)
        return
    tmp = raw.astype(np.int64)
    tmp *= int(slope)
    tmp += int(inter)
    dst[...] = tmp


def _fix_high_bits(raw: np.ndarray, fi) -> np.ndarray:
    """Clear (unsigned) or sign-extend (signed) the bits above BitsStored."""
    extra = fi.bits_allocated - fi.bits_stored
    if fi.signed:
        return (raw << extra) >> extra
    return raw & raw.dtype.type((1 << fi.bits_stored) - 1)


def _check_excess(fi, need: int, per_frame: int) -> None:
    """Refuse PixelData holding a whole frame more than the header says, or a compressed value.

    A file without its NumberOfFrames gave its first frame alone, and compressed
    fragments under an uncompressed transfer syntax were read as samples, both
    without a word. Less than a frame more (not the standard's one padding byte)
    is said and left unread.
    """
    with open(fi.path, "rb") as fh:
        fh.seek(fi.pixel_offset)
        head = fh.read(4)
    if head == b"\xfe\xff\x00\xe0":  # an item tag: encapsulated fragments
        raise FormatError(f"{fi.path}: the pixel data is encapsulated (compressed) but the "
                          f"transfer syntax ({fi.transfer_syntax}) says uncompressed")
    extra = fi.pixel_length - need
    if extra >= per_frame:
        raise FormatError(f"{fi.path}: the pixel data holds {fi.pixel_length} bytes, "
                          f"{fi.pixel_length / per_frame:.4g} frames of {fi.rows} x {fi.columns}, "
                          f"but NumberOfFrames says {fi.n_frames} (missing or wrong?)")
    from ...runscope import first_said

    if first_said(("dicom-excess-pixels", os.path.dirname(fi.path))):  # (once a folder, a run)
        log.warning("warning: %s: the pixel data holds %d bytes more than %d frame(s) of %d x "
                    "%d need (and maybe other files of its folder); they are not read",
                    fi.path, extra, fi.n_frames, fi.rows, fi.columns)


def _read_native(fi, items, dtype: np.dtype, out: np.ndarray) -> None:
    sdt = stored_dtype(fi.bits_allocated, fi.signed).newbyteorder("<")
    per_frame = fi.rows * fi.columns * sdt.itemsize
    need = per_frame * fi.n_frames
    if fi.pixel_length is not None and fi.pixel_length < need:
        raise FormatError(f"{fi.path}: pixel data is truncated: expected {need} bytes "
                          f"({fi.n_frames} x {fi.rows} x {fi.columns} x {sdt.itemsize}), "
                          f"the element holds {fi.pixel_length}")
    if fi.pixel_length is not None and fi.pixel_length > need + 1:
        _check_excess(fi, need, per_frame)
    direct = (sdt == dtype and fi.dose_scaling is None and fi.bits_stored == fi.bits_allocated
              and all(fr.slope == 1 and fr.intercept == 0 for _, _, fr in items))
    buf = None if direct else np.empty((fi.rows, fi.columns), dtype=sdt)
    try:
        with open_unchanged(fi) as fh:
            for frame, slot, fr in sorted(items, key=lambda t: t[0]):
                fh.seek(fi.pixel_offset + frame * per_frame)
                target = out[slot] if direct else buf
                got = fh.readinto(memoryview(target).cast("B"))
                if got != per_frame:
                    raise FormatError(f"{fi.path}: file is truncated: pixel data of frame "
                                      f"{frame + 1} has {got} of {per_frame} bytes")
                if not direct:
                    _store(buf, fi, fr, dtype, out[slot])
                elif fi.bits_stored < fi.bits_allocated:  # pragma: no cover - direct excludes
                    out[slot] = _fix_high_bits(out[slot], fi)
    except OSError as exc:
        raise FormatError(f"{fi.path}: cannot read ({exc.strerror})") from None


def _source(fi, fh):
    """What pydicom's pixel functions read: the open file, or the dataset of a deflated file.

    Given a file they parse it themselves, without inflating a Deflated
    Explicit VR Little Endian body (they find no Pixel Data in it); ``dcmread``
    inflates it, so those files are read whole into a dataset first (their
    pixel data is in memory anyway: it lies inside the deflated stream).
    """
    if fi.transfer_syntax != DEFLATED:
        return fh
    import pydicom

    return pydicom.dcmread(fh, force=True)


@contextmanager
def open_unchanged(fi):
    """The file of ``fi`` (a :class:`._scan.FileInfo`), opened to read its pixels: the one scanned.

    Its pixels are read by what its header scan found (their offset, their
    layout, the slices they are): another file put in its place, or this one
    rewritten, since the scan (a series exported again into its folder while
    a command reads it slab by slab) gave that file's pixels as this file's
    slices, a mix of two series written with exit 0. Refused instead
    (:func:`~volwarp_cli.io.mapped.unchanged`).
    """
    from ..mapped import unchanged

    with open(fi.path, "rb") as fh:
        if fi.stamp is not None and not unchanged(fh.fileno(), fi.stamp):
            raise FormatError(f"{fi.path}: the file changed after its header was read "
                              "(replaced or rewritten by another program?); the series "
                              "is not read")
        yield fh


def _read_decoded(fi, items, dtype: np.dtype, out: np.ndarray) -> None:
    from pydicom.pixels import iter_pixels, pixel_array

    items = sorted(items, key=lambda t: t[0])
    try:
        with warnings.catch_warnings(), open_unchanged(fi) as fh:
            warnings.simplefilter("ignore")
            src = _source(fi, fh)
            if fi.n_frames == 1:
                frames = nullcontext([pixel_array(src, raw=True)])
            else:  # (closed while its file is open: left suspended, it seeked the closed
                # file when collected, and Python printed that traceback on stderr)
                frames = closing(iter_pixels(src, indices=[t[0] for t in items], raw=True))
            with frames as arrays:
                for (frame, slot, fr), arr in zip(items, arrays, strict=False):
                    if arr.shape != (fi.rows, fi.columns):
                        raise FormatError(f"{fi.path}: frame {frame + 1} decodes to shape "
                                          f"{arr.shape}, expected ({fi.rows}, {fi.columns})")
                    _store(arr, fi, fr, dtype, out[slot])
    except FormatError:
        raise
    except Exception as exc:  # pydicom and its plugins raise many types for damaged data
        text = " ".join(str(exc).split())[:300]
        raise FormatError(f"{fi.path}: cannot decode pixel data ({fi.ts_name}): "
                          f"{type(exc).__name__}: {text}") from None
