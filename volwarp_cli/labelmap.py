"""Whether a volume looks like a label map (a segmentation): the one rule.

``warp``, ``distance`` and ``morph`` follow it by default, pyramids take
their levels' mode by it, ``info`` hints it. Three functions give its answer:
:func:`looks_like_labels` (an array), :func:`looks_like_labels_by_blocks` (a
sliceable source read box by box: the same answer, for outputs written by
blocks) and :func:`scan_labels` (the answer and the distinct values, what
the commands need); :func:`label_map_hint` is ``info``'s form (its count
of values and the first 16, whatever their number: the commands' answer).

**Candidates.** Integer samples, and float samples whose values are all
finite integers within the type's exact range (2**24 for float32): nibabel's
``get_fdata`` and MONAI write segmentations as float32/float64 with integer
ids, and an intensity warp of those wrote 138,582 distinct values. Floats
with any fraction (a distance field, a resampled scan) are not read further
than the first box that has one.

**The rule.** A candidate with at least 2 distinct values is a label map
when both hold, on about :data:`SAMPLED_PLANES` sampled planes ``z``, each
with its next plane ``z + 1``:

1. *Piecewise constant where it is not background*: at least
   :data:`MIN_EQUAL_PAIRS` of the neighbour pairs (along x, y and z) whose
   two voxels are both neither 0 nor the most frequent value are equal.
   Leaving out every pair that touches 0 or the mode (not only the pairs
   that are both 0, as before) is what lets small structures in: 20
   landmarks of 2x2x2 voxels in a large 0 background scored 0.34 when a
   landmark/0 pair counted as unequal, and 1.00 now; leaving out the mode
   is what keeps a CT clipped at -1024 HU out, its air pairs all equal
   (0.66 with them, 0.01 without).
2. *Its values occupy regions*: at least :data:`MIN_IN_REGIONS` of the
   sampled voxels whose value is not one of the two most frequent ones
   have a neighbour (x +-1, y +-1, z + 1) of their own value. A label map's
   smaller labels are regions too (0.97 to 1.00 of their voxels); an
   antialiased (smooth-edged) density is two dominant values, background and
   plateau, and intermediate values that live only on a 1-voxel shell
   between them, each voxel with its own blend (0.15 to 0.22). Test 1 alone
   takes such a density for labels: its plateau's pairs are equal (0.75 to
   0.86). With two values only, nothing is left for this test: every
   2-valued candidate is a label map (a mask: an intensity warp would blend
   it into values it does not have).
3. *Its values jump, they do not step through levels*: with
   :data:`MIN_GRADED_VALUES` values or more, fewer than :data:`MIN_GRADED`
   graded crossings per voxel of those values, on the plane after each
   sampled one: a voxel whose two neighbours along an axis (x, y, or the
   planes before and after) both differ from it, one lower and one higher
   (each axis counts, so a voxel gives up to 3). A density aligned with the
   axes passes tests 1 and 2 (each level of a smooth ramp is a flat region
   one voxel thick: the tree-wind example's leaf map, the clay block warped
   as intensities, an integer-rounded distance field) and was taken for
   labels; its levels lie between their neighbours' (0.6 to 1.6). The ids of
   a label map of many labels do so only where a region one voxel thick lies
   between a lower and a higher id (0.00 to 0.16); a few ordered labels in
   thin layers do so as often as a density (a head's scalp, skull and CSF
   at 3 mm 0.35, a shell one voxel thick 0.75, Otsu's 7 classes 0.28 to
   0.68), so the test is for what has levels to step through.

Measured (``S``: test 1; ``R``: test 2; ``before``: the rule before, the
share of equal x pairs that are not both 0, at least 0.5, with the mode's
pairs left out too above 256 values; ``*``: it gave the wrong answer;
``(3)``: by test 3, below):

=========================================  ======  =====  =====  ======
data                                       before  S      R      labels
=========================================  ======  =====  =====  ======
colin27 brain (uint8, bundled)             0.12    0.12   0.40   no
T1 head (int16, bundled)                   0.03    0.03   0.14   no
block_int16_aniso (a ramp, bundled)        0.00    0.00   0.00   no
nibabel anatomical.nii                     0.00    0.00   0.00   no
nibabel example4d (volume 0)               0.01    0.01   0.05   no
nibabel example_nifti2 (volume 0)          0.01    0.01   0.06   no
nibabel example4d+orig BRIK (volume 0)     0.00    0.00   0.01   no
pydicom CT_small                           0.02    0.02   0.06   no
pydicom MR_small                           0.01    0.01   0.04   no
pydicom emri_small                         0.02    0.01   0.07   no
CT_small in HU, -1024 outside its FOV      0.31    0.02   0.06   no
CT, -1024 air around a noisy body          0.66    0.01   0.04   no
that CT windowed to [-160, 240] (clipped)  0.73*   0.05   0.05   no
  the same as float64                      (no)    0.05   0.05   no
Gaussian-smoothed mask (uint8)             0.11    0.12   0.19   no
antialiased warped ball (132 values)       0.75*   0.86   0.21   no
supersampled ball x3 (16 values)           0.65*   0.75   0.22   no
supersampled ball x4 (57 values)           0.79*   0.85   0.15   no
frog-like map warped as intensity          0.38    0.45   0.56   no
k-means map, wide ids, warped as intensity 0.23    0.23   0.20   no
Voronoi atlas warped as intensity          0.35    0.37   0.54   no
landmarks warped as intensity              0.01    0.09   0.28   no
k-means (4 labels) of the bundled T1       0.63    0.71   0.97   yes
  its ids permuted (uint16, up to 60000)   0.63    0.71   0.97   yes
  its ids 1-4, 1 the background (no 0)     0.91    0.71   0.97   yes
  as float32                               (no)*   0.71   0.97   yes
343 blocks (int16)                         0.85    0.85   1.00   yes
Voronoi atlas (652 ids of 1000, int16)     0.73    0.77   1.00   yes
frog-like tissue map                       0.74    0.92   1.00   yes
20 landmarks of 2x2x2 (ids 10..200)        0.34*   1.00   1.00   yes
1-voxel-wide random walks (3 ids)          0.31*   0.94   0.99   yes
the bundled 0/200 ball                     0.86    1.00   --     yes
nibabel standard.nii.gz (random 0/255)     0.13    1.00   --     yes
integer-rounded distance field (35 values) 0.51    0.52   0.99   no (3)
=========================================  ======  =====  =====  ======

Test 3 (``G``), measured on the cases above that pass tests 1 and 2 and on
densities aligned with the axes (every scan above fails test 1 or 2; the
scans' own ``G`` is 0.0 to 2.7; ``n``: distinct values):

=========================================  ====  =====  =====  =====  ======
data                                       n     S      R      G      labels
=========================================  ====  =====  =====  =====  ======
tree-wind leaf map (smooth step)           256   0.81   0.77   0.81   no
clay block warped as intensity             124   0.59   0.85   1.55   no
a smooth ramp along x, 20 voxels wide      21    0.84   1.00   1.00   no
integer-rounded distance field             35    0.52   0.99   0.62   no
frog tissue map (bundled)                  26    0.98   1.00   0.01   yes
Voronoi atlas                              652   0.70   0.99   0.07   yes
343 blocks                                 343   0.85   1.00   0.00   yes
k-means (4 labels) of the bundled T1       4     0.71   0.97   0.14   yes
head at 3 mm: scalp, skull, CSF, brain     5     0.87   1.00   0.35   yes
a shell one voxel thick between 1 and 3    4     0.91   1.00   0.75   yes
Otsu's 7 classes of the bundled T1         7     0.53   0.90   0.41   yes
1-voxel-wide random walks (3 ids)          4     0.91   0.98   0.11   yes
=========================================  ====  =====  =====  =====  ======

Ambiguous by nature, and taken for labels: a density whose levels are
two voxels wide or more (a ramp of wide steps, a distance field rounded
on a fine grid, a scan upsampled by nearest neighbour: no level lies
between two others within one voxel), a density of fewer than 16 levels
(an antialiased box aligned with the axes: 5 values), and a random 0/255
pattern (two values). A distance field (float, not integers) and a float fMRI
volume are not candidates. Single-voxel landmarks are no regions: not a label
map (a sparse noise is no different). ``--values`` decides where the rule
cannot.

**Cost.** One pass over the samples to count the distinct values (a count
table for ranges under 2**24, else a sort; box by box, so that memory does
not grow with the volume) and about 3 x :data:`SAMPLED_PLANES` planes for
the neighbours; no cap on the number of values is needed for speed. The
value counts are merged over any boxes, and the planes are the same, so the
answer never depends on how the source was read.

Core code (numpy only): the writers of :mod:`volwarp_cli.io` (pyramids),
``warp``, ``distance`` and ``info`` use it.
"""

