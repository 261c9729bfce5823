"""2-D images (PNG, TIFF, EXR, JPEG, ...) through OpenImageIO.

Arrays are ``[row, column, channel]`` with row 0 at the top of the picture.
OpenImageIO silently writes garbage for a 2-D array, so one-channel images
are always passed to it as ``(H, W, 1)``.
"""

from __future__ import annotations

import errno
import os
import threading
import time
from pathlib import Path

import numpy as np

from ..errors import FormatError, VolwarpError
from .atomic import atomic_output

_OIIO_TYPES = {"uint8": "UINT8", "uint16": "UINT16", "float32": "FLOAT", "float16": "HALF"}

#: the image extensions volwarp's renders and sheets are written to
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp")


def check_image_extension(path: str | os.PathLike) -> str | os.PathLike:
    """``path`` itself when its extension is a known image one, else raise listing them.

    An option's check, before any work.
    """
    ext = Path(path).suffix.lower()
    if ext not in IMAGE_EXTENSIONS:
        raise VolwarpError(f"{path}: unknown image extension {ext or '(none)'} "
                           f"(known: {' '.join(IMAGE_EXTENSIONS)})")
    return path


def read_image(path: str | os.PathLike, *, normalize: bool = True) -> np.ndarray:
    """Read an image as ``(H, W, C)`` with every channel as stored in the file.

    With ``normalize`` (default), integer images are scaled to float32 in
    [0, 1] (255 -> 1.0 for 8-bit, 65535 -> 1.0 for 16-bit) and float images are
    returned as float32 unchanged; otherwise the file's own type is kept.

    Alpha is *not* multiplied into the colour channels: OpenImageIO
    premultiplies RGBA files by default (``oiio:UnassociatedAlpha`` off), which
    would darken colour wherever alpha is low; volwarp treats channels as
    independent fields (a sweep template's opacity and colour, for instance).
    """
    import OpenImageIO as oiio

    where = str(path)
    if not Path(path).is_file():
        raise FormatError(f"{where}: no such image file")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(where, config)
    if inp is None:
        raise FormatError(f"{where}: cannot read image ({oiio.geterror().strip()})")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, spec.format)
        if pixels is None:
            raise FormatError(f"{where}: cannot read image data ({inp.geterror().strip()})")
    finally:
        inp.close()
    arr = np.asarray(pixels)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3:
        raise FormatError(f"{where}: expected a 2-D image, got shape {arr.shape}")
    return normalized(arr) if normalize else arr


