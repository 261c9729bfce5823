"""TIFF stacks (one page per z slice, or an ImageJ hyperstack) via tifffile.

Spacing is read the way ImageJ/Fiji store it: x and y from the resolution
tags (pixels per unit), z from the ImageJ description's ``spacing`` (1 without
it: ImageJ writes none for a depth of 1), all in its ``unit``, converted to
millimetres where that is a length (``micron``, ``um``, ``cm``, ...;
:func:`imagej_unit_mm`; ``pixel`` keeps the numbers). As in ImageJ, tags of
ResolutionUnit centimetre under ``unit=um`` count pixels per centimetre.
Plain TIFFs with a ResolutionUnit of inch, centimetre, millimetre or
micrometre (tifffile's 4 and 5) are converted to millimetres; tags that give
no size (none, no ResolutionUnit, 72 per inch) are uncalibrated, as ImageJ
reads them, and what a plain TIFF does not give is said (:func:`_uncalibrated`,
:func:`_say_uncalibrated`).

A file of several images (OME ``Image`` elements, tifffile series) is read
one image at a time, chosen by ``volume_index`` (:func:`_choose_image`); an
image's planes must be z slices (:func:`_check_image_axes`); an ImageJ
straight-line value calibration is applied (:func:`_imagej_calibration`).

An OME-TIFF's ``PhysicalSizeX``/``Y``/``Z`` (of its first ``Pixels``
element) come ahead of those: each is converted to millimetres from its
``PhysicalSizeXUnit``/``Y``/``Z`` (any length of the OME schema's
``UnitsLength``: nm, µm (or um), mm, cm, m, Å, in, ...; µm when the unit is
not given, the schema's default), and meta ``unit`` is then ``mm``. An axis
whose size is missing, not a positive number, or in a unit that is no length
(``pixel``, ``reference frame``) keeps the source it had before (the
resolution tags for x and y, 1 for z), except x or y where the other has one:
that one, with a warning, as Bio-Formats reads it; a stack of several planes whose OME
metadata give x or y but no ``PhysicalSizeZ`` is read with z spacing 1 and a
warning. volwarp also stores its exact spacing, origin
and direction (keys ``volwarp_spacing``, ``volwarp_origin``,
``volwarp_direction``) so that a round trip keeps the geometry to the bit,
since TIFF resolutions are rationals.

ImageJ can only hold uint8, int16, uint16 and float32 stacks; other types are
written as plain multi-page TIFFs with the same resolution tags and the
geometry in tifffile's JSON description.
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import logging
import math
import os
import re
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import BadUsage, ChoiceNeeded, FormatError, VolwarpError
from ..geometry import check_placement
from ..memory import ensure_fits_in_memory
from ..progress import log
from ..runscope import first_said
from ..samples import check_dtype, voxel_count
from ..volume import Volume, zyx_to_xyz
from .atomic import atomic_output
from .common import (
    make_volume,
    native,
    read_exact,
    with_byte_order,
)
from .units import OME_LENGTH_TO_MM, length_unit_mm

_IMAGEJ_TYPES = ("uint8", "int16", "uint16", "float32")
#: TIFF ResolutionUnit values (tifffile's RESUNIT: 4 and 5 are its own extension) in mm
_RESUNIT_MM = {2: ("inch", 25.4), 3: ("centimeter", 10.0), 4: ("millimeter", 1.0),
               5: ("micrometer", 1e-3)}

#: the schema's default PhysicalSize unit
_OME_DEFAULT_UNIT = "\u00b5m"


def _floats(value, n, where, name):
    if isinstance(value, str):
        value = value.replace(",", " ").split()
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise FormatError(f"{where}: cannot read {name} {value!r}") from None
    if len(out) != n:
        raise FormatError(f"{where}: {name} must have {n} values")
    return out


class _TifffileLog(logging.Handler):
    """Receives tifffile's log records, so that none reaches stderr.

    While :func:`_collect_tifffile_log` is active in a thread, that thread's
    records are kept for the reader to judge (a broken chain of pages is an
    error); any other record is passed on to volwarp's log at DEBUG level.
    """

    _local = threading.local()

    def emit(self, record: logging.LogRecord) -> None:
        records = getattr(self._local, "records", None)
        if records is not None:
            records.append(record)
        else:
            log.debug("tifffile: %s", record.getMessage())


_HANDLER = _TifffileLog()


@contextlib.contextmanager
def _collect_tifffile_log():
    """Keep tifffile's log records of this thread in a list, off stderr."""
    logger = logging.getLogger("tifffile")
    if _HANDLER not in logger.handlers:
        logger.addHandler(_HANDLER)
        logger.propagate = False  # not to the root logger, nor Python's last resort
    outer = getattr(_TifffileLog._local, "records", None)
    records: list[logging.LogRecord] = []
    _TifffileLog._local.records = records
    try:
        yield records
    finally:
        _TifffileLog._local.records = outer
        for rec in records:
            log.debug("tifffile: %s", rec.getMessage())


#: tifffile log messages that mean the pages (or the tags volwarp needs) are
#: not all in the file: a truncated or damaged file, never a readable one.
_BROKEN_CHAIN = ("invalid page offset", "corrupted tag list", "invalid offset to page",
                 "circular reference", "invalid next page")
_BROKEN_DATA = ("missing data offset", "missing data bytecounts", "missing bytecounts",
                "incorrect stripbytecounts", "incorrect stripoffsets")
