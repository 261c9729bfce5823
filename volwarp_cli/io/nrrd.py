r"""NRRD (``.nrrd`` attached, ``.nhdr`` detached) reading and writing.

Reads NRRD0001-5 headers with encodings raw, gzip, bzip2 and ascii, either
endian, ``space``/``space directions``/``space origin`` or ``spacings``/``axis
mins``/``axis maxs``/``centerings`` geometry (placed as ITK places it: cell
centering unless ``node`` is given, see :func:`_axis_geometry`), detached
data (one file, ``LIST`` or a ``%d`` pattern), line and byte skips.
Key/value pairs (``key:=value``) are kept in ``Volume.meta``, with teem's
two escapes (``\n`` a newline, ``\\`` a backslash: :func:`_unescape`); the
descriptive fields ``content``, ``space units`` and ``measurement frame``
are kept as ``NRRD_content`` etc. (ITK's names), and written back; so are
``sample units``, ``thicknesses`` and ``labels`` (the last two of a 3-D
file), true of the samples as read on their grid: ``convert`` keeps them, a
command that computes new samples drops them
(:func:`volwarp_cli.provenance.stamp`). ``centerings`` is read for the
geometry and not written back (volwarp writes ``space directions``, cell
centred as ITK takes them).

Writes deterministic files (no timestamp, gzip with mtime 0) that pynrrd,
SimpleITK and 3D Slicer open with the same geometry. The header is parsed
here rather than by pynrrd so that every error names the field and the file.
"""

from __future__ import annotations

import os
import re
import zlib
from pathlib import Path

import numpy as np

from ..errors import BadUsage, ChoiceNeeded, FormatError, VolwarpError
from ..geometry import check_placement
from ..memory import ensure_fits_in_memory
from ..samples import check_dtype, voxel_count
from ..volume import Header, Volume, frame_to_lps, xyz_to_zyx
from .common import (
    ascii_values,
    header_bytes,
    header_line,
    header_name,
    make_volume,
    native,
    open_input,
    pattern_count,
    pattern_files,
    pattern_numbers,
    read_data_files,
    read_exact,
    read_gzip_exact,
    short_text,
    with_byte_order,
    write_samples,
    write_with_header,
)
from .mapped import guard

_TYPES = {
    "signed char": "int8", "int8": "int8", "int8_t": "int8",
    "uchar": "uint8", "unsigned char": "uint8", "uint8": "uint8", "uint8_t": "uint8",
    "short": "int16", "short int": "int16", "signed short": "int16", "signed short int": "int16",
    "int16": "int16", "int16_t": "int16",
    "ushort": "uint16", "unsigned short": "uint16", "unsigned short int": "uint16",
    "uint16": "uint16", "uint16_t": "uint16",
    "int": "int32", "signed int": "int32", "int32": "int32", "int32_t": "int32",
    "uint": "uint32", "unsigned int": "uint32", "uint32": "uint32", "uint32_t": "uint32",
    "longlong": "int64", "long long": "int64", "long long int": "int64", "signed long long": "int64",
    "signed long long int": "int64", "int64": "int64", "int64_t": "int64",
    "ulonglong": "uint64", "unsigned long long": "uint64", "unsigned long long int": "uint64",
    "uint64": "uint64", "uint64_t": "uint64",
    "float": "float32", "double": "float64",
}
_WRITE_TYPES = {"int8": "int8", "uint8": "uint8", "int16": "int16", "uint16": "uint16",
                "int32": "int32", "uint32": "uint32", "float32": "float", "float64": "double"}
_ENCODINGS = {"raw": "raw", "gzip": "gzip", "gz": "gzip", "bzip2": "bzip2", "bz2": "bzip2",
              "hex": "hex",
              "ascii": "ascii", "txt": "ascii", "text": "ascii"}
_KEPT_FIELDS = ("content", "space units", "measurement frame")
#: fields true of the samples as read, on their grid (``NRRD_<field>``): kept by ``convert``
#: only (:data:`volwarp_cli.provenance.AS_READ_KEYS`); the two of an entry an axis from a 3-D
#: file only (a 4-D file's name its component axis too)
AS_READ_FIELDS = ("sample units", "thicknesses", "labels")
_PER_AXIS = ("thicknesses", "labels")
#: the NRRD field names (to tell a field from a file name after "data file: LIST")
_FIELDS = frozenset((
    "dimension", "type", "block size", "blocksize", "encoding", "endian", "content", "number",
    "min", "max", "old min", "oldmin", "old max", "oldmax", "data file", "datafile",
    "line skip", "lineskip", "byte skip", "byteskip", "sample units", "sampleunits", "sizes",
    "spacings", "thicknesses", "axis mins", "axismins", "axis maxs", "axismaxs", "centers",
    "centerings", "labels", "units", "kinds", "space", "space dimension", "space units",
    "space origin", "space directions", "measurement frame"))
#: spellings of one field (spaces dropped): each may be given once
_SAME_FIELD = {"centerings": "centers"}
_VECTOR = re.compile(r"\(([^()]*)\)")
#: the fields of vectors, "(x,y,z)", whose entries are the words between spaces
_VECTOR_FIELDS = ("space directions", "space origin", "measurement frame")
#: teem's escapes in key/value pairs (what ITK and Slicer write): \\ and \n
_ESCAPE = re.compile(r"\\([\\n])")


def _unescape(text: str) -> str:
    r"""A key or value as teem reads it: ``\\`` a backslash, ``\n`` a newline.

    Left to right, as teem does: ``\\n`` is a backslash and an ``n``; any
    other backslash is kept (a DICOM value's ``ORIGINAL\PRIMARY`` read as
    ITK reads it).
    """
    return _ESCAPE.sub(lambda m: "\n" if m.group(1) == "n" else "\\", text) if "\\" in text \
        else text


def _escape(text: str) -> str:
    r"""A key or value as teem writes it (:func:`_unescape` reads it back the same).

    A carriage return, vertical tab or form feed becomes a space, as teem
    writes them (a ``\r`` kept made the line one ITK cannot read).
    """
    return text.replace("\\", "\\\\").replace("\n", "\\n").translate(_SPACED)


_SPACED = str.maketrans({"\r": " ", "\v": " ", "\f": " "})


