"""Pieces every reader and writer shares: byte order, exact reads, data files, ascii samples.

Sample types and casting live in :mod:`volwarp_cli.samples`, the memory checks
in :mod:`volwarp_cli.memory` (the numeric core needs them too, and imports
nothing from ``io/``); their names are imported here for the readers.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np

from ..errors import BadUsage, FormatError, VolwarpError
from ..memory import available_memory, ensure_fits_in_memory  # noqa: F401
from ..memory import human_bytes as _human  # noqa: F401
from ..runscope import run_files
from ..samples import SUPPORTED_DTYPES, cast_samples, check_dtype, voxel_count  # noqa: F401
from . import writeback


def header_line(raw: bytes) -> str:
    """A text header's line (NRRD, MetaImage): UTF-8, else Latin-1.

    3D Slicer and ITK write key/values and file names as UTF-8 ("Läsion");
    read as Latin-1 they came out "LÃ¤sion" in info, NIfTI and OME-Zarr. A
    line that is not UTF-8 is an older Latin-1 header, read as before. The
    writers write UTF-8 (:data:`HEADER_ENCODING`).
    """
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def header_name(raw: bytes) -> str:
    """A file name in a text header (a detached data file): its bytes, whatever they are.

    A name that is not UTF-8 (a Latin-1 file system's) keeps its bytes as
    the file system gives them (surrogate escapes), so it opens the file it names;
    :func:`header_bytes` writes them back as they were.
    """
    return raw.decode("utf-8", "surrogateescape")


#: how NRRD and MetaImage headers are written (every character kept, as Slicer writes them)
HEADER_ENCODING = "utf-8"


def header_bytes(text: str) -> bytes:
    """A header's text as UTF-8, never an error.

    A file name's undecodable bytes (surrogate escapes, from the file system)
    are written back as they were.
    """
    return text.encode(HEADER_ENCODING, "surrogateescape")


def make_volume(where: str, data: np.ndarray, *, error=FormatError, **geometry):
    """A :class:`~volwarp_cli.volume.Volume`, or ``error`` naming the file ``where``.

    The Volume's own checks (a singular direction, a spacing that is not
    positive, ...) do not know which file the geometry came from.
    """
    from ..volume import Volume

    try:
        return Volume(data, **geometry)
    except VolwarpError as exc:
        raise error(f"{where}: {exc}") from None


def native(data: np.ndarray) -> np.ndarray:
    """The same samples in the machine's byte order (C-contiguous)."""
    if data.dtype.byteorder not in ("=", "|") and data.dtype != data.dtype.newbyteorder("="):
        data = data.astype(data.dtype.newbyteorder("="))
    return np.ascontiguousarray(data)


def with_byte_order(data: np.ndarray, byte_order: str) -> np.ndarray:
    """Samples in ``little`` or ``big`` byte order, for writing."""
    if byte_order not in ("little", "big"):
        raise VolwarpError(f"byte order must be little or big, got {byte_order!r}")
    code = "<" if byte_order == "little" else ">"
    return np.ascontiguousarray(data, dtype=data.dtype.newbyteorder(code))


#: bytes of samples (the wider of their type and the output's) cast or put in the file's
#: byte order at a time, where samples are written by slabs of z planes (:func:`write_samples`)
SLAB_BYTES = 4 << 20