#: the tags whose loss changes what volwarp reads: sizes, sample type, strips
#: and tiles, resolution, the description holding the ImageJ/volwarp metadata
_TAG_NAMES = {256: "ImageWidth", 257: "ImageLength", 258: "BitsPerSample", 259: "Compression",
              262: "PhotometricInterpretation", 270: "ImageDescription", 273: "StripOffsets",
              277: "SamplesPerPixel", 278: "RowsPerStrip", 279: "StripByteCounts",
              282: "XResolution", 283: "YResolution", 284: "PlanarConfiguration",
              296: "ResolutionUnit", 317: "Predictor", 322: "TileWidth", 323: "TileLength",
              324: "TileOffsets", 325: "TileByteCounts", 339: "SampleFormat",
              32997: "ImageDepth", 32998: "TileDepth", 50838: "IJMetadataByteCounts",
              50839: "IJMetadata"}
#: tags whose loss changes what volwarp reads
_NEEDED_TAGS = set(_TAG_NAMES)
_TAG_CODE = re.compile(r"TiffTag (\d+) @")


def _tifffile_message(record: logging.LogRecord) -> str:
    """A tifffile log message without its leading ``<tifffile.X @n>`` object name."""
    text = re.sub(r"^<[^>]*>\s*", "", record.getMessage())
    return " ".join(text.split())[:200]


def _check_tifffile_log(records, where: str, npages: int) -> None:
    """Raise for a logged sign of truncation or damage (see ``_BROKEN_*``)."""
    for rec in records:
        if rec.levelno < logging.WARNING:
            continue
        msg = rec.getMessage()
        low = msg.lower()
        if any(k in low for k in _BROKEN_CHAIN):
            raise FormatError(f"{where}: TIFF is truncated or damaged: the list of pages breaks "
                              f"after {npages} page{'s' if npages != 1 else ''} "
                              f"({_tifffile_message(rec)})")
        if any(k in low for k in _BROKEN_DATA):
            raise FormatError(f"{where}: TIFF is truncated or damaged "
                              f"({_tifffile_message(rec)})")
        m = _TAG_CODE.search(msg)
        if m and int(m.group(1)) in _NEEDED_TAGS and "invalid" in low:
            code = int(m.group(1))
            what = ("lies outside the file" if "offset" in low
                    else f"cannot be read ({_tifffile_message(rec)})")
            raise FormatError(f"{where}: TIFF is truncated or damaged: the value of tag {code} "
                              f"({_TAG_NAMES.get(code, 'tag')}) {what}")


def _declared_pages(tif, pages, ij, where: str) -> tuple[int, str] | None:
    """The number of pages the file's own metadata declares, and which metadata says so."""
    if ij:
        try:
            if "images" in ij:
                return int(ij["images"]), f"ImageJ metadata (images={ij['images']})"
            if "slices" in ij:
                n = int(ij["slices"]) * int(ij.get("channels", 1)) * int(ij.get("frames", 1))
                return n, f"ImageJ metadata (slices={ij['slices']})"
        except (TypeError, ValueError):
            raise FormatError(f"{where}: ImageJ metadata has a count that is not a whole "
                              "number") from None
        return None
    shaped = 0
    found = False
    for page in pages:  # tifffile's shaped series: JSON {"shape": [...]} on each first page
        desc = page.description
        if not desc.startswith("{") or '"shape"' not in desc:
            continue
        try:
            shape = [int(v) for v in json.loads(desc)["shape"]]
        except (ValueError, TypeError, KeyError):
            continue
        plane = int(np.prod(page.shape))  # (a volumetric page's shape holds its depth)
        total = int(np.prod(shape))
        if plane <= 0 or total % plane:
            continue
        shaped += total // plane
        found = True
    if found:
        return shaped, "tifffile metadata (shape)"
    if getattr(tif, "is_ome", False):
        return _ome_pages(tif)
    return None


def _ome_pixels(tif) -> tuple[list[dict], bool] | None:
    """The attributes of each OME ``Pixels`` element, and whether the file is of a multi-file set.

    None without readable OME metadata.

    The OME-XML is parsed once per open file (the result is kept on ``tif``).
    """
    cached = getattr(tif, "_volwarp_ome_pixels", _NOT_PARSED)
    if cached is _NOT_PARSED:
        cached = _parse_ome_pixels(tif)
        with contextlib.suppress(AttributeError):
            tif._volwarp_ome_pixels = cached
    return cached


_NOT_PARSED = object()


def _parse_ome_pixels(tif) -> tuple[list[dict], bool] | None:
    import xml.etree.ElementTree as ET

    if not getattr(tif, "is_ome", False) or not tif.ome_metadata:
        return None
    try:
        root = ET.fromstring(tif.ome_metadata)
    except Exception:  # not parseable: nothing declared
        return None
    pixels, multi_file = [], False
    for el in root.iter():
        tag = el.tag.rsplit("}", 1)[-1]
        if tag == "UUID" and el.get("FileName"):
            multi_file = True
        elif tag == "Pixels":
            pixels.append(dict(el.attrib))
    return pixels, multi_file


def _ome_pages(tif) -> tuple[int, str] | None:
    """SizeZ x SizeC x SizeT summed over the OME images of a one-file OME-TIFF."""
    ome = _ome_pixels(tif)
    if ome is None or ome[1] or not ome[0]:  # a multi-file set: this file holds some planes
        return None
    try:
        total = sum(int(p.get("SizeZ", 1)) * int(p.get("SizeC", 1)) * int(p.get("SizeT", 1))
                    for p in ome[0])
    except ValueError:
        return None
    return total, "OME metadata"


