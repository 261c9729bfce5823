"""MetaImage (``.mha`` attached, ``.mhd`` detached: ITK's format) reading and writing.

Reads 3-D images (and 4-D ones or multi-channel ones, one volume or channel at
a time) whose header is ``Key = Value`` lines ending with ``ElementDataFile``:
binary or ASCII samples, either byte order, zlib-compressed data
(``CompressedData``, with or without ``CompressedDataSize``), ``HeaderSize``
(``-1``: the samples are the last bytes of the file), and data in the header's
file (``LOCAL``), in one other file, in a ``LIST`` of files or in files named
by a printf pattern (``name%03d.raw <min> <max> <step>``).

Geometry is ITK's: ``TransformMatrix`` (synonyms ``Rotation``, ``Orientation``)
holds the direction *columns* one after the other (its first three numbers are
the unit vector of index axis i), ``Offset`` (``Origin``, ``Position``) the
world position of voxel (0, 0, 0) and ``ElementSpacing`` (else ``ElementSize``,
as ITK falls back) the spacing (synonyms that disagree are refused); all in LPS,
volwarp's own frame, so no conversion. Field names are case-sensitive, as in MetaIO. ``AnatomicalOrientation``
is not geometry (ITK ignores it on read): volwarp writes the one ITK would
compute from the direction (``RAI`` for the identity), and on read keeps a
file's value in ``meta`` only where it disagrees with that.

``meta``: MetaIO's descriptive fields (``Comment``, ``Name``, ``Modality``, ...)
are kept as ``MetaImage_<Key>`` and written back (``ElementMin``/``ElementMax``, the
samples' range, by ``convert`` only: a command's new samples drop them); other (user) fields are kept
under their own name, as ITK puts them in its metadata dictionary, so that they
survive a trip through NRRD and back. Writes deterministic files, header fields
in the order ITK writes them, floats exact (``repr``).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ..errors import BadUsage, ChoiceNeeded, FormatError
from ..geometry import check_placement
from ..memory import ensure_fits_in_memory
from ..samples import check_dtype, voxel_count
from ..volume import LPS, Header, Volume, xyz_to_zyx
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

#: MetaIO element types -> numpy (MET_LONG is 4 bytes in MetaIO, as ITK reads it)
_TYPES = {
    "MET_UCHAR": "uint8", "MET_CHAR": "int8", "MET_USHORT": "uint16", "MET_SHORT": "int16",
    "MET_UINT": "uint32", "MET_INT": "int32", "MET_ULONG": "uint32", "MET_LONG": "int32",
    "MET_ULONG_LONG": "uint64", "MET_LONG_LONG": "int64", "MET_FLOAT": "float32",
    "MET_DOUBLE": "float64",
}
_WRITE_TYPES = {"uint8": "MET_UCHAR", "int8": "MET_CHAR", "uint16": "MET_USHORT",
                "int16": "MET_SHORT", "uint32": "MET_UINT", "int32": "MET_INT",
                "float32": "MET_FLOAT", "float64": "MET_DOUBLE"}
#: header names that mean the same field (two that disagree: :func:`header_fields`)
_SYNONYMS = {"Origin": "Offset", "Position": "Offset", "Rotation": "TransformMatrix",
             "Orientation": "TransformMatrix", "ElementByteOrderMSB": "BinaryDataByteOrderMSB"}
#: fields that describe the layout or geometry: read here, written by volwarp itself
_STRUCTURE = frozenset((
    "ObjectType", "NDims", "BinaryData", "BinaryDataByteOrderMSB", "ElementByteOrderMSB",
    "CompressedData", "CompressedDataSize", "TransformMatrix", "Rotation", "Orientation",
    "Offset", "Origin", "Position", "CenterOfRotation", "AnatomicalOrientation",
    "ElementSpacing", "ElementSize", "DimSize", "ElementType", "ElementDataFile",
    "HeaderSize", "ElementNumberOfChannels"))
#: MetaIO's descriptive fields, kept in meta as MetaImage_<Key>
_DESCRIPTIVE = frozenset((
    "Comment", "ObjectSubType", "TransformType", "Name", "ID", "ParentID", "Color",
    "Modality", "SequenceID", "ElementMin", "ElementMax", "DistanceUnits", "AcquisitionDate"))
PREFIX = "MetaImage_"
#: those true of the samples as read (their range): kept by ``convert`` only
#: (:data:`volwarp_cli.provenance.AS_READ_KEYS`)
AS_READ_FIELDS = ("ElementMin", "ElementMax")
_MAX_HEADER_LINES = 100_000
_TRUE = ("true", "1")
_FALSE = ("false", "0")


def header_fields(pairs, where: str) -> dict[str, tuple[str, str]]:
    """The header's ``(key, value)`` pairs by field: canonical key -> (name in file, value).

    Synonyms (:data:`_SYNONYMS`) that disagree are refused: ITK takes
    TransformMatrix, Origin, BinaryDataByteOrderMSB over the others whatever
    their order, other readers the last one; such a header means two grids.
    """
    fields: dict[str, tuple[str, str]] = {}
    for key, value in pairs:
        canonical = _SYNONYMS.get(key, key)
        known = fields.get(canonical)
        if known is not None and known[0] != key and not _same_value(known[1], value):
            raise FormatError(f"{where}: the header gives {known[0]} = {short_text(known[1])} "
                              f"and {key} = {short_text(value)}, names of one field that "
                              "disagree (tools read one or the other): keep one")
        fields[canonical] = (key, value)
    return fields


def _same_value(a: str, b: str) -> bool:
    """Whether two synonyms' values say the same: the same numbers, or the same truth."""
    try:
        return [float(v) for v in a.split()] == [float(v) for v in b.split()]
    except ValueError:
        pass
    a, b = a.strip().lower(), b.strip().lower()
    return a == b or (a in _TRUE and b in _TRUE) or (a in _FALSE and b in _FALSE)


