"""A warp spec turned into a sequence of control lattices (one per animation frame).

The plan is computed on the lattice alone (moves, and handle solves against
the write map, need no pushforward), before any volume work, so every spec
error (an index outside the lattice, a handle outside the model) is reported
with its key path and line before anything is written.

A step may ``move`` control points (``by`` a displacement or ``to`` a point),
``drag`` handles (solved together, least norm, optionally limited to control
points within ``radius`` of a handle), and run over ``frames`` equal
increments. Moves are applied first, in order, then the drags are solved
against the moved lattice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..progress import log
from ..volume import Volume
from .handles import HandleError, map_params, solve
from .lattice import Lattice


@dataclass
class CaptureSettings:
    """The spec's ``capture`` settings: lattice, placement, oversample, pad, sampling."""

    lattice: tuple[int, int, int] = (9, 9, 9)
    placement: str = "uniform"
    oversample: float = 2.0
    pad: tuple[int, int, int] | None = None
    sampling: str = "linear"


@dataclass
class Frame:
    """One lattice state: 1-based spec step and increment within it, and its offsets ``dq``.

    ``handles``: on a step's last frame, its drags as ``(from, to, reached)``
    input-voxel positions (x, y, z), ``reached`` where the solved lattice sends
    ``from`` (for the miss report).

    A step's last frame holds its lattice (``end``); an increment before it holds
    only the step's start and change, shared by the step's frames, and makes its
    lattice when asked (``start + change * fraction``, the same numbers each time).
    A step of 10,000 frames on a 64^3 lattice would otherwise hold 63 GB of
    lattices that only ``--frames-to`` ever uses.
    """

    step: int
    sub: int
    handles: list = field(default_factory=list)
    end: np.ndarray | None = None
    start: np.ndarray | None = None
    change: np.ndarray | None = None
    fraction: float = 1.0

    @property
    def dq(self) -> np.ndarray:
        """The frame's control-point offsets (a new array for an increment before the end)."""
        if self.end is not None:
            return self.end
        return self.start + self.change * self.fraction


@dataclass
class WarpSpec:
    """Typed settings of a warp spec (see :func:`read_warp_spec`); the steps as given.

    ``background``, ``values`` and ``grid`` are None where the spec says
    nothing (the warp then decides: :mod:`volwarp_cli.warp.defaults`).
    """

    units: str = "world"
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    capture_given: set = field(default_factory=set)
    pushforward: str = "box"
    evaluator: str = "separable"
    background: float | None = None
    steps: list = field(default_factory=list)
    values: str | None = None
    grid: str | None = None


def _vec3(v):
    """Three ints of a schema integer or list of three (7.0 is an integer to the schema)."""
    return tuple(int(x) for x in ([v] * 3 if isinstance(v, (int, float)) else v))


def read_warp_spec(doc) -> WarpSpec:
    """Typed settings from a schema-validated warp :class:`SpecDoc`."""
    d = doc.data
    cap = d.get("capture", {}) or {}
    settings = CaptureSettings()
    if "lattice" in cap:
        settings.lattice = _vec3(cap["lattice"])
    if "placement" in cap:
        settings.placement = cap["placement"]
        if settings.placement == "tripled" and min(settings.lattice) < 6:
            raise doc.error(("capture", "placement"),
                            "the tripled placement needs a lattice of at least 6 points per axis")
    if "oversample" in cap:
        settings.oversample = float(cap["oversample"])
    if "pad" in cap:
        settings.pad = _vec3(cap["pad"])
    if "sampling" in cap:
        settings.sampling = cap["sampling"]
    steps = d.get("steps", [])
    for s, step in enumerate(steps):
        if "radius" in step and "drag" not in step:
            raise doc.error(("steps", s, "radius"), "radius limits a drag; this step has none")
    background = d.get("background")
    if background is not None:
        background = float(background)
        if not np.isfinite(background):
            raise doc.error(("background",), f"the background must be a finite number, got "
                            f"{background}")
    grid = d.get("grid")
    if grid == "input" and "pad" in cap:
        raise doc.error(("capture", "pad"), "pads a grown grid, but the spec's grid is input "
                        "(the output on the input's grid): remove one of them")
    return WarpSpec(units=d.get("units", "world"), capture=settings, capture_given=set(cap),
                    pushforward=d.get("pushforward", "box"),
                    evaluator=d.get("evaluator", "separable"),
                    background=background, steps=steps, values=d.get("values"), grid=grid)


class SpecUnits:
    """A spec's points and displacements in input voxels (world LPS mm or voxel units)."""

    def __init__(self, vol: Volume, units: str = "world"):
        self.vol = vol
        self.units = units
        self.matrix = vol.direction * vol.spacing[None, :]
        self.inverse = np.linalg.inv(self.matrix)

    def point(self, p) -> np.ndarray:
        """Input voxel indices of spec point ``p`` (given in the spec's units)."""
        p = np.asarray(p, dtype=np.float64)
        return p if self.units == "voxel" else self.vol.world_to_index(p)

    def vector(self, v) -> np.ndarray:
        """Spec displacement ``v`` (in the spec's units) in input voxels."""
        v = np.asarray(v, dtype=np.float64)
        return v if self.units == "voxel" else self.inverse @ v

    def world(self, idx) -> np.ndarray:
        """World (LPS mm) points of input voxel indices ``idx``."""
        return self.vol.index_to_world(idx)