#: tifffile's axis letters of a series that hold z slices: ``Z``, and the unnamed
#: ``Q`` and ``I`` of a shaped series written without axes (one page a plane)
_Z_AXES = "ZQI"
_AXIS_WORDS = {"C": "channels", "T": "time points", "Q": "entries along an unnamed axis"}


def _check_image_axes(series, where: str) -> None:
    """Refuse an image (tifffile's OME or shaped series) whose planes are not only z slices.

    Its axes as tifffile squeezes them (an axis of size 1 is dropped): y and x,
    and before them at most one axis, of z. A channel or time axis, or a
    second one of any kind, would otherwise be stacked along z.
    """
    axes, shape = series.axes, tuple(series.shape)
    lead = [(a, n) for a, n in zip(axes[:-2], shape[:-2], strict=True) if n > 1]
    if axes[-2:] == "YX" and (not lead or (len(lead) == 1 and lead[0][0] in _Z_AXES)):
        return
    kind = "OME-TIFF" if series.kind == "ome" else "TIFF"
    extra = [(a, n) for a, n in lead if a not in "Z"] or lead or [(axes, 0)]
    axis, n = extra[0]
    what = f"{n} {_AXIS_WORDS.get(axis, f'entries along axis {axis}')}" if n else "no y, x planes"
    raise FormatError(f"{where}: {kind} image has {what} (axes {axes}, shape "
                      f"{'x'.join(map(str, shape))}); volwarp reads single-channel, "
                      "single-time-point z stacks")


def _choose_image(tif, npages: int, where: str, volume_index: int | None):
    """``(image, page indices)``: the image of the file ``volume_index`` picks, and its planes.

    An OME-TIFF holds an image per OME ``Image`` element, a tifffile "shaped"
    file one per series (``append=True``): each a volume, with its own size and
    spacing, never stacked into one. Other TIFFs hold one stack of pages.
    """
    series = tif.series
    if not series or series[0].kind not in ("ome", "shaped"):
        series = []
    count = max(len(series), 1)
    if count > 1 and volume_index is None:
        raise ChoiceNeeded(f"{where}: TIFF holds {count} images "
                           f"({'OME Image elements' if series[0].kind == 'ome' else 'tifffile series'}"
                           f"); volwarp reads one: choose it with --volume-index 0..{count - 1}")
    if volume_index is not None and not 0 <= volume_index < count:
        raise BadUsage(f"{where}: --volume-index {volume_index} is outside 0..{count - 1}: "
                       f"the TIFF holds {count} image{'s' if count > 1 else ''}")
    image = volume_index or 0
    if series:
        _check_image_axes(series[image], where)
    if count == 1:
        return image, list(range(npages))
    indices = [getattr(p, "index", None) for p in series[image].pages]
    if None in indices:
        raise FormatError(f"{where}: TIFF image {image} lacks some of its planes (pages)")
    return image, indices


@dataclass(frozen=True)
class TiffStack:
    """A TIFF's stack as volwarp reads it, its checks made (:func:`read_tiff_stack`).

    ``shape``: (z, y, x); ``dtype``: the samples' type (native), ``file_dtype``
    the same in the file's byte order; ``placement``: the Volume keywords but
    ``data`` (:func:`tiff_placement`); ``planes_at``: where ImageJ's layout of
    a stack over 4 GiB (one IFD, every plane back to back after it) has its
    first plane, else None (one page a slice, or one volumetric page);
    ``pages``: the indices of the image's pages in the file; ``image``: which
    image of the file (tifffile's series); ``calibration``: ImageJ's straight
    line ``(c0, c1)`` from the file's samples to ``dtype``'s (:func:`calibrate`).
    """

    shape: tuple[int, int, int]
    dtype: np.dtype
    file_dtype: np.dtype
    placement: dict
    planes_at: int | None = None
    pages: tuple[int, ...] = (0,)
    image: int = 0
    calibration: tuple[float, float] | None = None


def read_tiff(path: str | os.PathLike, volume_index: int | None = None) -> Volume:
    """Read a TIFF stack, its spacing as the module notes say (OME, ImageJ, resolution tags).

    ``volume_index``: which image of a file holding several (:func:`_choose_image`).
    """
    return _open_tiff(path, volume_index, _read_samples)


def read_tiff_stack(path: str | os.PathLike, volume_index: int | None = None) -> TiffStack:
    """The :class:`TiffStack` of the TIFF at ``path``, without its samples.

    The checks are :func:`read_tiff`'s, with its errors word for word (the
    block-wise reader refuses what the whole reader refuses).
    """
    return _open_tiff(path, volume_index, lambda tif, stack, where, records: stack)


def _open_tiff(path, volume_index, then):
    """``then(tif, stack, where, records)`` on the open, checked TIFF at ``path``.

    tifffile's log records stay off stderr (judged by :func:`_check_tifffile_log`,
    else logged at debug level); its exceptions are FormatErrors naming the file.
    """
    import tifffile

    where = str(path)
    with _collect_tifffile_log() as records:
        try:
            tif = tifffile.TiffFile(path)
        except OSError as exc:
            raise FormatError(f"{where}: cannot open ({exc.strerror or exc})") from None
        except Exception as exc:  # tifffile raises many types for damaged files
            _check_tifffile_log(records, where, 0)
            raise FormatError(f"{where}: not a readable TIFF ({_reason(exc)})") from None
        with tif:
            try:
                return then(tif, _check_stack(tif, where, records, volume_index), where,
                            records)
            except VolwarpError:  # (FormatError, and the usage errors of --volume-index)
                raise
            except Exception as exc:  # tifffile raises many types for damaged files
                raise FormatError(f"{where}: TIFF is damaged ({_reason(exc)})") from None