_FIRST_LINE = re.compile(rb"\s*[A-Za-z_][A-Za-z0-9_]*[ \t]*=")


def looks_like_metaimage(head: bytes) -> bool:
    """True when ``head`` (a file's first bytes) starts with a ``Key = Value`` line.

    The content check for ``.mha``/``.mhd``: ITK writes ``ObjectType = Image``
    first, other writers may begin with ``NDims =`` or ``Comment =``.
    """
    return bool(_FIRST_LINE.match(head))


# -- header ---------------------------------------------------------------------

def _referenced_data_files(header_path: Path) -> list[str]:
    """The data file an existing ``.mhd`` names.

    A single file; none for LOCAL, LIST or a pattern, which volwarp does not write.
    """
    with open(header_path, "rb") as fh:
        value = dict(read_header(fh, str(header_path))).get("ElementDataFile", "")
    return [] if value in ("LOCAL", "Local", "local") or "%" in value or value.startswith(
        "LIST") else [value]


def read_header(fh, where: str) -> list[tuple[str, str]]:
    """Parse the ``Key = Value`` lines of a MetaImage header, up to ``ElementDataFile``.

    Returns the (key, value) pairs in file order; ``fh`` is left at the first
    byte after the ``ElementDataFile`` line.
    """
    pairs: list[tuple[str, str]] = []
    for _ in range(_MAX_HEADER_LINES):
        raw = fh.readline(1 << 20)
        if not raw:
            break
        line = header_line(raw).rstrip("\r\n")
        if not line.strip():
            continue
        if "=" not in line:
            shown = line if len(line) <= 80 else line[:77] + "..."
            if not pairs:
                raise FormatError(f"{where}: not a MetaImage file (first line {shown!r} is "
                                  "not 'Key = Value')")
            raise FormatError(f"{where}: malformed header line {shown!r} (expected "
                              "'Key = Value')")
        key, value = line.split("=", 1)
        key, value = key.strip(), value.strip()
        if key == "ElementDataFile":  # (a file name: its bytes, as they are)
            value = header_name(raw).split("=", 1)[1].strip()
        if not key:
            raise FormatError(f"{where}: header line {line[:80]!r} has no key")
        pairs.append((key, value))
        if key == "ElementDataFile":
            return pairs
    raise FormatError(f"{where}: header has no 'ElementDataFile' field (it must be the "
                      "last field of the header)")


