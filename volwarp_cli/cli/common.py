"""Small helpers the subcommands share: loading inputs, describing volumes."""

from __future__ import annotations

import click
import numpy as np

from ..io import read_volume
from ..progress import timed
from ..provenance import PROVENANCE_KEYS, provenance, stamp  # noqa: F401  (the commands')
from ..volume import Volume


def load_input(path, raw=None, volume_index=None, mmap=False, dicom=None) -> Volume:
    """Read a command's input; options that do not apply to its format are usage errors.

    A file with a header describes itself: the options would be ignored.
    """
    check_input_options(path, raw, dicom)
    with timed(f"read {path}"):
        return read_volume(path, raw=raw, volume_index=volume_index, mmap=mmap, dicom=dicom)


def check_input_options(path, raw=None, dicom=None) -> None:
    """Usage errors for ``--raw-*`` or DICOM options given for an input of another format.

    (:func:`volwarp_cli.io.check_read_options`, as click's usage errors.)
    """
    from ..errors import BadUsage
    from ..io import check_read_options

    try:
        check_read_options(path, raw, dicom)
    except BadUsage as exc:
        raise click.UsageError(str(exc)) from None


def describe_volume(vol: Volume, fmt: str) -> dict:
    """The stable ``volwarp info --json`` description of a volume.

    min, max and mean are those of the finite samples; ``nonfinite`` (only
    when there are any) counts the NaN and infinite ones, so the JSON stays
    strict (no NaN or Infinity tokens).
    """
    import itertools
    import math

    def mean_of(a, lo, hi) -> float:
        """The float64 mean of finite ``a`` (min ``lo``, max ``hi``), without overflow.

        The plain float64 mean is kept whenever its sum stays finite (every integer
        volume, every float32 one: the result is what it has always been); only a
        float64 sum beyond 1.8e308 (finite samples near the largest double) is
        redone on the samples scaled by a power of two (exact) below 1 in
        magnitude, summed exactly (``math.fsum``) block by block.
        """
        with np.errstate(over="ignore", invalid="ignore"):
            m = float(a.mean(dtype=np.float64))
        if math.isfinite(m):
            return m
        e = math.frexp(max(abs(float(lo)), abs(float(hi))))[1]
        inv = math.ldexp(1.0, -e)  # |a * inv| < 1, exactly a power-of-two scaling
        flat = a.reshape(-1)
        block = 1 << 20
        scaled = itertools.chain.from_iterable(
            (flat[k:k + block].astype(np.float64) * inv).tolist()
            for k in range(0, flat.size, block))
        ms = math.fsum(scaled) / flat.size  # the exact sum, rounded once
        ms = min(max(ms, float(lo) * inv), float(hi) * inv)  # rounding stays in range
        return math.ldexp(ms, e)

    data = vol.data
    nonfinite = 0
    if data.size:
        lo = data.min()
        hi = data.max()
        if not (np.isfinite(lo) and np.isfinite(hi)):  # NaN or inf: describe the rest
            finite = data[np.isfinite(data)]
            nonfinite = data.size - finite.size
            lo, hi = (finite.min(), finite.max()) if finite.size else (None, None)
            mean = mean_of(finite, lo, hi) if finite.size else None
        else:
            mean = mean_of(data, lo, hi)
    else:  # pragma: no cover - volumes always have samples
        lo = hi = mean = None
    def num(v):
        if v is None:
            return None
        return int(v) if np.issubdtype(type(v), np.integer) else float(v)
    extra = {"nonfinite": nonfinite} if nonfinite else {}
    return {
        "format": fmt,
        "shape": list(vol.shape_xyz),
        "dtype": data.dtype.name,
        "spacing": [float(v) for v in vol.spacing],
        "origin": [float(v) for v in vol.origin],
        "direction": [[float(v) for v in row] for row in vol.direction],
        "space": vol.space,
        "file_space": vol.file_space,
        "min": num(lo),
        "max": num(hi),
        "mean": mean,
        "meta": {str(k): str(v) for k, v in sorted(vol.meta.items())},
        **extra,
    }
