"""The sweep spec as objects: sweeps, scenes (CVG operator trees) and the output grid.

:func:`parse_sweep_spec` turns a schema-checked :class:`~volwarp_cli.spec.SpecDoc`
into a :class:`SweepSpec`; every semantic error found here (a missing
template, a zero-length segment, an unknown field in ``combine``) is a
:class:`~volwarp_cli.errors.SpecError` with the key path and line.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import Geometry
from ..spec.functions import (
    MAX_ANGLE,
    MAX_VALUE,
    Function,
    check_bounded,
    parse_function,
    spec_error,
)
from .cvg import OPERATORS, resolve_ops
from .frames import (
    Frames,
    RotationMinimising,
    Secondary,
    SweepFunctions,
    compute_frames,
    prepare_frames,
)
from .templates import Template, TemplateLoader
from .trajectory import Arc, Bezier, Line, Polyline, Segment

DEFAULT_LONGEST_SIDE = 128


@dataclass
class Sweep:
    """One sweep: a template per field, the trajectory's segments and their functions.

    ``ops``: the per-field operators where the sweep meets itself; ``tau``: its own
    voxelising step, if given.
    """

    templates: dict[str, Template]
    segments: list[Segment]
    functions: list[SweepFunctions]
    ops: dict[str, str]
    tau: float | None = None
    key: tuple = ()

    def bounds(self, samples: int = 257) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box of the swept template squares (sampled densely)."""
        pts = []
        for i, (seg, fns) in enumerate(zip(self.segments, self.functions, strict=True)):
            s = seg.dense_parameters(samples)
            fr = compute_frames(seg, fns, s, i)
            pts.append(fr.corners().reshape(-1, 3))
            if isinstance(seg, Polyline):  # joints turn about the vertices
                left = compute_frames(seg, fns, seg.breaks(), i, left=True)
                pts.append(left.corners().reshape(-1, 3))
                r = 0.5 * np.hypot(left.SX, left.SY)
                pts.append(left.P - r[:, None])
                pts.append(left.P + r[:, None])
        p = np.concatenate(pts)
        return p.min(axis=0), p.max(axis=0)

    def frames(self, index: int, s) -> Frames:
        """The template frames of segment ``index`` at normalised parameters ``s``."""
        return compute_frames(self.segments[index], self.functions[index], np.asarray(s), index)

    def joined_ends(self) -> list[bool]:
        """Per segment: whether its last template is the next segment's first.

        The next of the last segment is the first (a closed trajectory: a full
        arc, a loop of segments). Where they join, the plane of that template is
        one instance met from both sides, not two: it belongs to the next
        segment only, as inside a segment each template plane belongs to the
        piece that starts there. Counted twice, ``difference`` emptied it and
        ``sum`` doubled it. Frames join when position, axes and size agree to
        1e-9 (relative to the template's size and distance from the origin), and
        the path crosses the template's plane the same way on both sides: a path
        that turns back (out and back under a constant direction) meets the
        plane again from the side it came from, a second instance.
        """
        from .frames import _tangent

        n = len(self.segments)
        ends = [self.frames(i, [1.0]) for i in range(n)]
        starts = [self.frames(i, [0.0]) for i in range(n)]
        out = []
        for i in range(n):
            j = (i + 1) % n
            a, b = ends[i], starts[j]
            size = max(1.0, float(np.abs(a.P).max()), float(a.SX[0]), float(a.SY[0]))
            same = bool(
                np.abs(a.P - b.P).max() <= 1e-9 * size
                and max(np.abs(getattr(a, f) - getattr(b, f)).max()
                        for f in ("EX", "EY", "EZ")) <= 1e-9
                and abs(float(a.SX[0] - b.SX[0])) <= 1e-9 * size
                and abs(float(a.SY[0] - b.SY[0])) <= 1e-9 * size)
            if same:  # (the way through the plane: the tangent's side of its normal)
                ta = _tangent(self.segments[i], np.array([1.0]), True)[0]
                tb = _tangent(self.segments[j], np.array([0.0]), False)[0]
                way_a = float(ta @ a.EZ[0]) / max(float(np.linalg.norm(ta)), 1e-300)
                way_b = float(tb @ b.EZ[0]) / max(float(np.linalg.norm(tb)), 1e-300)
                # (turned back: clearly opposite ways; a path along its plane goes on)
                same = not (way_a * way_b < 0 and min(abs(way_a), abs(way_b)) > 1e-9)
            out.append(same)
        return out