def _numbers(fields, key: str, n: int, where: str, kind=float) -> list | None:
    """``n`` numbers of field ``key`` (None when absent); FormatError naming it otherwise."""
    if key not in fields:
        return None
    name, value = fields[key]
    parts = value.split()
    try:
        vals = [kind(p) for p in parts]
    except ValueError:
        what = "whole numbers" if kind is int else "numbers"
        raise FormatError(f"{where}: {name}: {value!r} is not {n} {what}") from None
    if len(vals) != n:
        raise FormatError(f"{where}: {name}: expected {n} values, got {len(vals)} "
                          f"({value!r})")
    if kind is float and not all(np.isfinite(vals)):
        raise FormatError(f"{where}: {name}: values must be finite, got {value!r}")
    return vals


def _bool(fields, key: str, default: bool, where: str) -> bool:
    if key not in fields:
        return default
    name, value = fields[key]
    low = value.lower()
    if low in _TRUE:
        return True
    if low in _FALSE:
        return False
    raise FormatError(f"{where}: {name}: {value!r} is not True or False")


def _int(fields, key: str, default: int, where: str) -> int:
    vals = _numbers(fields, key, 1, where, int)
    return default if vals is None else vals[0]


# -- reading ------------------------------------------------------------------------

def read_metaimage(path: str | os.PathLike, volume_index: int | None = None) -> Volume:
    """Read a 3-D MetaImage volume (``.mha`` or ``.mhd``).

    A 4-D file (several volumes along the 4th axis) or a file with several
    channels per voxel (``ElementNumberOfChannels``) reads one volume or
    channel, chosen by ``volume_index``; a 4-D file with one volume, or a
    single-channel file, reads without it.
    """
    return _read_metaimage(path, volume_index)[0]


def read_metaimage_components(path: str | os.PathLike) -> tuple[Volume, np.ndarray]:
    """A MetaImage file's every channel (or 4-D volume) per voxel, read once.

    ``(Volume, samples)``: ``samples`` (z, y, x, n) in the machine's byte
    order (n = 1 for a plain 3-D file); the Volume is the first one's.
    """
    return _read_metaimage(path, 0, every=True)


def _read_metaimage(path, volume_index, every: bool = False):
    """``(Volume of the selection, all of them (z, y, x, n) or None)``: :func:`read_metaimage`."""
    path = Path(path)
    where = str(path)
    with open_input(path, where) as fh:
        pairs = read_header(fh, where)
        fields = header_fields(pairs, where)
        for req in ("NDims", "DimSize", "ElementType"):
            if req not in fields:
                raise FormatError(f"{where}: header has no '{req}' field")
        if "ObjectType" in fields and fields["ObjectType"][1] != "Image":
            raise FormatError(f"{where}: ObjectType is {fields['ObjectType'][1]!r}; volwarp "
                              "reads MetaImage files of ObjectType Image")
        ndims = _int(fields, "NDims", 0, where)
        if ndims not in (3, 4):
            raise FormatError(f"{where}: volwarp reads 3-D volumes (or 4-D ones, one volume "
                              f"at a time); this file has NDims {ndims}")
        sizes = _numbers(fields, "DimSize", ndims, where, int)
        if any(s <= 0 for s in sizes):
            raise FormatError(f"{where}: DimSize must be positive, got {fields['DimSize'][1]!r}")
        channels = _int(fields, "ElementNumberOfChannels", 1, where)
        if channels < 1:
            raise FormatError(f"{where}: ElementNumberOfChannels must be at least 1, "
                              f"got {channels}")
        type_name = fields["ElementType"][1]
        if type_name not in _TYPES:
            raise FormatError(f"{where}: ElementType: unknown type {type_name!r} (volwarp "
                              f"reads {', '.join(_WRITE_TYPES.values())})")
        dtype = check_dtype(_TYPES[type_name], f"{where}: ElementType {type_name}")
        select = _selection(where, ndims, sizes, channels, volume_index)
        spacing, origin, direction = _geometry(fields, ndims, where)
        binary = _bool(fields, "BinaryData", True, where)
        msb = _bool(fields, "BinaryDataByteOrderMSB", False, where)
        compressed = _bool(fields, "CompressedData", False, where)
        comp_size = _int(fields, "CompressedDataSize", -1, where) if compressed else -1
        header_size = _int(fields, "HeaderSize", 0, where)
        if header_size < -1:
            raise FormatError(f"{where}: HeaderSize must be -1 (data at the end of the file) "
                              f"or at least 0, got {header_size}")
        file_dtype = dtype.newbyteorder(">" if msb else "<")
        count = voxel_count(sizes) * channels
        nbytes = count * dtype.itemsize
        ensure_fits_in_memory(nbytes, f"{where} ({'x'.join(map(str, sizes))} {dtype.name})")
        layout = _Layout(file_dtype, binary, compressed, comp_size, header_size)
        spec = fields["ElementDataFile"][1]
        if spec in ("LOCAL", "Local", "local"):
            data = _read_piece(fh, layout, count, where, local=True)
        else:
            data = read_data_files(
                path, _data_files(spec, path, fh, where, sizes), count, where,
                lambda dfh, n, name: _read_piece(dfh, layout, n, name, local=False))
    shape = xyz_to_zyx(sizes) + ((channels,) if channels > 1 else ())
    data = data.reshape(shape)
    every_one = None
    if every:  # (t, z, y, x) or (z, y, x, c) or (z, y, x) -> (z, y, x, n)
        every_one = (data if channels > 1 else np.moveaxis(data, 0, -1) if ndims == 4
                     else data[..., None])
        every_one = native(every_one)
    for axis, index in select:
        data = np.take(data, index, axis=axis)
    data = native(np.ascontiguousarray(data))
    meta = _meta(pairs, direction)
    return make_volume(where, data, spacing=spacing, origin=origin, direction=direction,
                       space=LPS, file_space=LPS, meta=meta), every_one