from __future__ import annotations

import math
import re

import numpy as np

#: ``--values`` of the commands that follow the rule (warp, distance): the samples taken as
#: intensities, or as label ids
VALUES = ("intensity", "labels")

#: the DICOM modalities whose samples are a label map by construction, as volwarp reads them
_SEGMENTATIONS = {"SEG": "a DICOM SEG", "RTSTRUCT": "a DICOM RTSTRUCT"}


#: a NIfTI's intent code for a label map (NIFTI_INTENT_LABEL)
NIFTI_INTENT_LABEL = 1002


#: the key/value a capture given ``--values`` records its choice in (a warp of the
#: capture, and of the outputs that keep its key/values, takes it, not the rule)
VALUES_KEY = "volwarp_values"


#: key prefixes that describe a label map's samples (a SEG's segments, an RTSTRUCT's ROIs)
_LABEL_KEY_PREFIXES = ("NIfTI_intent_", "DICOM_Segment", "DICOM_ROI_", "DICOM_Structure",
                       "DICOM_ContentLabel", "OME_image_label")
#: 3D Slicer's segmentation keys (a .seg.nrrd): ``Segment0_LabelValue``, ``Segmentation_...``
_SLICER_KEY = re.compile(r"Segment\d+_|Segmentation_")


def without_label_keys(meta) -> dict:
    """``meta`` without what says its samples are labels: for an output of other samples.

    A distance field, a warp's Jacobian or fields, a morph frame computed from a
    label map kept its NIfTI intent (label), a SEG's modality and segments and a
    capture's ``volwarp_values``: the next command took the field for labels
    (``apply`` resampled it by nearest neighbour, ``warp`` refused it, an
    OME-Zarr pyramid took the mode of distances) and viewers showed it as one.
    """
    out = {}
    for k, v in (meta or {}).items():
        if k.startswith(_LABEL_KEY_PREFIXES) or k == VALUES_KEY or _SLICER_KEY.match(k):
            continue
        if k == "DICOM_Modality" and str(v).strip().upper() in _SEGMENTATIONS:
            continue
        out[k] = v
    return out