def write_samples(fh, data: np.ndarray, byte_order: str = "little", dtype=None, *,
                  what: str = "volume") -> None:
    """Write ``data`` ([z, ...], cast to ``dtype`` where given) to ``fh`` in ``byte_order``.

    The bytes of the whole's :func:`~volwarp_cli.samples.cast_samples` and
    :func:`with_byte_order` (both work sample by sample); where either has
    something to do, a slab of z planes at a time (:data:`SLAB_BYTES`), so
    that the write holds a slab's copy, never the whole's. ``what``: names
    the output in a refusal of the cast (NaN for an integer type).
    """
    out = check_dtype(data.dtype if dtype is None else dtype, what)
    out = out.newbyteorder("<" if byte_order == "little" else ">")
    if data.dtype == out and data.flags.c_contiguous:
        writeback.write(fh, memoryview(data).cast("B"))
        return
    plane = max(1, data[:1].size * max(out.itemsize, data.dtype.itemsize))
    step = max(1, SLAB_BYTES // plane)
    for z in range(0, data.shape[0], step):
        part = data[z:z + step]
        if dtype is not None:
            part = cast_samples(part, dtype, what=what)
        writeback.write(fh, memoryview(with_byte_order(part, byte_order)).cast("B"))


def read_exact(fh, nbytes: int, where: str) -> np.ndarray:
    """Read exactly ``nbytes`` from ``fh`` into a new uint8 buffer, or raise 'truncated'.

    The buffer is not zeroed first (a bytearray would be: one more pass over
    every byte of a large volume).
    """
    buf = np.empty(nbytes, dtype=np.uint8)
    view = memoryview(buf)
    got = 0
    try:
        while got < nbytes:
            n = fh.readinto(view[got:])
            if not n:
                break
            got += n
    except EOFError as exc:
        raise FormatError(f"{where}: compressed data is truncated ({exc})") from None
    except (OSError, ValueError, zlib.error) as exc:
        raise FormatError(f"{where}: corrupt compressed data ({exc})") from None
    if got < nbytes:
        raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes, found {got}")
    return buf


def read_gzip_exact(fh, nbytes: int, where: str) -> bytearray:
    """Decompress a gzip (or zlib) stream from ``fh`` into exactly ``nbytes``.

    Faster than ``gzip.GzipFile`` (pieces written in place); refuses
    truncated streams and streams holding more than ``nbytes`` (after at
    most a piece beyond them). Members, empty ones and NUL padding as
    :func:`.deflate.inflate_pieces` reads them.
    """
    out = bytearray(nbytes)
    view = memoryview(out)

    def place(at: int, piece) -> None:
        view[at:at + len(piece)] = piece

    inflate_exact(fh, nbytes, where, place)
    return out


def inflate_exact(fh, nbytes: int, where: str, sink) -> None:
    """:func:`read_gzip_exact`'s stream, each inflated piece to ``sink(at, piece)`` in order."""
    from .deflate import ERRORS, Truncated, inflate_pieces

    pos = 0
    try:
        for piece in inflate_pieces(fh):
            if pos + len(piece) > nbytes:
                raise FormatError(f"{where}: compressed data holds more than {nbytes} bytes "
                                  "(wrong sizes or type in the header?)")
            sink(pos, piece)
            pos += len(piece)
    except ERRORS as exc:
        raise FormatError(f"{where}: corrupt compressed data ({exc})") from None
    except Truncated:
        if pos >= nbytes:
            raise FormatError(f"{where}: compressed data is truncated (no end-of-stream "
                              "marker)") from None
        raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes, "
                          f"found {pos}") from None
    if pos < nbytes:
        raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes, found {pos}")


# -- detached data files -------------------------------------------------------------

#: set to 1 to let detached headers read data files outside their own folder
ALLOW_OUTSIDE_DATA = "VOLWARP_ALLOW_OUTSIDE_DATA"


def note_input(file) -> None:
    """Record an input of this run (an open file or a path; :mod:`volwarp_cli.runscope`).

    Then no output of the run replaces it behind the user's back.
    """
    st = os.fstat(file.fileno()) if hasattr(file, "fileno") else os.stat(file)
    run_files().inputs.add((st.st_dev, st.st_ino))


def open_input(path: Path, where: str):
    """Open ``path`` to read (binary), recorded as an input of this run (:func:`note_input`).

    A file that cannot be opened is a FormatError naming it (``where``).
    """
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise FormatError(f"{where}: cannot open ({exc.strerror})") from None
    note_input(fh)  # a detached header's data file may then be rewritten with it
    return fh


