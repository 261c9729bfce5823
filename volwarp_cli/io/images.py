"""2-D images (PNG, TIFF, EXR, JPEG, ...) through OpenImageIO.

Arrays are ``[row, column, channel]`` with row 0 at the top of the picture.
OpenImageIO silently writes garbage for a 2-D array, so one-channel images
are always passed to it as ``(H, W, 1)``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import FormatError, VolwarpError
from .atomic import atomic_output

_OIIO_TYPES = {"uint8": "UINT8", "uint16": "UINT16", "float32": "FLOAT", "float16": "HALF"}


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
    if not normalize:
        return arr
    if arr.dtype.kind in "ui":
        return (arr.astype(np.float32) / np.float32(np.iinfo(arr.dtype).max))
    return arr.astype(np.float32)


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
    with atomic_output(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise VolwarpError(f"{path}: no image writer for {ext!r} ({oiio.geterror().strip()})")
        try:
            if not out.open(str(tmp), spec) or not out.write_image(arr):
                raise VolwarpError(f"{path}: cannot write image ({out.geterror().strip()})")
        finally:
            out.close()