def check_indices(doc, spec: WarpSpec, lattice) -> None:
    """Every move index inside the lattice, else a SpecError naming it."""
    for s, step in enumerate(spec.steps):
        for m, mv in enumerate(step.get("move", [])):
            idx = mv["index"]
            if any(i >= c for i, c in zip(idx, lattice, strict=False)):
                raise doc.error(("steps", s, "move", m, "index"),
                                f"control point {idx} is outside the {lattice[0]}x{lattice[1]}x"
                                f"{lattice[2]} lattice (indices 0..{lattice[0] - 1}, "
                                f"0..{lattice[1] - 1}, 0..{lattice[2] - 1})")


#: The largest control point displacement (input voxels) a spec may ask for: the box
#: pushforward's spans and fixed-point sums run in 64-bit integers, and a move of 1e42
#: wrapped them (values far outside the input's range, exit 0); 2**40 voxels is beyond any
#: model and far within them.
MAX_DISPLACEMENT = float(2 ** 40)


def _check_reach(doc, key: tuple, displacement) -> None:
    """A spec error at ``key`` if ``displacement`` (input voxels) is beyond :data:`MAX_DISPLACEMENT`."""
    reach = float(np.abs(displacement).max(initial=0.0))
    if not reach <= MAX_DISPLACEMENT:  # (NaN too)
        raise doc.error(key, f"moves a control point {reach:.3g} input voxels, beyond the "
                        f"{MAX_DISPLACEMENT:.3g} the warp's exact sums can place (a value in "
                        "the wrong units?)")


def plan(doc, spec: WarpSpec, grid: Lattice, dq0: np.ndarray, geom: SpecUnits) -> list[Frame]:
    """The lattice after every increment of every step, in order."""
    check_indices(doc, spec, grid.lattice)
    uniform = grid.uniform_positions()
    frames = []
    current = np.array(dq0, dtype=np.float64)
    for s, step in enumerate(spec.steps):
        work = current.copy()
        _warn_idle(s, step)
        moves = step.get("move", [])
        moved = []  # (each move's offset as it left it: one check below, 729 took 1.1 ms)
        with np.errstate(over="ignore", invalid="ignore"):  # (a later move of one refused)
            for mv in moves:
                i, j, k = (int(v) for v in mv["index"])  # (7.0: an integer to the schema)
                if "by" in mv:
                    work[k, j, i] += geom.vector(mv["by"])
                else:
                    work[k, j, i] = geom.point(mv["to"]) - uniform[k, j, i]
                moved.append(work[k, j, i].tolist())
        if moved:
            m = int(np.argmin(np.all(np.abs(moved) <= MAX_DISPLACEMENT, axis=1)))  # (NaN too)
            _check_reach(doc, ("steps", s, "move", m, "by" if "by" in moves[m] else "to"),
                         moved[m])
        if "drag" in step:
            drags = step["drag"]
            src = np.array([geom.point(h["from"]) for h in drags])
            dst = np.array([geom.point(h["to"]) for h in drags])
            free = None
            if "radius" in step:
                radius = float(step["radius"])
                pts = uniform + work  # input voxels
                if geom.units == "world":
                    pts_w = geom.world(pts.reshape(-1, 3)).reshape(pts.shape)
                    src_w = geom.world(src)
                else:
                    pts_w, src_w = pts, src
                dist = np.linalg.norm(pts_w[None] - src_w[:, None, None, None, :], axis=-1)
                free = np.any(dist <= radius, axis=0)
            try:
                delta, params, residual = solve(work, grid, src, dst, free)
            except HandleError as exc:
                message = str(exc)
                if "outside the region" in message:  # in the spec's own numbers and units
                    given = [float(v) for v in drags[exc.index]["from"]]
                    units = "LPS mm" if geom.units == "world" else "input voxels x y z"
                    message = (f"point {[round(v, 4) for v in given]} ({units}) is outside "
                               "the region the warped model covers (the input's voxel box, "
                               "carried by the earlier steps)")
                raise doc.error(("steps", s, "drag", exc.index, "from"), message) from None
            # (the handle that asks the most, before a warning about a compromise it forced)
            _check_reach(doc, ("steps", s, "drag",
                               int(np.argmax(np.abs(dst - src).max(axis=1))), "to"), delta)
            if free is not None:
                _warn_strong_radius(s, float(step["radius"]), delta, src, dst, geom)
            work = work + delta
            reached = map_params(work, grid, params)
            handles = [(src[i], dst[i], reached[i]) for i in range(len(src))]
            if residual > 1e-3:  # (the miss in the spec's units: 2 voxels of 2.5 mm are 5 mm)
                miss = reached - dst if geom.units == "voxel" else (reached - dst) @ geom.matrix.T
                log.warning("steps[%d]: the handles cannot all be reached (largest miss %.3g "
                            "%s): they conflict, or lie closer together than the control "
                            "points and pull apart; used a bounded least-squares compromise",
                            s, float(np.linalg.norm(miss, axis=1).max()),
                            "voxel" if geom.units == "voxel" else "mm")
        else:
            handles = []
        _check_reach(doc, ("steps", s), work)  # (the moves and drags together)
        n = int(step.get("frames", 1))
        total = work - current if n > 1 else None
        for f in range(1, n):
            frames.append(Frame(s + 1, f, start=current, change=total, fraction=f / n))
        frames.append(Frame(s + 1, n, handles, end=work.copy()))
        current = work
    return frames