def _reason(exc: Exception) -> str:
    """The complaint of tifffile (or struct, numpy) about a damaged file, in one short line."""
    text = " ".join(str(exc).split())[:200]
    if isinstance(exc, struct.error):
        return f"file ends too early: {text}"
    return text or type(exc).__name__


def unreadable_data(where: str, exc: Exception) -> FormatError:
    """The error of a stack whose samples cannot be decoded (read whole or by box)."""
    return FormatError(f"{where}: cannot read TIFF data ({_reason(exc)})")


def _check_stack(tif, where: str, records, volume_index: int | None = None) -> TiffStack:
    """The stack of an open TIFF, or a FormatError for one volwarp does not read.

    Refused: a broken or looping list of pages, several samples a pixel, pages
    of different shapes or types, an ImageJ hyperstack's channels or frames,
    an OME or tifffile image's channels or time points, several images without
    ``volume_index``, several volumetric pages, fewer pages than the metadata
    declare, an ImageJ value calibration other than a straight line, a
    compression or predictor tifffile cannot decode (:func:`_check_codecs`).
    """
    pages = []
    seen: dict[int, int] = {}
    try:
        for page in tif.pages:  # reads every page's IFD
            # A damaged "next page" offset can point back to an earlier page:
            # tifffile would then go round the loop until memory runs out.
            if page.offset in seen:
                raise FormatError(f"{where}: TIFF is truncated or damaged: page {len(pages)} "
                                  f"is page {seen[page.offset]} again (the list of pages "
                                  "loops)")
            seen[page.offset] = len(pages)
            pages.append(page)
    except FormatError:
        raise
    except Exception as exc:
        _check_tifffile_log(records, where, len(pages))
        raise FormatError(f"{where}: TIFF is truncated or damaged: page {len(pages)} cannot be "
                          f"read ({_reason(exc)})") from None
    _check_tifffile_log(records, where, len(pages))
    if len(pages) == 0:
        raise FormatError(f"{where}: TIFF has no pages")
    if pages[0].samplesperpixel > 1:
        raise FormatError(f"{where}: TIFF has {pages[0].samplesperpixel} samples per pixel; "
                          "volwarp reads one-channel stacks")
    image, indices = _choose_image(tif, len(pages), where, volume_index)
    first = pages[indices[0]]
    shape0, dtype0 = first.shape, first.dtype
    if first.samplesperpixel > 1:
        raise FormatError(f"{where}: TIFF image {image} has {first.samplesperpixel} samples "
                          "per pixel; volwarp reads one-channel stacks")
    for i in indices:
        page = pages[i]
        if page.shape != shape0 or page.dtype != dtype0:
            raise FormatError(f"{where}: page {i} has shape {page.shape} {page.dtype}, "
                              f"page {indices[0]} has {shape0} {dtype0}; all slices must match")
    if first.imagedepth > 1 and len(indices) > 1:
        raise FormatError(f"{where}: TIFF has {len(indices)} volumetric pages (of depth "
                          f"{first.imagedepth}); volumetric TIFFs of more than one page are "
                          "not supported")
    if dtype0 is None:
        raise FormatError(f"{where}: unsupported TIFF sample format")
    _check_codecs({(pages[i].compression, pages[i].predictor) for i in indices}, where)
    dtype = check_dtype(dtype0, where)
    ij = tif.imagej_metadata
    if ij:
        for key in ("channels", "frames"):
            if int(ij.get(key, 1)) > 1:
                raise FormatError(f"{where}: ImageJ hyperstack has {ij[key]} {key}; "
                                  "volwarp reads single-channel, single-frame stacks")
    ny, nx = shape0[-2], shape0[-1]
    nz = len(indices) if first.imagedepth == 1 else first.imagedepth
    declared = _declared_pages(tif, pages, ij, where)
    planes_at = None
    if declared is not None and declared[0] != len(pages):
        count, source = declared
        npages = len(pages)
        if ij and npages == 1 and count > 1 and _is_imagej_big_stack(tif, first, count):
            planes_at, nz = int(first.dataoffsets[0]), count  # ImageJ's stacks over 4 GiB
        else:
            raise FormatError(f"{where}: TIFF has {npages} page{'s' if npages != 1 else ''} "
                              f"but its {source} declares {count}: the file is truncated or "
                              "damaged")
    shape = (nz, ny, nx)
    calibration = _imagej_calibration(ij, dtype, where)
    out_dtype = dtype if calibration is None else calibrated_dtype(dtype, calibration)
    return TiffStack(shape, out_dtype, dtype.newbyteorder(tif.byteorder),
                     tiff_placement(tif, first, ij, shape, where, image), planes_at,
                     tuple(indices), image, calibration)


def _check_codecs(schemes, where: str) -> None:
    """Refuse pages whose compression or predictor tifffile cannot decode, naming it.

    Before any work (a run by blocks met it at its first block, after the
    stack's warnings); the error is the one a read of the samples gives.
    """
    from tifffile import TIFF

    for compression, predictor in sorted(schemes):
        try:
            TIFF.DECOMPRESSORS[compression]
            # (an image codec's predictor is ignored, as tifffile does; 0 is left to the read:
            # an ImageJ stack over 4 GiB is read without tifffile)
            if predictor not in (0, 1) and compression not in TIFF.IMAGE_COMPRESSIONS:
                TIFF.UNPREDICTORS[predictor]
        except KeyError as exc:  # (tifffile's message: "<COMPRESSION.PIXARLOG: 32909> not
            # supported", "... requires the 'imagecodecs' package")
            raise unreadable_data(where, ValueError(*exc.args)) from None