def meta_as_taken(meta, labels: bool, against_rule: bool) -> dict:
    """An output's key/values saying what its samples are, as its command took the input's.

    Intensities made of a label map (``--values intensity``): without its label
    keys, which would call the blend a label map (the next command resampled
    it by nearest neighbour, or asked). A label map the user said is one
    ``against_rule`` (the option or the spec, of sparse ids the rule takes for
    intensities) whose file says nothing of it: the choice recorded
    (:data:`VALUES_KEY`), so that the next command takes the output for the
    label map it is instead of blending its ids (where the rule agrees, the
    output is the one the rule's choice writes, byte for byte); a record of
    intensities the input carried (a warp of a capture made ``--values
    intensity``) is replaced, whatever the rule says.
    """
    meta = dict(meta or {})
    if labels:
        if recorded_values(meta) == "intensity" or (against_rule
                                                    and segmentation_of(meta) is None):
            meta[VALUES_KEY] = "labels"
        return meta
    return without_label_keys(meta) if segmentation_of(meta) else meta


def recorded_values(meta) -> str | None:
    """The values choice ``meta`` records (:data:`VALUES_KEY`), or None."""
    value = str((meta or {}).get(VALUES_KEY, ""))
    return value if value in VALUES else None


def segmentation_of(meta) -> str | None:
    """What says a volume is a label map by its key/values (a DICOM SEG, ...), else None.

    A DICOM SEG or RTSTRUCT, a NIfTI whose intent is NIFTI_INTENT_LABEL, a 3D
    Slicer segmentation (``Segment0_LabelValue`` ...), an OME-Zarr labels image
    and a volume whose ``volwarp_values`` says labels (the file itself says it
    holds labels; a Slicer file of single-voxel fiducials was blended, and a
    pyramid of a warp's labels took the mean): such a volume is a label map
    whatever its samples look like. The rule below looks at its neighbours,
    and a SEG of single-voxel segments (or landmarks, or thin contours) fails
    its region test, so a warp blended its ids and ``convert --dtype uint8``
    merged ids 300 and 1000 into 255. The keys stay with the map through
    volwarp's outputs (a NRRD converted from a SEG).
    """
    meta = meta or {}
    modality = str(meta.get("DICOM_Modality", "")).strip().upper()
    if modality in _SEGMENTATIONS:
        return _SEGMENTATIONS[modality]
    if str(meta.get("NIfTI_intent_code", "")).strip() == str(NIFTI_INTENT_LABEL):
        return "a NIfTI label map (intent NIFTI_INTENT_LABEL)"
    if any(re.fullmatch(r"Segment\d+_LabelValue", str(k)) for k in meta):
        return "a 3D Slicer segmentation (its Segment keys)"
    if "OME_image_label" in meta:
        return "an OME-Zarr labels image (image-label)"
    if recorded_values(meta) == "labels":
        return "a label map by its record (volwarp_values)"
    return None


