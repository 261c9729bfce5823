"""The ``volwarp warp`` core: a captured volume, a spec, and the warped frames.

:func:`prepare` checks the spec against the capture, plans every lattice
state (see :mod:`volwarp_cli.bspline.plan`) and builds the :class:`~volwarp_cli.bspline.scene.Scene`;
:func:`run` computes the frames (incremental updates between them) and
:func:`output_volume` turns a target array into a Volume in the right place.
"""

from __future__ import annotations

import numpy as np

from ..bspline.capture import Capture
from ..bspline.plan import SpecUnits, WarpSpec, default_pad, plan, warn_folds
from ..bspline.scene import Scene
from ..errors import BadUsage, SpecError, VolwarpError
from ..progress import log, progress, timed
from ..samples import cast_samples
from ..volume import Volume
from .defaults import GRIDS, output_grid


def capture_as_spec(capture, settings, name: str, *inputs):
    """``capture(*inputs)`` with a spec's capture ``settings``; its errors name ``name``.

    ``capture``: one of :mod:`volwarp_cli.bspline.capture`'s (or
    :func:`.labels.capture_labels`), taking ``lattice``, ``placement``,
    ``oversample`` and ``sampling``; ``name``: the input's file.
    """
    try:
        return capture(*inputs, lattice=settings.lattice, placement=settings.placement,
                       oversample=settings.oversample, sampling=settings.sampling)
    except VolwarpError as exc:  # (a reader's error names its file already: once)
        text = str(exc)
        raise VolwarpError(text if text.startswith(f"{name}: ") else f"{name}: {text}") from None


def check_capture_settings(doc, spec: WarpSpec, cap: Capture, source: str) -> None:
    """A spec's capture settings must agree with an already captured scene."""
    have = {"lattice": tuple(cap.grid.lattice), "placement": cap.placement,
            "oversample": cap.oversample, "sampling": cap.sampling}
    want = {"lattice": tuple(spec.capture.lattice), "placement": spec.capture.placement,
            "oversample": spec.capture.oversample, "sampling": spec.capture.sampling}
    for key in ("lattice", "placement", "oversample", "sampling"):
        if key in spec.capture_given and have[key] != want[key]:
            raise doc.error(("capture", key),
                            f"is {want[key]!r} but {source} was captured with {have[key]!r} "
                            "(remove the key or capture again)")


#: the largest growth of the output per axis that a warp's own padding may cause
#: without --allow-growth (a mistyped 320 mm drag made a 181x217x1701 output): twice the
#: input, or 64 voxels more where that is larger (small inputs, moves of a few mm)
MAX_GROWTH = 2.0
MIN_GROWTH_VOXELS = 64


def pad_given(spec: WarpSpec, cap: Capture | None) -> str | None:
    """Where a target padding was given (which asks for the grown grid), or None."""
    if "pad" in spec.capture_given:
        return "capture.pad"
    if spec.capture.pad is not None or (cap is not None and cap.pad is not None):
        return "the capture file's pad"
    return None


def grid_of(spec: WarpSpec, cap: Capture | None, option: str | None = None) -> tuple[str, str]:
    """The output grid (``"input"`` or ``"grow"``) and why: :func:`.defaults.output_grid`."""
    return output_grid(option, spec.grid, pad_given(spec, cap))


def background_of(spec: WarpSpec, cap: Capture, option: float | None = None
                  ) -> tuple[float, str]:
    """The background value and why: :func:`.defaults.background_choice` of ``cap``'s border.

    (The option's, the spec's, else what the scan has outside its anatomy
    where the capture knows it, else 0.)
    """
    from .defaults import background_choice

    return background_choice(option, spec.background, cap.border)