def _selection(where, ndims, sizes, channels, index) -> list[tuple[int, int]]:
    """(array axis, index) pairs, last axis first, that take one volume or channel.

    The samples are shaped ``[t, z, y, x, c]`` (``t`` for 4-D files, ``c`` for
    several channels); the result leaves ``[z, y, x]``.
    """
    n_vol = sizes[3] if ndims == 4 else 1
    if n_vol > 1 and channels > 1:
        raise FormatError(f"{where}: has {n_vol} volumes of {channels} channels per voxel; "
                          "volwarp reads files with one of the two")
    n, what = (channels, "component") if channels > 1 else (n_vol, "volume")
    if n == 1 and index not in (None, 0):
        raise BadUsage(f"{where}: --volume-index {index} given, but the file has one "
                       "volume of one component")
    if n > 1 and index is None:
        noun = "components per voxel" if what == "component" else "volumes"
        raise ChoiceNeeded(f"{where}: has {n} {noun}; select one with --volume-index "
                          f"0..{n - 1}")
    if n > 1 and not 0 <= index < n:
        raise BadUsage(f"{where}: --volume-index {index} is out of range: the file has "
                       f"{n} {what}s")
    steps = []
    if channels > 1:
        steps.append((ndims, index))
    if ndims == 4:
        steps.append((0, index if n_vol > 1 else 0))
    return steps


def _geometry(fields, ndims: int, where: str):
    """(spacing, origin, direction) in (x, y, z) from the header (ITK's defaults)."""
    spacing = _numbers(fields, "ElementSpacing", ndims, where)
    if spacing is None:
        spacing = _numbers(fields, "ElementSize", ndims, where)
    spacing = np.ones(3) if spacing is None else np.array(spacing[:3])
    if np.any(spacing <= 0):
        key = "ElementSpacing" if "ElementSpacing" in fields else "ElementSize"
        raise FormatError(f"{where}: {key} must be positive, got {fields[key][1]!r}")
    origin = _numbers(fields, "Offset", ndims, where)
    origin = np.zeros(3) if origin is None else np.array(origin[:3])
    matrix = _numbers(fields, "TransformMatrix", ndims * ndims, where)
    if matrix is None:
        direction = np.eye(3)
    else:
        # axis i's unit vector is numbers [i*n, i*n + n): rows of the reshape, columns here
        direction = np.array(matrix).reshape(ndims, ndims).T[:3, :3].copy()
    return check_placement(spacing, origin, direction, _sizes(fields, ndims), where=where,
                           fields=_field_names(fields))


def _field_names(fields) -> dict[str, str]:
    """The header's own names of the geometry's fields (for the errors that name them)."""
    def name(key, default):
        return fields[key][0] if key in fields else default

    return {"spacing": name("ElementSpacing", name("ElementSize", "ElementSpacing")),
            "origin": name("Offset", "Offset"), "direction": name("TransformMatrix",
                                                                  "TransformMatrix")}