#: test 1: at least this share of the neighbour pairs that are both neither 0 nor the
#: mode are equal (scans 0.00 to 0.12, label maps 0.71 and more)
MIN_EQUAL_PAIRS = 0.5
#: test 2: at least this share of the voxels of values other than the two most frequent
#: have a neighbour of their own value (antialiased densities 0.15 to 0.22, label maps
#: 0.97 and more)
MIN_IN_REGIONS = 0.5
#: test 3: from this share of graded crossings among those voxels (each axis counted) on,
#: the values step through levels (a density), not jump between regions (a label map)
MIN_GRADED = 0.3
#: test 3 applies to candidates of at least this many values (thin layers of a few ordered
#: labels, nested shells, Otsu's classes, step through their neighbours too: 0.35 to 0.75)
MIN_GRADED_VALUES = 16
#: about this many planes are sampled for the neighbour tests (each with its next plane)
SAMPLED_PLANES = 64


def refuse_merged_ids(ids, dtype, name: str, option: str = "--dtype") -> None:
    """A :class:`~volwarp_cli.errors.BadUsage` where ``dtype`` cannot hold every id of ``ids``.

    A label map's ids are never merged: the clipping that ``--dtype`` gives
    intensities would turn ids 300 and 1000 into one id 255 of uint8 (and a
    float32 holds integers exactly up to 2**24 only).
    """
    from .errors import BadUsage

    dt = np.dtype(dtype)
    ids = np.asarray(ids)
    if dt.kind in "iu":
        info = np.iinfo(dt)
        lost = ids[(ids < info.min) | (ids > info.max)]
    else:  # (exactly: 4000000000 is a float32, 4000000001 is not; inf and 1e300 neither)
        big = ids[~(np.abs(ids) <= 2.0 ** (np.finfo(dt).nmant + 1))]
        with np.errstate(over="ignore"):
            lost = big[[not math.isfinite(v) or float(dt.type(v)) != v for v in big.tolist()]]
    if lost.size:
        shown = ", ".join(f"{v:.17g}" for v in lost[:3].tolist())
        more = f" and {lost.size - 3} more" if lost.size > 3 else ""
        raise BadUsage(f"{name}: {option} {dt.name} cannot hold its label ids {shown}{more} "
                       "(a label map's ids are never merged or changed): give a type that "
                       "holds them, or --values intensity to clip them as intensities")


def keep_label_ids(data, dtype, name: str, labels="auto", meta=None) -> None:
    """:func:`refuse_merged_ids` for samples written as ``dtype``, if they are a label map.

    ``labels``: True (they are), False (they are not: clipped to the type's
    range, nothing checked) or ``"auto"`` (the rule decides, one pass over
    ``data``, and a segmentation's samples by ``meta``, :func:`segmentation_of`,
    are labels), as :func:`~volwarp_cli.io.write_volume`'s.
    """
    if labels is False:
        return
    if labels == "auto" and segmentation_of(meta):
        labels = True
    looks, ids, _ = scan_labels(data, detect=labels == "auto")
    if ids is not None and (looks or labels is True):
        refuse_merged_ids(ids, dtype, name)