def prepare(cap: Capture, doc, spec: WarpSpec, *, method: str | None = None,
            evaluator: str | None = None, background: float | None = None,
            allow_growth: bool = False, grid: str | None = None):
    """The scene (with its target padding) and the planned frames.

    ``method``, ``evaluator``: override the spec's; ``background``: the
    spec's, else the input's border (:func:`background_of`). ``grid``:
    ``"input"``, the output on the input's grid (no padding: what moves
    past it is cut off), or ``"grow"``, a target padded to hold every move
    (the spec's or the capture's pad, else the largest displacement + 1);
    None: :func:`grid_of` (input unless the spec or a pad asks for growth).
    ``allow_growth`` (the grown grid only): let the padding the moves need
    make the output more than ``MAX_GROWTH`` times the input, and more than
    ``MIN_GROWTH_VOXELS`` voxels larger, along an axis (refused otherwise,
    before anything of that size is made). The target is not made here: the
    one-shot warp computes it block by block (:class:`.blocks.WarpOperation`,
    the executor deciding whether the whole fits), the frames in full
    (:meth:`~volwarp_cli.bspline.scene.Scene.compute` refuses what does not fit).
    """
    if grid is None:
        grid, _ = grid_of(spec, cap)
    if grid not in GRIDS:
        raise ValueError(f"grid must be one of {', '.join(GRIDS)}, got {grid!r}")
    if allow_growth and grid == "input":
        raise BadUsage("--allow-growth lets a grown grid grow past twice the input, but the "
                       "output is on the input's grid (give --grid grow)")
    geom = SpecUnits(cap.geometry, spec.units)
    dq0 = cap.dq
    with timed("plan lattice moves"):
        frames = plan(doc, spec, cap.grid, dq0, geom)
    if grid == "input":
        pad = (0, 0, 0)
        given = pad_given(spec, cap)
        if given is not None:
            log.info("%s not used: the output is on the input's grid", given)
    elif spec.capture.pad is not None:
        pad = spec.capture.pad
    elif cap.pad is not None:
        pad = cap.pad
    else:
        pad = default_pad(frames, dq0)
        sizes = [(int(i), int(i) + 2 * int(p)) for i, p in zip(cap.grid.input_shape, pad,
                                                                 strict=True)]
        grown = [t / i for i, t in sizes]
        if not allow_growth and any(t > max(MAX_GROWTH * i, i + MIN_GROWTH_VOXELS)
                                    for i, t in sizes):
            shape = "x".join(_voxels(int(i) + 2 * int(p))
                             for i, p in zip(cap.grid.input_shape, pad, strict=True))
            times = f"{max(grown):.1f}" if max(grown) < 1e6 else f"{max(grown):.3g}"
            raise SpecError(f"the moves reach so far that the output would be {shape} "
                            f"voxels ({times} times the input's "
                            f"{'x'.join(map(str, cap.grid.input_shape))} along an axis): a "
                            "mistyped move or drag? Give --allow-growth (or the spec's "
                            "capture.pad) to make it", file=getattr(doc, "file", None))
    needed = default_pad(frames, dq0)
    _check_target_shape([int(i) + 2 * int(p) for i, p in zip(cap.grid.input_shape, pad,
                                                             strict=True)], pad)
    if grid == "grow" and any(p < n - 1 for p, n in zip(pad, needed, strict=False)):
        log.warning("pad %s is smaller than the largest displacement %s: material moved "
                    "outside the padded grid is cut off", list(pad), [max(n - 1, 0) for n in needed])
    warn_folds(frames, cap.grid)
    scene = Scene(cap.voxmap, cap.grid, dq0, pad, method=method or spec.pushforward,
                  evaluator=evaluator or spec.evaluator,
                  background=background_of(spec, cap, background)[0],
                  domain_range=cap.stats[:2])
    return scene, frames


def _voxels(v: int) -> str:
    """A count of voxels for a message: as it is, or ``2e+19`` past a billion."""
    return str(v) if v < 10**9 else f"{v:.3g}"


def _check_target_shape(tshape, pad) -> None:
    """Refuse a padded target longer than :data:`~volwarp_cli.samples.MAX_AXIS` along an axis.

    Before anything of its size, or its shape, is made (numpy cannot make
    some); a target within it is the executor's to fit in memory or blocks.
    """
    from ..errors import OutOfMemoryError
    from ..memory import human_bytes
    from ..samples import MAX_AXIS, voxel_count

    if max(tshape) <= MAX_AXIS:
        return
    raise OutOfMemoryError(f"the warped target ({'x'.join(map(_voxels, tshape))} voxels, pad "
                           f"{' '.join(_voxels(int(p)) for p in pad)}) needs "
                           f"{human_bytes(voxel_count(tshape) * 4)}: more than {MAX_AXIS} "
                           "voxels along an axis, which no memory or disk holds")