def _read_samples(tif, stack: TiffStack, where: str, records) -> Volume:
    """The Volume of a checked stack (:func:`_check_stack`): its samples read whole."""
    nz, ny, nx = stack.shape
    ensure_fits_in_memory(voxel_count((nx, ny, nz)) * stack.dtype.itemsize,
                          f"{where} ({nx}x{ny}x{nz} {stack.dtype.name})")
    try:
        if stack.planes_at is not None:
            tif.filehandle.seek(stack.planes_at)
            data = np.frombuffer(read_exact(tif.filehandle, nz * ny * nx * stack.dtype.itemsize,
                                            where), dtype=stack.file_dtype)
        elif len(stack.pages) > 1:
            data = tif.asarray(key=list(stack.pages))
        else:  # one plane, or one volumetric page of nz planes
            data = tif.pages[stack.pages[0]].asarray()
    except FormatError:
        raise
    except Exception as exc:  # tifffile raises many types for damaged files
        raise unreadable_data(where, exc) from None
    _check_tifffile_log(records, where, nz)
    data = calibrate(native(np.asarray(data).reshape(nz, ny, nx)), stack.calibration)
    return make_volume(where, data, **stack.placement)


def _ome_spacing(tif, where: str, image: int = 0) -> list[float | None] | None:
    """The OME ``PhysicalSizeX/Y/Z`` of image ``image`` in mm, or None without OME metadata.

    An axis without a usable size is None.
    """
    ome = _ome_pixels(tif)
    if ome is None or len(ome[0]) <= image:
        return None
    pixels = ome[0][image]
    out: list[float | None] = []
    for axis in "XYZ":
        text = pixels.get(f"PhysicalSize{axis}")
        unit = pixels.get(f"PhysicalSize{axis}Unit", _OME_DEFAULT_UNIT).strip()
        if text is None:
            out.append(None)
            continue
        try:
            value = float(text)
        except ValueError:
            value = float("nan")
        scale = OME_LENGTH_TO_MM.get(unit)
        if not (np.isfinite(value) and value > 0) or scale is None:
            log.debug("%s: OME PhysicalSize%s=%r %r is not a positive length: ignored",
                      where, axis, text, unit)
            out.append(None)
            continue
        out.append(value * scale)
    return out


def _is_imagej_big_stack(tif, first, count: int) -> bool:
    """True for ImageJ's layout of a stack: one IFD, all planes stored back to back after it."""
    if not first.is_contiguous or first.compression != 1 or first.predictor not in (0, 1):
        return False
    if getattr(first, "fillorder", 1) != 1 or len(first.dataoffsets) == 0:
        return False
    need = first.dataoffsets[0] + count * first.nbytes
    return need <= tif.filehandle.size


def imagej_unit_mm(unit: str) -> float | None:
    """An ImageJ stack's ``unit`` in millimetres, None for no length (``pixel``, unknown).

    ImageJ's spacings (the resolution tags' and ``spacing``) are in that unit:
    a stack of 0.25 um voxels is 0.00025 mm ones (it was read as 0.25 mm).
    """
    return length_unit_mm(unit)


#: ImageJ's value calibration functions (``ij.measure.Calibration``): a straight line, none
_IJ_STRAIGHT_LINE, _IJ_NONE = 0, 20


def _imagej_calibration(ij, dtype: np.dtype, where: str) -> tuple[float, float] | None:
    """An ImageJ stack's value calibration ``(c0, c1)``, value = c0 + c1 x sample, or None.

    Fiji saves a signed 16-bit stack as uint16 with ``cf=0 c0=-32768 c1=1``:
    read raw, every value is 32768 too high. ImageJ drops the calibration of a
    float32 stack (``Calibration.setImage``), and so does volwarp; a
    calibration function other than a straight line is refused.
    """
    if not ij or "cf" not in ij or dtype.kind == "f":
        return None
    try:
        cf = int(ij["cf"])
        line = (float(ij["c0"]), float(ij["c1"])) if "c0" in ij and "c1" in ij else None
    except (TypeError, ValueError):
        raise FormatError(f"{where}: ImageJ value calibration (cf, c0, c1) is not a "
                          "number") from None
    if cf == _IJ_NONE or line is None:  # (ImageJ too keeps no function without coefficients)
        return None
    if cf != _IJ_STRAIGHT_LINE:
        raise FormatError(f"{where}: ImageJ value calibration function {cf} is not a straight "
                          "line (cf=0); volwarp applies straight-line calibrations only")
    if str(ij.get("zeroclip", "false")).lower() == "true" or not np.all(np.isfinite(line)):
        raise FormatError(f"{where}: ImageJ value calibration c0={line[0]:g} c1={line[1]:g} "
                          f"zeroclip={ij.get('zeroclip', 'false')} cannot be applied")
    return None if line == (0.0, 1.0) else line


def calibrated_dtype(dtype: np.dtype, calibration: tuple[float, float]) -> np.dtype:
    """The sample type of calibrated values: int16 for Fiji's signed 16-bit, else float32.

    (``dtype`` in either byte order: a big stack's samples are read in the file's.)
    """
    if np.dtype(dtype).newbyteorder("=") == np.uint16 and calibration == (-32768.0, 1.0):
        return np.dtype(np.int16)
    return np.dtype(np.float32)