@dataclass
class SceneNode:
    """A node of a scene's CVG operator tree: its children combined per field by ``ops``."""

    ops: dict[str, str]
    children: list  # Sweep | SceneNode
    key: tuple = ()

    def sweeps(self) -> list[Sweep]:
        """Every sweep under this node, depth first, in order."""
        out = []
        for c in self.children:
            out.extend(c.sweeps() if isinstance(c, SceneNode) else [c])
        return out

    def field_names(self) -> list[str]:
        """The fields of the sweeps under this node, each once, in order of appearance."""
        names: list[str] = []
        for sw in self.sweeps():
            for n in sw.templates:
                if n not in names:
                    names.append(n)
        return names


@dataclass
class SweepSpec:
    """A parsed sweep spec: one sweep or a scene, the grid settings, ``tau``, the method."""

    root: Sweep | SceneNode
    grid: dict = field(default_factory=dict)
    tau: float | None = None
    method: str = "voxelize"
    doc: object = None

    def sweeps(self) -> list[Sweep]:
        """Every sweep of the spec, in order."""
        return self.root.sweeps() if isinstance(self.root, SceneNode) else [self.root]

    def field_names(self) -> list[str]:
        """The output fields, each once, in order of appearance."""
        if isinstance(self.root, SceneNode):
            return self.root.field_names()
        return list(self.root.templates)

    def bounds(self):
        """World bounding box ``(min, max)`` of all the sweeps' template squares."""
        los, his = zip(*(sw.bounds() for sw in self.sweeps()), strict=True)
        return np.min(los, axis=0), np.max(his, axis=0)


# -- parsing ------------------------------------------------------------------------
def _vec(doc, path, value, n=3, name="value", bounded=True) -> np.ndarray:
    """``n`` finite numbers at key ``path``; ``bounded``: each within ``MAX_VALUE``.

    (A point of 1e300 made a direction of inf / inf, and a ZeroDivisionError.)
    """
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise spec_error(doc, path, f"{name} must be {n} finite numbers")
    if bounded:
        check_bounded(doc, path, arr.tolist())
    return arr


def _urange(doc, path, body) -> tuple[float, float]:
    if "u" not in body:
        return 0.0, 1.0
    u = _vec(doc, path + ("u",), body["u"], 2, "u", bounded=False)
    if u[0] == u[1]:
        raise spec_error(doc, path + ("u",), "u range must not be empty")
    return float(u[0]), float(u[1])


