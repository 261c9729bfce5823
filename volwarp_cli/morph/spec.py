"""The morph job: read from a YAML spec (``specs/morph.schema.json``) or built from options.

Semantic checks the schema cannot express are reported with the key path and
line of the offending entry (exit 2): unequal landmark lists, times outside
[0, 1], a gaussian warp without sigma, an affine that cannot be built.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import VolwarpError
from ..spec.functions import MAX_ANGLE, MAX_VALUE, check_bounded
from .align import affine_from_params


@dataclass
class ShapeRef:
    """A shape of the morph: its volume file and what its shape is, as ``distance`` takes it.

    ``iso``, ``inside``: the samples' level (None: a label map needs none);
    ``values``, ``label``: ``distance``'s ``--values`` and ``--label``
    (:func:`volwarp_cli.distance.labels.choose_shape` decides with them).
    """

    path: Path
    iso: float | None
    inside: str = "above"
    values: str | None = None
    label: int | None = None


@dataclass
class AttributeRef:
    """An attribute blended along with the shapes: its source and target volumes, output type."""

    name: str
    source: Path
    target: Path
    dtype: str | None = None
    values: str | None = None


@dataclass
class MorphJob:
    """A morph as the spec or the options give it: shapes, times, alignment, warp, grid, output."""

    source: ShapeRef
    target: ShapeRef
    times: list[float]
    metric: str = "euclidean"
    surface: str = "auto"
    output: str = "sdf"
    density_width: float | None = None
    density_range: str = "unit"
    align_source: dict | None = None
    align_target: dict | None = None
    warp_kind: str = "thin-plate"
    warp_sigma: float | None = None
    warp_mode: str = "static"
    warp_source_points: np.ndarray | None = None
    warp_target_points: np.ndarray | None = None
    grid: object = None
    margin: float = 2.0
    max_distance: float | None = None
    attributes: list[AttributeRef] = field(default_factory=list)
    doc: object = None  # the spec document (SpecDoc) it came from, for errors found later

    @property
    def moved(self) -> bool:
        """True when an alignment or a landmark warp is given."""
        return bool(self.align_source or self.align_target
                    or self.warp_source_points is not None)


#: largest world coordinate or length a morph spec may give (1e15 mm is 1e9 km): beyond
#: it squared distances overflow and the results are noise
MAX_COORD = MAX_VALUE


def check_affine_params(doc, path: tuple, params) -> None:
    """Refuse (key path and line) an affine's numbers out of bounds (:mod:`.align`'s keys).

    Coordinates, lengths and matrix entries within :data:`MAX_COORD`, a scale
    within ``[1 / MAX_COORD, MAX_COORD]``, angles within
    :data:`~volwarp_cli.spec.functions.MAX_ANGLE` degrees. (A transform
    ``scale: 1e300`` wrote a field of -inf with exit 0, ``rotate: 1e300`` a
    turn by an angle with no digits left.)
    """
    if not isinstance(params, dict):
        return
    for name, what in (("translate", None), ("center", None), ("matrix", "matrix entries"),
                       ("scale", "scales")):
        check_bounded(doc, path + (name,), params.get(name),
                      what=what or "world coordinates and lengths")
    check_bounded(doc, path + ("rotate",), params.get("rotate"), limit=MAX_ANGLE,
                  what="rotation angles (degrees)")
    scale = params.get("scale")
    for i, v in (enumerate(scale) if isinstance(scale, list) else [(None, scale)]):
        if isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < 1 / MAX_COORD:
            key = path + ("scale",) + (() if i is None else (i,))
            raise doc.error(key, f"{v:g} is too small (a scale is at least {1 / MAX_COORD:g})")


def _check_spacing(doc, sp) -> None:
    """The grid's spacing within the bounds every volume keeps (a spec error with its key).

    (The geometry's own check said it without the key and with exit 1.)
    """
    from ..geometry import PLACEMENT_LIMIT

    values = sp if isinstance(sp, list) else [sp]
    for i, a in enumerate(values):
        if isinstance(a, (int, float)) and not isinstance(a, bool) and not (
                1.0 / PLACEMENT_LIMIT <= a <= PLACEMENT_LIMIT):
            path = ("grid", "spacing", i) if isinstance(sp, list) else ("grid", "spacing")
            raise doc.error(path, f"{a:g} is not a voxel size volwarp keeps (positive, "
                                  f"{1 / PLACEMENT_LIMIT:g} to {PLACEMENT_LIMIT:g})")


def spec_terms(message: str) -> str:
    """``distance``'s options in a message as a spec's keys: ``--values intensity``, ``values: intensity``."""
    message = re.sub(r"--(iso|inside|label|values|surface) "
                     r"(V|N|-?[0-9][0-9.e+-]*|intensity|labels|subvoxel|above|below)\b",
                     r"\1: \2", message)
    return re.sub(r"--(iso|inside|label|values|surface)\b", r"\1", message)


def check_shape_options(ref: ShapeRef, surface: str, *, doc=None, key: str = "source") -> None:
    """``distance``'s usage errors found without the samples, for one shape.

    In a spec's keys, at the shape's line (``doc``); else as the options say them.
    """
    from ..distance.labels import check_options
    from ..errors import BadUsage

    try:
        check_options(values=ref.values, label=ref.label, iso=ref.iso, surface=surface)
    except BadUsage as exc:
        if doc is None:
            raise
        raise doc.error((key,), spec_terms(str(exc))) from None


def job_from_spec(doc) -> MorphJob:
    """A :class:`MorphJob` from a loaded, schema-valid spec document."""
    d = doc.data
    for side in ("source", "target"):
        check_affine_params(doc, ("align", side), d.get("align", {}).get(side))
    for name in ("pairs", "source_points", "target_points", "sigma"):
        check_bounded(doc, ("warp", name), d.get("warp", {}).get(name))
    if isinstance(d.get("grid"), dict):
        for name in ("origin", "spacing"):
            check_bounded(doc, ("grid", name), d["grid"].get(name))
        sp = d["grid"].get("spacing")
        _check_spacing(doc, sp)
        size = d["grid"].get("size")
        if isinstance(sp, (int, float)) and isinstance(size, list) and size:
            sp = [sp] * len(size)
        if isinstance(sp, list) and isinstance(size, list):
            for i, (a, n) in enumerate(zip(sp, size, strict=False)):
                if isinstance(a, (int, float)) and isinstance(n, int) and a * n > MAX_COORD:
                    raise doc.error(("grid", "size", i), f"the grid is {a * n:g} world units "
                                    f"long along {'xyz'[i]} (at most {MAX_COORD:g})")
    if "density" in d:
        check_bounded(doc, ("density", "width"), d["density"].get("width"))

    def shape(key):
        s = d[key]
        iso = s.get("iso")
        return ShapeRef(doc.input_file(s["volume"]), None if iso is None else float(iso),
                        s.get("inside", "above"), s.get("values"), s.get("label"))

    if "times" in d:
        times = [float(t) for t in d["times"]]
        for i, t in enumerate(times):
            if not 0.0 <= t <= 1.0:
                raise doc.error(("times", i), f"time {t:g} is outside [0, 1]")
    elif "frames" in d:
        times = [i / (d["frames"] - 1) for i in range(d["frames"])]
    else:
        raise doc.error((), "give frames (a count) or times (a list of t in [0, 1])")
    job = MorphJob(source=shape("source"), target=shape("target"), times=times,
                   metric=d.get("metric", "euclidean"), surface=d.get("surface", "auto"),
                   output=d.get("output", "sdf"))
    if job.surface == "subvoxel" and job.metric != "euclidean":
        raise doc.error(("surface",), "subvoxel surfaces need metric: euclidean")
    for key in ("source", "target"):
        check_shape_options(getattr(job, key), job.surface, doc=doc, key=key)
    dens = d.get("density", {})
    if dens and job.output != "density":
        raise doc.error(("density",), "density settings need output: density")
    job.density_width = dens.get("width")
    job.density_range = dens.get("range", "unit")
    if job.density_range == "source" and job.source.iso is None:
        raise doc.error(("density", "range"), "range: source puts the source's iso level on "
                        "the surface: give the source an iso (or range: unit)")
    align = d.get("align", {})
    for side in ("source", "target"):
        params = align.get(side)
        if params:
            try:  # check now, with a dummy centre, so errors point at the spec
                affine_from_params(params, default_center=(0.0, 0.0, 0.0))
            except VolwarpError as exc:
                raise doc.error(("align", side), str(exc)) from None
        setattr(job, f"align_{side}", params or None)
    if "warp" in d:
        w = d["warp"]
        job.warp_kind = w.get("kind", "thin-plate")
        job.warp_mode = w.get("mode", "static")
        job.warp_sigma = w.get("sigma")
        if job.warp_kind == "gaussian" and job.warp_sigma is None:
            raise doc.error(("warp", "kind"), "a gaussian warp needs sigma (world units)")
        if job.warp_kind != "gaussian" and job.warp_sigma is not None:
            raise doc.error(("warp", "sigma"), "sigma applies to kind: gaussian only")
        has_pairs = "pairs" in w
        has_lists = "source_points" in w or "target_points" in w
        if has_pairs and has_lists:
            raise doc.error(("warp", "source_points"),
                            "give either pairs or source_points/target_points, not both")
        if has_pairs:
            src = [p[0] for p in w["pairs"]]
            tgt = [p[1] for p in w["pairs"]]
        else:
            src = w.get("source_points", [])
            tgt = w.get("target_points", [])
            if len(src) != len(tgt):
                raise doc.error(("warp", "target_points"),
                                f"landmark lists differ in length: {len(src)} source points, "
                                f"{len(tgt)} target points")
        if not src:
            raise doc.error(("warp",), "a warp needs landmark pairs")
        job.warp_source_points = np.asarray(src, dtype=np.float64)
        job.warp_target_points = np.asarray(tgt, dtype=np.float64)
        try:
            from .landmarks import LandmarkWarp

            LandmarkWarp.fit(job.warp_source_points, job.warp_target_points,
                             kind=job.warp_kind, sigma=job.warp_sigma)
        except VolwarpError as exc:
            raise doc.error(("warp",), str(exc)) from None
    job.grid = d.get("grid")
    if isinstance(job.grid, dict):
        from .grid import GridError, explicit_grid

        try:
            explicit_grid(job.grid)
        except GridError as exc:
            raise doc.error(exc.key, str(exc)) from None
    job.margin = float(d.get("margin", 2.0))
    if "max_distance" in d:
        check_bounded(doc, ("max_distance",), d["max_distance"])
        from ..distance.field import band_problem

        if band_problem(float(d["max_distance"])):
            raise doc.error(("max_distance",), band_problem(float(d["max_distance"])))
        job.max_distance = float(d["max_distance"])
    names = set()
    for i, a in enumerate(d.get("attributes", [])):
        if a["name"] in names:
            raise doc.error(("attributes", i, "name"), f"attribute name {a['name']!r} repeats")
        names.add(a["name"])
        job.attributes.append(AttributeRef(a["name"], doc.input_file(a["source"]),
                                           doc.input_file(a["target"]), a.get("dtype"),
                                           a.get("values")))
    job.doc = doc
    return job
