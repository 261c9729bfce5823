"""Whether an integer volume looks like a label map (a segmentation).

Two answers with one rule. :func:`label_map_hint`, ``info``'s hint: an
integer volume with 2 to :data:`HINT_MAX_LABELS` distinct values that is
piecewise constant (at least :data:`HINT_MIN_EQUAL` of the pairs of x
neighbours that are not both 0 are equal: a scan with few grey levels varies
from voxel to voxel, a segmentation does not). :func:`looks_like_labels`,
the choice of a pyramid's downsampling (mode or mean), which also takes maps
with more labels (see there), which also has a form that reads a sliceable
source box by box and gives the whole array's answer (outputs written by
blocks).

Core code (numpy only): the writers of :mod:`volwarp_cli.io` (pyramids) and
``info`` use it.
"""

from __future__ import annotations

import numpy as np

#: ``info``'s label-map hint: an integer volume with at most this many distinct values...
HINT_MAX_LABELS = 256
#: ...where at least this share of the x-neighbour pairs that are not both 0 are equal
#: (piecewise constant: a label map; the bundled scans have 0.03 and 0.12, their
#: binary ball 0.86).
HINT_MIN_EQUAL = 0.5


def label_map_hint(data: np.ndarray) -> dict | None:
    """``{"labels": n, "values": [...]}`` when an integer volume looks like a label map.

    An integer dtype, 2 to :data:`HINT_MAX_LABELS` distinct values, and
    piecewise constant (module notes). None otherwise (the values: the first 16).
    """
    data = np.asarray(data)
    if np.dtype(data.dtype).kind not in "iu" or data.size == 0:
        return None
    values, _ = value_counts(data)
    return _hint(values, data.shape, lambda z: data[z])


def looks_like_labels(data: np.ndarray) -> bool:
    """Whether ``labels="auto"`` takes ``data`` for a label map (its levels: the mode).

    Up to :data:`HINT_MAX_LABELS` (256) distinct
    values this is ``info``'s hint, :func:`label_map_hint`:
    an integer volume with 2 to 256 values, piecewise constant (at least
    :data:`HINT_MIN_EQUAL` of the pairs of x
    neighbours that are not both 0 are equal). Above 256 values that cap alone
    made every parcellation or instance segmentation with more labels
    averaged, and the mean invents labels: between 10 and 30 lies 20, another
    structure's id. So above 256 values an integer volume is a label map too
    when it is piecewise constant, with the pairs that are both 0 *or both
    its most frequent value* left out of the share. That second exclusion is
    what keeps scans out: a CT clipped at -1024 HU has a large constant
    background that is not 0 and would pass the test on its own, while its
    body, which the test then sees alone, varies from voxel to voxel. Why
    lean towards the mode at all: the two mistakes are not alike. The mode of
    an intensity image still gives each coarse voxel one of its block's own
    values (a blockier preview); the mean of a segmentation writes ids that
    are not there. Other cases a caller knows better (``--pyramid-method``).

    Cost: as the hint's, one pass to count the distinct values (a count table
    for ranges under 2**24, else a sort; the most frequent value comes with
    it) and about 64 planes for the neighbour pairs; no cap on the number of
    values is needed for speed.
    """
    data = np.asarray(data)
    if np.dtype(data.dtype).kind not in "iu" or data.size == 0:
        return False
    values, counts = value_counts(data)
    return _labels(values, counts, data.shape, lambda z: data[z])


def looks_like_labels_by_blocks(source, boxes) -> bool:
    """:func:`looks_like_labels` of a sliceable ``source`` read box by box (``boxes`` tile it).

    The same answer without holding more than a box and a plane (for outputs
    written by blocks): the value counts are merged over the boxes.
    """
    shape = tuple(source.shape)
    if np.dtype(source.dtype).kind not in "iu" or 0 in shape:
        return False
    parts = [value_counts(np.asarray(source[box.slices])) for box in boxes]
    values, inverse = np.unique(np.concatenate([v for v, _ in parts]), return_inverse=True)
    counts = np.bincount(inverse, weights=np.concatenate([c for _, c in parts]),
                         minlength=len(values)).astype(np.int64)
    return _labels(values, counts, shape, lambda z: np.asarray(source[z]))


#: Voxels of one box of :func:`scan_labels` (its counting takes about 10 bytes a voxel).
SCAN_BOX_VOXELS = 1 << 22