def label_map_hint(data: np.ndarray, meta=None) -> dict | None:
    """``{"labels": n, "values": [...]}`` when ``data`` is taken for a label map (``info``).

    The rule (module notes), whatever the number of distinct values: the
    answer the commands' defaults follow (a hint capped at 256 values said
    nothing of a map of 344 labels, which ``mesh`` and ``distance`` took for
    one), or the file's own word (``meta``, :func:`segmentation_of`: a NIfTI of
    intent label, which every command takes as labels, had no hint), then with
    ``"why"``; None otherwise (the values: the first 16).
    """
    data = np.asarray(data)
    if not _candidate(data) or data.size == 0:
        return None
    counted = _count(data, scan_boxes(data.shape))
    said = segmentation_of(meta)
    if counted is None or len(counted[0]) < (1 if said else 2):
        return None
    values, counts = counted
    if not said and not _rule(values, counts, data.shape, lambda z: data[z]):
        return None
    hint = {"labels": int(len(values)), "values": [int(v) for v in values[:16]]}
    return {**hint, "why": said} if said else hint


def looks_like_labels(data: np.ndarray) -> bool:
    """Whether the rule (module notes) takes the array ``data`` (``[z, y, x]``) for a label map.

    Why lean towards labels for a pyramid: the two mistakes are not alike.
    The mode of an intensity image still gives each coarse voxel one of its
    block's own values (a blockier preview); the mean of a segmentation
    writes ids that are not there (between 10 and 30 lies 20, another
    structure's). Other cases a caller knows better (``--pyramid-method``).
    """
    data = np.asarray(data)
    return looks_like_labels_by_blocks(data, scan_boxes(data.shape))


def looks_like_labels_by_blocks(source, boxes) -> bool:
    """:func:`looks_like_labels` of a sliceable ``source`` read box by box (``boxes`` tile it).

    The same answer without holding more than a box and two planes (for
    outputs written by blocks): the value counts are merged over the boxes.
    """
    if not _candidate(source) or 0 in tuple(source.shape):
        return False
    counted = _count(source, boxes)
    if counted is None:
        return False
    return _rule(*counted, tuple(source.shape), lambda z: np.asarray(source[z]))


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


def scan_labels(source, *, detect: bool = True, box_voxels: int = SCAN_BOX_VOXELS):
    """``(looks like labels, distinct values, their counts)`` of ``source``, read once by boxes.

    What the commands that follow the rule need before any work (``warp``'s
    and ``distance``'s choice, a label's presence, the count for ``-v``), in
    memory as by blocks: ``source`` is an array or a sliceable lazy source,
    read box by box (:func:`scan_boxes`), so the answer is the same either
    way. ``detect=False`` only counts. Samples that cannot be labels (floats
    with a fraction, or not finite) give ``(False, None, None)``, read no
    further than the first box that shows it; bool samples are counted but
    are no label map.
    """
    shape = tuple(int(n) for n in source.shape)
    kind = np.dtype(source.dtype).kind
    if (kind != "b" and not _candidate(source)) or 0 in shape:
        return False, None, None
    counted = _count(source, scan_boxes(shape, box_voxels))
    if counted is None:
        return False, None, None
    values, counts = counted
    looks = detect and kind != "b" and _rule(values, counts, shape,
                                             lambda z: np.asarray(source[z]))
    return bool(looks), values, counts


def whole_ids(data, planes: int = 8) -> bool:
    """Whether every sample of ``data`` is an id (:func:`integer_samples`), read by slabs.

    A few planes at a time: a mapped float volume is never copied whole.
    """
    if np.dtype(data.dtype).kind in "iub":
        return True
    return all(integer_samples(data[z:z + planes]) is not None
               for z in range(0, max(1, data.shape[0]), planes))