def _parse_vector(text: str, where: str, name: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise FormatError(f"{where}: '{name}': cannot read vector ({short_text(text)})") from None


def _numbers(fields: dict[str, str], name: str, where: str) -> list[float]:
    """A per-axis float field (``spacings``, ``axis mins``): NaN marks a non-spatial axis."""
    try:
        return [float(v) for v in fields[name].split()]
    except ValueError:
        raise FormatError(f"{where}: '{name}' must be numbers, got "
                          f"{short_text(fields[name])!r}") from None


def _whole(fields: dict[str, str], names: tuple[str, ...], where: str, default: int = 0,
           minimum: int = 0) -> int:
    """A whole-number field (``line skip``, ``byte skip``) under any of its spellings."""
    for name in names:
        if name in fields:
            text = fields[name]
            try:
                value = int(text)
            except ValueError:
                raise FormatError(f"{where}: '{name}' must be a whole number, got "
                                  f"{short_text(text)!r}") from None
            if value < minimum:
                raise FormatError(f"{where}: '{name}' must be at least {minimum}, got {value}")
            return value
    return default


def read_header(fh, where: str) -> tuple[dict[str, str], dict[str, str]]:
    """Parse a NRRD header from a binary file positioned at its start.

    Returns (fields, key/values), fields with lower-case names. The file is
    left at the first byte after the header's blank line.
    """
    magic = fh.readline(64)
    if not re.match(rb"^NRRD000[1-9]\s*$", magic):
        raise FormatError(f"{where}: not a NRRD file (no NRRD000x magic line)")
    fields: dict[str, str] = {}
    keyvals: dict[str, str] = {}
    seen: set[str] = set()
    listing = False  # after "data file: LIST": the file names follow the last field
    while True:
        pos = fh.tell()
        raw = fh.readline(1 << 20)
        if not raw:
            break  # detached header ends at end of file
        line = header_line(raw).rstrip("\r\n")
        if line == "":
            break
        if line.startswith("#"):
            continue
        if listing and ":=" not in line and (
                ": " not in line or line.split(": ", 1)[0].strip().lower() not in _FIELDS):
            fh.seek(pos)  # the first data file name
            break
        if ":=" in line:
            key, value = line.split(":=", 1)
            keyvals[_unescape(key)] = _unescape(value)
            continue
        if ": " not in line:
            shown = line if len(line) <= 80 else line[:77] + "..."
            raise FormatError(f"{where}: malformed header line {shown!r}")
        name, value = line.split(": ", 1)
        name = name.strip().lower()
        if name not in _FIELDS:  # (a misspelt field: 'spacing' for 'spacings' lost the spacing)
            raise FormatError(f"{where}: unknown NRRD field {name!r} (a key/value pair is "
                              "written 'key:=value')")
        same = _SAME_FIELD.get(name.replace(" ", ""), name.replace(" ", ""))
        if same in seen:  # (teem and pynrrd refuse it; the last one won silently)
            raise FormatError(f"{where}: the NRRD field {name!r} is given twice")
        seen.add(same)
        if name in ("data file", "datafile"):  # (a file name: its bytes, as they are)
            value = header_name(raw).rstrip("\r\n").split(": ", 1)[1]
        if name in _VECTOR_FIELDS:  # ("(0.5, 0, 0)": teem and ITK read spaces in a vector)
            value = _VECTOR.sub(lambda m: "(" + "".join(m.group(1).split()) + ")", value)
        fields[name] = value.strip()
        if name in ("data file", "datafile") and value.split()[:1] == ["LIST"]:
            listing = True
    return fields, keyvals


def file_type(fields: dict[str, str], dtype: np.dtype, encoding: str, where: str) -> np.dtype:
    """The samples' type as the file stores them: ``dtype`` in the header's byte order.

    Samples wider than a byte in a binary encoding need the ``endian`` field (teem
    and pynrrd refuse a header without it; taken for little-endian, a big-endian
    file's samples came out byte-swapped).
    """
    endian = fields.get("endian")
    if endian is None:
        if dtype.itemsize > 1 and encoding != "ascii":
            raise FormatError(f"{where}: no 'endian' field: {dtype.itemsize}-byte samples in "
                              f"{encoding} encoding need it (little or big)")
        endian = "little"
    endian = endian.lower()
    if endian not in ("little", "big"):
        raise FormatError(f"{where}: unknown endian {fields.get('endian')!r}")
    return dtype.newbyteorder("<" if endian == "little" else ">")


def _geometry(fields: dict[str, str], dim: int, where: str):
    """Return (spacing, origin, direction, space) in (x, y, z) for a 3-D header.

    Checked by :func:`~volwarp_cli.geometry.check_placement`: a refusal names
    the header field the bad number came from.
    """
    _check_space_fields(fields, where)
    spacing, origin, direction, space = _header_geometry(fields, dim, where)
    scale = length_scale(fields, dim, where)
    if scale is not None:  # (numbers in microns, cm, ...: to millimetres)
        matrix = direction * spacing[None, :] * scale[:, None]
        spacing = np.linalg.norm(matrix, axis=0)
        direction = matrix / spacing[None, :]
        origin = origin * scale
    if "space directions" in fields:
        names = {"spacing": "'space directions'", "direction": "'space directions'",
                 "origin": "'space origin'"}
    else:
        names = {"spacing": "'spacings'",
                 "origin": "'space origin'" if "space origin" in fields else "'axis mins'"}
    spacing, origin, direction = check_placement(spacing, origin, direction,
                                                 _spatial_sizes(fields, dim, where),
                                                 where=where, fields=names)
    return spacing, origin, direction, space


#: the per-axis fields that place an axis without a surrounding space
_AXIS_PLACING = ("spacings", "axis mins", "axismins", "axis maxs", "axismaxs")
#: the fields that only a header with a space (``space`` or ``space dimension``) may give
_SPACE_ONLY = ("space directions", "space origin", "space units", "measurement frame")


def _check_space_fields(fields: dict[str, str], where: str) -> None:
    """Refuse the space fields teem refuses, or that ITK and teem would place apart.

    ``space`` and ``space dimension`` are one field (teem refuses both), the
    dimension 3; a field in that space (``space directions``, ``space origin``,
    ``space units``, ``measurement frame``) needs one of them (teem refuses it
    without: the origin was dropped, the directions read without a frame). An
    axis with a direction vector takes no ``spacings``, ``axis mins``/``maxs``
    or ``units`` (teem refuses them; they were dropped). A space without
    ``space directions`` leaves its axes without a direction: ``spacings`` there
    are refused by ITK, ``axis mins``/``maxs`` read by teem's origin and
    ignored by ITK, and a RAS or LAS space is mirrored by volwarp's frame and
    not by ITK's (its ``space origin`` is): each refused, naming the field.
    """
    if "space" in fields and "space dimension" in fields:
        raise FormatError(f"{where}: 'space' and 'space dimension' are both given (one "
                          "of the two says the space)")
    if "space dimension" in fields:
        text = fields["space dimension"]
        if text != "3":
            raise FormatError(f"{where}: 'space dimension' must be 3 (volwarp reads volumes "
                              f"in a 3-D space), got {short_text(text)!r}")
    elif "space" not in fields:
        for name in _SPACE_ONLY:
            if name in fields:
                raise FormatError(f"{where}: '{name}' without 'space' or 'space dimension' "
                                  "(the space it is given in)")
        return
    placed = {n: _placed_axes(fields, n) for n in (*_AXIS_PLACING, "units") if n in fields}
    if "space directions" in fields:  # (a ``none`` axis, a sequence's time, may have them)
        directed = {a for a, e in enumerate(fields["space directions"].split())
                    if e.lower() != "none"}
        given = [n for n, axes in placed.items() if axes & directed]
        if given:  # (teem refuses them; they were dropped silently)
            raise FormatError(f"{where}: '{given[0]}' beside 'space directions': an axis with "
                              f"a direction vector takes no {given[0]} (give NaN, or one of "
                              "the two)")
        return
    given = [n for n, axes in placed.items() if axes]
    if given:
        raise FormatError(f"{where}: '{given[0]}' in a 'space' without 'space directions': "
                          "the axes have no direction in it (ITK refuses or ignores "
                          f"{given[0]} there; give 'space directions')")
    try:
        frame = frame_to_lps(fields.get("space"))
    except VolwarpError as exc:
        raise FormatError(f"{where}: 'space': {exc}") from None
    if frame is not None and not np.array_equal(frame, np.eye(3)):
        raise FormatError(f"{where}: 'space: {fields['space']}' without 'space directions': "
                          "the axes have no direction in it (give 'space directions')")


def _placed_axes(fields: dict[str, str], name: str) -> set[int]:
    """The axes a per-axis field (``spacings``, ``axis mins``, ``units``...) gives a value.

    NaN gives none, nor an empty, ``???`` or ``none`` unit: teem's rule is
    per axis (an axis with a direction vector takes none of them), and
    3D Slicer writes ``units: "" "" "" "s"`` for a sequence's time axis.
    """
    if name == "units":
        words = _unit_words(fields, name) or []
        return {a for a, w in enumerate(words) if w.strip().lower() not in ("", "???", "none")}
    return {a for a, v in enumerate(fields[name].split()) if v.lower() != "nan"}


_QUOTED = re.compile(r'"([^"]*)"')


def _unit_words(fields: dict[str, str], name: str) -> list[str] | None:
    """The quoted words of a units field (``"mm" "mm" "mm"``), or None when it is not there."""
    if name not in fields:
        return None
    words = _QUOTED.findall(fields[name])
    return words if words else fields[name].split()


def length_scale(fields: dict[str, str], dim: int, where: str) -> np.ndarray | None:
    """Millimetres per header unit along each world axis (x y z), or None: the numbers are mm.

    ``space units`` (one a world axis, in a ``space``) or ``units``
    (one an axis, beside ``spacings``) in a length other than millimetres
    (``microns``, ``cm``, ``m``: :func:`~volwarp_cli.io.units.length_unit_mm`)
    scale spacing and origin to millimetres, as volwarp's NIfTI, TIFF and
    OME-Zarr readers do; ITK's NRRD reader takes the numbers as they are (it
    reads no unit), so this is said once a run. A unit that is no known length
    (``pixel``, a free word) leaves the numbers, and is said too; empty,
    ``???`` and ``none`` are no unit.
    """
    from ..progress import log
    from ..runscope import first_said
    from .units import length_unit_mm

    if "space" in fields or "space dimension" in fields:  # (its numbers are in the space's units)
        name, words = "space units", _unit_words(fields, "space units")
        if words is not None and len(words) != 3:
            raise FormatError(f"{where}: 'space units' has {len(words)} entries for a 3-D space")
    else:
        name, words = "units", _unit_words(fields, "units")
        if words is not None:
            if len(words) != dim:
                raise FormatError(f"{where}: 'units' has {len(words)} entries, 'dimension' "
                                  f"is {dim}")
            if dim != 3:  # (the spatial axes': the component axis has no length)
                sizes = [int(v) for v in fields.get("sizes", "").split()]
                comp = _component_axis(fields, dim, sizes, where)
                words = [w for a, w in enumerate(words) if a != comp]
    if words is None:
        return None
    scale, unknown = np.ones(3), []
    for axis, word in enumerate(words):
        if word.strip().lower() in ("", "???", "none"):
            continue
        mm = length_unit_mm(word)
        if mm is None:
            unknown.append(word)
        else:
            scale[axis] = mm
    key = ("nrrd units", os.path.abspath(where))
    if unknown and first_said(key + ("unknown",)):
        log.warning("%s: '%s' %s: not a length volwarp knows; the numbers are taken as "
                    "millimetres", where, name, " ".join(f'"{w}"' for w in unknown))
    if np.all(scale == 1.0):
        return None
    if first_said(key):
        log.warning("%s: '%s' %s: spacing and origin converted to millimetres (ITK and "
                    "SimpleITK read NRRD numbers as millimetres whatever the unit)", where,
                    name, " ".join(f'"{w}"' for w in words))
    return scale


def _spatial_sizes(fields: dict[str, str], dim: int, where: str) -> list[int] | None:
    """The sizes of the three space axes (x, y, z), or None when ``sizes`` does not say."""
    try:
        sizes = [int(v) for v in fields.get("sizes", "").split()]
    except ValueError:
        return None
    if len(sizes) != dim:
        return None
    if "space directions" in fields:
        entries = fields["space directions"].split()
        keep = [a for a, e in enumerate(entries) if e.lower() != "none"]
    else:
        comp = None if dim == 3 else _component_axis(fields, dim, sizes, where)
        keep = [a for a in range(dim) if a != comp]
    return [sizes[a] for a in keep] if len(keep) == 3 else None


def _header_geometry(fields: dict[str, str], dim: int, where: str):
    """(spacing, origin, direction, space) as the header gives them (not yet checked)."""
    space = fields.get("space")
    spacing = np.ones(3)
    origin = np.zeros(3)
    direction = np.eye(3)
    if "space directions" in fields:
        entries = fields["space directions"].split()
        if len(entries) != dim:
            raise FormatError(f"{where}: 'space directions' has {len(entries)} entries, "
                              f"'dimension' is {dim}")
        vectors = [e for e in entries if e.lower() != "none"]
        if len(vectors) != 3:
            raise FormatError(f"{where}: 'space directions' must give 3 axis vectors")
        cols = []
        for e in vectors:
            m = _VECTOR.fullmatch(e)
            if not m:
                raise FormatError(f"{where}: cannot read 'space directions' entry {e!r}")
            v = _parse_vector(m.group(1), where, "space directions")
            if len(v) != 3:
                raise FormatError(f"{where}: 'space directions' vectors must have 3 components")
            cols.append(v)
        mat = np.array(cols, dtype=np.float64).T  # columns are the axes
        if not np.all(np.isfinite(mat)):
            raise FormatError(f"{where}: 'space directions' has a non-finite axis")
        big = np.abs(mat).max(axis=0)
        if np.any(big == 0):
            raise FormatError(f"{where}: 'space directions' has a zero axis")
        spacing, direction = _axis_lengths(mat, big)
    elif "space" not in fields and "space dimension" not in fields:
        spacing, origin = _axis_geometry(fields, dim, where)
    if "space origin" in fields:  # (a space without directions too, as ITK reads it)
        m = _VECTOR.fullmatch(fields["space origin"].strip())
        if not m:
            raise FormatError(f"{where}: cannot read 'space origin'")
        origin = np.array(_parse_vector(m.group(1), where, "space origin"))
        if origin.shape != (3,):
            raise FormatError(f"{where}: 'space origin' must have 3 components")
    return spacing, origin, direction, space


def _axis_lengths(mat: np.ndarray, big: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Spacing and direction of axis vectors (columns of ``mat``; ``big``: their largest entries).

    Each length scaled first ((1e200, 1e200, 0) is 1.4e200 long, not an
    overflow), the direction the vector divided by it: written back
    (``spacing * direction``), the axes are the file's again, to the bit
    for the files tested (a convert, a SEG's grid through an NRRD). teem
    (ITK's reader) takes ``sqrt(x*x + y*y + z*z)`` and the vector times its
    reciprocal: an oblique axis can be an ULP apart from ITK's, which decides
    only where a point lies exactly on an edge (docs/apply.md); the
    reciprocal broke the round trip (1.5 came back 1.5000000000000002).
    """
    spacing = big * np.linalg.norm(mat / big[None, :], axis=0)
    return spacing, mat / spacing[None, :]


#: teem's centerings: "???" and "none" are unknown (then ITK takes cell)
_CENTERS = {"cell": "cell", "node": "node", "???": None, "none": None}


def _axis_values(fields: dict[str, str], names: tuple[str, ...], dim: int, where: str):
    """A per-axis number field under any of its spellings: ``dim`` numbers (NaN: none), or None."""
    for name in names:
        if name in fields:
            vals = _numbers(fields, name, where)
            if len(vals) != dim:
                raise FormatError(f"{where}: '{name}' has {len(vals)} entries, 'dimension' "
                                  f"is {dim}")
            if any(np.isinf(v) for v in vals):
                raise FormatError(f"{where}: '{name}' must be finite (or nan), got "
                                  f"{short_text(fields[name])!r}")
            return vals
    return None


def _axis_geometry(fields: dict[str, str], dim: int, where: str):
    """Spacing and origin (x, y, z) of a header without ``space directions``, as ITK reads it.

    ITK (``NrrdImageIO``) takes each domain axis' ``spacings`` entry (1 when
    there is none: ``axis maxs`` do not give a spacing) and teem's
    ``nrrdOriginCalculate`` with cell centering by default: per axis, with
    its ``centerings`` entry (``???`` or ``none``: cell; ``node``: none of this)
    and its spacing, or else ``(max - min) / size``, the origin is
    ``min + spacing / 2`` for cells, ``min`` for nodes. The origin is 0 when
    the first domain axis has no ``axis mins``, or some axis has neither a
    spacing nor an ``axis maxs`` entry (teem's NoMin and NoMaxOrSpacing: ITK
    then leaves the origin at 0); an axis without a min after a first one that
    has it would be NaN in ITK, and is an error here.
    """
    try:
        sizes = [int(v) for v in fields.get("sizes", "").split()]
    except ValueError:
        sizes = []
    if dim == 3:
        axes = [0, 1, 2]
    else:
        comp = _component_axis(fields, dim, sizes, where)
        axes = [a for a in range(dim) if a != comp]
    spacings = _axis_values(fields, ("spacings",), dim, where)
    mins = _axis_values(fields, ("axis mins", "axismins"), dim, where)
    maxs = _axis_values(fields, ("axis maxs", "axismaxs"), dim, where)
    centers: list = [None] * dim
    for name in ("centerings", "centers"):
        if name in fields:
            words = fields[name].split()
            if len(words) != dim:
                raise FormatError(f"{where}: '{name}' has {len(words)} entries, 'dimension' "
                                  f"is {dim}")
            for a, w in enumerate(words):
                if w.lower() not in _CENTERS:
                    raise FormatError(f"{where}: '{name}' entry {w!r} is not cell, node, "
                                      "??? or none")
                centers[a] = _CENTERS[w.lower()]
            break
    given = [spacings[a] if spacings is not None and not np.isnan(spacings[a]) else None
             for a in axes]
    if any(g is not None and not g > 0 for g in given):
        raise FormatError(f"{where}: 'spacings' must be positive and finite")
    spacing = np.array([1.0 if g is None else g for g in given])
    origin = np.zeros(3)
    if mins is None or np.isnan(mins[axes[0]]):
        return spacing, origin  # teem: nrrdOriginStatusNoMin
    if any(given[i] is None and (maxs is None or np.isnan(maxs[a]))
           for i, a in enumerate(axes)):
        return spacing, origin  # teem: nrrdOriginStatusNoMaxOrSpacing
    for i, a in enumerate(axes):
        lo = mins[a]
        if np.isnan(lo):
            raise FormatError(f"{where}: 'axis mins' has no value (nan) for axis {a} but has "
                              f"one for axis {axes[0]}: the origin is undefined")
        if (centers[a] or "cell") == "cell":
            step = given[i] if given[i] is not None else (maxs[a] - lo) / sizes[a]
            lo = lo + step / 2.0
        origin[i] = lo
    return spacing, origin


def _data_files(fields: dict[str, str], header_path: Path, fh, where: str, sizes: list[int]):
    """List the files holding the data (None means: after the header, in ``fh``).

    The forms ``<format> <min> <max> <step> [<subdim>]`` and ``LIST [<subdim>]``
    split the data into pieces of ``subdim`` axes (default: all axes but the
    slowest). As in teem, there must be one file per piece when ``subdim`` is
    below the dimension; each file may also hold a slab of the slowest axis
    (the files then divide its size). The number of files is checked before
    any is listed: a header naming a billion files is refused at once.
    """
    spec = fields.get("data file", fields.get("datafile"))
    if spec is None:
        return None
    base = header_path.parent
    parts = spec.split()
    if parts and parts[0] == "LIST":
        subdim = _subdim(parts[1:], sizes, where, "LIST")
        names = []
        for raw in fh:
            name = header_name(raw).strip()
            if name:
                names.append(base / name)
        _check_file_count(len(names), subdim, sizes, where)
        return names
    if len(parts) >= 4 and "%" in parts[0]:
        fmt = parts[0]
        lo, hi, step = pattern_numbers(fmt, parts[1:4], "'data file'", where)
        subdim = _subdim(parts[4:], sizes, where, fmt)
        n = pattern_count(lo, hi, step, "'data file'", where)
        _check_file_count(n, subdim, sizes, where)
        return pattern_files(base, fmt, lo, step, n, "'data file'", where)
    return [base / spec]


def _referenced_data_files(header_path: Path) -> list[str]:
    """The data file an existing detached header names.

    A single file; none for LIST or a pattern, which volwarp does not write.
    """
    with open(header_path, "rb") as fh:
        fields, _ = read_header(fh, str(header_path))
    spec = fields.get("data file", fields.get("datafile", ""))
    return [] if not spec or spec.startswith("LIST") or "%" in spec else [spec]


def _subdim(rest: list[str], sizes: list[int], where: str, what: str) -> int | None:
    """The optional ``<subdim>`` after a data file pattern or ``LIST`` (None: not given)."""
    if not rest:
        return None
    dim = len(sizes)
    try:
        subdim = int(rest[0])
    except ValueError:
        raise FormatError(f"{where}: 'data file' {what}: <subdim> {rest[0]!r} is not a "
                          "whole number") from None
    if len(rest) > 1 or not 1 <= subdim <= dim:
        raise FormatError(f"{where}: 'data file' {what}: <subdim> must be one number in "
                          f"1..{dim}, got {' '.join(rest)!r}")
    return subdim


def _check_file_count(n: int, subdim: int | None, sizes: list[int], where: str) -> None:
    """Refuse a number of data files that cannot split ``sizes`` (see :func:`_data_files`)."""
    dim = len(sizes)
    slow = sizes[-1]
    if subdim is not None and subdim < dim:
        pieces = voxel_count(sizes[subdim:])
        if n != pieces:
            raise FormatError(f"{where}: 'data file' names {n} file{'s' if n != 1 else ''}, "
                              f"but sizes {' '.join(map(str, sizes))} in {subdim}-D pieces "
                              f"need {pieces}")
        return
    if n < 1 or n > slow or slow % n:
        raise FormatError(f"{where}: 'data file' names {n} file{'s' if n != 1 else ''}, "
                          f"which do not split the slowest axis (size {slow}) evenly")


def read_nrrd(path: str | os.PathLike, component: int | None = None, *,
              mmap: bool = False) -> Volume:
    """Read a 3-D NRRD volume (attached or detached).

    ``mmap``: samples stored raw, in this machine's byte order, in the header's
    own file are mapped read-only instead of copied (the array is not writable).

    A 4-D file with one non-spatial axis (``space directions`` entry ``none``,
    e.g. the vector files ``volwarp sweep --multi`` writes) holds several
    components per voxel: ``component`` picks one (its name, when the file
    names them, is kept as ``volwarp_component``). A single-component 4-D file
    reads without it.
    """
    return _read_nrrd(path, component, mmap=mmap)[0]


def read_nrrd_components(path: str | os.PathLike) -> tuple[Volume, np.ndarray]:
    """A NRRD file's every component per voxel, read once: ``(Volume, samples)``.

    ``samples`` (z, y, x, n) in the machine's byte order (n = 1 for a 3-D
    file); the Volume is the first component's (geometry, key/values).
    """
    return _read_nrrd(path, 0, mmap=False, every=True)


def _read_nrrd(path, component, *, mmap: bool, every: bool = False):
    """``(Volume of the component, all components (z, y, x, n) or None)``: :func:`read_nrrd`."""
    path = Path(path)
    where = str(path)
    with open_input(path, where) as fh:
        fields, keyvals = read_header(fh, where)
        for req in ("type", "dimension", "sizes", "encoding"):
            if req not in fields:
                raise FormatError(f"{where}: header has no '{req}' field")
        type_name = fields["type"].lower()
        if type_name not in _TYPES:
            raise FormatError(f"{where}: unknown 'type' {fields['type']!r}")
        try:
            dim = int(fields["dimension"])
            sizes = [int(s) for s in fields["sizes"].split()]
        except ValueError:
            raise FormatError(f"{where}: 'dimension' or 'sizes' is not a whole number") from None
        if len(sizes) != dim:
            raise FormatError(f"{where}: 'sizes' has {len(sizes)} entries, 'dimension' is {dim}")
        if any(s <= 0 for s in sizes):
            raise FormatError(f"{where}: 'sizes' must be positive, got {sizes}")
        comp_axis = _component_axis(fields, dim, sizes, where)
        n_comp = sizes[comp_axis] if comp_axis is not None else 1
        if comp_axis is None and component not in (None, 0):
            raise BadUsage(f"{where}: --volume-index {component} given, but the file "
                           "has one component")
        if comp_axis is not None and component is None and n_comp > 1:
            names = keyvals.get("volwarp_components", "")
            raise ChoiceNeeded(f"{where}: has {n_comp} components per voxel"
                              f"{f' ({names})' if names else ''}; "
                              f"select one with --volume-index 0..{n_comp - 1}")
        if component is not None and component >= n_comp:
            raise BadUsage(f"{where}: --volume-index {component} is out of range: "
                           f"the file has {n_comp} component{'s' if n_comp > 1 else ''}")
        encoding = _ENCODINGS.get(fields["encoding"].lower())
        if encoding is None:
            raise FormatError(f"{where}: unknown encoding {fields['encoding']!r} "
                              "(supported: raw, gzip, bzip2, ascii, hex)")
        dtype = np.dtype(_TYPES[type_name])
        check_dtype(dtype, where)
        file_dtype = file_type(fields, dtype, encoding, where)
        spacing, origin, direction, space = _geometry(fields, dim, where)
        count = voxel_count(sizes)
        nbytes = count * dtype.itemsize
        ensure_fits_in_memory(nbytes, f"{where} ({'x'.join(map(str, sizes))} {dtype.name})")
        files = _data_files(fields, path, fh, where, sizes)
        lineskip = _whole(fields, ("line skip", "lineskip"), where)
        byteskip = _whole(fields, ("byte skip", "byteskip"), where, minimum=-1)
        if files is None:
            data = _read_data(fh, file_dtype, count, encoding, lineskip, byteskip, where,
                              exact_end=True, mmap=mmap)
        else:
            data = read_data_files(
                path, files, count, where,
                lambda dfh, n, name: _read_data(dfh, file_dtype, n, encoding, lineskip,
                                                byteskip, name, exact_end=True))
    meta = dict(keyvals)
    every_component = None
    if comp_axis is not None:
        index = component or 0
        data = data.reshape(sizes[::-1])
        if every:  # the component axis last: (z, y, x, n), a view where it is the fastest
            every_component = native(np.moveaxis(data, dim - 1 - comp_axis, -1))
        data = np.take(data, index, axis=dim - 1 - comp_axis)
        sizes = [s for a, s in enumerate(sizes) if a != comp_axis]
        names = meta.pop("volwarp_components", "").split()
        if len(names) == n_comp:
            meta["volwarp_component"] = names[index]
    data = native(np.ascontiguousarray(data.reshape(xyz_to_zyx(sizes))))
    if every and every_component is None:
        every_component = data[..., None]
    meta.update(kept_fields(fields, space, where))
    return make_volume(where, data, spacing=spacing, origin=origin, direction=direction,
                       space=space, meta=meta), every_component


def kept_fields(fields: dict, space, where: str) -> dict:
    """The header's kept fields as key/values ``NRRD_<field>`` (the measurement frame in LPS)."""
    meta = {f"NRRD_{name}": fields[name] for name in _KEPT_FIELDS if name in fields}
    for name in AS_READ_FIELDS:
        if name not in fields or not fields[name].strip():
            continue
        if name in _PER_AXIS:
            dim = int(fields["dimension"])
            _check_axis_entries(fields, name, dim, where)  # (written back: teem's own checks)
            if dim != 3:
                continue
        meta[f"NRRD_{name}"] = fields[name].strip()
    if "NRRD_space units" in meta and length_scale(fields, 3, where) is not None:
        meta["NRRD_space units"] = '"mm" "mm" "mm"'  # (the numbers are millimetres now)
    if "measurement frame" in fields:
        meta["NRRD_measurement frame"] = _measurement_frame_lps(fields, space, where)
    return meta


def _check_axis_entries(fields: dict[str, str], name: str, dim: int, where: str) -> None:
    """Refuse a malformed ``thicknesses`` or ``labels`` (kept, they are written back).

    A number or nan an axis, a quoted string an axis: written back as read, a
    malformed one made an output teem and pynrrd refuse.
    """
    if name == "thicknesses":
        _axis_values(fields, (name,), dim, where)
        return
    text = fields[name]
    words = _QUOTED.findall(text)
    if len(words) != dim or _QUOTED.sub("", text).strip():
        raise FormatError(f"{where}: '{name}' must be {dim} quoted strings, one an axis, got "
                          f"{short_text(text)!r}")


def _measurement_frame_lps(fields: dict[str, str], space, where: str) -> str:
    """The ``measurement frame`` (its vectors are world directions) in LPS.

    The Volume converts origin and direction from the file's frame; the
    measurement frame, which only NRRD has, is converted with the same matrix
    (without a ``space``, its numbers as they stand).
    """
    frame = measurement_frame(fields["measurement frame"], where)
    if space is not None:
        try:
            frame = frame_to_lps(space) @ frame
        except VolwarpError as exc:
            raise FormatError(f"{where}: 'space': {exc}") from None
    return " ".join(_vec(frame[:, a]) for a in range(3))


def measurement_frame(text: str, where: str = "NRRD_measurement frame") -> np.ndarray:
    """A ``measurement frame`` (or the kept ``NRRD_measurement frame``) as a matrix.

    Its vectors are the columns: a vector of components ``v`` measured in the
    frame is the world vector ``matrix @ v`` (teem's meaning; kept, in LPS
    where the file had a ``space``: :func:`kept_fields`).
    """
    vectors = [_parse_vector(m.group(1), where, "measurement frame")
               for m in _VECTOR.finditer(text)]
    if len(vectors) != 3 or any(len(v) != 3 for v in vectors):
        raise FormatError(f"{where}: 'measurement frame' must be 3 vectors of 3 numbers, got "
                          f"{short_text(text)!r}")
    return np.array(vectors, dtype=np.float64).T


def vector_frame(path: str | os.PathLike) -> np.ndarray:
    """The matrix taking the vector components of the NRRD at ``path`` to LPS millimetres.

    teem's meaning: the components are measured along the ``measurement
    frame``'s axes (the world vector is the frame times them, identity when
    there is none), in the file's ``space`` (to LPS), in its length units (to
    mm, as the geometry: :func:`length_scale`). A RAS file whose frame is
    ``(-1,0,0) (0,-1,0) (0,0,1)`` holds LPS vectors (turned by the space's
    signs alone, they were mirrored in x and y); a field in microns holds
    microns (taken as mm, they moved points 1000 times too far). ITK and
    SimpleITK take the components as LPS mm whatever the file says; where a
    measurement frame makes the two differ, that is said once a run.
    """
    from ..progress import log
    from ..runscope import first_said

    where = str(path)
    with open_input(Path(path), where) as fh:
        fields, _ = read_header(fh, where)
    frame = np.eye(3)
    if "measurement frame" in fields:
        frame = measurement_frame(fields["measurement frame"], where)
    matrix = frame if fields.get("space") is None else frame_to_lps(fields["space"]) @ frame
    if not np.array_equal(frame, np.eye(3)) and not np.array_equal(matrix, np.eye(3)) \
            and first_said(("nrrd measurement frame", os.path.abspath(where))):
        log.warning("%s: its 'measurement frame' turns the vectors (to LPS: %s); ITK and "
                    "SimpleITK read the components unchanged, as LPS", where,
                    " ".join(_vec(matrix[:, a]) for a in range(3)))
    scale = length_scale(fields, int(fields["dimension"]), where)
    return matrix if scale is None else scale[:, None] * matrix


#: NRRD ``kinds`` of an axis that may be a volume's: a domain (teem's domain kinds, time
#: among them: ITK reads a 2-D+t file as a volume), or unknown, or none said
_SPATIAL_KINDS = ("domain", "space", "time", "???", "none")

#: teem's kinds (lower case, its other spellings too) and the axis size each needs (0: any)
_KIND_SIZES = {
    **dict.fromkeys(("domain", "space", "time", "list", "point", "vector",
                     "contravariant-vector", "covariant-vector", "normal", "???", "none"), 0),
    "stub": 1, "scalar": 1, "complex": 2, "2-vector": 2,
    **dict.fromkeys(("3-color", "rgb-color", "rgbcolor", "rgb", "hsv-color", "hsvcolor", "hsv",
                     "xyz-color", "3-vector", "3-gradient", "3-normal"), 3),
    **dict.fromkeys(("4-color", "rgba-color", "rgbacolor", "rgba", "4-vector", "quaternion"), 4),
    **{f"2d-{m}-{w}": n for m, n in (("symmetric", 3), ("sym", 3), ("masked-symmetric", 4),
                                     ("masked-sym", 4)) for w in ("matrix", "tensor")},
    **{f"3d-{m}-{w}": n for m, n in (("symmetric", 6), ("sym", 6), ("masked-symmetric", 7),
                                     ("masked-sym", 7)) for w in ("matrix", "tensor")},
    "2d-matrix": 4, "2d-tensor": 4, "2d-masked-matrix": 5, "2d-masked-tensor": 5,
    "3d-matrix": 9, "3d-tensor": 9, "3d-masked-matrix": 10, "3d-masked-tensor": 10,
}


def _kinds(fields: dict[str, str], sizes: list[int], where: str) -> list[str] | None:
    """The ``kinds`` field, one lower-case kind an axis, or None when it is not given.

    Refused as teem refuses it: a count other than the dimension (one kind too
    few was ignored, and the component axis guessed), a kind teem does not know,
    and a kind whose axis has another size than it needs (a ``3-vector`` axis
    of 4 samples, an ``RGB-color`` of 2: read as that many components).
    """
    if "kinds" not in fields:
        return None
    words = fields["kinds"].split()
    if len(words) != len(sizes):
        raise FormatError(f"{where}: 'kinds' has {len(words)} entries, 'dimension' is "
                          f"{len(sizes)}")
    for axis, (word, size) in enumerate(zip(words, sizes, strict=True)):
        want = _KIND_SIZES.get(word.lower())
        if want is None:
            raise FormatError(f"{where}: 'kinds': {word!r} (axis {axis}) is not a NRRD kind")
        if want and want != size:
            raise FormatError(f"{where}: 'kinds': a {word} axis has {want} sample"
                              f"{'s' if want > 1 else ''}, axis {axis} has {size}")
    return [w.lower() for w in words]


def _component_axis(fields: dict[str, str], dim: int, sizes: list[int], where: str):
    """The index of the one non-spatial axis of a 4-D header (None for 3-D).

    A 3-D header with a non-spatial axis (``kinds: RGB-color domain domain``,
    a ``none`` space direction) is a 2-D image of several components per
    pixel, as ITK reads it: refused (its components were read as an x axis).
    """
    kinds = _kinds(fields, sizes, where) or []
    if dim == 3:
        if kinds:  # (the kinds say what each axis is: a none direction of a time axis)
            other = [k for k in kinds if k not in _SPATIAL_KINDS]
        else:
            other = ["none"] * fields.get("space directions", "").lower().split().count("none")
        if other:
            raise FormatError(f"{where}: a 2-D image with components per pixel ('kinds: "
                              f"{fields.get('kinds', '')}', sizes {sizes}), not a volume: "
                              "volwarp reads 3-D volumes")
        return None
    if dim == 4:
        entries = fields.get("space directions", "").split()
        if len(entries) == 4:
            nonspatial = [a for a, e in enumerate(entries) if e.lower() == "none"]
            said = [a for a, k in enumerate(kinds) if k not in ("domain", "space", "???", "none")]
            if len(kinds) == 4 and said and said != nonspatial:  # (one was read, silently)
                raise FormatError(f"{where}: 'kinds' ({fields['kinds']}) and 'space "
                                  f"directions' disagree on which axis holds the components")
        else:  # no space directions: the kinds say which axis is not a domain
            nonspatial = ([a for a, k in enumerate(kinds) if k not in ("domain", "space")]
                          if len(kinds) == 4 else [])
        if len(nonspatial) == 1:
            return nonspatial[0]
    raise FormatError(f"{where}: volwarp reads 3-D volumes (or 4-D ones with one component "
                      f"axis); this file has dimension {dim} (sizes {sizes})")


def _read_data(fh, file_dtype, count, encoding, lineskip, byteskip, where, exact_end,
               mmap=False):
    for _ in range(lineskip):
        if not fh.readline():
            raise FormatError(f"{where}: file ends inside 'line skip'")
    nbytes = count * file_dtype.itemsize
    if encoding == "raw":
        start = fh.tell()
        size = os.fstat(fh.fileno()).st_size
        if byteskip == -1:  # (the last nbytes: never inside the header, a file cut short)
            start, header_end = size - nbytes, start
            if start < header_end:
                raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes of "
                                  f"samples at the end ('byte skip: -1'), the file has "
                                  f"{max(size - header_end, 0)} after its header")
        else:
            start += byteskip
        have = size - start
        if have < nbytes:
            raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes of samples, "
                              f"file has {max(have, 0)}")
        if have > nbytes and byteskip != -1:
            raise FormatError(f"{where}: file has {have} bytes of samples, expected {nbytes} "
                              "(wrong sizes or type in the header?)")
        if mmap and file_dtype.isnative:
            guard(fh, where)  # a truncation meanwhile: one line and exit 1, not a crash
            try:
                return np.memmap(fh, dtype=file_dtype, mode="r", offset=start, shape=(count,))
            except (ValueError, OSError):  # truncated between the size check and the map
                raise FormatError(f"{where}: the file was truncated while it was being read "
                                  "(replaced by another program?)") from None
        fh.seek(start)
        return np.frombuffer(read_exact(fh, nbytes, where), dtype=file_dtype)
    if encoding in ("ascii", "hex") and byteskip:  # (teem skips them too: they were read)
        if byteskip == -1:
            raise FormatError(f"{where}: 'byte skip: -1' (samples at the end) needs raw "
                              f"encoding, not {encoding} (as teem refuses it)")
        if len(fh.read(byteskip)) < byteskip:
            raise FormatError(f"{where}: file ends inside 'byte skip'")
    if encoding == "ascii":
        text = fh.read().decode("latin-1")
        values = ascii_values(text, file_dtype.newbyteorder("="), count, where)
        if file_dtype.kind in "iu":
            _say_decimal_integers(text, where)
        return values
    if encoding == "hex":
        return np.frombuffer(_hex_bytes(fh.read(), nbytes, where), dtype=file_dtype)
    if encoding == "gzip" and byteskip == 0:  # the common case: one pass, in place
        return np.frombuffer(read_gzip_exact(fh, nbytes, where), dtype=file_dtype)
    # A byte skip of compressed data counts decompressed bytes, and -1 means the samples
    # are the stream's last bytes (as teem, ITK and pynrrd read it).
    import bz2  # (bzip2, and gzip with a byte skip: rare files)
    import gzip

    stream = gzip.GzipFile(fileobj=fh) if encoding == "gzip" else bz2.BZ2File(fh)
    with stream:
        if byteskip == -1:
            buf = _stream_tail(stream, nbytes, where)
        else:
            _skip_stream(stream, byteskip, where)
            buf = read_exact(stream, nbytes, where)
            if exact_end and _read_stream(stream, 1, where):
                raise FormatError(f"{where}: compressed data holds more than {nbytes} bytes "
                                  "(wrong sizes or type in the header?)")
    return np.frombuffer(buf, dtype=file_dtype)