def _sizes(fields, ndims: int) -> list[int] | None:
    """DimSize of the three space axes, or None when it is not readable here."""
    try:
        sizes = [int(v) for v in fields["DimSize"][1].split()]
    except (KeyError, ValueError):
        return None
    return sizes[:3] if len(sizes) == ndims else None


class _Layout:
    def __init__(self, file_dtype, binary, compressed, comp_size, header_size):
        self.file_dtype = file_dtype
        self.binary = binary
        self.compressed = compressed
        self.comp_size = comp_size
        self.header_size = header_size


def compressed_start(comp_size: int, header_size: int, size: int, start: int,
                     where: str) -> int:
    """Where a compressed piece's stream starts in its file of ``size`` bytes.

    ``start``: after the header (or the ``HeaderSize``); ``comp_size``:
    ``CompressedDataSize`` (-1: not given), checked against the file; with
    ``HeaderSize = -1`` the stream is the file's last ``comp_size`` bytes.
    """
    have = size - start
    if comp_size >= 0:
        if header_size == -1:
            start, have = size - comp_size, comp_size
        if have < comp_size or start < 0:
            raise FormatError(f"{where}: compressed data is truncated: CompressedDataSize "
                              f"is {comp_size} bytes, found {max(have, 0)}")
        if have > comp_size:
            raise FormatError(f"{where}: file has {have} bytes of compressed data, "
                              f"CompressedDataSize is {comp_size}")
    return start


def _read_piece(fh, layout: _Layout, count: int, where: str, *, local: bool) -> np.ndarray:
    """``count`` samples from ``fh`` (positioned after the header when ``local``)."""
    nbytes = count * layout.file_dtype.itemsize
    size = os.fstat(fh.fileno()).st_size
    start = fh.tell() if local else 0
    if layout.header_size > 0:
        start = layout.header_size  # from the start of the file, also for LOCAL (as ITK)
    if not layout.binary:
        fh.seek(start)
        return ascii_values(fh.read().decode("latin-1"), layout.file_dtype.newbyteorder("="),
                             count, where)
    if layout.compressed:
        fh.seek(compressed_start(layout.comp_size, layout.header_size, size, start, where))
        return np.frombuffer(read_gzip_exact(fh, nbytes, where), dtype=layout.file_dtype)
    if layout.header_size == -1:  # (the last nbytes: never inside the header, a short file)
        start, header_end = size - nbytes, start
        if start < header_end:
            raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes of samples "
                              f"at the end ('HeaderSize = -1'), the file has "
                              f"{max(size - header_end, 0)} after its header")
    have = size - start
    if have < nbytes or start < 0:
        raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes of samples, "
                          f"found {max(have if start >= 0 else size, 0)}")
    if have > nbytes:
        raise FormatError(f"{where}: file has {have} bytes of samples, expected {nbytes} "
                          "(wrong DimSize or ElementType in the header?)")
    fh.seek(start)
    return np.frombuffer(read_exact(fh, nbytes, where), dtype=layout.file_dtype)