def _warn_idle(s: int, step: dict) -> None:
    """Say a step that moves nothing, and a control point that one step moves twice.

    Both are the spec's right (a step of frames only holds the model still;
    moves apply in order: the ``by``s add up, the last ``to`` wins), and
    both are more often a slip: a step's moves left out, an index typed twice.
    """
    if not step.get("move") and not step.get("drag"):
        log.warning("warning: steps[%d] moves nothing: its %s the same lattice", s,
                    f"{int(step.get('frames', 1))} frames are" if int(step.get("frames", 1)) > 1
                    else "frame is")
    seen = set()
    for m, mv in enumerate(step.get("move", [])):
        index = tuple(int(v) for v in mv["index"])
        if index in seen:
            log.warning("warning: steps[%d].move[%d]: control point %s is moved again in this "
                        "step (a 'by' adds to its move, a 'to' replaces it)", s, m, list(index))
        seen.add(index)


def warn_folds(frames: list[Frame], grid: Lattice) -> None:
    """Warn of each step whose lattice folds the map (:func:`.folds.fold_count`).

    Called once the plan is accepted (a refusal is said alone). The warp goes
    on: the pushforward sums what lands where, and the exports say where a
    field has no single preimage.
    """
    from .folds import fold_count

    uniform = grid.uniform_positions()
    last = {frame.step: frame for frame in frames}  # (each step's last frame: its lattice)
    before, was = None, 0
    for step, frame in last.items():
        if before is None or not np.array_equal(frame.dq, before):
            folded, samples = fold_count(uniform + frame.dq)
        before = frame.dq
        if folded and not was:  # (the step that folds it; the later ones only carry it)
            log.warning("warning: steps[%d]: the lattice folds the map: its Jacobian's sign "
                        "flips at %d of %d points sampled across the lattice (parts of the "
                        "model pass through each other, their samples summed where they "
                        "land); smaller moves, or a larger radius, keep it one-to-one",
                        step - 1, folded, samples)
        was = folded


#: A radius whose freed control points must move this many times as far as the handles
#: gets a warning (none: about 2.4 times; a one-point radius: 3.4 times and more).
STRONG_RADIUS = 3.0


def _warn_strong_radius(s: int, radius: float, delta, src, dst, geom) -> None:
    """Warn when ``radius`` left so few control points free that they move far past the drag.

    A smaller radius makes a drag stronger, not gentler: the fewer free points
    must move farther to carry the handles (and still reach two lattice
    spacings around themselves). Lengths in world mm (the spec's voxels with
    ``units: voxel``).
    """
    to_len = (lambda v: v) if geom.units == "voxel" else (lambda v: v @ geom.matrix.T)
    moved = np.linalg.norm(to_len(np.asarray(delta).reshape(-1, 3)), axis=1)
    drag = np.linalg.norm(to_len(np.asarray(dst) - np.asarray(src)), axis=1)
    if drag.max() <= 0:
        return
    ratio = float(moved.max() / drag.max())
    if ratio > STRONG_RADIUS:
        unit = "voxels" if geom.units == "voxel" else "mm"
        log.warning("steps[%d]: with radius %g, %d free control point(s) move up to %.3g %s, "
                    "%.1f times the largest drag (%.3g %s): a smaller radius makes a drag "
                    "stronger, not gentler; for a local, smooth edit give a larger radius or "
                    "a finer lattice", s, radius, int(np.count_nonzero(moved > 0)),
                    moved.max(), unit, ratio, drag.max(), unit)


def default_pad(frames: list[Frame], dq0: np.ndarray) -> tuple[int, int, int]:
    """Padding that holds the image of every frame's map: max control-point displacement + 1.

    The B-spline weights are non-negative and sum to one, so no point moves
    further (per axis) than the largest control-point displacement.
    """
    pad = np.zeros(3)
    for fr in frames:
        pad = np.maximum(pad, np.abs(fr.dq - dq0).reshape(-1, 3).max(axis=0))
    return tuple(int(math.ceil(p - 1e-9)) + 1 if p > 0 else 0 for p in pad)
