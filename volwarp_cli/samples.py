"""Sample types, counts and casting: what a volume's samples may be, and converting them.

Shared by the readers and writers (``io/``) and by the numeric core (a warp or
a morph frame cast back to the input's type), so it lives in neither.
"""

from __future__ import annotations

import numpy as np

from .errors import FormatError, VolwarpError

#: The sample types volwarp reads and writes unchanged.
SUPPORTED_DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")


def check_dtype(dtype, where: str = "") -> np.dtype:
    """Return the native-order dtype for a supported sample type, else raise."""
    dt = np.dtype(dtype)
    native = dt.newbyteorder("=")
    if native.name not in SUPPORTED_DTYPES:
        prefix = f"{where}: " if where else ""
        raise FormatError(f"{prefix}unsupported sample type {dt.name!r} "
                          f"(supported: {', '.join(SUPPORTED_DTYPES)})")
    return native


#: the most samples a volume may have along an axis (2^31: beyond it no memory or disk
#: holds a volume, and numpy may not even make its shape)
MAX_AXIS = 1 << 31


def voxel_count(shape) -> int:
    """The number of samples of a grid of ``shape`` (any axis order), as a Python int.

    A Python int does not overflow, as a product of a header's sizes in int64
    could (``np.prod``) before the memory check sees it.
    """
    n = 1
    for s in shape:
        n *= int(s)
    return n


def _float_bounds(ftype, info) -> tuple:
    """The smallest and largest floats of ``ftype`` inside an integer type's range ``info``."""
    ftype = np.dtype(ftype).type
    lo, hi = ftype(info.min), ftype(info.max)
    if float(lo) < info.min:
        lo = np.nextafter(lo, ftype(0))
    if float(hi) > info.max:
        hi = np.nextafter(hi, ftype(0))
    return lo, hi


def cast_samples(data: np.ndarray, dtype, *, what: str = "volume") -> np.ndarray:
    """Convert samples to ``dtype``: integers are rounded and clipped to the type's range.

    NaN cannot be stored in an integer type and is refused rather than
    silently turned into 0.
    """
    dt = check_dtype(dtype)
    if data.dtype == dt:
        return data
    if dt.kind in "iu":
        if data.dtype.kind == "f":
            if np.isnan(data).any():
                raise VolwarpError(f"{what} contains NaN, which {dt.name} cannot hold")
            info = np.iinfo(dt)
            out = np.rint(data)
            lo, hi = _float_bounds(out.dtype, info)
            if float(lo) == info.min and float(hi) == info.max:  # (the range exact here)
                np.clip(out, lo, hi, out=out)
                return out.astype(dt)
            # the type's range is not exact in these floats (int32 from float32: its max
            # rounds up to 2**31, which wrapped to -2**31): clipped inside it, then the ends
            over, under = out > hi, out < lo
            np.clip(out, lo, hi, out=out)
            res = out.astype(dt)
            res[over], res[under] = info.max, info.min
            return res
        info = np.iinfo(dt)
        src = np.iinfo(data.dtype)
        if src.min >= info.min and src.max <= info.max:
            return data.astype(dt)
        return np.clip(data, max(info.min, src.min), min(info.max, src.max)).astype(dt)
    return data.astype(dt)