def calibrate(samples: np.ndarray, calibration: tuple[float, float] | None) -> np.ndarray:
    """``samples`` (the file's, native order) with an ImageJ straight line applied.

    Element by element, so that a box read alone is the whole read's box.
    """
    if calibration is None:
        return samples
    c0, c1 = calibration
    if calibrated_dtype(samples.dtype, calibration) == np.int16:  # exact
        return (samples.astype(np.int32) - 32768).astype(np.int16)
    return (c0 + c1 * samples.astype(np.float64)).astype(np.float32)


def tiff_placement(tif, first, ij, shape_zyx, where: str, image: int = 0) -> dict:
    """The Volume keywords but ``data`` (spacing, origin, direction, space, meta) of a stack.

    ``shape_zyx``: the stack's shape; the placement is checked for it.
    ``image``: which image (tifffile series) of the file the stack is.
    """
    meta: dict = {}
    spacing = [1.0, 1.0, 1.0]
    names = ["XResolution", "YResolution", "z spacing"]  # where each axis' spacing came from
    origin = [0.0, 0.0, 0.0]
    direction = np.eye(3)
    extra = {}
    ij_scale = None  # an ImageJ unit's millimetres (x, y and z are in it)
    if ij:
        extra = ij
        if ij.get("unit"):
            meta["unit"] = str(ij["unit"])
            ij_scale = imagej_unit_mm(str(ij["unit"]))
            if ij_scale is not None:
                meta["unit"] = "mm"
        if "spacing" in ij:
            spacing[2] = _floats([ij["spacing"]], 1, where, "ImageJ spacing")[0]
            spacing[2] *= ij_scale or 1.0
            names[2] = "ImageJ spacing"
        elif ij_scale is not None:  # ImageJ writes no spacing for a depth of 1 unit
            spacing[2] = ij_scale
    elif tif.shaped_metadata and len(tif.shaped_metadata) > image:
        extra = tif.shaped_metadata[image]
        if "unit" in extra:
            meta["unit"] = str(extra["unit"])
    scale = ij_scale or 1.0
    tags = first.tags
    if ij and ij.get("unit") == "um" and _resolution_unit(tags) == 3:
        scale = _RESUNIT_MM[3][1]  # (ImageJ's FileOpener: the tags count pixels per cm)
    code = _resolution_unit(tags)
    plain = not ij and "volwarp_spacing" not in extra
    held = _resolutions(tags)
    uncalibrated = _uncalibrated(tags, held, code) if plain else None
    unitless = uncalibrated or ("ResolutionUnit none" if plain and code == 1 else None)
    if ij and ij_scale is None:  # (ImageJ's pixel, no unit, a word: x, y and z in no length)
        unitless = f"ImageJ unit {ij['unit']!r}" if ij.get("unit") else "no ImageJ unit"
    if plain and code is not None and uncalibrated is None:
        if code in _RESUNIT_MM:
            scale = _RESUNIT_MM[code][1]
            meta["unit"] = "mm"
        elif code != 1:  # 1: no unit, the numbers as they are
            log.warning("%s: TIFF ResolutionUnit %d is no known unit: x and y spacing are "
                        "1 / resolution, in no unit", where, code)
    for axis, tag in ((0, "XResolution"), (1, "YResolution")):
        if tag in held and uncalibrated is None:
            num, den = held[tag]
            spacing[axis] = scale * den / num
    if uncalibrated is None and len(held) == 1:  # (y was 1 beside x's 0.25 mm)
        (tag, _), = held.items()
        given = ("XResolution", "YResolution").index(tag)
        spacing[1 - given] = spacing[given]
        if first_said(("tiff resolution pair", os.path.abspath(where))):
            other = ("XResolution", "YResolution")[1 - given]
            what = (f"its {other} is {'/'.join(map(str, tags[other].value))}, no size"
                    if other in tags else f"it has no {other}")
            log.warning("%s: TIFF %s: it is %s, as the OME PhysicalSizeX/Y are read",
                        where, what, tag)
    if "volwarp_spacing" in extra:
        stored = _floats(extra["volwarp_spacing"], 3, where, "volwarp_spacing")
        if _calibration_disagrees(stored, spacing, names, tags, ij):
            log.warning("%s: the stack's calibration (%s mm) is not the spacing volwarp stored "
                        "with it (%s mm): another program changed it after volwarp wrote the "
                        "file, so the calibration is read", where,
                        " ".join(f"{v:.6g}" for v in spacing),
                        " ".join(f"{v:.6g}" for v in stored))
        else:
            spacing = stored
            names = ["volwarp_spacing"] * 3
    elif "spacing" in extra and not ij and not isinstance(extra["spacing"], (int, float)):
        spacing = _floats(extra["spacing"], 3, where, "spacing")
        names = ["spacing"] * 3
    ome = _ome_spacing(tif, where, image) if "volwarp_spacing" not in extra else None
    z_said = False  # (the OME metadata's missing PhysicalSizeZ)
    if ome and (ome[0] is None) != (ome[1] is None):
        # as Bio-Formats' calibration: the tags' y beside OME's x mixed units (1 with 0.0005 mm)
        given, missing = (0, 1) if ome[1] is None else (1, 0)
        ome[missing] = ome[given]
        log.warning("%s: the OME metadata give no PhysicalSize%s: it is PhysicalSize%s, "
                    "%g mm, as Bio-Formats reads it", where, "XY"[missing], "XY"[given],
                    ome[given])
    if ome and any(v is not None for v in ome):
        for axis, value in enumerate(ome):
            if value is not None:
                spacing[axis] = value
                names[axis] = f"OME PhysicalSize{'XYZ'[axis]}"
        meta["unit"] = "mm"
        if ome[2] is None and shape_zyx[0] > 1:
            log.warning("%s: the OME metadata give no PhysicalSizeZ: z spacing is %g", where,
                        spacing[2])
            z_said = True
    stacked = shape_zyx[0] > 1 and not z_said
    if ij:
        z_lacks = unitless if stacked and names[2] in ("z spacing", "ImageJ spacing") else None
    else:
        z_lacks = "the file holds no slice spacing" if stacked and names[2] == "z spacing" \
            else None
    if plain or (ij and "volwarp_spacing" not in extra):  # (volwarp's own numbers: read)
        xy_lacks = unitless if names[:2] == ["XResolution", "YResolution"] else None
        _say_uncalibrated(where, spacing, meta, xy_lacks, z_lacks)
    if "volwarp_origin" in extra:
        origin = _floats(extra["volwarp_origin"], 3, where, "volwarp_origin")
    elif ij:
        origin = _imagej_origin(ij, spacing, where)
    if "volwarp_direction" in extra:
        direction = np.array(_floats(extra["volwarp_direction"], 9, where,
                                     "volwarp_direction")).reshape(3, 3)
    space = extra.get("volwarp_space") or None
    if "volwarp_spacing" in extra:
        # written by volwarp: its key/values are exactly the volume's meta
        try:
            meta = dict(json.loads(extra.get("volwarp_meta", "{}")))
        except (TypeError, ValueError):
            raise FormatError(f"{where}: volwarp_meta is not valid JSON") from None
    spacing, origin, direction = check_placement(
        spacing, origin, direction, zyx_to_xyz(shape_zyx), where=where,
        fields={"spacing": names, "origin": "volwarp_origin", "direction": "volwarp_direction"})
    return {"spacing": spacing, "origin": origin, "direction": direction, "space": space,
            "meta": meta}