def open_data_file(header: Path, path: Path, where: str):
    """Open a detached header's data file for reading, refusing one outside its folder.

    A batch tool reprocessing headers from many sources must not let a header
    (``data file: /etc/shadow``, ``../../x``, a symbolic link or a ``LIST`` or
    ``%d`` name leading out) copy other files into its outputs: after every
    link is followed, the data file must lie inside the header's own folder,
    unless ``VOLWARP_ALLOW_OUTSIDE_DATA=1`` or the run's
    ``--allow-outside-data`` (:class:`volwarp_cli.runscope.RunFiles`) says otherwise.
    """
    allowed = (run_files().allow_outside_data
               or os.environ.get(ALLOW_OUTSIDE_DATA, "") in ("1", "yes", "true"))
    if not allowed:
        base = os.path.realpath(header.parent)
        real = os.path.realpath(path)
        if os.path.commonpath([base, real]) != base:
            raise FormatError(f"{where}: data file {str(path)!r} lies outside the header's "
                              f"folder ({real}); give --allow-outside-data (or set "
                              f"{ALLOW_OUTSIDE_DATA}=1) to read it")
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise FormatError(f"{where}: data file {str(path)!r}: {exc.strerror}") from None
    note_input(fh)
    return fh


def data_file_name_problem(name: str) -> str | None:
    """Why a detached header cannot name its data file ``name`` (None: it can).

    NRRD's ``data file`` and MetaImage's ``ElementDataFile`` take the rest of
    their line as the name, and their readers (teem, ITK's MetaIO, volwarp's
    own) strip the spaces around it and read a name beginning with ``LIST``
    (teem's ``SKIPLIST``), one with a ``%`` (a numbered pattern) and
    ``LOCAL`` as forms of their own: written as it is, such a name reads as
    another file, or as none (``-o ' x.nhdr'`` read an unrelated ``x.raw``).
    """
    if "\n" in name or "\r" in name:
        return "a line break would end the header's line"
    if name != name.strip():
        return "readers strip the spaces around it, so it would name another file"
    if "%" in name:
        return "a name with '%' reads as a numbered pattern of files"
    if name.startswith(("LIST", "SKIPLIST")):
        return "a name beginning with LIST reads as a list of files"
    if name.lower() == "local":
        return "LOCAL means samples inside the header's own file"
    return None


def refuse_unnamable_data_file(path: Path, option: str | None = None) -> None:
    """A usage error when the detached header ``path`` could not name its data file.

    ``-o scan.nhdr`` writes ``scan.raw`` and a header naming it
    (:func:`data_file_name_problem` says which names a header cannot hold);
    checked with every output (:func:`~volwarp_cli.io.atomic.check_output_path`).
    """
    import re

    from .inputs import output_files

    for data in output_files(path)[1:]:  # (none but a detached header's)
        why = data_file_name_problem(data.name)
        if why is None:
            continue
        name = re.sub(r"[\r\n%]+", "_", path.name).strip()
        name = "_" + name if name.startswith(("LIST", "SKIPLIST")) else name
        better = path.with_name(name if name[:1] != "." else "out" + name)
        attached = better.with_suffix(".nrrd" if path.suffix.lower() == ".nhdr" else ".mha")
        raise BadUsage(f"{option + ' ' if option else ''}{str(path)!r}: its data file cannot "
                       f"be named {data.name!r} ({why}): choose another name, e.g. "
                       f"{better.name!r}, or write one file ({attached.name!r})")


def pattern_numbers(fmt: str, words: list[str], what: str, where: str) -> list[int]:
    """The whole numbers (``<min> <max> <step>``) after a data file pattern ``fmt``.

    ``what``: the header field, as errors name it (``'data file'``, ``ElementDataFile``).
    """
    try:
        return [int(v) for v in words]
    except ValueError:
        raise FormatError(f"{where}: {what} pattern needs whole numbers <min> <max> <step> "
                          f"after {fmt!r}, got {' '.join(words)!r}") from None


def pattern_count(lo: int, hi: int, step: int, what: str, where: str) -> int:
    """How many files a data file pattern's ``lo``, ``hi``, ``step`` name (``hi`` included)."""
    if step == 0:
        raise FormatError(f"{where}: {what} pattern has step 0")
    if (hi - lo) * step < 0:
        raise FormatError(f"{where}: {what} pattern: max {hi} is not reached from min {lo} by "
                          f"step {step}")
    return (hi - lo) // step + 1