def integer_samples(block) -> np.ndarray | None:
    """``block`` as integers: integer (or bool) samples as they are; None when they are not ids.

    Float samples are ids when every one is a finite integer within the
    type's exact range (2**24 for float32, 2**53 for float64): then as
    int64. Otherwise None (a fraction, a NaN, an infinity).
    """
    block = np.asarray(block)
    kind = block.dtype.kind
    if kind in "iub":
        return block
    if kind != "f":
        return None
    if block.size == 0:
        return block.astype(np.int64)
    if not np.isfinite(block).all():
        return None
    exact = 2.0 ** (np.finfo(block.dtype).nmant + 1)
    if float(np.abs(block).max()) > exact:
        return None
    ints = block.astype(np.int64)
    return ints if np.array_equal(ints, block) else None


#: samples counted at a time by :func:`value_counts`
_COUNT_PIECE = 1 << 20
#: value ranges :func:`value_counts` counts by comparing with each value
_COMPARED_SPAN = 8


def value_counts(data: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The sorted distinct values of an integer array (int64) and how often each occurs.

    A count table where the range of values is small (at most 65536, or four
    times the samples, and under 2**24), else a sort: a box of a map with a
    few labels spread over a wide range makes no table of the range's size.
    Integer-valued floats are counted as their integers (ValueError for
    others: :func:`integer_samples`).
    """
    ints = integer_samples(data)
    if ints is None:
        raise ValueError(f"samples of type {np.asarray(data).dtype} that are not all integers")
    data = ints
    lo, hi = int(data.min()), int(data.max())
    span = hi - lo + 1
    if span <= _COMPARED_SPAN:  # (a mask: a comparison a value, 30x faster than a table)
        counts = np.array([np.count_nonzero(data == v) for v in range(lo, hi + 1)], np.int64)
        where = np.flatnonzero(counts)
        return (where + lo).astype(np.int64), counts[where]
    if span < 1 << 24 and span <= max(1 << 16, 4 * data.size):
        # shifted in intp (in the array's own type 100 - (-100) wraps: int8), a million
        # samples at a time (no intp copy of a whole scan: 134 MB of fresh pages at 256^3)
        flat = data.reshape(-1)
        piece_size = _COUNT_PIECE if span <= _COUNT_PIECE else flat.size  # (a table a piece)
        table = np.zeros(span, dtype=np.int64)
        for a in range(0, flat.size, piece_size):
            piece = flat[a:a + piece_size].astype(np.intp)
            piece -= lo
            table += np.bincount(piece, minlength=span)
        where = np.flatnonzero(table)
        return (where + lo).astype(np.int64), table[where].astype(np.int64)
    values, counts = np.unique(data, return_counts=True)
    return values.astype(np.int64), counts.astype(np.int64)


def _candidate(source) -> bool:
    """Whether ``source``'s sample type can hold ids: integers, or floats (their values decide)."""
    return np.dtype(source.dtype).kind in "iuf"


def _count(source, boxes):
    """``(values, counts)`` of ``source`` read box by box, merged; None when they are not ids."""
    if np.dtype(source.dtype).kind == "f" and integer_samples(_probe(source)) is None:
        return None  # (a scan's fraction, seen in a few rows: no box read whole)
    parts = []
    for box in boxes:
        block = integer_samples(source[box.slices])
        if block is None:
            return None
        if block.size:
            parts.append(value_counts(block))
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    values, inverse = np.unique(np.concatenate([v for v, _ in parts]), return_inverse=True)
    counts = np.bincount(inverse.ravel(), weights=np.concatenate([c for _, c in parts]),
                         minlength=len(values)).astype(np.int64)
    return values, counts


#: rows of the middle plane :func:`_probe` reads
_PROBE_ROWS = 16


def _probe(source) -> np.ndarray:
    """A few rows across the middle of ``source``: where a float scan shows its fractions.

    A float volume is no label map when any sample is not an integer, so
    these rows decide it for most scans without reading the first box whole
    (64 planes of 256^3: 0.2 s of a warp's start, its pages read and copied
    to int64); rows of integers (a mask, a map, a background) decide
    nothing, and the boxes are read as before.
    """
    nz, ny, _ = (int(n) for n in source.shape)
    y0 = max(0, ny // 2 - _PROBE_ROWS // 2)
    return np.asarray(source[nz // 2:nz // 2 + 1, y0:y0 + _PROBE_ROWS])


def _rule(values, counts, shape, plane) -> bool:
    """The rule (module notes) from the value counts and the planes ``plane(z)``."""
    if len(values) < 2:
        return False
    order = np.lexsort((values, -counts))  # most frequent first; a tie: the smaller value
    top = values[order[:2]]
    counts = _neighbours(shape, plane, skip=(0, int(top[0])), top=tuple(int(v) for v in top))
    pairs, equal, minor, in_regions, middle, graded = counts
    piecewise = not pairs or equal >= MIN_EQUAL_PAIRS * pairs
    regions = not minor or in_regions >= MIN_IN_REGIONS * minor
    # (test 3 where there are levels to step through: a few ordered labels in thin layers,
    # a head's scalp, skull and CSF, cross between their neighbours as often)
    steps = (len(values) >= MIN_GRADED_VALUES and bool(middle)
             and graded >= MIN_GRADED * middle)
    return piecewise and regions and not steps


def _neighbours(shape, plane, *, skip, top) -> tuple[int, int, int, int, int, int]:
    """The counts of the three tests on about :data:`SAMPLED_PLANES` planes and the two after.

    ``(pairs, equal pairs, minor voxels, minor voxels with a neighbour of their
    value, minor voxels of the plane after, their graded crossings)``: pairs
    along x, y, z whose voxels are both none of ``skip``; minor voxels: those
    whose value is none of ``top``; a graded crossing: a minor voxel of plane
    ``z + 1`` whose two neighbours along an axis (x, y, or planes ``z`` and
    ``z + 2``) both differ from it, one lower and one higher (each axis counts).
    """
    nz = int(shape[0])
    pairs = equal = minor = in_regions = middle = graded = 0
    for z in range(0, nz, max(1, nz // SAMPLED_PLANES)):
        p = np.asarray(plane(z))
        q = np.asarray(plane(z + 1)) if z + 1 < nz else None
        if q is not None:
            after = np.asarray(plane(z + 2)) if z + 2 < nz else None
            m, g = _graded(p, q, after, top)
            middle += m
            graded += g
        keep = _none_of(p, skip)
        same = np.zeros(p.shape, dtype=bool)  # a neighbour of the same value
        for a, b, ka, kb, sa, sb in _pairs(p, keep, same):
            eq = a == b
            both = ka & kb
            pairs += int(np.count_nonzero(both))
            equal += int(np.count_nonzero(both & eq))
            sa |= eq
            sb |= eq
        if q is not None:
            eq = p == q
            both = keep & _none_of(q, skip)
            pairs += int(np.count_nonzero(both))
            equal += int(np.count_nonzero(both & eq))
            same |= eq
        small = _none_of(p, top)
        minor += int(np.count_nonzero(small))
        in_regions += int(np.count_nonzero(small & same))
    return pairs, equal, minor, in_regions, middle, graded


def _graded(before, p, after, top) -> tuple[int, int]:
    """``(minor voxels of plane p, their graded crossings)``: :func:`_neighbours`' third count."""
    small = _none_of(p, top)
    lines = [(p[:, :-2], p[:, 1:-1], p[:, 2:], small[:, 1:-1]),
             (p[:-2], p[1:-1], p[2:], small[1:-1])]
    if after is not None:
        lines.append((before, p, after, small))
    graded = 0
    for lo, v, hi, keep in lines:
        graded += int(np.count_nonzero(keep & (np.minimum(lo, hi) < v) & (v < np.maximum(lo, hi))))
    return int(np.count_nonzero(small)), graded


def _pairs(p, keep, same):
    """The x and y neighbour pairs of plane ``p``: both sides of it, of ``keep``, of ``same``."""
    yield p[:, :-1], p[:, 1:], keep[:, :-1], keep[:, 1:], same[:, :-1], same[:, 1:]
    yield p[:-1], p[1:], keep[:-1], keep[1:], same[:-1], same[1:]


def _none_of(p: np.ndarray, values) -> np.ndarray:
    """Where ``p`` is none of ``values`` (a bool array)."""
    out = np.ones(p.shape, dtype=bool)
    for v in set(values):
        out &= p != v
    return out
