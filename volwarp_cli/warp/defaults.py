"""What a warp does where its user says nothing.

DESIGN.md's "label maps are labels" and "a scan stays where it was":

- **Values** (:func:`choose_values`): an input that
  :func:`volwarp_cli.labelmap.looks_like_labels` takes for a label map is
  warped as labels (ids never averaged: an intensity warp of the frog's
  tissue map wrote ids 18, 19 and 22 that it does not have); the user's
  ``--values`` (``--labels``, the spec's ``values:``) overrides, and labels
  asked for on a volume that does not look like a label map get a warning.
- **Grid** (:func:`output_grid`): the output is on the input's grid (the
  same shape, origin and spacing: a scan stays where it was), unless growth
  is asked for (``--grid grow``, the spec's ``grid: grow``, or a padding
  given: ``capture.pad``, ``capture --pad``), the papers' modelling case,
  where the grid grows to hold the whole moved model.
- **Background** (:func:`~volwarp_cli.border.border_value`): where nothing of the model lands,
  the output gets what the scan has outside its anatomy, the (lower) median
  of its border samples (-1024 in a CT, 0 in an MRI, a positive distance in
  a distance field), not 0 (0 HU is water). A label map's is its most
  frequent border label (:func:`~volwarp_cli.border.border_label`), one of its own ids.
- **Resampling** (:func:`resampling_warning`): a capture on the spanning
  grid (a non-integer oversample, the tripled placement) changes voxels the
  warp does not move; said once per run.

Numpy only, no click: the command line passes the user's choices in and
prints what comes out.
"""

from __future__ import annotations

import contextvars
from dataclasses import dataclass, field

import numpy as np

from ..border import not_ids
from ..labelmap import SCAN_BOX_VOXELS, VALUES, segmentation_of  # noqa: F401  (VALUES: warp's)
from ..progress import log

#: ``--grid``: the input's grid, or grown to hold the whole moved model
GRIDS = ("input", "grow")


#: why the default background is what it is (``-v``: ``background: -1024 (...)``)
BORDER_WHY = "the median of the input's border"


def background_choice(option: float | None, spec_background: float | None,
                      border: float | None) -> tuple[float, str]:
    """An intensity warp's background and why: the option's, the spec's, else the border's.

    ``border``: :func:`~volwarp_cli.border.border_value` of the input where the capture knows
    it (None: 0, the default).
    """
    if option is not None:
        return float(option), "given"
    if spec_background is not None:
        return float(spec_background), "the spec's background"
    if border is not None:
        return float(border), BORDER_WHY
    return 0.0, "default"


@dataclass(frozen=True)
class ValuesChoice:
    """How a warp takes its input's samples, and why.

    ``values``: ``"labels"`` or ``"intensity"``; ``why``: ``"given"``,
    ``"looks like a label map: 5 labels"``, ``"not a label map"``, ...;
    ``labels``: the distinct values counted (None when not counted);
    ``warning``: a line to say once (labels asked for on a volume that
    does not look like a label map; a sparse volume of a few ids taken for
    intensities, :func:`sparse_ids_warning`), or None; ``ids``: the distinct values
    themselves where they were counted (an output type must hold them:
    :func:`~volwarp_cli.labelmap.refuse_merged_ids`); ``against_rule``: labels
    given of samples the rule takes for intensities (an output records the
    choice: :func:`~volwarp_cli.labelmap.meta_as_taken`).
    """

    values: str
    why: str
    labels: int | None = None
    warning: str | None = None
    ids: np.ndarray | None = field(default=None, compare=False, repr=False)
    against_rule: bool = False

    @property
    def is_labels(self) -> bool:
        """Whether the input is warped as a label map."""
        return self.values == "labels"

    @property
    def ruled(self) -> bool:
        """Whether the rule chose (not the user, nor a capture's record): messages name the way out."""
        return self.why != "given" and not self.why.startswith("recorded")

    def describe(self) -> str:
        """One line for ``-v``: ``values: labels (looks like a label map: 5 labels)``."""
        return f"values: {self.values} ({self.why})"


def label_scan(source, *, box_voxels: int = SCAN_BOX_VOXELS):
    """``(looks like a label map, its distinct values, their counts)`` of ``source``, read once.

    The rule is :func:`~volwarp_cli.labelmap.looks_like_labels` (by boxes:
    :func:`~volwarp_cli.labelmap.scan_labels`, the same answer in memory as
    by blocks). Samples that cannot be ids (floats with a fraction, a NaN;
    other types) are no label map: ``(False, None, None)``, read no further than
    the first box that shows it.
    """
    from ..labelmap import scan_labels

    if np.dtype(source.dtype).kind not in "iuf":
        return False, None, None
    return scan_labels(source, box_voxels=box_voxels)


