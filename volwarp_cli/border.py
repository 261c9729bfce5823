"""What surrounds a volume's anatomy: the samples of its six faces.

Their lower median is a scan's background value (what a warp writes where
nothing of the model lands), their most frequent label a label map's
background label. Only the faces are read, so a lazy source does.
"""

from __future__ import annotations

import numpy as np


def border_samples(source) -> np.ndarray:
    """The samples of the six faces of ``source`` (``[z, y, x]``), one flat array.

    A voxel on an edge comes once per face it lies on.
    """
    nz, ny, nx = (int(n) for n in source.shape)
    if 0 in (nz, ny, nx):
        return np.zeros(0, dtype=source.dtype)
    faces = [source[0:1], source[nz - 1:nz], source[:, 0:1], source[:, ny - 1:ny],
             source[:, :, 0:1], source[:, :, nx - 1:nx]]
    return np.concatenate([np.asarray(f).ravel() for f in faces])


def border_value(source) -> float:
    """The lower median of the samples on the six faces of ``source`` (``[z, y, x]``), no NaN.

    Why: it is what a scan has outside its anatomy, so it is what a warp
    writes where nothing of the model lands (0 there would be water in a
    CT). Why the median and not the most frequent value (the rule before):
    where one value covers more than half of the border (-1024 HU of a CT's
    padding, an MRI's 0) the two are that value, but the mode of a float
    field or a noisy border is a coincidence. A distance field's border mode
    was -2e-06, a value inside the shape (its faces hold thousands of
    distinct distances, one of them twice): the grown margin of its warp
    became inside (614,588 voxels); a 16x16x5 CT with a noisy air border got
    -7, which 13 of its 832 border samples had. The median of a distance
    field's border is a distance outside the shape (positive), and that of
    a noisy air border is air. The lower median is a sample of the border
    (never a mean of two): an integer scan gets one of its own values.

    ``source``: an array or a sliceable lazy source (only its faces are
    read). A voxel on an edge counts once per face it lies on. NaN only
    when every border sample is NaN.
    """
    return lower_median(border_samples(source))


def lower_median(samples: np.ndarray) -> float:
    """:func:`border_value` of the faces' samples already read (:func:`border_samples`' array)."""
    if samples.dtype.kind == "f":
        samples = samples[~np.isnan(samples)]
        if not samples.size:
            return float("nan")
    if not samples.size:
        return 0.0
    k = (samples.size - 1) // 2
    return float(np.partition(samples, k)[k])


def border_label(source) -> int:
    """The most frequent label on the six faces of the label map ``source``: its background.

    Where nothing of the model lands a label warp writes this label (0 in
    the usual map; a map whose ids are 1 to 4 with 1 around the anatomy
    gained 1,093 voxels of an id 0 it does not have). The mode, not the
    median: labels are names, and the background is the one that surrounds
    the map. A voxel on an edge counts once per face it lies on; a tie goes
    to the smallest label. ``source``: integer (or integer-valued) samples,
    an array or a sliceable lazy source (only its faces are read).
    """
    from .labelmap import integer_samples, value_counts

    samples = border_samples(source)
    if not samples.size:
        return 0
    if integer_samples(samples) is None:
        raise not_ids("the label map", samples.dtype)
    values, counts = value_counts(samples)
    return int(values[int(np.argmax(counts))])  # (sorted: the first maximum is the smallest)


def not_ids(name: str, dtype) -> Exception:
    """The error for float samples taken as labels that are not all integers (raise it).

    A usage error (exit 2): labels were asked for (the rule never takes such
    samples for a label map).
    """
    from .errors import BadUsage

    return BadUsage(f"{name}: a label map needs integer ids, and its {np.dtype(dtype)} "
                        "samples are not all integers (a fraction, a NaN or an infinity): "
                        "warp it as intensities (--values intensity)")