def _data_files(spec: str, header_path: Path, fh, where: str, sizes: list[int]) -> list[Path]:
    """The files that hold the data, for ``ElementDataFile`` = a name, LIST or a pattern.

    ``LIST [<dim>]``: the names follow, one a line; each file holds a
    ``<dim>``-D piece (default: all axes but the slowest), so there must be one
    name per piece. ``<pattern> <min> <max> <step>``: one file per index of the
    slowest axis, named by ``pattern % i`` (MetaIO's form ``<pattern>`` alone
    counts from 1, ``<pattern> <min>`` from min). Relative names are relative
    to the header's folder.
    """
    base = header_path.parent
    ndims = len(sizes)
    parts = spec.split()
    if parts[:1] == ["LIST"]:
        fdim = ndims - 1
        if len(parts) > 1:
            m = re.fullmatch(r"(\d+)[dD]?", parts[1])
            if not m or len(parts) > 2:
                raise FormatError(f"{where}: ElementDataFile: LIST takes one optional "
                                  f"dimension (like 2 or 2D), got {spec!r}")
            fdim = int(m.group(1))
            if fdim == 0 or fdim > ndims:  # MetaIO's default for these
                fdim = ndims - 1
        n = voxel_count(sizes[fdim:])
        names = []
        for raw in fh:
            name = header_name(raw).strip()
            if not name:
                continue
            if len(names) == n:
                raise FormatError(f"{where}: ElementDataFile LIST names more than the {n} "
                                  f"file{'s' if n > 1 else ''} DimSize {' '.join(map(str, sizes))}"
                                  f" in {fdim}-D pieces needs")
            names.append(base / name)
        if len(names) != n:
            raise FormatError(f"{where}: ElementDataFile LIST names {len(names)} "
                              f"file{'s' if len(names) != 1 else ''}, but DimSize "
                              f"{' '.join(map(str, sizes))} in {fdim}-D pieces needs {n}")
        return names
    if "%" in spec:
        slow = sizes[-1]
        words = parts
        if len(words) >= 4:
            fmt, nums = " ".join(words[:-3]), words[-3:]
        elif len(words) == 3:
            raise FormatError(f"{where}: ElementDataFile pattern needs <min> <max> <step>, "
                              f"got {spec!r}")
        else:
            fmt, nums = words[0], words[1:]
        vals = pattern_numbers(fmt, nums, "ElementDataFile", where)
        if len(vals) == 3:
            lo, hi, step = vals
        else:
            lo = vals[0] if vals else 1
            hi, step = lo + slow - 1, 1
        n = pattern_count(lo, hi, step, "ElementDataFile", where)
        if n != slow:
            raise FormatError(f"{where}: ElementDataFile pattern names {n} "
                              f"file{'s' if n != 1 else ''} ({lo}..{hi} step {step}), but "
                              f"the slowest axis of DimSize has {slow} slices")
        return pattern_files(base, fmt, lo, step, n, "ElementDataFile", where)
    return [base / spec]


def _meta(pairs, direction) -> dict[str, str]:
    """The header's non-geometry key/values, as volwarp keeps them (see module doc)."""
    meta: dict[str, str] = {}
    for key, value in pairs:
        if key in _DESCRIPTIVE:
            meta[PREFIX + key] = value
        elif key == "CenterOfRotation":
            try:
                zero = all(float(v) == 0 for v in value.split())
            except ValueError:
                zero = False
            if not zero:  # only a non-default one carries information
                meta[PREFIX + key] = value
        elif key == "AnatomicalOrientation":
            if value.upper() != anatomical_orientation(direction):
                meta[PREFIX + key] = value
        elif key not in _STRUCTURE:
            meta[key] = value
    return meta


# -- writing ------------------------------------------------------------------------

_LETTERS = (("R", "L"), ("A", "P"), ("I", "S"))


def anatomical_orientation(direction) -> str:
    """The ``AnatomicalOrientation`` ITK writes for ``direction`` (LPS; ``RAI`` = identity).

    As ITK's AnatomicalOrientation: repeatedly take the largest remaining
    ``|direction[row, col]|`` (ties: the last in row-major order), give index
    axis ``col`` world axis ``row``, and drop that row and column. The letter
    is the side the axis comes *from* (ITK's convention): x R/L, y A/P, z I/S
    for a positive/negative component.
    """
    d = np.asarray(direction, dtype=np.float64)
    cand = [(abs(d[r, c]), r, c) for r in range(3) for c in range(3)]
    terms = ["?"] * 3
    for _ in range(3):
        _, r, c = max(cand)
        terms[c] = _LETTERS[r][0 if d[r, c] > 0 else 1]
        cand = [x for x in cand if x[1] != r and x[2] != c]
    return "".join(terms)


def _fmt(x: float) -> str:
    text = repr(float(x))
    return text[:-2] if text.endswith(".0") else text


def _nums(values) -> str:
    return " ".join(_fmt(v) for v in values)