#: the most values besides the background a sparse map of ids has (:func:`sparse_ids_warning`)
SPARSE_IDS = 256
#: the share of the voxels the most frequent value holds above which the rule's answer
#: "intensities" rests on too few voxels to be sure of (:func:`sparse_ids_warning`)
SPARSE_SHARE = 0.99


def sparse_ids_warning(name: str, values, counts) -> str | None:
    """A warning when the rule took a sparse volume of a few integer values for intensities.

    Landmarks or points, one voxel each with ids 1..20 in zeros (or beside a
    mask's 0 and 1), have no regions for the rule to see: it answers
    intensities, and an intensity warp or resampling blends the ids away (a
    review: 20 landmarks became values 0..7 over 103 voxels, 6 ids gone,
    nothing said). Said, not decided: a sparse intensity image is possible
    too, and one whose values are many (above :data:`SPARSE_IDS`) or spread
    out (over four times as many integers as there are values, as ids 1..N
    are not) says nothing.
    """
    if values is None or counts is None or not 3 <= len(values) <= SPARSE_IDS + 1:
        return None
    values, counts = np.asarray(values), np.asarray(counts)
    total = int(counts.sum())
    order = np.argsort(-counts, kind="stable")
    # the background, and a mask beside it where one holds more than the sparse share
    kept = order[:2] if counts[order[1]] > (1 - SPARSE_SHARE) * total else order[:1]
    rest = np.setdiff1d(np.arange(len(values)), kept)
    few = int(counts[rest].sum())
    if total == 0 or few > (1 - SPARSE_SHARE) * total:
        return None
    ids = values[values != values[order[0]]].astype(np.float64)
    if ids.max() - ids.min() + 1 > 4 * len(ids):  # (values spread out: a sparse image's)
        return None
    beside = " and ".join(f"{v:g}" for v in values[kept])
    return (f"warning: {name}: its {few} voxels of {len(rest)} integer values besides "
            f"{beside} are taken for intensities (too few regions for the label rule to "
            "tell landmarks or points from a sparse image); if they are ids, give --values "
            "labels")


def choose_values(source, given: str | None = None, *, name: str = "the input",
                  meta=None) -> ValuesChoice:
    """How to warp ``source``'s samples: as labels or as intensities (module notes).

    ``given``: the user's choice (``--values``, ``--labels``, the spec's
    ``values:``), or None for the rule. ``"intensity"`` reads nothing; the
    rule, and ``"labels"`` (to say when the volume does not look like a
    label map), read the samples once (integers, and floats that may hold
    integer ids). Labels asked for on float samples that are not all
    integers are an error (:class:`~volwarp_cli.errors.VolwarpError`): a
    fraction is no id. ``name`` (the input's file) goes into the messages.
    ``meta``: the input's key/values; a segmentation's integer samples
    (:func:`~volwarp_cli.labelmap.segmentation_of`) are labels, whatever the rule says.
    """
    if given is not None and given not in VALUES:
        raise ValueError(f"values must be one of {', '.join(VALUES)}, got {given!r}")
    from ..labelmap import recorded_values

    recorded = recorded_values(meta) if given is None else None
    if recorded is not None:  # (capture --values: the choice travels in the file)
        choice = choose_values(source, recorded, name=name)
        return ValuesChoice(choice.values, "recorded in the file (volwarp_values)",
                            choice.labels, choice.warning, choice.ids)
    if given == "intensity":
        return ValuesChoice("intensity", "given")
    kind = np.dtype(source.dtype).kind
    if given == "labels" and kind not in "iuf":  # (the label warp says why it cannot)
        return ValuesChoice("labels", "given")
    looks, ids, counts = label_scan(source)
    n = None if ids is None else int(len(ids))
    if given == "labels":
        if n is None:
            raise not_ids(name, source.dtype)
        warning = None
        # (not when the rule could not tell: a sparse map of a few ids, landmarks)
        if not looks and sparse_ids_warning(name, ids, counts) is None:
            warning = (f"warning: {name} does not look like a label map ({n} distinct "
                       f"value{'s' if n != 1 else ''}"
                       f"{'' if n < 2 else ': the label rule takes it for intensities'}): "
                       "warped as labels as asked (each output voxel one of its values, "
                       "never a blend)")
        return ValuesChoice("labels", "given", n, warning, ids, against_rule=not looks)
    if looks:
        return ValuesChoice("labels", f"looks like a label map: {n} labels", n, ids=ids)
    segmentation = segmentation_of(meta)
    if segmentation and n is not None:
        return ValuesChoice("labels", f"read from {segmentation}: {n} labels", n, ids=ids)
    if segmentation and kind == "f" and _ids_but_not_finite(source):
        from ..errors import ChoiceNeeded  # (a label map with a NaN: no guess either way)

        raise ChoiceNeeded(f"{name} is {segmentation}, but some of its samples are NaN or "
                           "infinite (no id): give --values intensity to treat them as "
                           "intensities, or replace them first")
    return ValuesChoice("intensity", "not a label map", n,
                        sparse_ids_warning(name, ids, counts))


