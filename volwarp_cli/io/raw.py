"""Headerless raw volumes: samples only, x fastest, geometry given by the user."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError, VolwarpError
from ..geometry import check_placement
from ..memory import ensure_fits_in_memory
from ..samples import check_dtype, voxel_count
from ..volume import Volume, xyz_to_zyx, zyx_to_xyz
from .atomic import atomic_output
from .common import (
    make_volume,
    native,
    read_exact,
    write_samples,
)


@dataclass(frozen=True)
class RawLayout:
    """How to read a headerless file: sizes (x, y, z), sample type, byte order, geometry."""

    shape: tuple[int, int, int]
    dtype: str
    endian: str = "little"
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    header_bytes: int = 0


def read_raw(path: str | os.PathLike, layout: RawLayout | None) -> Volume:
    """Read a headerless file as ``layout`` describes it (a VolwarpError without one)."""
    where = str(path)
    if layout is None:
        raise VolwarpError(f"{where}: a raw file needs --raw-shape and --raw-dtype "
                           "(or a detached .nhdr header pointing at it)")
    dtype = check_dtype(layout.dtype, where)
    if any(int(s) <= 0 for s in layout.shape):
        raise VolwarpError(f"{where}: --raw-shape must be positive, got {layout.shape}")
    if layout.header_bytes < 0:
        raise VolwarpError(f"{where}: --raw-header-bytes must not be negative")
    count = voxel_count(layout.shape)
    nbytes = count * dtype.itemsize
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise FormatError(f"{where}: cannot open ({exc.strerror})") from None
    expected = nbytes + layout.header_bytes
    if size != expected:
        raise FormatError(
            f"{where}: file is {size} bytes but {'x'.join(map(str, layout.shape))} {dtype.name}"
            f"{f' after {layout.header_bytes} header bytes' if layout.header_bytes else ''}"
            f" needs {expected} bytes")
    ensure_fits_in_memory(nbytes, where)
    file_dtype = dtype.newbyteorder("<" if layout.endian == "little" else ">")
    with open(path, "rb") as fh:
        fh.seek(layout.header_bytes)
        buf = read_exact(fh, nbytes, where)
    data = np.frombuffer(buf, dtype=file_dtype).reshape(xyz_to_zyx(layout.shape))
    return make_volume(where, native(data), error=VolwarpError,
                       **raw_placement(layout, where, data.shape))


def raw_placement(layout: RawLayout, where: str, shape_zyx) -> dict:
    """The spacing and origin a raw file's options give, checked (naming the option).

    The geometry comes from the command line: a bad one is not the file's
    fault, hence a VolwarpError rather than a FormatError (exit 1 both).
    """
    spacing, origin, _ = check_placement(
        layout.spacing, layout.origin, np.eye(3), zyx_to_xyz(shape_zyx), where=where,
        fields={"spacing": "--raw-spacing", "origin": "--raw-origin"}, error=VolwarpError)
    return {"spacing": spacing, "origin": origin}


def write_raw(vol: Volume, path: str | os.PathLike, *, byte_order: str = "little",
              dtype=None) -> None:
    """Write the samples only (x fastest). Geometry is not stored: use .nhdr to keep it.

    ``dtype``: the samples cast to it as they are written, by slabs.
    """
    check_dtype(vol.data.dtype if dtype is None else dtype, str(path))
    with atomic_output(Path(path)) as tmp:
        with open(tmp, "wb") as fh:
            write_samples(fh, vol.data, byte_order, dtype, what=str(path))