def parse_segment(doc, path: tuple, item: dict) -> Segment:
    """One trajectory segment from the spec (a SpecError for a degenerate one)."""
    kind = next(iter(item))
    body = item[kind]
    bp = path + (kind,)
    u0, u1 = _urange(doc, bp, body)
    if kind == "line":
        a = _vec(doc, bp + ("from",), body["from"], name="from")
        b = _vec(doc, bp + ("to",), body["to"], name="to")
        if np.linalg.norm(b - a) == 0:
            raise spec_error(doc, bp, "a line needs two different points ('from' equals 'to')")
        return Line(u0=u0, u1=u1, path=bp, start=a, stop=b)
    if kind == "arc":
        c = _vec(doc, bp + ("center",), body["center"], name="center")
        axis = _vec(doc, bp + ("axis",), body.get("axis", [0, 0, 1]), name="axis")
        if np.linalg.norm(axis) == 0:
            raise spec_error(doc, bp + ("axis",), "the arc's axis must not be zero")
        check_bounded(doc, bp + ("radius",), body["radius"])
        for key in ("start", "end"):
            check_bounded(doc, bp + (key,), body.get(key), limit=MAX_ANGLE,
                          what="arc angles (degrees)")
        r = float(body["radius"])
        start = float(body.get("start", 0.0))
        end = float(body.get("end", 360.0))
        if start == end:
            raise spec_error(doc, bp + ("end",), "an arc needs 'end' different from 'start'")
        if r <= 0:
            raise spec_error(doc, bp + ("radius",), "radius must be positive")
        return Arc(u0=u0, u1=u1, path=bp, center=c, radius=r, axis=axis, start_deg=start,
                   end_deg=end)
    pts = np.asarray(body["points"], dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise spec_error(doc, bp + ("points",), "points must be a list of [x, y, z]")
    check_bounded(doc, bp + ("points",), pts.tolist())
    if kind == "bezier":
        if np.ptp(pts, axis=0).max() == 0:
            raise spec_error(doc, bp + ("points",), "a Bezier curve needs control points "
                             "that are not all the same")
        return Bezier(u0=u0, u1=u1, path=bp, points=pts)
    steps = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    if np.any(steps == 0):
        i = int(np.argmax(steps == 0)) + 1
        raise spec_error(doc, bp + ("points", i), "a polyline point repeats the previous one")
    edges = np.diff(pts, axis=0) / steps[:, None]
    # (the sweep's joint rotates one edge's frame into the next: no rotation turns back)
    back = np.flatnonzero(np.sum(edges[1:] * edges[:-1], axis=1) < np.cos(np.pi - 1e-6))
    if back.size:
        raise spec_error(doc, bp + ("points", int(back[0]) + 1), "the polyline turns back on "
                         "itself (180 degrees) at this point: no turn of the template leads "
                         "from one edge to the next")
    return Polyline(u0=u0, u1=u1, path=bp, points=pts)


def parse_trajectory(doc, path: tuple, items) -> list[Segment]:
    """The segments of a spec trajectory (a SpecError if it has none)."""
    if not isinstance(items, list) or not items:
        raise spec_error(doc, path, "the trajectory needs at least one segment")
    return [parse_segment(doc, path + (i,), it) for i, it in enumerate(items)]


def _vector_fn(doc, path, value, name) -> Function:
    fn = parse_function(value, path, doc, dim=3, name=name, limit=MAX_VALUE)
    return fn


def _direction(doc, path, value, n_segments):
    if value is None or value == "tangent":
        return "tangent"
    if isinstance(value, dict) and "trajectory" in value:
        return _secondary(doc, path, value, n_segments)
    return _vector_fn(doc, path, value, "direction")


def _up(doc, path, value, n_segments):
    if value is None:  # the default: a rotation-minimising frame (see frames.py)
        return RotationMinimising()
    if value == "binormal":
        return "binormal"
    if isinstance(value, dict) and "trajectory" in value:
        return _secondary(doc, path, value, n_segments)
    return _vector_fn(doc, path, value, "up")


def _secondary(doc, path, value, n_segments) -> Secondary:
    segs = parse_trajectory(doc, path + ("trajectory",), value["trajectory"])
    if len(segs) not in (1, n_segments):
        raise spec_error(doc, path + ("trajectory",),
                         f"a secondary trajectory has 1 segment or one per trajectory segment "
                         f"({n_segments}), got {len(segs)}")
    return Secondary(segs, path)


def parse_sweep(doc, path: tuple, body: dict, loader: TemplateLoader) -> Sweep:
    """One sweep: ``fields``, ``trajectory`` and its functions, at key ``path``."""
    segments = parse_trajectory(doc, path + ("trajectory",), body.get("trajectory"))
    n = len(segments)
    fields_spec = body.get("fields")
    if not fields_spec:
        raise spec_error(doc, path + ("fields",), "a sweep needs at least one field")
    templates = {}
    for name, fspec in fields_spec.items():
        fp = path + ("fields", name)
        if isinstance(fspec, (int, float)) and not isinstance(fspec, bool):
            fspec = {"value": fspec}
        path_fn = None
        if "path" in fspec:
            if "frames" not in fspec:
                raise spec_error(doc, fp + ("path",), "'path' (f(u)) goes with 'frames'")
            path_fn = parse_function(fspec["path"], fp + ("path",), doc, dim=None, name="path",
                                     limit=MAX_VALUE)
        templates[name] = loader.load(name, fspec, fp, path_fn)
    top = {k: body.get(k) for k in ("direction", "up", "scale")}
    functions = []
    for i, _seg in enumerate(segments):
        kind = next(iter(body["trajectory"][i]))
        sbody = body["trajectory"][i][kind]
        sp = path + ("trajectory", i, kind)

        def pick(key, sbody=sbody, sp=sp):
            if key in sbody:
                return sbody[key], sp + (key,)
            return top[key], path + (key,)

        dval, dpath = pick("direction")
        uval, upath = pick("up")
        sval, spath = pick("scale")
        if sval is None:
            sval = [1.0, 1.0]
        functions.append(SweepFunctions(
            direction=_direction(doc, dpath, dval, n),
            up=_up(doc, upath, uval, n),
            scale=parse_function(sval, spath, doc, dim=2, name="scale", limit=MAX_VALUE),
            direction_path=dpath, up_path=upath, doc=doc))
    ops = _ops(doc, path + ("combine",), body.get("combine"), list(templates))
    prepare_frames(segments, functions)
    tau = body.get("tau")
    return Sweep(templates, segments, functions, ops,
                 None if tau is None else float(tau), path)


def _ops(doc, path, value, names) -> dict[str, str]:
    if isinstance(value, dict):
        for k, v in value.items():
            if k != "default" and k not in names:
                raise spec_error(doc, path + (k,), f"no field named {k!r} "
                                 f"(fields: {', '.join(names)})")
            if v not in OPERATORS:
                raise spec_error(doc, path + (k,), f"unknown operator {v!r} "
                                 f"(known: {', '.join(OPERATORS)})")
    elif value is not None and value not in OPERATORS:
        raise spec_error(doc, path, f"unknown operator {value!r} (known: {', '.join(OPERATORS)})")
    return resolve_ops(value, names)


def parse_scene(doc, path: tuple, node: dict, loader: TemplateLoader):
    """A :class:`Sweep` or, for an ``of`` node, a :class:`SceneNode` of its children."""
    if "sweep" in node:
        return parse_sweep(doc, path + ("sweep",), node["sweep"], loader)
    children = [parse_scene(doc, path + ("of", i), c, loader) for i, c in enumerate(node["of"])]
    scene = SceneNode({}, children, path)
    scene.ops = _ops(doc, path + ("op",), node.get("op"), scene.field_names())
    return scene


def parse_sweep_spec(doc) -> SweepSpec:
    """A :class:`SweepSpec` from a schema-checked sweep spec."""
    data = doc.data
    loader = TemplateLoader(doc)
    if "scene" in data:
        for key in ("fields", "trajectory", "direction", "up", "scale", "combine"):
            if key in data:
                raise spec_error(doc, (key,), f"'{key}' belongs inside a sweep of the scene "
                                 "(a spec has either a scene or one sweep)")
        root = parse_scene(doc, ("scene",), data["scene"], loader)
    else:
        if "trajectory" not in data:
            raise spec_error(doc, (), "a sweep spec needs 'trajectory' and 'fields' (or 'scene')")
        root = parse_sweep(doc, (), data, loader)
    tau = data.get("tau")
    return SweepSpec(root, dict(data.get("grid") or {}), None if tau is None else float(tau),
                     data.get("method", "voxelize"), doc)


# -- the output grid ------------------------------------------------------------------
def _three(v):
    arr = np.asarray(v, dtype=np.float64)
    return np.full(3, float(arr)) if arr.ndim == 0 else arr


def fit_grid(spec: dict, lo: np.ndarray, hi: np.ndarray) -> Geometry:
    """The output grid from ``grid`` keys (shape, origin, spacing, margin) and the bounds.

    Given keys are kept; missing ones are fitted so the grid covers
    ``[lo - margin, hi + margin]``: without spacing the longest side gets
    ``shape`` (or 128) samples at isotropic spacing; without shape it is the
    count that covers the box; without origin the grid is centred on the box.
    The default margin is two voxels. The grid is axis-aligned (identity
    direction), as the sweep's samplers take it.
    """
    return sweep_geometry(*fit_grid_values(spec, lo, hi))


def sweep_geometry(shape_xyz, origin, spacing) -> Geometry:
    """The axis-aligned :class:`~volwarp_cli.geometry.Geometry` of a sweep's output grid.

    ``shape_xyz`` (x, y, z), ``origin`` and ``spacing``; the direction is the identity.
    """
    grid = Geometry.from_xyz(shape_xyz, spacing, origin)
    assert grid.identity_direction  # the sweep's samplers ignore direction
    return grid


def fit_grid_values(spec: dict, lo: np.ndarray,
                    hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The numbers of :func:`fit_grid`, not yet checked: shape (x, y, z), origin, spacing.

    For a caller that refuses absurd numbers (a spacing of 1e-300, a margin of
    1e300) with its own message before they make a grid.
    """
    shape = spec.get("shape")
    origin = spec.get("origin")
    spacing = spec.get("spacing")
    margin = spec.get("margin")
    ext0 = np.maximum(hi - lo, 1e-9)
    if spacing is None:
        n = np.asarray(shape, dtype=np.float64) if shape is not None else None
        longest = DEFAULT_LONGEST_SIDE if n is None else None
        m = margin if margin is not None else 0.0
        for _ in range(2):  # margin in voxels depends on spacing: settle it twice
            ext = ext0 + 2 * m
            if n is not None:
                sp = float(np.max(ext / np.maximum(n - 1, 1)))
            else:
                sp = float(ext.max() / (longest - 1))
            if margin is None:
                m = 2 * sp
        spacing = np.full(3, sp)
        margin = m
    spacing = _three(spacing)
    if margin is None:
        margin = 2 * float(spacing.min())
    glo = lo - margin
    ghi = hi + margin
    if shape is None:
        start = glo if origin is None else _three(origin)
        shape = np.maximum(np.ceil((ghi - start) / spacing - 1e-9).astype(int) + 1, 1)
    shape = np.asarray(shape, dtype=np.int64)
    if origin is None:
        centre = 0.5 * (glo + ghi)
        origin = centre - spacing * (shape - 1) / 2
    return shape, _three(origin), spacing


def output_grid(spec: SweepSpec, *, shape=None, spacing=None) -> Geometry:
    """The sweep's output grid: the spec's ``grid``, or ``shape`` or ``spacing`` instead.

    ``shape`` (x, y, z samples; the spacing fitted) or ``spacing`` (isotropic;
    the shape fitted) replace the spec's grid, keeping its margin
    (``volwarp sweep --shape/--spacing``); then :func:`fit_grid_values` fits
    what is missing around the sweep's bounds. Absurd numbers (a spacing of
    1e-300, a margin of 1e300, over :data:`~volwarp_cli.samples.MAX_AXIS`
    samples an axis) are refused before they make a grid: a
    :class:`~volwarp_cli.errors.SpecError` at the spec's key that made them,
    a :class:`~volwarp_cli.errors.BadUsage` when ``shape`` or ``spacing`` did.
    """
    from ..errors import BadUsage

    if shape is not None and spacing is not None:
        raise BadUsage("give --shape or --spacing, not both")
    if shape is not None and (np.ndim(shape) != 1 or len(shape) != 3
                              or any(int(v) != v or v < 1 for v in shape)):
        raise BadUsage(f"--shape: three whole numbers of samples (x y z), got {shape!r}")
    if spacing is not None and not (np.ndim(spacing) == 0 and np.isfinite(spacing)
                                    and spacing > 0):
        raise BadUsage(f"--spacing: a positive number, got {spacing!r}")
    grid_spec = dict(spec.grid)
    from ..samples import MAX_AXIS

    for i, n in enumerate(grid_spec.get("shape") or []):  # (1e20 was an OverflowError)
        if shape is None and spacing is None and isinstance(n, int) and n > MAX_AXIS:
            raise spec.doc.error(("grid", "shape", i), f"{n} samples is over the {MAX_AXIS} "
                                 "an axis may have")
    if shape is not None:
        grid_spec = {"shape": [int(v) for v in shape], "margin": grid_spec.get("margin")}
    elif spacing is not None:
        grid_spec = {"spacing": float(spacing), "margin": grid_spec.get("margin")}
    grid_spec = {k: v for k, v in grid_spec.items() if v is not None}
    lo, hi = spec.bounds()
    with np.errstate(over="ignore", invalid="ignore"):
        values = fit_grid_values(grid_spec, lo, hi)  # shape (x, y, z), origin, spacing
    _check_grid(*values, spec.doc, shape is not None or spacing is not None, lo, hi,
                grid_spec.get("margin"))
    return sweep_geometry(*values)


def _check_grid(shape_xyz, origin, spacing, doc, from_options: bool, lo, hi,
                margin=None) -> None:
    """Refuse a grid whose numbers are absurd (a spacing of 1e-300, a margin of 1e300).

    ``shape_xyz``, ``origin``, ``spacing``: the fitted grid's numbers, before they
    make a :class:`~volwarp_cli.geometry.Geometry`. A spec error at ``grid`` (a
    usage error when --shape/--spacing made it).
    """
    from ..errors import BadUsage
    from ..samples import MAX_AXIS

    shape = np.asarray(shape_xyz, dtype=np.float64)
    spacing = np.asarray(spacing, np.float64)
    values = np.concatenate([np.asarray(origin, np.float64).ravel(), spacing.ravel()])
    bounds = np.concatenate([np.ravel(lo), np.ravel(hi)]).astype(np.float64)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        across = (np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
                  + 2 * float(margin or 0.0)) / spacing
        ok = (np.all(np.isfinite(values)) and np.all((shape >= 1) & (shape <= MAX_AXIS))
              and np.all(np.abs(values) <= MAX_VALUE) and np.all(across <= MAX_AXIS))
    if ok:
        return
    what = (f"the output grid ({'x'.join(str(int(v)) if 0 <= v < 1e18 else '?' for v in shape)}"
            f" samples, spacing {' '.join(f'{v:g}' for v in np.ravel(spacing))}) is "
            f"absurd: at most {MAX_AXIS} samples per axis and coordinates within 1e15")
    if from_options:
        raise BadUsage(f"--shape/--spacing: {what}")
    given = doc.data.get("grid") or {}

    def extreme(name):
        v = np.abs(np.asarray(given[name], dtype=np.float64))
        return bool(np.any(v > MAX_VALUE) or (name == "spacing" and np.any(v < 1e-9)))
    names = [n for n in ("spacing", "margin", "origin", "shape") if n in given]
    bad = [n for n in names if extreme(n)]
    if bad:
        raise doc.error(("grid", bad[0]), what)
    if not np.all(np.abs(bounds) <= MAX_VALUE):  # the sweep itself: its trajectory or scale
        for name in ("scale", "trajectory", "scene"):
            if name in doc.data:
                raise doc.error((name,), f"the sweep reaches {np.abs(bounds).max():.3g} world "
                                "units from the origin (at most 1e15)")
    raise doc.error(("grid", names[0]) if names else ("grid",), what)