def pattern_files(base: Path, fmt: str, lo: int, step: int, n: int, what: str,
                  where: str) -> list[Path]:
    """The ``n`` data files ``fmt % i`` (``i`` from ``lo`` by ``step``) in the folder ``base``."""
    try:
        return [base / (fmt % i) for i in range(lo, lo + n * step, step)]
    except (TypeError, ValueError) as exc:
        raise FormatError(f"{where}: {what} pattern {fmt!r} is not a file name with one %d "
                          f"({exc})") from None


def read_data_files(header: Path, files: list[Path], count: int, where: str, read):
    """The ``count`` samples of a detached header's data ``files``, in equal parts, in order.

    ``read(fh, n, name)``: ``n`` samples of the open data file ``name``. Each file
    is opened by :func:`open_data_file` (inside the header's folder).
    """
    per_file = count // len(files) if files else 0
    if not files or per_file * len(files) != count:
        raise FormatError(f"{where}: {len(files)} data files do not divide {count} samples")
    chunks = []
    for f in files:
        with open_data_file(header, f, where) as fh:
            chunks.append(read(fh, per_file, str(f)))
    return np.concatenate(chunks) if len(chunks) > 1 else chunks[0]


def write_with_header(path: Path, header: bytes, write_samples, *,
                      data_path: Path | None = None, referenced=None, siblings=()) -> None:
    """Write a header and its samples (``write_samples(fh)``), atomically.

    Both in one file ``path``, the samples after the header; or, with
    ``data_path``, a detached header ``path`` and its data file, renamed
    together (:func:`~volwarp_cli.io.atomic.atomic_outputs`) after
    :func:`check_data_output` (``referenced``: the data files an existing
    header names). ``siblings``: the other names the writer gives this
    header's data file (``x.raw.gz`` beside ``x.raw``): one the existing
    header names is the earlier output's, removed with the commit (it was
    left behind, and refused the next write of that name).
    """
    from .atomic import atomic_output, atomic_outputs

    if data_path is None:
        with atomic_output(path) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(header)
                write_samples(fh)
        return
    check_data_output(data_path, path, referenced)
    stale = _earlier_data_files(path, data_path, referenced, siblings)
    with atomic_outputs(data_path, path, replaced=stale) as (tmp_data, tmp_header):
        with open(tmp_data, "wb") as fh:
            write_samples(fh)
        tmp_header.write_bytes(header)


def _earlier_data_files(header_path: Path, data_path: Path, referenced, siblings) -> list:
    """The ``siblings`` of ``data_path`` the existing header names (not inputs of the run)."""
    from .atomic import check_output_path

    if not siblings or not header_path.exists():
        return []
    try:
        names = referenced(header_path)
    except (OSError, VolwarpError):
        return []
    named = {os.path.realpath(header_path.parent / n) for n in names}
    stale = []
    for sibling in siblings:
        sibling = Path(sibling)
        if (sibling == data_path or not sibling.exists()
                or os.path.realpath(sibling) not in named):
            continue
        try:
            check_output_path(sibling)  # (an input of this run is never removed)
        except VolwarpError:
            continue
        if _named_by_another_header(sibling, header_path):
            continue
        stale.append(sibling)
    return stale


#: the detached headers that may name a data file beside them
_HEADER_SUFFIXES = (".nhdr", ".mhd")


def _named_by_another_header(data: Path, header_path: Path) -> bool:
    """Whether a detached header beside ``data`` other than ``header_path`` may name it.

    Its name anywhere in the header's text (a data file field, a LIST): an
    ``.mhd`` written by hand over the ``.raw`` of an ``.nhdr`` (one file, two
    tools) lost its data when the ``.nhdr`` was rewritten compressed (a review).
    Conservative: a header that cannot be read keeps it too.
    """
    name = data.name.encode()
    mine = os.path.realpath(header_path)
    try:
        entries = list(os.scandir(data.parent))
    except OSError:
        return True
    for entry in entries:
        if not entry.name.lower().endswith(_HEADER_SUFFIXES) or (
                os.path.realpath(entry.path) == mine):
            continue
        try:
            with open(entry.path, "rb") as fh:
                if name in fh.read(1 << 16):
                    return True
        except OSError:
            return True
    return False