#: ImageJ's uncalibrated resolution: the pixels per inch image editors, Pillow and many
#: export tools write when they know no size (``ij.io.TiffDecoder``)
_EDITORS_DPI = 72.0


def _resolutions(tags) -> dict:
    """``{tag: (num, den)}`` of the XResolution/YResolution tags that give a size.

    A resolution of 0, or of denominator 0, gives none: ImageJ's TiffDecoder
    takes it for a missing tag (Pillow writes 0/1 for ``dpi=(0, 0)``; such a
    file was refused, and before that read 1 beside the other axis' tag).
    """
    held = {}
    for tag in ("XResolution", "YResolution"):
        if tag in tags:
            num, den = tags[tag].value
            if num > 0 and den > 0:
                held[tag] = (num, den)
    return held


def _uncalibrated(tags, held: dict, code) -> str | None:
    """Why a plain TIFF's resolution tags give no voxel size (x and y are then 1), or None.

    As ImageJ's TiffDecoder reads them: no ResolutionUnit, or XResolution 72
    per inch, is uncalibrated (72 dpi read as a length made 0.353 mm voxels);
    so are tags of 0 (``held``: :func:`_resolutions`).
    """
    if not held:
        return ("no resolution tags" if "XResolution" not in tags
                and "YResolution" not in tags else "resolution tags of 0")
    if code is None:
        return "resolution tags without a ResolutionUnit"
    if code == 2 and "XResolution" in held:
        num, den = held["XResolution"]
        if num / den == _EDITORS_DPI:
            return "72 pixels per inch, what image editors write for no size"
    return None


#: inside :func:`samples_only`: the file is read for its samples (a sweep's template stack)
_SAMPLES_ONLY = contextvars.ContextVar("tiff_samples_only", default=False)


@contextlib.contextmanager
def samples_only():
    """Read TIFFs inside for their samples only: their missing voxel size is not said.

    A sweep's template stack is placed by its sweep, not by its calibration:
    the warning of a stack without one (every plain stack) was noise there.
    """
    token = _SAMPLES_ONLY.set(True)
    try:
        yield
    finally:
        _SAMPLES_ONLY.reset(token)


def _say_uncalibrated(where, spacing, meta, xy_lacks, z_lacks) -> None:
    """Warn, once a run, of the voxel size a TIFF does not give and volwarp takes.

    ``xy_lacks``, ``z_lacks``: why x and y, and z, have no length in the
    file (:func:`_uncalibrated`, ResolutionUnit none, ImageJ's ``pixel``,
    a plain stack's missing slice spacing), or None where they have one.
    """
    if xy_lacks and xy_lacks == z_lacks:
        parts = [f"x, y and z ({xy_lacks})"]
    else:
        parts = [f"{axes} ({why})" for axes, why in (("x and y", xy_lacks), ("z", z_lacks))
                 if why]
    if not parts or _SAMPLES_ONLY.get() or not first_said(("tiff uncalibrated",
                                                            os.path.abspath(where))):
        return
    unit = "mm" if meta.get("unit") == "mm" else "in no unit, taken as mm"
    log.warning("%s: no voxel size in the TIFF for %s: spacing %s (%s); volwarp has no "
                "option to set it: set it in Fiji (Image > Properties) and save, or convert "
                "to .nhdr and edit 'space directions'", where,
                " nor ".join(parts), " ".join(f"{v:g}" for v in spacing), unit)