def run(scene: Scene, frames, on_frame) -> np.ndarray:
    """Render every frame, incrementally: ``on_frame(n, frame_or_None, target)`` after each.

    Frame 0 (the unmoved lattice) is computed in full, keeping the
    accumulators; each later frame is a local update of them (see
    :meth:`Scene.set_lattice`). Returns the last target. (The final lattice
    alone is the one-shot warp, :class:`.blocks.WarpOperation`.)
    """
    with timed("warp frame 0 (full)"):
        on_frame(0, None, scene.compute())
    with progress(len(frames), "warp") as bar:
        for n, fr in enumerate(frames, start=1):
            with timed(f"warp frame {n} (step {fr.step}, increment {fr.sub})"):
                scene.set_lattice(fr.dq)
            on_frame(n, fr, scene.out)
            bar.advance()
    return scene.out


def output_volume(cap: Capture, scene: Scene, target: np.ndarray, *, crop: bool = False,
                  dtype=None) -> Volume:
    """The target as a Volume: the input's dtype, spacing, direction and meta.

    The padded target's origin is shifted by ``pad`` voxels so that unwarped
    anatomy stays at the same world position; ``crop`` cuts back to the
    input's extent (and origin).
    """
    window, origin = _output_window(cap, scene, crop)
    data = cast_samples(np.ascontiguousarray(target[window]), dtype or cap.input_dtype,
                        what="warped volume")
    return cap.geometry.with_data(data, origin=origin)


def output_planes(cap: Capture, scene: Scene, *, crop: bool = False, dtype=None):
    """:func:`output_volume` for a target that arrives as z planes.

    Returns the output's :class:`~volwarp_cli.volume.Header` (its shape, dtype
    and geometry: the file's header), and ``convert(z0, planes)``: target planes
    [z0, z0 + k) as ``(output z0, samples)``, the part :func:`output_volume`
    keeps and converts in the same way, or None when it keeps none of them.
    """
    window, origin = _output_window(cap, scene, crop)
    out_dtype = np.dtype(dtype or cap.input_dtype)
    shape = tuple(w.stop - w.start for w in window)
    header = cap.geometry.replace(shape=shape, dtype=out_dtype, origin=origin)
    wz, wy, wx = window

    def convert(z0: int, planes: np.ndarray):
        a, b = max(z0, wz.start), min(z0 + len(planes), wz.stop)
        if a >= b:
            return None
        part = np.ascontiguousarray(planes[a - z0:b - z0, wy, wx])
        return a - wz.start, cast_samples(part, out_dtype, what="warped volume")

    return header, convert


def output_window_box(cap: Capture, scene: Scene, crop: bool):
    """The output's part of the target as a :class:`~volwarp_cli.box.Box` (z, y, x)."""
    from ..box import Box

    window, _ = _output_window(cap, scene, crop)
    return Box([w.start for w in window], [w.stop for w in window])


def _output_window(cap: Capture, scene: Scene, crop: bool):
    """The output's part of the target (slices z, y, x) and its origin.

    The padded target's origin is shifted by ``pad`` voxels so that unwarped
    anatomy stays in place; ``crop`` keeps the input's extent (and origin).
    """
    g = cap.geometry
    pad = np.array(scene.pad)
    tx, ty, tz = scene.target_shape
    if crop:
        px, py, pz = (int(v) for v in pad)
        nx, ny, nz = cap.grid.input_shape
        return (slice(pz, pz + nz), slice(py, py + ny), slice(px, px + nx)), g.origin
    origin = g.origin - g.direction @ (g.spacing * pad)
    return (slice(0, tz), slice(0, ty), slice(0, tx)), origin