def check_data_output(data_path: Path, header_path: Path, referenced) -> None:
    """Refuse to write a detached header's data file over a file that is not its own.

    ``-o scan.nhdr`` also writes ``scan.raw``, a file the user did not name:
    it may replace an earlier run's data file (the existing header at
    ``header_path`` names it: ``referenced(header_path)`` lists the data file
    names it refers to, or raises), never an input of this command
    (:func:`~volwarp_cli.io.atomic.check_output_path`, a usage error) and never
    any other existing file.
    """
    from .atomic import check_output_path

    check_output_path(data_path)
    if not data_path.exists():
        return
    try:
        names = referenced(header_path) if header_path.exists() else []
    except (OSError, VolwarpError):
        names = []
    if not any(os.path.realpath(header_path.parent / n) == os.path.realpath(data_path)
               for n in names):
        raise VolwarpError(f"{header_path}: its data file {data_path} exists and is not an "
                           "earlier output's (no header of that name refers to it): volwarp "
                           "does not replace a file -o does not name; remove it or choose "
                           "another name")


# -- ascii samples (NRRD and MetaImage) ----------------------------------------------

def ascii_values(text: str, dtype: np.dtype, count: int, where: str) -> np.ndarray:
    """Parse ASCII samples into ``dtype``, refusing values the type cannot hold.

    An integer type takes only finite, whole numbers within its range (no
    silent wrap-around, truncation or NaN-to-0). A float type keeps NaN and
    infinities as data, as the binary encodings do, but refuses a finite value
    too large for it (which would become infinity).
    """
    tokens = text.replace(",", " ").split()
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        bad = next((i, t) for i, t in enumerate(tokens) if not is_number(t))
        raise FormatError(f"{where}: ascii data value {bad[1][:40]!r} (sample {bad[0]}) is "
                          "not a number") from None
    if values.size != count:
        raise FormatError(f"{where}: ascii data has {values.size} values, expected {count}")
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(values) | (values != np.floor(values)) | (values < info.min) | (
                values > info.max)
        if bad.any():
            i = int(np.argmax(bad))
            v = values[i]
            why = ("is not a number" if np.isnan(v) else
                   "is infinite" if not np.isfinite(v) else
                   "is not a whole number" if v != np.floor(v) else
                   "is out of range")
            raise FormatError(f"{where}: ascii data value {tokens[i][:40]!r} (sample {i}) "
                              f"{why}: type {dtype.name} holds whole numbers "
                              f"{info.min}..{info.max}")
        return values.astype(dtype)
    with np.errstate(over="ignore"):
        out = values.astype(dtype)
    big = np.isinf(out) & np.isfinite(values)  # finite in the file, too large for the type
    if big.any():
        i = int(np.argmax(big))
        raise FormatError(f"{where}: ascii data value {tokens[i][:40]!r} (sample {i}) is "
                          f"outside the range of {dtype.name}")
    return out


def is_number(token: str) -> bool:
    """True when ``token`` reads as a float (as ``float()`` takes it: ``nan``, ``1e3``)."""
    try:
        float(token)
    except ValueError:
        return False
    return True


def dicom_read_options(series=None, irregular=None, duplicates=None, keep_shear=False,
                       keep_phi=False, reference=None, segment=None,
                       structure=None) -> dict | None:
    """The DICOM read options given, as keyword arguments of ``read_dicom`` (None: none).

    The command line's options and the Python API's keywords alike: a series
    given as digits is its number, flags only when set.
    """
    given = {}
    if series is not None:
        given["series"] = int(series) if str(series).isdigit() else series
    for key, value in (("irregular", irregular), ("duplicates", duplicates),
                       ("reference", reference), ("segment", segment),
                       ("structure", structure)):
        if value is not None:
            given[key] = value
    for key, flag in (("keep_shear", keep_shear), ("keep_phi", keep_phi)):
        if flag:
            given[key] = True
    return given or None


def short_text(text: str, n: int = 60) -> str:
    """``text`` cut to ``n`` characters for a one-line message (a header's value)."""
    return text if len(text) <= n else text[:n - 3] + "..."