def _ids_but_not_finite(source) -> bool:
    """Whether float ``source``'s finite samples are all whole numbers and some are not finite.

    A label map with a NaN, not a field of fractions that kept its map's keys (an
    intensity warp's output before 0.1.10): those stay intensities, as before.
    By slabs of planes (a lazy source is read once).
    """
    step = max(1, (1 << 22) // max(1, int(np.prod(source.shape[1:]))))
    nonfinite = False
    for z in range(0, source.shape[0], step):
        block = np.asarray(source[z:z + step])
        finite = np.isfinite(block)
        if not finite.all():
            nonfinite = True
            block = block[finite]
        if not np.array_equal(block, np.rint(block)):
            return False
    return nonfinite


def output_grid(option: str | None, spec_grid: str | None,
                pad_given: str | None) -> tuple[str, str]:
    """The output's grid, ``"input"`` or ``"grow"``, and why.

    Why input by default: a warped scan must lie where the scan lay, on its
    grid (a 16x16x5 CT came out 38x16x5 when the grid grew). ``option``: the
    command line's (``--grid``; ``--crop`` is ``input``); ``spec_grid``: the
    spec's ``grid:``; ``pad_given``: where a padding was given (``"capture.pad"``,
    ``"the capture file's pad"``) or None: a padding asks for the grown grid
    unless a ``grid`` says otherwise.
    """
    for grid in (option, spec_grid):
        if grid is not None and grid not in GRIDS:
            raise ValueError(f"grid must be one of {', '.join(GRIDS)}, got {grid!r}")
    if option is not None:
        return option, "given"
    if spec_grid is not None:
        return spec_grid, "the spec's grid"
    if pad_given is not None:
        return "grow", f"{pad_given} given"
    return "input", "default"


def spanning_cause(placement: str, oversample: float) -> str:
    """Why a capture is on the spanning grid (its samples blends of the input's), in words.

    Every cause: the tripled placement, a non-integer oversample; neither: a
    capture file of version 1, whose grid spans the input at any oversample.
    """
    causes = []
    if placement != "uniform":
        causes.append("the tripled placement")
    if not float(oversample).is_integer():
        causes.append(f"oversample {oversample:g} (not an integer)")
    return " and ".join(causes) or "a capture file of version 1 (its grid spans the input)"


def resampling_warning(placement: str, oversample: float, subdivision: int) -> str | None:
    """The line to say when a capture does not keep unmoved voxels exact, or None.

    Only the uniform placement at an integer oversample (the subdivision
    grid) makes an unmoved region an exact copy; otherwise the capture and
    the pushforward each resample, and voxels far from every moved control
    point change (18% of the bundled brain on an identity warp, by up to 82
    of 255). ``subdivision``: the capture grid's (0: the spanning grid; a
    capture file of version 1 has it at any oversample).
    """
    if subdivision:
        return None
    return (f"warning: {spanning_cause(placement, oversample)}: the capture resamples, so "
            "voxels the warp does not move change too; the uniform placement with an integer "
            "oversample keeps them exact")


_said: contextvars.ContextVar[set | None] = contextvars.ContextVar("volwarp_warp_said",
                                                                   default=None)


def new_run() -> None:
    """Start a run: :func:`warn_once` says each line again once (the command calls this)."""
    _said.set(set())


def warn_once(line: str | None) -> None:
    """Log ``line`` as a warning unless this run said it already (None: nothing)."""
    if line is None:
        return
    said = _said.get()
    if said is not None:
        if line in said:
            return
        said.add(line)
    log.warning("%s", line)
