"""The files an input stands for, and the rule that no output may be one of them.

A scan given as ``scan.nhdr`` is two files (the header and the data file it
names), a DICOM series is a folder of files, a NRRD ``LIST`` header is as
many files as it lists. ``distance scan.nii.gz -o scan.nii.gz`` or ``-o
scan_data.raw`` would replace the scan (atomically, so with exit 0 and
nothing on stderr): the one mistake a tool that reprocesses scans overnight
must never make. So every output of every command is checked against every
input's files, symbolic links followed and hard links seen, before any work
(the command line declares its inputs as it parses them, the spec loaders
as they resolve the files a spec names) and again when the output is
written (:func:`volwarp_cli.io.atomic.check_output_path`, which also knows
every file a reader actually opened).

Only headers are read here, never samples: the check is cheap and runs
before anything else. A header that cannot be parsed stands for itself
alone (its reader will report what is wrong with it).
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import BadUsage, FormatError
from ..runscope import run_files

#: extensions of detached headers, whose data files are inputs too
_NRRD = (".nhdr", ".nrrd")
_METAIMAGE = (".mhd", ".mha")


def declare_input(path: str | os.PathLike) -> None:
    """Record ``path`` as an input of this run, before it is read.

    Then :func:`refuse_output_over_input` (every output check of the run)
    refuses an output that is one of its files.
    """
    run_files().declared.setdefault(str(path), None)


def declare_input_glob(pattern: str | os.PathLike) -> None:
    """Record a glob whose files are inputs of this run (a sweep's template frames).

    :func:`refuse_output_over_input` then refuses an output it would match:
    a render named ``fr_003.png`` beside frames ``fr_*.png`` was written, and
    the next run of the command read it as a fourth frame (a review).
    """
    files = run_files()
    pattern = os.path.abspath(pattern)
    if pattern not in files.globs:
        files.globs.append(pattern)


def refuse_stream_input(path: str | os.PathLike) -> None:
    """Refuse, before it is opened, an input that is a pipe or a device (a FormatError).

    volwarp opens an input more than once (its content checked, then its
    header, then its samples): from a named pipe the first open drained the
    stream and the next waited for a writer that had gone, forever (a cron
    job that never ended). Inputs read once from start to end (specs, CSV
    files) may be pipes (:class:`~volwarp_cli.cli.options.InputPath`).
    """
    from .atomic import special_kind

    kind = special_kind(path, follow=True)
    if kind is not None:
        raise FormatError(f"{path}: is {kind}, not a regular file; volwarp opens an input "
                          "more than once (to check it, then to read it), which a stream "
                          "cannot give: write the stream to a file first and give that file")


def opened_as_input(path: str | os.PathLike) -> bool:
    """True when ``path`` is (the same file as) one this run's readers opened."""
    ident = _identity(path)
    return ident is not None and ident in run_files().inputs


def input_files(path: str | os.PathLike) -> list[Path]:
    """``path`` and the data files its header names (detached NRRD and MetaImage, a DICOMDIR's images).

    ``LIST`` headers and ``%d`` patterns name several. A folder (a DICOM
    series, an OME-Zarr store) is itself (:func:`refuse_output_over_input`
    treats every file inside it as the input's) and the files outside it its
    links lead its reader to (:func:`linked_files`): a series of links to
    slices kept elsewhere had a slice replaced by an output named after the
    link's target (an RTSTRUCT over a CT slice of its reference, exit 0). A
    header that does not parse gives ``[path]``.
    """
    path = Path(path)
    files = [path]
    if path.is_dir():
        try:
            return files + linked_files(path)
        except Exception:  # noqa: BLE001 - a folder its reader will refuse: the read says why
            return files
    if not path.is_file():
        return files
    name = path.name.lower()
    try:
        if name.endswith(_NRRD):
            files += _nrrd_data_files(path)
        elif name.endswith(_METAIMAGE):
            files += _metaimage_data_files(path)
        else:
            files += _dicomdir_data_files(path)
    except Exception:  # noqa: BLE001 - a header its reader will refuse: the read says why
        pass
    return files


def folder_files(folder: Path) -> list[Path]:
    """Every file under ``folder``, in a fixed order (hidden temporaries too: they are content).

    Through linked folders where its reader goes through them: an OME-Zarr
    store's (zarr opens each key's path, links and all), each real folder
    once (a link back up ends no walk); not a DICOM series' (its reader's
    walk does not follow them). A linked file is read, whatever the folder.
    """
    return [Path(f) for f, _ in _walk_folder(folder)]


def linked_files(folder: Path) -> list[Path]:
    """The files outside ``folder`` that its reader reaches through links in it.

    Walked as :func:`folder_files` walks; only links' (and folders') real
    paths are looked up: a store's thousands of chunks, each resolved, took
    0.1 s of a command for 4096 (24 us a file).
    """
    return [Path(f) for f, outside in _walk_folder(folder) if outside]


def _walk_folder(folder: Path) -> list[tuple[str, bool]]:
    """Each file under ``folder`` as its reader walks (:func:`folder_files`), and whether it lies outside.

    Top-down, sorted, a folder's files before its subfolders' (as
    ``os.walk`` goes); a file lies outside where a link leads there.
    """
    from . import volume_format

    follow = volume_format(folder, reading=True) != "dicom"
    base = _real(folder)
    seen = {base}
    out: list[tuple[str, bool]] = []
    stack = [(str(folder), False)]  # (a folder, whether it lies outside ``folder``)
    while stack:
        here, outside = stack.pop()
        try:
            with os.scandir(here) as it:
                entries = sorted(it, key=lambda e: e.name)
        except OSError:
            continue
        below = []
        for e in entries:
            try:
                is_dir = e.is_dir()  # (links followed, as os.walk sorts them)
            except OSError:
                is_dir = False
            if not is_dir:
                out.append((e.path, outside or (
                    e.is_symlink() and not _inside(_real(e.path), base))))
            elif not follow:  # (a series' reader walks into no linked folder)
                if not e.is_symlink():
                    below.append((e.path, outside))
            else:
                real = _real(e.path)
                if real not in seen:  # (each real folder once)
                    seen.add(real)
                    below.append((e.path, real != base and not _inside(real, base)))
        stack += reversed(below)
    return out


def _dicomdir_data_files(path: Path) -> list[Path]:
    """The images a DICOMDIR lists (what a batch must hash: the DICOMDIR alone is an index).

    Known by content, as the reader knows one (``INDEX.DCM`` is one too): a
    file read as DICOM whose header (no pixel data) is a directory's; [] for
    any other file.
    """
    from . import volume_format

    if not (has_dicom_preamble(path) or path.suffix.lower() == ".dcm"
            or path.name.upper() == "DICOMDIR"):
        return []  # (no DICOM file: pydicom is not imported for a spec, a transform...)
    if volume_format(path, reading=True) != "dicom":
        return []
    from .dicom._scan import _files_of

    return [Path(f) for f, _ in _files_of(path)[0] if Path(f) != path]


def has_dicom_preamble(path: str | os.PathLike) -> bool:
    """True for a file with DICOM's preamble (``DICM`` at byte 128)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(132)
    except OSError:
        return False
    return len(head) == 132 and head[128:132] == b"DICM"


def _nrrd_data_files(path: Path) -> list[Path]:
    from .nrrd import _data_files, read_header

    with open(path, "rb") as fh:
        fields, _ = read_header(fh, str(path))
        sizes = [int(v) for v in fields.get("sizes", "").split()]
        return list(_data_files(fields, path, fh, str(path), sizes) or [])


def _metaimage_data_files(path: Path) -> list[Path]:
    from .metaimage import _data_files, read_header

    with open(path, "rb") as fh:
        fields = dict(read_header(fh, str(path)))
        spec = fields.get("ElementDataFile", "").strip()
        if not spec or spec.lower() == "local":
            return []
        sizes = [int(v) for v in fields.get("DimSize", "").split()]
        return list(_data_files(spec, path, fh, str(path), sizes))


def one_file_twice(named) -> tuple | None:
    """Of ``(key, path)`` pairs, the first two keys whose paths are one file, with that path.

    ``(first key, second key, path)``, links followed; None when every path
    is a file of its own (a pattern's frames, a label map's meshes).
    """
    seen: dict[str, object] = {}
    for key, path in named:
        real = os.path.realpath(path)
        if real in seen:
            return seen[real], key, path
        seen[real] = key
    return None


def output_files(path: str | os.PathLike) -> list[Path]:
    """The files writing ``path`` may create or replace.

    A detached header writes its data file beside it: ``scan.nhdr`` also
    ``scan.raw`` (``scan.raw.gz`` compressed), ``scan.mhd`` also ``scan.raw``
    (``scan.zraw``).
    """
    path = Path(path)
    name = path.name.lower()
    if name.endswith(".nhdr"):
        return [path, path.with_suffix(".raw"), path.with_suffix(".raw.gz")]
    if name.endswith(".mhd"):
        return [path, path.with_suffix(".raw"), path.with_suffix(".zraw")]
    return [path]


def refuse_output_over_input(output: str | os.PathLike,
                             inputs: list[str | os.PathLike] | None = None,
                             *, option: str | None = None) -> None:
    """Raise :class:`~volwarp_cli.errors.BadUsage` when ``output`` would replace an input.

    ``inputs``: the input paths to check against (default: this run's
    declared inputs, :func:`declare_input`). An output collides with an
    input when, symbolic links followed, it is one of the input's files
    (:func:`input_files`), the same file under another name (a hard link),
    a file inside an input folder, or a folder (an OME-Zarr store it would
    replace) holding an input. ``option`` names the output's option in the
    message (``--frames-to``); the message names both files, on one line.
    """
    if inputs is None:
        inputs = list(run_files().declared)
        _refuse_output_in_glob(output, option)
    if not inputs:
        return
    targets = [(p, _real(p), _identity(p)) for p in output_files(output)]
    for given in inputs:
        for file in _expanded(given):
            real = _real(file)
            ident = _identity(file)
            for target, target_real, target_ident in targets:
                if _collide(target_real, target_ident, real, ident, Path(file).is_dir()):
                    raise BadUsage(_message(output, target, given, file, option))


class InputIndex:
    """Many inputs, each with who reads it, for many outputs to be checked against at once.

    The same collisions as :func:`refuse_output_over_input` (links followed,
    hard links, files inside an input folder, a folder output holding an
    input), found by lookups instead of a pass over every input for every
    output: a batch checks each scan's outputs against every scan's table
    cells (thousands of each).
    """

    def __init__(self) -> None:
        self._by_real: dict[str, tuple] = {}
        self._by_ident: dict[tuple, tuple] = {}
        self._folders: dict[str, tuple] = {}
        self._sorted: list[str] | None = None  # (the inputs' real paths, for prefixes)

    def add(self, given, who: str) -> None:
        """Add the input ``given`` (its data files too, :func:`input_files`), read by ``who``."""
        for file in _expanded(given):
            entry = (given, file, who)
            real = _real(file)
            self._by_real.setdefault(real, entry)
            ident = _identity(file)
            if ident is not None:
                self._by_ident.setdefault(ident, entry)
            if Path(file).is_dir():
                self._folders.setdefault(real, entry)
        self._sorted = None

    def refuse(self, output, option: str | None = None) -> None:
        """Raise :class:`~volwarp_cli.errors.BadUsage` where ``output`` would replace an input."""
        for target in output_files(output):
            real, ident = _real(target), _identity(target)
            entry = self._by_real.get(real) or (self._by_ident.get(ident) if ident else None)
            parent = os.path.dirname(real)
            while entry is None and parent != os.path.dirname(parent):  # (inside a folder)
                entry = self._folders.get(parent)
                parent = os.path.dirname(parent)
            if entry is None and self._folders.get(parent) is not None:  # (the root)
                entry = self._folders[parent]
            if entry is None and os.path.isdir(real):  # (a folder output holding an input)
                entry = self._holding(real)
            if entry is not None:
                given, file, who = entry
                raise BadUsage(f"{_message(output, target, given, file, option)} ({who})")

    def _holding(self, folder: str):
        """The entry of an input inside ``folder``, by bisection of the sorted real paths."""
        import bisect

        if self._sorted is None:
            self._sorted = sorted(self._by_real)
        prefix = folder.rstrip(os.sep) + os.sep
        k = bisect.bisect_left(self._sorted, prefix)
        if k < len(self._sorted) and self._sorted[k].startswith(prefix):
            return self._by_real[self._sorted[k]]
        return None


def _refuse_output_in_glob(output, option: str | None) -> None:
    """Refuse an output whose name an input glob of this run matches (:func:`declare_input_glob`)."""
    import fnmatch

    globs = run_files().globs
    if not globs:
        return
    def matches(name: str, pattern: str) -> bool:  # (as glob does: no * across a /)
        parts, wild = name.split(os.sep), pattern.split(os.sep)
        return len(parts) == len(wild) and all(
            fnmatch.fnmatchcase(a, b) for a, b in zip(parts, wild, strict=True))

    names = {os.path.abspath(output), _real(output)}
    for pattern in globs:
        if any(matches(name, pattern) for name in names):
            what = f"{option} {output}" if option else str(output)
            raise BadUsage(f"{what} matches the input pattern {pattern}: the next run would "
                           "read it as an input (a frame of the template); choose a name the "
                           "pattern does not match")


def _expanded(given) -> list[Path]:
    """:func:`input_files` of ``given``, once per run (headers are read once)."""
    cache = run_files().expanded
    key = str(given)
    if key not in cache:
        cache[key] = input_files(given)
    return cache[key]


def _collide(target_real: str, target_ident, real: str, ident, folder: bool) -> bool:
    if target_real == real:
        return True
    if target_ident is not None and target_ident == ident:
        return True  # another name of the same file (a hard link)
    if folder and _inside(target_real, real):
        # inside an input folder (a DICOM series, a store): an existing file is one of the
        # input's, and a new one would be read with it next time (a rerun would refuse it)
        return True
    if os.path.isdir(target_real) and _inside(real, target_real):
        return True  # a folder output (a store) that would replace the input inside it
    return False


def _message(output, target: Path, given, file: Path, option: str | None) -> str:
    what = f"{option} {output}" if option else str(output)
    if Path(target) != Path(output):
        what += f" (its data file {target})"
    if Path(file) != Path(given) and Path(given).is_dir():  # (through a link in it)
        is_what = f"{_real(file)}, which {file} of the input folder {given} links to"
    elif Path(file) != Path(given):
        is_what = f"the data file {file} of the input {given}"
    elif Path(given).is_dir() and _real(target) != _real(given):
        is_what = (f"a file of the input folder {given}" if _identity(target) is not None
                   else f"the input folder {given} (an output inside it)")
    elif os.path.isdir(target) and _real(target) != _real(given):
        is_what = f"the input {given} inside it"
    else:
        is_what = f"the input {given}"
    if _real(target) != os.path.abspath(target) and _identity(target) is not None:
        is_what += f" (links followed: {_real(target)})"
    return (f"{what} would overwrite {is_what}; volwarp never replaces an input: "
            "choose another output name")


def _real(path) -> str:
    return os.path.realpath(path)


def _identity(path) -> tuple[int, int] | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


#: why an output inside another's store is refused (:func:`nested_outputs`)
NESTED_WHY = ("a store's rename replaces its folder, with whatever lies in it; give each "
              "output a place of its own")


def nested_outputs(real: str, writes) -> list[tuple[str, str, object]]:
    """The outputs of ``writes`` (:class:`~volwarp_cli.runscope.Outputs`) nested with ``real``.

    ``(how, path, who)``: the output ``real`` "lies inside" the folder output
    ``path`` (an OME-Zarr store: its rename replaces the folder, the file with
    it, or the file is renamed into the earlier store, then replaced), or
    ``real`` is a folder output that "holds" ``path``.
    """
    nested = []
    folder, parent = real, os.path.dirname(real)
    while parent != folder:
        if parent in writes:
            nested.append(("lies inside", parent, writes[parent]))
        folder, parent = parent, os.path.dirname(parent)
    held = writes.holding.get(real)
    if held is not None:
        nested.append(("holds", held, writes[held]))
    return nested


def _inside(path: str, folder: str) -> bool:
    try:
        return path != folder and os.path.commonpath([path, folder]) == folder
    except ValueError:
        return False


def _has_fields(text: str) -> bool:
    """Whether the ``str.format`` pattern ``text`` has a field (``{frame}``)."""
    import string

    return any(f is not None for _, f, _, _ in string.Formatter().parse(text))


def pattern_regex(name: str, value: str) -> str:
    """A regular expression of the names ``str.format`` pattern ``name`` gives, each field ``value``."""
    import re
    import string

    return "".join(re.escape(text) + ("" if field is None else f"({value})")
                   for text, field, _, _ in string.Formatter().parse(name))


#: what a numbered pattern's field gives: an integer or a decimal number ({i}, {t:.2f})
NUMBER = r"[-+ ]*[0-9][0-9.eE+-]*"


def note_pattern(pattern: str, option: str) -> None:
    """Record that this run writes the numbered outputs of ``pattern`` (said after the commit)."""
    run_files().patterns.append((str(pattern), option))


def earlier_pattern_files(pattern: str, written) -> list[str]:
    """Files of ``pattern``'s folder it could name that are not among ``written`` (sorted).

    An earlier run's frames beyond this run's count (8 frames, then 4): a
    movie or a glob of the pattern would mix them with this run's. None for
    a pattern with fields in its folder.
    """
    import re

    folder, name = os.path.split(pattern)
    if _has_fields(folder):
        return []
    regex = pattern_regex(name, NUMBER)
    mine = {os.path.realpath(p) for p in written}
    try:
        entries = sorted(os.listdir(folder or "."))
    except OSError:
        return []
    return [e for e in entries if re.fullmatch(regex, e)
            and os.path.realpath(os.path.join(folder or ".", e)) not in mine]


def say_earlier_pattern_files() -> None:
    """Warn, once the run's outputs are in place, of each pattern's files this run did not write.

    Not removed (they are files the user may want): said, with the way out.
    """
    files = run_files()
    first = {}  # (a pattern noted twice, under its two spellings -o and --output: once)
    for pattern, option in files.patterns:
        first.setdefault(pattern, option)
    for pattern, option in first.items():
        left = earlier_pattern_files(pattern, files.committed)
        if not left:
            continue
        from ..progress import log

        shown = ", ".join(left[:4]) + (f", ... ({len(left)} files)" if len(left) > 4 else "")
        if pattern.lower().endswith((".nhdr", ".mhd")):  # (detached: their data files too)
            shown += " (with their data files)"
        log.warning("warning: %s %s: %s match%s the pattern but %s not this run's (an "
                    "earlier run's): remove %s, or give each run a folder of its own, so that "
                    "a glob of the pattern does not mix the runs", option, pattern, shown,
                    "es" if len(left) == 1 else "", "is" if len(left) == 1 else "are",
                    "it" if len(left) == 1 else "them")


def refuse_pattern_over_input(pattern: str, *, option: str | None = None,
                              inputs: list[str | os.PathLike] | None = None,
                              numbers: bool = True) -> None:
    """:func:`refuse_output_over_input` for every name a ``str.format`` pattern can give.

    For outputs numbered by fields (``--frames-to 'f_{frame:03d}.nrrd'``)
    whose count is not known before the work: any input file whose path
    (links followed) the pattern could produce is refused, whatever the
    fields' values, and so is any existing file of such a name that is an
    input under another name (a link to it, a hard link). ``numbers``: the
    fields are integers (frame and label numbers: digits, a sign, padding),
    so ``head_{frame}.nrrd`` can never name ``head_t1.nrrd``.
    """
    import re

    if inputs is None:
        inputs = list(run_files().declared)
    folder, name = os.path.split(pattern)
    if _has_fields(folder):
        base, name = "", pattern  # fields in the folder too: match whole paths
    else:
        base = os.path.realpath(folder or ".")
    regex = pattern_regex(name, r"[-+ ]*\d+" if numbers else r"[^/]+")
    for given in inputs:
        for file in _expanded(given):
            real = _real(file)
            if base:
                head, tail = os.path.split(real)
                hit = head == base and re.fullmatch(regex, tail)
            else:
                hit = re.fullmatch(regex, real) or re.fullmatch(regex, str(file))
            if hit:
                raise BadUsage(_message(pattern, Path(pattern), given, file, option))
    if base:  # names the pattern gives that exist already: links, hard links to an input
        try:
            names = sorted(os.listdir(folder or "."))
        except OSError:
            return
        for entry in names:
            if re.fullmatch(regex, entry):
                refuse_output_over_input(os.path.join(folder, entry), inputs, option=option)


def claim_output(output: str | os.PathLike, option: str) -> None:
    """Record that ``option`` writes ``output``; refuse a file two options would write.

    ``-o x.nrrd --jacobian-to x.nrrd`` kept the last write, silently (the
    volume lost); a detached header's data file counts as written by its
    header's option. The same option naming a file again is fine (a check
    made twice). A file inside a folder output (an OME-Zarr store) another
    output names is refused too, whichever option names it: ``-o o.ome.zarr
    --frames-to 'o.ome.zarr/f_{frame}.nrrd'`` put the frames in the earlier
    store, which the new one then replaced (the frames lost, exit 0).
    """
    claims = run_files().claimed
    for target in output_files(output):
        real = _real(target)
        other = claims.get(real)
        if other is not None and other != option:
            raise BadUsage(f"{option} {output} and {other} name the same file {target}: one "
                           "would overwrite the other; give each output its own name")
        for how, path, other in nested_outputs(real, claims):
            raise BadUsage(f"{option} {output} {how} {path}, which {other} writes: "
                           f"{NESTED_WHY}")
    for target in output_files(output):
        claims.setdefault(_real(target), option)
