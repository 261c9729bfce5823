"""A label map's surfaces: its labels, read block by block, and each one's indicator.

The surface of a label is the isosurface at 0.5 of its indicator (1 where
the label is, 0 elsewhere), closed at the volume's border (``cap``): a
label's voxels enclosed by their faces, bevelled at edges and corners.

DESIGN.md's "label maps are labels": a volume the label rule takes for a
label map (:func:`mesh_values`), meshed without ``--label``/``--labels``,
gives the surface of every voxel with a non-zero label (the union's
indicator), never an isosurface of its ids as intensities. The middle of the
value range of a map with ids 0..29 is 14.5: the old default meshed the
structures whose ids happened to be above it, and any level between two ids
moves each vertex by the ratio of the two numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import BadUsage, VolwarpError


def check_label_map(dtype, name: str, what: str) -> None:
    """Refuse samples that cannot be a label map for ``what`` (``--label``...).

    Integers, or floats (a segmentation written as floats, as nibabel and
    MONAI do, which ``distance --label`` takes too): their values must then be
    integers, which :func:`label_values` checks as it reads them.
    """
    if np.dtype(dtype).kind not in "iuf":
        raise VolwarpError(f"{name}: {what} needs a label map (integer samples), got "
                           f"{np.dtype(dtype)}")


class LabelIndicator:
    """The indicator of one label of a sliceable label map (1 inside, float32), read by boxes.

    ``label`` None: of every non-zero label (their union). Picklable when the
    map is (a :class:`~volwarp_cli.io.lazy.LazySource`).
    """

    def __init__(self, source, label: int | None):
        self.source, self.label = source, None if label is None else int(label)
        self.shape = tuple(source.shape)
        self.dtype = np.dtype(np.float32)
        self.ndim = 3

    def __getitem__(self, key) -> np.ndarray:
        samples = np.asarray(self.source[key])
        inside = samples != 0 if self.label is None else samples == self.label
        return inside.astype(np.float32)


@dataclass(frozen=True)
class ValuesChoice:
    """How ``volwarp mesh`` takes its input: ``values`` ``"labels"`` or ``"intensity"``, and why.

    ``why``: ``"given"``, ``"not a label map"`` or ``"looks like a label map:
    26 labels"`` (the distinct values, 0 included, as ``warp`` counts them).
    """

    values: str
    why: str

    @property
    def labels(self) -> bool:
        """Whether the surface is that of the non-zero labels' voxels."""
        return self.values == "labels"


def mesh_values(source, *, values: str | None = None, iso: float | None = None,
                inside: str = "above", name: str = "the input", meta=None,
                allow_empty: bool = False) -> ValuesChoice:
    """How a volume meshed without ``--label``/``--labels`` is taken (module notes).

    ``values``: the command line's ``--values`` (None: the label rule
    decides, one pass over ``source``, box by box). A label map of several
    labels has the surface of its non-zero labels (their indicator's at 0.5,
    between the voxels whatever the ids); an ``iso`` level is accepted only
    where it selects exactly those voxels, and ``inside`` only with such a
    level. A mask (two values at most) is meshed at its level as asked: any
    level between its two values is its one label's surface, the ids mix
    nothing, and ``--iso``, ``--inside`` and ``--cap`` mean what they say.
    Anything else is a :class:`~volwarp_cli.errors.BadUsage` naming the ways
    out; labels asked for on a map with no non-zero label, a
    :class:`~volwarp_cli.errors.VolwarpError` unless ``allow_empty`` (an
    empty mesh). ``meta``: the input's key/values (a segmentation's ids are
    labels whatever the rule says).
    """
    from ..distance.field import inside_mask
    from ..distance.labels import scan_values
    from ..labelmap import segmentation_of

    if values == "intensity":
        return ValuesChoice("intensity", "given")
    scan = scan_values(source)
    segmentation = segmentation_of(meta) if scan.values is not None else None
    if values is None and not scan.looks_like and segmentation is None:
        return ValuesChoice("intensity", "not a label map")
    if values is None and len(scan.values) <= 2:
        return ValuesChoice("intensity", f"a mask ({len(scan.values)} values): the surface at "
                                         "its level is its label's")
    if scan.values is None:
        what = "samples that are not all integers" if scan.dtype.kind == "f" else "samples"
        raise BadUsage(f"{name}: --values labels needs a label map (integer ids), got "
                       f"{scan.dtype} {what}; mesh the samples' level with --iso V")
    if values is None and scan.looks_like:
        why = f"looks like a label map: {len(scan.values)} labels"
        what = f"{name} looks like a label map ({len(scan.values)} labels)"
    elif values is None:
        why = f"read from {segmentation}: {len(scan.values)} labels"
        what = f"{name} is a label map ({segmentation}, {len(scan.values)} labels)"
    else:
        why, what = "given", f"{name} is taken as a label map (--values labels)"
        if not scan.looks_like:  # (as warp and distance say it; the work goes on as asked)
            from ..progress import log

            log.warning("warning: %s does not look like a label map (%d distinct values): its "
                        "ids taken as labels as asked (--values labels)", name, len(scan.values))
    ways_out = ("give --label N (one label's surface), --labels (a mesh for each), or "
                "--values intensity to take the ids as intensities")
    ids = scan.values[scan.values != 0]
    if not ids.size and not allow_empty:
        raise VolwarpError(f"{name}: no label other than 0 in the volume (--allow-empty "
                           "writes an empty mesh)")
    if iso is not None:
        if not np.array_equal(scan.values[inside_mask(scan.values, iso, inside)], ids):
            side = "" if inside == "above" else f" --inside {inside}"
            raise BadUsage(f"{what}: --iso {iso:g}{side} selects other voxels than its "
                           f"non-zero labels; {ways_out}")
    elif inside != "above":
        raise BadUsage(f"{what}: --inside goes with --iso V (the surface is that of its "
                       f"non-zero labels); {ways_out}")
    return ValuesChoice("labels", why)


def label_values(source, boxes, run=None, name: str = "the volume") -> list[int]:
    """The distinct values of a sliceable label map, ascending, read by ``boxes``.

    The boxes one after the other here, or by ``run(task, boxes)`` (an
    engine's map).
    """
    def task(box):
        return np.unique(np.asarray(source[box.slices]))

    parts = run(task, boxes) if run is not None else [task(b) for b in boxes]
    values = np.unique(np.concatenate(parts)) if parts else np.empty(0, np.int64)
    if values.dtype.kind == "f":  # (a float map's ids: whole numbers only)
        odd = values[~(np.isfinite(values) & (values == np.rint(values)))]
        if odd.size:
            raise VolwarpError(f"{name}: --labels needs a label map (integer ids); its float "
                               f"samples include {odd[0]:g}")
    return [int(v) for v in values]