def scan_boxes(shape, box_voxels: int = SCAN_BOX_VOXELS):
    """Boxes of whole rows, planes where they fit, of about ``box_voxels`` at most, tiling ``shape``."""
    from .box import Box

    nz, ny, nx = (int(n) for n in shape)
    plane = max(1, ny * nx)
    if plane <= box_voxels:
        chunk = (max(1, min(nz, box_voxels // plane)), ny, nx)
    else:
        chunk = (1, max(1, min(ny, box_voxels // max(1, nx))), nx)
    return Box.from_shape(shape).blocks(chunk)


class _Counted:
    """A sliceable source that keeps the value counts of the boxes read through it.

    :func:`looks_like_labels_by_blocks` reads every box once; counting them
    as they pass gives the distinct values without a second read.
    """

    def __init__(self, source):
        self.source = source
        self.shape = tuple(int(n) for n in source.shape)
        self.dtype = np.dtype(source.dtype)
        self.parts: list = []
        self.voxels = 0

    def __getitem__(self, key):
        block = np.asarray(self.source[key])
        if isinstance(key, tuple) and block.ndim == 3 and block.size:
            self.parts.append(value_counts(block))
            self.voxels += block.size
        return block


def scan_labels(source, *, detect: bool = True, box_voxels: int = SCAN_BOX_VOXELS):
    """``(looks like labels, distinct values, their counts)`` of ``source``, read once by boxes.

    What the commands that follow the rule need before any work (``warp``'s
    and ``distance``'s choice, a label's presence, the count for ``-v``), in
    memory as by blocks: ``source`` is an array or a sliceable lazy source,
    read box by box (:func:`scan_boxes`), so the answer is the same either
    way. ``detect=False`` only counts. Samples that are not integers (or
    bool) are not read: ``(False, None, None)``.
    """
    shape = tuple(int(n) for n in source.shape)
    if np.dtype(source.dtype).kind not in "iub" or 0 in shape:
        return False, None, None
    boxes = scan_boxes(shape, box_voxels)
    counted = _Counted(source)
    looks = bool(looks_like_labels_by_blocks(counted, boxes)) if detect else False
    parts = counted.parts
    if counted.voxels != int(np.prod(shape)):  # (the rule read otherwise: count here)
        parts = [value_counts(np.asarray(source[box.slices])) for box in boxes]
    values, inverse = np.unique(np.concatenate([v for v, _ in parts]), return_inverse=True)
    counts = np.bincount(inverse, weights=np.concatenate([c for _, c in parts]),
                         minlength=len(values)).astype(np.int64)
    return looks, values.astype(np.int64), counts


def value_counts(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sorted distinct values of an integer array (int64) and how often each occurs.

    A count table where the range of values is small (at most 65536, or four
    times the samples, and under 2**24), else a sort: a box of a map with a
    few labels spread over a wide range makes no table of the range's size.
    """
    lo, hi = int(data.min()), int(data.max())
    span = hi - lo + 1
    if span < 1 << 24 and span <= max(1 << 16, 4 * data.size):
        # shifted in intp: in the array's own type 100 - (-100) wraps (int8)
        table = np.bincount(data.ravel().astype(np.intp) - lo, minlength=hi - lo + 1)
        where = np.flatnonzero(table)
        return (where + lo).astype(np.int64), table[where].astype(np.int64)
    values, counts = np.unique(data, return_counts=True)
    return values.astype(np.int64), counts.astype(np.int64)


def _hint(values, shape, plane) -> dict | None:
    """The hint from the distinct ``values`` and the planes ``plane(z)`` (module notes)."""
    if not 2 <= len(values) <= HINT_MAX_LABELS or not _piecewise_constant(shape, plane):
        return None
    return {"labels": int(len(values)), "values": [int(v) for v in values[:16]]}


def _labels(values, counts, shape, plane) -> bool:
    """:func:`looks_like_labels` from the value counts and the planes ``plane(z)``."""
    if len(values) < 2:
        return False
    common = values[int(np.argmax(counts))] if len(values) > HINT_MAX_LABELS else None
    return _piecewise_constant(shape, plane, also_skip=common)


def _piecewise_constant(shape, plane, also_skip=None) -> bool:
    """At least :data:`HINT_MIN_EQUAL` of the x-neighbour pairs are equal, on about 64 planes.

    Pairs that are both 0 (or both ``also_skip``) are left out.
    """
    if shape[-1] <= 1:
        return True
    n = equal = 0
    for z in range(0, shape[0], max(1, shape[0] // 64)):  # about 64 planes are enough
        p = plane(z)
        a, b = p[:, :-1], p[:, 1:]
        some = (a != 0) | (b != 0)
        if also_skip is not None:
            some &= (a != also_skip) | (b != also_skip)
        n += int(some.sum())
        equal += int((some & (a == b)).sum())
    return not (n and equal < HINT_MIN_EQUAL * n)