_DECIMAL = re.compile(r"[^\s,]*[.eE][^\s,]*")


def _say_decimal_integers(text: str, where: str) -> None:
    """Say once a run that integer samples written as decimals are read as their numbers.

    ``-5.000e+01`` (``numpy.savetxt``'s default) of a ``short`` file is -50 to
    volwarp (as MetaIO reads its ascii samples), while teem, and so ITK and
    SimpleITK, read the digits before the ``.`` or ``e``: -5.
    """
    from ..progress import log
    from ..runscope import first_said

    m = _DECIMAL.search(text)
    if m and first_said(("nrrd ascii decimals", os.path.abspath(where))):
        log.warning("%s: integer samples written as decimals (%r): read as the numbers they "
                    "write; teem, ITK and SimpleITK read only the digits before the '.' or "
                    "'e'", where, short_text(m.group(0), 24))


def _read_stream(stream, n: int, where: str) -> bytes:
    """``stream.read(n)`` of a decompressing stream, its failures as file errors."""
    try:
        return stream.read(n)
    except EOFError:
        raise FormatError(f"{where}: compressed data is truncated (the stream ends before "
                          "its end-of-stream marker)") from None
    except (OSError, ValueError, zlib.error) as exc:
        raise FormatError(f"{where}: corrupt compressed data ({exc})") from None


