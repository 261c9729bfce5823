"""Compressed inputs larger than memory: their samples inflated once into a scratch file.

A deflate stream (a ``.nii.gz``, a gzip NRRD, a compressed MetaImage) has no
index: a box of its samples cannot be read without inflating everything
before it. An input whose samples are more than their share of the memory
budget (:func:`~volwarp_cli.memory.read_by_box`) is therefore inflated once,
a piece at a time (a few MB held), into a raw file in a scratch folder, and
read from there box by box as an uncompressed file is
(:class:`InflatedArray`, a :class:`.filearray.FileArray`). Every check of the
in-memory read still holds: the whole stream is inflated, so a truncated or
corrupt file is the same one-line error, before any work. A file opened again
in the same run (a morph's source that is also its target) reuses its copy.

Copies are made inside a command's run only (a library call outside any
:func:`~volwarp_cli.runscope.run_scope` reads the file whole), by the
command's process (a worker process reopening an input reads it whole: the
copy, where there is one, travels with the input instead). The scratch
folder is made beside the run's first output (its disk is the one the
outputs need anyway; named and cleaned as the output's temporaries), else in
the system's temporary folder (a command without an output file: a remote
cluster's workers cannot see that one, so a worker that does not find the
copy reads the input whole, as one without a copy does), and removed when the run ends
(:func:`~volwarp_cli.runscope.at_run_end`), on a stop, or, after a kill, by
the next run writing the same output. A disk without room for the samples
leaves the input to be read whole, as before, and the refusal says so.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from ..errors import OutOfMemoryError
from .filearray import FileArray


class InflatedArray(FileArray):
    """A compressed input's samples in their scratch file: read by box, carried to workers.

    ``portable``: a :class:`.lazy.LazySource` pickles it with itself, so that
    a worker process reads the same scratch file instead of inflating the
    input again; where that file is not (:meth:`reachable`: a worker on
    another machine), the source reopens the input instead.
    """

    portable = True

    def reachable(self) -> bool:
        """Whether this process sees the scratch file (a remote worker may not)."""
        return os.path.exists(self.path)


class NoRoom(Exception):
    """The scratch folder's disk cannot take the samples (``args[0]`` says so)."""


@contextlib.contextmanager
def naming_no_room(no_room: str | None):
    """A memory refusal inside (the input then read whole) also says why no copy was made.

    ``no_room``: the :class:`NoRoom` message, or None (the refusal as it is).
    """
    try:
        yield
    except OutOfMemoryError as exc:
        if no_room is None:
            raise
        raise OutOfMemoryError(f"{exc}; {no_room}") from None


def inflated_array(original: Path, nbytes: int, file_dtype, shape_zyx, where: str,
                   fill, part=0) -> InflatedArray:
    """``shape_zyx`` samples of ``file_dtype``, inflated by ``fill(sink)`` into a scratch file.

    ``fill(sink)`` inflates the input and hands every piece of its samples,
    in order, to ``sink(at, piece)`` (``at``: the piece's byte position among
    the samples), raising the reader's own errors for a damaged file.
    ``original``: the compressed file, noted as an input of the run; ``part``:
    which of its sample blocks (a 4-D file's volume: its first byte). Raises
    :class:`NoRoom` when the folder's disk has less than ``nbytes`` free.
    """
    from ..progress import timed
    from ..runscope import run_files
    from ..signals import check_stop
    from .common import note_input
    from .mapped import watch

    note_input(original)
    watch(original)  # (rewritten while it is inflated: a mix; refused before any rename)
    st = os.stat(original)
    key = (os.path.realpath(original), st.st_size, st.st_mtime_ns, part, nbytes,
           str(file_dtype), tuple(shape_zyx))
    copies = run_files().copies
    if key in copies and os.path.exists(copies[key].path):  # (the same file opened again)
        return copies[key]
    folder = _scratch_for(original, nbytes)
    try:
        path = folder / "samples.raw"
        with open(path, "wb") as fh, timed(f"inflate {where} to a scratch file"):
            def sink(at: int, piece) -> None:
                check_stop()
                fh.write(piece)

            fill(sink)
            if fh.tell() != nbytes:  # (the readers' own checks refuse a short stream first)
                from ..errors import FormatError

                raise FormatError(f"{where}: data is truncated: expected {nbytes} bytes, "
                                  f"found {fh.tell()}")
    except BaseException:
        _remove(folder)
        raise
    copies[key] = InflatedArray(path, file_dtype, 0, shape_zyx)
    return copies[key]


def _scratch_for(original: Path, nbytes: int) -> Path:
    """A scratch folder for ``nbytes`` beside the run's first output (else the temporary folder)."""
    import shutil

    from ..memory import human_bytes
    from ..runscope import at_run_end, run_files
    from .atomic import make_scratch_folder

    outputs = list(run_files().claimed)
    near = Path(outputs[0]) if outputs else Path(tempfile.gettempdir()) / Path(original).name
    try:
        free = shutil.disk_usage(near.parent).free
    except OSError as exc:
        raise NoRoom(f"{near.parent}: {exc.strerror}") from None
    if nbytes > free:
        raise NoRoom(f"inflating it to read by blocks needs {human_bytes(nbytes)} where "
                     f"{near.parent} has {human_bytes(free)} free")
    folder = make_scratch_folder(near)
    at_run_end(lambda: _remove(folder))
    return folder


def _remove(folder: Path) -> None:
    from .atomic import remove_scratch_folder

    if os.path.isdir(folder):
        remove_scratch_folder(folder)