def normalized(samples: np.ndarray) -> np.ndarray:
    """Samples as float32, integers scaled so their type's largest value is 1.0 (as images are)."""
    if samples.dtype.kind in "ui":
        return samples.astype(np.float32) / np.float32(np.iinfo(samples.dtype).max)
    return samples.astype(np.float32)


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write ``image`` (``(H, W)`` or ``(H, W, C)``; uint8, uint16 or float32) atomically.

    Float images are written as they are to formats that hold floats (EXR,
    TIFF) and scaled from [0, 1] to 8 bits (clipped) for the others.
    """
    import OpenImageIO as oiio

    path = Path(path)
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4):
        raise VolwarpError(f"{path}: an image must be (H, W) or (H, W, 1..4), got {arr.shape}")
    ext = path.suffix.lower()
    if arr.dtype.kind == "f" and ext not in (".exr", ".tif", ".tiff", ".hdr"):
        arr = np.clip(np.nan_to_num(arr), 0.0, 1.0)
        arr = np.rint(arr * 255.0).astype(np.uint8)
    elif arr.dtype == np.float64:
        arr = arr.astype(np.float32)
    if arr.dtype.name not in _OIIO_TYPES:
        raise VolwarpError(f"{path}: cannot write images of type {arr.dtype}")
    arr = np.ascontiguousarray(arr)
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, getattr(oiio, _OIIO_TYPES[arr.dtype.name]))
    # our colours are not premultiplied by alpha: without this, PNG's writer
    # would divide them by alpha (read_image reads them back the same way)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    # no time stamp: the TIFF writer adds the time of writing (DateTime, and XMP's
    # CreateDate) unless it is given; empty, it writes none (identical runs, same bytes)
    spec.attribute("DateTime", "")
    with atomic_output(path) as tmp:
        _write_checked(oiio, path, tmp, spec, arr)


#: the error OpenImageIO's TIFF writer reports on every close, the file being complete
_BENIGN_CLOSE = "failed TIFFWriteCustomDirectory() of the Exif data"

#: the last 12 bytes of every complete PNG: the IEND chunk (length 0, type, CRC)
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def _oiio_errors(obj) -> str:
    """The pending error text of an OpenImageIO object (or the global one), on one line."""
    import OpenImageIO as oiio

    text = obj.geterror() if obj is not None else ""
    text = text or oiio.geterror()
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    if not lines:
        return "unknown error"
    return lines[0] + (f" (and {len(lines) - 1} more)" if len(lines) > 1 else "")


def _write_checked(oiio, path: Path, tmp: Path, spec, arr: np.ndarray) -> None:
    r"""Write ``arr`` to the temporary ``tmp`` through OpenImageIO, checking every step.

    OpenImageIO's writers report a short write (a full disk, a quota) only through
    ``has_error``/``geterror()``, with ``write_image`` and ``close`` still returning
    success, and its JPEG writer's library ends the process on one ("Output file
    write error --- out of disk space?", leaving the temporaries behind). So the
    image is made in memory (a memory file, where the system has them), checked
    there (:func:`_check_encoded`), and its bytes written to ``tmp`` by Python,
    whose errors are caught, and synced. OpenImageIO is then never given the
    output's name either: one that is not UTF-8 (``caf\xe9.png``) it refused with
    an internal error.
    """
    ext = path.suffix.lower()
    memory = _memory_file()
    if memory is None:  # (no memory files: written and checked in place, as before)
        _encode(oiio, path, str(tmp), ext, spec, arr)
        _sync(path, tmp)
        _check_encoded(oiio, path, str(tmp), ext, arr.shape)
        return
    try:
        where = f"/proc/self/fd/{memory}"
        if ext in (".jpg", ".jpeg"):
            _encode_through_pipe(oiio, path, ext, spec, arr, memory)
        else:
            _encode(oiio, path, where, ext, spec, arr)
        _check_encoded(oiio, path, where, ext, arr.shape)
        try:
            with open(tmp, "wb") as fh:
                size = _copy_file(memory, fh.fileno())
                os.fsync(fh.fileno())
            if os.stat(tmp).st_size != size:
                raise OSError(0, "the file written is cut short")
        except OSError as exc:
            raise VolwarpError(f"{path}: cannot write image ({exc.strerror or exc})") from exc
    finally:
        os.close(memory)


def _copy_file(source: int, target: int) -> int:
    """Copy the whole file ``source`` (a descriptor) to ``target``'s; the bytes copied.

    By the kernel where it can (no copy of the image in this process's memory).
    """
    size = os.fstat(source).st_size
    done = 0
    try:
        while done < size:
            sent = os.sendfile(target, source, done, size - done)
            if sent == 0:
                raise OSError(0, "the file written is cut short")
            done += sent
        return done
    except OSError as exc:
        if done or exc.errno not in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
            raise
    os.lseek(source, 0, os.SEEK_SET)  # (no sendfile between these: by pieces)
    while chunk := os.read(source, 1 << 20):
        view = memoryview(chunk)
        while view:
            view = view[os.write(target, view):]
        done += len(chunk)
    return done


def _encode_through_pipe(oiio, path: Path, ext: str, spec, arr: np.ndarray, memory: int) -> None:
    """Make a JPEG through a pipe into the memory file ``memory``.

    A JPEG is written in one pass, so a pipe takes it, and a pipe has no file
    size limit: a memory file counts against ``ulimit -f``, and the JPEG
    library ends the process on a short write. A thread moves the bytes from
    the pipe to the memory file; a write it cannot make (``File too large``) is
    said once the image is done, and it reads on to the end whatever happens,
    so the writer never waits on a full pipe.
    """
    read_end, write_end = os.pipe()
    failed: list[BaseException] = []
    buffer = bytearray(1 << 16)  # (read into, allocated once: a read allocates nothing)

    def drain():
        # (the writer opens the pipe by its /proc name for reading and writing: it is a
        # reader of its own pipe, so a full pipe blocks it for ever, whatever this end
        # does; this thread reads on to the end, whatever fails)
        view = memoryview(buffer)
        while True:
            try:
                n = os.readv(read_end, [buffer])
            except InterruptedError:
                continue
            except BaseException as exc:  # pragma: no cover - a pipe that cannot be read
                failed.append(exc)
                time.sleep(0.01)
                continue
            if n == 0:
                return
            if failed:
                continue  # (read on to the end, keeping nothing)
            try:
                done = 0
                while done < n:
                    done += os.write(memory, view[done:n])
            except BaseException as exc:
                failed.append(exc)

    reader = threading.Thread(target=drain, name="volwarp-image-pipe", daemon=True)
    reader.start()
    try:
        _encode(oiio, path, f"/proc/self/fd/{write_end}", ext, spec, arr)
    except VolwarpError:
        if not failed:
            raise
    finally:
        os.close(write_end)  # (the writer's own end closed by now: the reader sees the end)
        reader.join()
        os.close(read_end)
    if failed:
        exc = failed[0]
        raise VolwarpError(f"{path}: cannot write image "
                           f"({getattr(exc, 'strerror', None) or exc})") from exc


def _memory_file() -> int | None:
    """A file in memory that OpenImageIO can open by name (``/proc/self/fd/N``), or None."""
    if not hasattr(os, "memfd_create") or not os.path.isdir("/proc/self/fd"):
        return None
    try:
        return os.memfd_create("volwarp-image", os.MFD_CLOEXEC)
    except OSError:
        return None


def _encode(oiio, path: Path, target: str, ext: str, spec, arr: np.ndarray) -> None:
    """Write ``arr`` to the file ``target`` in the format of ``ext``, every step's result checked."""
    oiio.geterror()  # drop any stale global error text
    out = oiio.ImageOutput.create(ext.lstrip("."))  # (by the format's name: target has none)
    if out is None:
        raise VolwarpError(f"{path}: no image writer for {ext!r} ({_oiio_errors(None)})")
    closed = False
    try:
        if not out.open(target, spec):
            raise VolwarpError(f"{path}: cannot write image ({_oiio_errors(out)})")
        ok = out.write_image(arr)
        if not ok or out.has_error:
            raise VolwarpError(f"{path}: cannot write image ({_oiio_errors(out)})")
        closed = True
        ok = out.close()
        if not ok:
            raise VolwarpError(f"{path}: cannot write image ({_oiio_errors(out)})")
        if out.has_error:
            text = out.geterror()
            lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
            # OpenImageIO's TIFF writer reports this on every close (its Exif directory),
            # with the image complete: the read-back checks it
            if not all(_BENIGN_CLOSE in ln for ln in lines):
                raise VolwarpError(f"{path}: cannot write image ({lines[0] if lines else text})")
    finally:
        if not closed:
            out.close()
            out.geterror()  # consumed: nothing reported at exit


def _sync(path: Path, tmp: Path) -> None:
    try:
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        raise VolwarpError(f"{path}: cannot write image ({exc.strerror or exc})") from exc


def _check_encoded(oiio, path: Path, target: str, ext: str, shape) -> None:
    """The image written to ``target`` is whole: not empty, a PNG's end there, it reads back."""
    try:
        size = os.stat(target).st_size
    except OSError as exc:
        raise VolwarpError(f"{path}: cannot write image ({exc.strerror or exc})") from exc
    if size == 0:
        raise VolwarpError(f"{path}: cannot write image (the file written is empty)")
    if ext == ".png":
        with open(target, "rb") as fh:
            fh.seek(max(0, size - len(_PNG_END)))
            if fh.read() != _PNG_END:
                raise VolwarpError(f"{path}: cannot write image (the PNG written is cut "
                                   f"short at {size} bytes: is the disk full?)")
    _verify_readback(oiio, path, target, tuple(shape))


def _verify_readback(oiio, path: Path, tmp, shape: tuple[int, int, int]) -> None:
    """Re-open the written image: it must read in full, with the size written."""
    inp = oiio.ImageInput.open(str(tmp))
    if inp is None:
        raise VolwarpError(f"{path}: cannot write image (the file written does not read "
                           f"back: {_oiio_errors(None)})")
    try:
        s = inp.spec()
        got = (s.height, s.width, s.nchannels)
        pixels = inp.read_image(0, 0, 0, s.nchannels, oiio.UINT8)
        bad = pixels is None or inp.has_error
        why = _oiio_errors(inp) if bad else ""
    finally:
        inp.close()
        inp.geterror()
    if bad:
        raise VolwarpError(f"{path}: cannot write image (the file written does not read "
                           f"back: {why})")
    if got != shape:
        raise VolwarpError(f"{path}: cannot write image (it reads back as {got[1]}x{got[0]} "
                           f"with {got[2]} channels, not {shape[1]}x{shape[0]} with "
                           f"{shape[2]})")