def _skip_stream(stream, nbytes: int, where: str) -> None:
    left = nbytes
    while left:
        got = len(_read_stream(stream, min(left, 1 << 22), where))
        if not got:
            raise FormatError(f"{where}: compressed data ends inside 'byte skip' "
                              f"({nbytes - left} of {nbytes} bytes)")
        left -= got


def _stream_tail(stream, nbytes: int, where: str) -> np.ndarray:
    """The last ``nbytes`` of a decompressing stream (``byte skip: -1``), in bounded memory."""
    buf = bytearray()
    while chunk := _read_stream(stream, 1 << 22, where):
        buf += chunk
        if len(buf) > 2 * nbytes + (1 << 22):
            del buf[:len(buf) - nbytes]
    if len(buf) < nbytes:
        raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes of samples, "
                          f"the compressed stream holds {len(buf)}")
    return np.frombuffer(bytes(buf[len(buf) - nbytes:]), dtype=np.uint8)


def _hex_bytes(text: bytes, nbytes: int, where: str) -> bytes:
    """Samples in NRRD's ``hex`` encoding: two hex digits a byte, white space ignored."""
    try:
        data = bytes.fromhex(text.decode("latin-1"))
    except ValueError:
        bad = next((c for c in text.decode("latin-1").split() if not _is_hex(c)), "?")
        raise FormatError(f"{where}: hex data is not pairs of hex digits (near "
                          f"{short_text(bad, 20)!r})") from None
    if len(data) != nbytes:
        what = "truncated" if len(data) < nbytes else "too long"
        raise FormatError(f"{where}: hex data is {what}: expected {nbytes} bytes of samples, "
                          f"found {len(data)}")
    return data