def _user_fields(meta: dict) -> list[tuple[str, str]]:
    """The meta key/values written to the header (sorted, as ITK writes its dictionary)."""
    out, dropped, changed = {}, [], []
    for key, value in meta.items():
        key = str(key)
        name = key[len(PREFIX):] if key.startswith(PREFIX) else key
        if (not name or name in _STRUCTURE or "=" in name or name != name.strip()
                or any(ch in name for ch in "\r\n")):
            # written by volwarp itself, or not a header key
            if not key.startswith(PREFIX):
                dropped.append(key)
            continue
        out[name] = str(value).replace("\r", " ").replace("\n", " ").strip()
        if out[name] != str(value):  # (a header line holds no line break, and is stripped)
            changed.append(key)
    from ..progress import log

    if dropped:
        log.warning("warning: key/value%s %s not written to the MetaImage header (MetaIO's "
                    "own fields, or not a header key)", "s" if len(dropped) > 1 else "",
                    ", ".join(map(repr, sorted(dropped))))
    if changed:
        log.warning("warning: key/value%s %s written to the MetaImage header with %s line "
                    "breaks as spaces and %s outer spaces left out (a header line holds "
                    "neither): .nrrd keeps them", "s" if len(changed) > 1 else "",
                    ", ".join(map(repr, sorted(changed))), *(("their",) * 2
                                                             if len(changed) > 1 else ("its",) * 2))
    return sorted(out.items())


def metaimage_header(vol: Volume | Header, dtype: np.dtype, *, byte_order: str, data_file: str,
                     compressed_size: int | None = None) -> bytes:
    """The header text of ``vol`` as volwarp writes it (deterministic)."""
    center = str(vol.meta.get(PREFIX + "CenterOfRotation", "0 0 0"))
    try:
        center_vals = [float(v) for v in center.split()]
        center = _nums(center_vals) if len(center_vals) == 3 else "0 0 0"
    except ValueError:
        center = "0 0 0"
    lines = [
        "ObjectType = Image",
        "NDims = 3",
        "BinaryData = True",
        f"BinaryDataByteOrderMSB = {byte_order == 'big'}",
        f"CompressedData = {compressed_size is not None}",
    ]
    if compressed_size is not None:
        lines.append(f"CompressedDataSize = {compressed_size}")
    lines += [
        "TransformMatrix = " + _nums(vol.direction.T.ravel()),  # column after column
        "Offset = " + _nums(vol.origin),
        f"CenterOfRotation = {center}",
        f"AnatomicalOrientation = {anatomical_orientation(vol.direction)}",
        "ElementSpacing = " + _nums(vol.spacing),
    ]
    lines += [f"{k} = {v}" for k, v in _user_fields(vol.meta)]
    lines += [
        "DimSize = " + " ".join(str(n) for n in vol.shape_xyz),
        f"ElementType = {_WRITE_TYPES[dtype.name]}",
        f"ElementDataFile = {data_file}",
    ]
    return header_bytes("\n".join(lines) + "\n")


def write_metaimage(vol: Volume, path: str | os.PathLike, *, compress: bool = False,
                    byte_order: str = "little", level: int = 1, dtype=None) -> None:
    """Write ``vol`` as MetaImage: a ``.mhd`` header and its data file, or one ``.mha``.

    ``.mhd`` writes a header plus ``.raw`` (``.zraw`` when compressed, as ITK names it)
    next to it, any other name one ``.mha``.

    Compressed data is one zlib stream (as MetaIO writes it), ``level`` 1..9.
    ``dtype``: the samples cast to it as they are written (uncompressed only:
    :func:`~volwarp_cli.io.write_volume` casts a compressed output's first).
    """
    path = Path(path)
    if dtype is not None and compress:
        raise ValueError("write_metaimage: a compressed output's samples are cast before")
    cast = dtype
    dtype = check_dtype(vol.data.dtype if cast is None else cast, str(path))
    if compress:  # (the header gives the stream's size: it is made whole first)
        from .deflate import zlib_bytes  # (not loaded for an uncompressed file)

        payload = zlib_bytes(memoryview(with_byte_order(vol.data, byte_order)).cast("B"), level)

        def write(fh):
            fh.write(payload)
    else:  # (cast and ordered by slabs where it must be)
        def write(fh):
            write_samples(fh, vol.data, byte_order, cast, what=str(path))
    size = len(payload) if compress else None
    if path.suffix.lower() == ".mhd":
        data_path = path.with_suffix(".zraw" if compress else ".raw")
        name = data_path.name  # (one a header can name: checked with the output's path)
    else:
        data_path, name = None, "LOCAL"
    header = metaimage_header(vol, dtype, byte_order=byte_order, data_file=name,
                              compressed_size=size)
    write_with_header(path, header, write, data_path=data_path,
                      referenced=_referenced_data_files,
                      siblings=() if data_path is None else
                      [path.with_suffix(".raw"), path.with_suffix(".zraw")])
