"""What a distance field is of: a label map's labels, or the samples on one side of a level.

DESIGN.md's "label maps are labels". When :func:`volwarp_cli.labelmap.looks_like_labels`
takes the input for a label map (integer ids, or floats that are all integers, as
nibabel and MONAI write segmentations), or the user says so (``values="labels"``,
or one ``label``), its distance is that of its labels' voxel surface: the shape
is every voxel with a non-zero id (or, with ``label``, the voxels of that id)
and the field is the one between voxel centres. The ids' values never enter:
renaming them (a bijection of the non-zero ids, 0 kept) gives the same field,
byte for byte. Taking the ids as intensities instead (``iso`` between two
ids, a sub-voxel surface interpolating them) made the field depend on which
number each tissue happened to get (up to 4.45 mm on a k-means segmentation
of the bundled T1 scan). ``values="intensity"`` keeps the samples' own rule:
``iso``, ``inside`` and, for smooth samples, the sub-voxel surface.

With a label map, an ``iso`` level is accepted when it selects exactly the
label rule's voxels (a 0/1 or 0/255 mask at 0.5: the field it always gave);
any other level, ``--inside`` without a level, and a sub-voxel surface are
usage errors (:class:`~volwarp_cli.errors.BadUsage`) naming the way out
(``--label N``, ``--values intensity``).

The rule reads the samples once, box by box (:func:`scan_values`), in
memory as by blocks: the same answer, and the distinct ids it counts decide
the checks (a missing label, a shape that fills the grid) before any pass.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import BadUsage, VolwarpError
from ..labelmap import SCAN_BOX_VOXELS, VALUES
from .field import inside_mask, signed_distance


class LabelAbsent(VolwarpError):
    """A label asked for (``--label N``, a spec's ``label: N``) that the volume does not hold.

    Its own class so that a spec's caller can name the key that asked for it.
    """


@dataclass(frozen=True)
class ShapeRule:
    """The shape a field is of, how it was chosen and why.

    ``values``: ``"labels"`` (the voxels of ``label``, or of every non-zero
    id when ``label`` is None) or ``"intensity"`` (the samples ``inside``
    ``iso``); ``why``: ``"looks like a label map: 4 labels"`` (the distinct
    values, 0 included, as ``warp`` counts them), ``"given"``, ``"not a label
    map"`` (no ids: renamed ids give the same note); ``ids``: the first few
    non-zero ids, for ``-v``; ``name``: the input's file, for the errors of
    the shape's checks (an empty shape, one filling the grid).
    """

    values: str
    why: str
    label: int | None = None
    iso: float | None = None
    inside: str = "above"
    ids: str = ""
    name: str = field(default="", compare=False)

    @property
    def labels(self) -> bool:
        """Whether the shape is a label map's voxels."""
        return self.values == "labels"

    def mask(self, data: np.ndarray) -> np.ndarray:
        """The shape's voxels in ``data`` (a bool array of its shape)."""
        if self.labels:
            return label_mask(data, self.label)
        return inside_mask(data, self.iso, self.inside)

    def note(self) -> str:
        """The shape's part of the output's ``volwarp_distance`` key."""
        if self.labels:
            which = "labels=all" if self.label is None else f"label={self.label}"
            return f"values=labels {which} ({self.why})"
        return f"iso={self.iso:g} inside={self.inside} values=intensity ({self.why})"

    def describe(self) -> str:
        """One line for ``-v`` (``warp``'s form): the choice, why, and what the shape is."""
        if not self.labels:
            return (f"values: intensity ({self.why}): the distance of the samples "
                    f"{self.inside} {self.iso:g}")
        which = (f"the voxels with a non-zero label ({self.ids})" if self.label is None
                 else f"the voxels of label {self.label}")
        return f"values: labels ({self.why}): the distance of {which}, on the voxel surface"


def label_mask(data: np.ndarray, label: int | None = None) -> np.ndarray:
    """The voxels of ``label`` in the label map ``data``; of every non-zero id when None."""
    data = np.asarray(data)
    return data != 0 if label is None else data == label


@dataclass(frozen=True)
class ValueScan:
    """What :func:`scan_values` found: the rule's answer and the distinct values.

    ``values`` (sorted, int64) and ``counts`` are None when the samples were
    not counted (not integers, or not needed).
    """

    looks_like: bool
    values: np.ndarray | None
    counts: np.ndarray | None
    size: int
    dtype: np.dtype


def scan_values(source, *, detect: bool = True,
                box_voxels: int = SCAN_BOX_VOXELS) -> ValueScan:
    """The label rule's answer for ``source`` (``detect``) and its distinct values, box by box.

    ``source``: an array or a sliceable lazy source. Integer (or bool)
    samples are counted, and float samples that are all integers (a
    segmentation written as floats, as nibabel and MONAI do); floats with a
    fraction are no label map (read no further than the first box that
    shows it), and other types are not read.
    """
    from ..labelmap import scan_labels

    shape = tuple(int(n) for n in source.shape)
    dtype = np.dtype(source.dtype)
    size = int(np.prod(shape))
    if dtype.kind not in "iubf" or size == 0:
        return ValueScan(False, None, None, size, dtype)
    looks, values, counts = scan_labels(source, detect=detect, box_voxels=box_voxels)
    return ValueScan(looks, values, counts, size, dtype)


_SUBVOXEL = ("its distance is that of its labels' voxel surface (between voxel centres): "
             "--surface subvoxel needs --values intensity and --iso V")


def check_options(*, values: str | None = None, label: int | None = None,
                  iso: float | None = None, surface: str = "auto") -> None:
    """The usage errors (:class:`BadUsage`) found without the samples."""
    if values is not None and values not in VALUES:
        raise BadUsage(f"values must be one of {', '.join(VALUES)}, got {values!r}")
    if values == "intensity":
        if label is not None:
            raise BadUsage("--label N takes one label's voxels: it does not go with "
                           "--values intensity (give --iso V)")
        if iso is None:
            raise BadUsage("--values intensity needs --iso V: the shape is the samples on "
                           "one side of V")
    elif surface == "subvoxel" and (values == "labels" or label is not None):
        given = "--values labels" if values == "labels" else "--label N"
        raise BadUsage(f"{given} takes a label map, and {_SUBVOXEL}")


def choose_shape(source, *, values: str | None = None, label: int | None = None,
                 iso: float | None = None, inside: str = "above", surface: str = "auto",
                 name: str = "the input", box_voxels: int = SCAN_BOX_VOXELS,
                 meta=None) -> ShapeRule:
    """The shape ``source``'s distance is of: its labels or its samples' level (module notes).

    ``values``: None (the label rule decides), ``"intensity"`` or
    ``"labels"``; ``label``: one label (implies labels unless ``values``
    says intensity); ``iso``, ``inside``, ``surface``: the options given.
    Raises :class:`BadUsage` for options that contradict the input (exit 2)
    and :class:`VolwarpError` for a shape with no surface (a missing label,
    labels filling the grid). ``meta``: the input's key/values (a
    segmentation's ids are labels whatever the rule says).
    """
    from ..labelmap import segmentation_of

    check_options(values=values, label=label, iso=iso, surface=surface)
    if values == "intensity":
        return ShapeRule("intensity", "given", iso=iso, inside=inside, name=name)
    scan = scan_values(source, box_voxels=box_voxels)  # (detected: to say so when asked)
    segmentation = segmentation_of(meta) if scan.values is not None else None
    looks_like = scan.looks_like or segmentation is not None
    if values is None and label is None and not looks_like:
        if iso is None:
            raise BadUsage(f"--iso V is required: {name} does not look like a label map, so "
                           f"the shape is the samples {inside} V (or give --values labels or "
                           "--label N to take its ids as labels)")
        return ShapeRule("intensity", "not a label map", iso=iso, inside=inside, name=name)
    given = "--values labels" if values == "labels" else "--label N"
    if scan.values is None:
        what = ("samples that are not all integers" if scan.dtype.kind == "f"
                else "samples")
        raise BadUsage(f"{name}: {given} needs a label map (integer ids), got {scan.dtype} "
                       f"{what}; give --iso V for the samples' level")
    ids = scan.values[scan.values != 0]
    if values != "labels" and looks_like:
        # (as warp counts them: the distinct values, 0 included)
        n = len(scan.values)
        if scan.looks_like:
            why, what = (f"looks like a label map: {n} labels",
                         f"{name} looks like a label map ({n} labels)")
        else:
            why, what = (f"read from {segmentation}: {n} labels",
                         f"{name} is a label map ({segmentation}, {n} labels)")
    else:
        why = "given"
        what = f"{name} is taken as a label map ({given})"
        if not looks_like:  # (as warp says it: once, and the work goes on as asked)
            from ..progress import log

            log.warning("warning: %s does not look like a label map (%d distinct values): its "
                        "ids taken as labels as asked (%s)", name, len(scan.values), given)
    if surface == "subvoxel":
        raise BadUsage(f"{what}: {_SUBVOXEL}")
    chosen = ids if label is None else scan.values[scan.values == label]
    if label is not None and not chosen.size:
        raise LabelAbsent(f"{name}: label {label} does not occur in the volume "
                           f"(its values: {_listed(scan.values)})")
    if label is None and not chosen.size:
        raise VolwarpError(f"{name}: no label other than 0 in the volume")
    if iso is not None:
        picked = scan.values[inside_mask(scan.values, iso, inside)]
        if not np.array_equal(picked, chosen):
            whose = "its non-zero labels" if label is None else f"label {label}"
            side = "" if inside == "above" else f" --inside {inside}"
            raise BadUsage(f"{what}: --iso {iso:g}{side} selects other voxels than {whose}; "
                           "give --label N for one label's distance, or "
                           "--values intensity to take the ids as intensities")
    elif inside != "above":
        raise BadUsage(f"{what}: --inside goes with --iso V (the shape is the labels' voxels; "
                       "--values intensity to take the ids as intensities)")
    count = int(scan.counts[np.isin(scan.values, chosen)].sum())
    if count == scan.size:
        whose = ("every voxel has a non-zero label (give --label N)" if label is None
                 else f"every voxel has label {label}")
        raise VolwarpError(f"{name}: {whose}, so the shape fills the whole grid and has no "
                           "surface")
    return ShapeRule("labels", why, label=label, ids=f"ids {_listed(ids)}", name=name)


def _listed(ids: np.ndarray, shown: int = 8) -> str:
    """``"1, 2, 3"``: the first few ids."""
    return ", ".join(str(int(v)) for v in ids[:shown]) + (", ..." if len(ids) > shown else "")



def rule_signed_distance(data: np.ndarray, spacing_zyx, rule: ShapeRule, *,
                         metric: str = "euclidean",
                         surface: str = "auto") -> tuple[np.ndarray, dict]:
    """:func:`.field.signed_distance` of ``rule``'s shape in ``data``.

    A label rule's shape is its voxels' mask, on the voxel surface (the ids'
    values never reach the kernels); an intensity rule is ``iso``, ``inside``
    and ``surface`` as given.
    """
    if rule.labels:
        return signed_distance(rule.mask(data), spacing_zyx, iso=0.5, metric=metric,
                               surface="voxel")
    return signed_distance(data, spacing_zyx, iso=rule.iso, inside=rule.inside, metric=metric,
                           surface=surface)