def _is_hex(token: str) -> bool:
    try:
        bytes.fromhex(token)
    except ValueError:
        return False
    return True


def _fmt(x: float) -> str:
    return repr(float(x))


def _vec(v) -> str:
    return "(" + ",".join(_fmt(x) for x in v) + ")"


def nrrd_header(vol: Volume | Header, dtype: np.dtype, *, encoding: str, byte_order: str,
                data_file: str | None = None, components: list[str] | None = None) -> bytes:
    """The header text of ``vol`` as volwarp writes it (deterministic)."""
    lines = ["NRRD0005", "# Complete NRRD file format specification at:",
             "# http://teem.sourceforge.net/nrrd/format.html",
             f"type: {_WRITE_TYPES[dtype.name]}"]
    sizes = list(vol.shape_xyz)
    dirs = [_vec(vol.direction[:, a] * vol.spacing[a]) for a in range(3)]
    kinds = ["domain"] * 3
    if components is not None:
        sizes = [len(components)] + sizes
        dirs = ["none"] + dirs
        kinds = ["vector"] + kinds
    lines.append(f"dimension: {len(sizes)}")
    if vol.space:
        lines.append(f"space: {vol.space}")
    else:
        lines.append("space dimension: 3")
    lines.append("sizes: " + " ".join(str(s) for s in sizes))
    lines.append("space directions: " + " ".join(dirs))
    lines.append("kinds: " + " ".join(kinds))
    if dtype.itemsize > 1:
        lines.append(f"endian: {byte_order}")
    lines.append(f"encoding: {encoding}")
    lines.append(f"space origin: {_vec(vol.origin)}")
    for name in _KEPT_FIELDS + AS_READ_FIELDS:
        value = vol.meta.get(f"NRRD_{name}")
        if value is None or (components is not None and name in _PER_AXIS):
            continue  # (a multi-component file has one axis more than the entries)
        lines.append(f"{name}: {' '.join(str(value).splitlines())}")  # (no escapes: one line)
    if data_file is not None:
        lines.append(f"data file: {data_file}")
    meta = {k: v for k, v in vol.meta.items() if not k.startswith("NRRD_")}
    if components is not None:
        meta["volwarp_components"] = " ".join(components)
    dropped = []
    for key in sorted(meta, key=str):
        if ":=" in str(key) or str(key).startswith("#") or not str(key):  # (not a key)
            dropped.append(str(key))
            continue
        lines.append(f"{_escape(str(key))}:={_escape(str(meta[key]))}")
    if dropped:
        from ..progress import log

        log.warning("warning: key/value%s %s not written to the NRRD header (a key cannot "
                    "be empty, hold ':=' or begin with '#')", "s" if len(dropped) > 1 else "",
                    ", ".join(map(repr, dropped)))
    text = "\n".join(lines) + "\n"
    if data_file is None:
        text += "\n"
    return header_bytes(text)