def _resolution_unit(tags) -> int | None:
    """The ResolutionUnit tag's code, None without the tag."""
    return int(tags["ResolutionUnit"].value) if "ResolutionUnit" in tags else None


#: how far (relatively) a stack's calibration may be from the spacing volwarp stored with
#: it and still be the same: the resolution tags are ratios of 32-bit integers
_CALIBRATION_RTOL = 1e-5


def _calibration_disagrees(stored, calibrated, names, tags, ij) -> bool:
    """Whether the spacing a TIFF's own tags give differs from volwarp's exact copy of it.

    volwarp writes both (the exact numbers, and the resolution tags and ImageJ
    ``spacing`` that Fiji reads); a program that changes the calibration keeps
    the key/values it does not know. Only the axes whose calibration the file
    holds are compared (a plain stack has no z spacing).
    """
    held = [("XResolution" in tags) and names[0] == "XResolution",
            ("YResolution" in tags) and names[1] == "YResolution",
            bool(ij) and names[2] == "ImageJ spacing"]
    return any(h and not math.isclose(float(a), float(b), rel_tol=_CALIBRATION_RTOL)
               for h, a, b in zip(held, stored, calibrated, strict=True))


def _imagej_origin(ij, spacing, where: str) -> list[float]:
    """The position of voxel 0 from an ImageJ stack's ``xorigin``, ``yorigin``, ``zorigin``.

    ImageJ's calibration origin is in pixels: the calibrated coordinate of
    pixel ``i`` is ``(i - xorigin) * pixelWidth`` (its ``Calibration.getX``),
    so voxel 0 lies at ``-xorigin * spacing``. 0 where a key is missing.
    """
    origin = [0.0, 0.0, 0.0]
    for axis, name in enumerate(("xorigin", "yorigin", "zorigin")):
        if name in ij:
            pixels = _floats([ij[name]], 1, where, f"ImageJ {name}")[0]
            origin[axis] = -pixels * spacing[axis] + 0.0
    return origin


def _imagej_origin_keys(vol: Volume) -> dict:
    """ImageJ's ``xorigin``... of ``vol`` (pixels) where its axes are the stack's, else none.

    Fiji then shows the volume's own coordinates. A rotated grid has no
    ImageJ calibration (volwarp's own keys hold it).
    """
    if not np.array_equal(vol.direction, np.eye(3)):
        return {}
    return {name: -float(o) / float(s) + 0.0 for name, o, s in
            zip(("xorigin", "yorigin", "zorigin"), vol.origin, vol.spacing, strict=True) if o}


def write_tiff(vol: Volume, path: str | os.PathLike, *, compress: bool = False,
               byte_order: str = "little") -> None:
    """Write ``vol`` as a TIFF stack (ImageJ where its type allows), atomically."""
    import tifffile

    path = Path(path)
    dtype = check_dtype(vol.data.dtype, str(path))
    meta = dict(vol.meta)
    # (the spacings written are millimetres: a key/value unit of length, "micron" from a
    # stack read before, made Fiji's voxels 1000x too small; no length, "pixel", is kept)
    unit = str(meta.get("unit", "mm"))
    unit = unit if imagej_unit_mm(unit) is None else "mm"
    geometry = {
        "volwarp_spacing": " ".join(repr(float(v)) for v in vol.spacing),
        "volwarp_origin": " ".join(repr(float(v)) for v in vol.origin),
        "volwarp_direction": " ".join(repr(float(v)) for v in vol.direction.ravel()),
    }
    if vol.space:
        geometry["volwarp_space"] = vol.space
    if meta:
        geometry["volwarp_meta"] = json.dumps(meta, sort_keys=True, default=str)
    for axis, tag in ((0, "XResolution"), (1, "YResolution")):
        # a RATIONAL of two 32-bit integers holds 1 / spacing (1e-30 mm failed inside tifffile)
        if not 2.0 ** -31 <= 1.0 / vol.spacing[axis] <= 2.0 ** 31:
            raise VolwarpError(f"{path}: spacing {vol.spacing[axis]:g} cannot be stored in "
                               f"TIFF's {tag} (a ratio of 32-bit integers); write .nrrd, "
                               ".nii.gz or .mha")
    data = with_byte_order(vol.data, byte_order)
    kwargs = dict(
        byteorder="<" if byte_order == "little" else ">",
        resolution=(1.0 / vol.spacing[0], 1.0 / vol.spacing[1]),
        compression="zlib" if compress else None,
        software="volwarp",
    )
    # tifffile takes a last axis of size 1 (x one voxel thick) for samples and drops it: the
    # axes are spelled out for ImageJ (the same bytes otherwise), and the plain TIFF's
    # description is written as tifffile would, without its squeezing of the shape
    nz, ny, nx = data.shape
    with atomic_output(path) as tmp:
        if dtype.name in _IMAGEJ_TYPES:
            tifffile.imwrite(tmp, data.reshape(nz, 1, ny, nx, 1), imagej=True,
                             metadata={"axes": "ZCYXS", "spacing": float(vol.spacing[2]),
                                       "unit": unit, **_imagej_origin_keys(vol), **geometry},
                             **kwargs)
        else:
            # minisblack: else tifffile stores a stack of 3 or 4 slices as one RGB(A) page
            shaped = json.dumps({"shape": [nz, ny, nx], "axes": "ZYX", "unit": unit,
                                 **geometry})
            tifffile.imwrite(tmp, data, description=shaped, metadata=None,
                             resolutionunit="NONE", photometric="minisblack", **kwargs)