def _write_payload(fh, data: np.ndarray, encoding: str, level: int, byte_order: str,
                   dtype, what: str) -> None:
    if encoding == "raw":  # (cast and ordered by slabs where it must be)
        write_samples(fh, data, byte_order, dtype, what=what)
        return
    from .deflate import gzip_to  # (ISA-L and gzip: 2 ms to load, not for raw data)

    gzip_to(fh, with_byte_order(data, byte_order), level=level)


def write_nrrd(vol: Volume, path: str | os.PathLike, *, compress: bool = False,
               byte_order: str = "little", level: int = 1,
               components: list[np.ndarray] | None = None,
               component_names: list[str] | None = None, dtype=None) -> None:
    """Write ``vol`` as NRRD (``.nhdr`` writes a detached header plus ``.raw``/``.raw.gz``).

    ``components`` (arrays shaped like ``vol.data``, or one array of them on a last
    axis, written without a copy) writes one multi-component file whose first,
    fastest axis holds them, in the order of ``component_names``.
    ``dtype``: the samples cast to it as they are written (uncompressed only:
    :func:`~volwarp_cli.io.write_volume` casts a compressed output's first).
    """
    path = Path(path)
    stacked = isinstance(components, np.ndarray)
    count = (components.shape[-1] if stacked else len(components)) if components is not None \
        else 0
    if components is not None and (component_names is None or len(component_names) != count):
        raise ValueError("write_nrrd: components need their names (the header's 4th axis)")
    encoding = "gzip" if compress else "raw"
    if dtype is not None and compress:
        raise ValueError("write_nrrd: a compressed output's samples are cast before")
    cast = dtype
    data = vol.data if components is None else \
        np.ascontiguousarray(components) if stacked else np.stack(components, axis=-1)
    dtype = check_dtype(data.dtype if cast is None else cast, str(path))
    data_path = None
    if path.suffix.lower() == ".nhdr":
        data_path = path.with_suffix(".raw.gz" if compress else ".raw")
    header = nrrd_header(vol, dtype, encoding=encoding, byte_order=byte_order,
                         data_file=None if data_path is None else data_path.name,
                         components=component_names)
    write_with_header(path, header, lambda fh: _write_payload(fh, data, encoding, level,
                                                              byte_order, cast, str(path)),
                      data_path=data_path, referenced=_referenced_data_files,
                      siblings=() if data_path is None else
                      [path.with_suffix(".raw"), path.with_suffix(".raw.gz")])

