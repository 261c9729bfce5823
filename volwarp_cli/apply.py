"""Resampling an input through a chain of transforms, as an operation of the executor.

An output voxel ``p`` (LPS mm, the output grid's) takes the input's sample at
``T(p)``, ``T`` the :class:`~volwarp_cli.transforms.model.Chain` (output ->
input, as ITK's ``Resample``, ``antsApplyTransforms`` and transformix). The
interpolation is ITK's: inside the input's buffer (continuous index within
``[-0.5, n - 0.5)``) linear with the neighbours beyond the edge clamped,
nearest rounded half up, or cubic B-spline on mirror-extended coefficients;
elsewhere the background.

:class:`ApplyOperation` computes any block of the output from the input
region the chain needs for it, bounded before any sample is read
(each step's ``box``): for a linear chain exactly, the box of the
block's corners mapped; through a displacement field, grown by the field's
range over the box (per-tile extremes, computed once); through a B-spline,
by the range of the coefficients whose support meets it (the convex hull
property); then the interpolation's support. The block's points are mapped
and sampled part by part from that region. In memory the whole output is
one block; by blocks each task reads its own region.

Cubic B-spline interpolation needs the input's spline coefficients, whose
exact prefilter (an infinite recursive filter, ``scipy.ndimage.spline_filter``)
makes every coefficient depend on the whole line: a block would then differ
from the whole by the cut. Here the prefilter is its impulse response
``sqrt(3) z^|k|`` (``z = sqrt(3) - 2``) truncated to ``|k| <= PREFILTER_TAPS``
on the mirror-extended input (the boundary ITK and ``mode="mirror"`` use):
every coefficient is then the same sum of the same samples whichever block
computes it, so in memory and by blocks give the same bytes, at the cost of
a halo of ``PREFILTER_TAPS`` voxels. The truncation's error is at most
``3 * 2 sqrt(3) |z|^16 / (1 - |z|)``, 1e-8 of the samples' largest magnitude
(measured against ``spline_filter(mode="mirror")`` on noise: 5.6e-9 of the
range).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .box import Box
from .errors import BadUsage
from .execute import Operation
from .samples import holds_value
from .transforms.model import Affine, Chain, DisplacementField

INTERPOLATIONS = ("linear", "nearest", "bspline")
#: half the prefilter's taps (see the module notes)
PREFILTER_TAPS = 15
_POLE = math.sqrt(3.0) - 2.0
#: output points mapped at a time by one thread
PART_POINTS = 1 << 18
#: coefficients mirrored beyond the input's edges for the cubic kernel (its support's reach)
CUBIC_PAD = 2
#: scipy's line buffers of one ``correlate1d`` (two of ``BUFFER_SIZE`` doubles, or of one line)
_LINE_BUFFER_DOUBLES = 256000
#: bytes of a point being mapped and sampled (its mapped coordinates twice, the samples, the cast)
SCRATCH_PER_POINT = 120
#: bytes of a block beyond its arrays (index arrays, the Python objects of its parts)
BLOCK_OVERHEAD = 1 << 16


def _prefilter_weights() -> np.ndarray:
    k = np.arange(-PREFILTER_TAPS, PREFILTER_TAPS + 1)
    return math.sqrt(3.0) * _POLE ** np.abs(k)


def _mirror(i: np.ndarray, n: int) -> np.ndarray:
    """Mirror indices into ``[0, n)`` without repeating the edge (ITK's, scipy's ``mirror``)."""
    if n == 1:
        return np.zeros_like(i)
    period = 2 * (n - 1)
    i = np.abs(i) % period
    return np.where(i >= n, period - i, i)


def index_affine(geometry) -> Affine:
    """A grid's index (x, y, z) -> world map."""
    return Affine(np.asarray(geometry.matrix, float), np.asarray(geometry.origin, float), "grid")


class ApplyOperation(Operation):
    """The input resampled on ``grid`` through ``chain`` (module notes).

    Parameters
    ----------
    source : (Z, Y, X) array or sliceable lazy source
        The input's samples.
    in_grid : Geometry
        The input's grid.
    chain : Chain
        Output (fixed) points to input (moving) points.
    grid : Geometry
        The output grid.
    interpolation : {"linear", "nearest", "bspline"}
    background : float
        The value of output voxels whose point is outside the input.
    target : Target
        The output (its ``dtype``: the samples are rounded and clipped to it).
    """

    KEY = "resampled"

    def __init__(self, source, in_grid, chain: Chain, grid, *, interpolation: str,
                 background: float, target, name: str = "the input"):
        if interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {INTERPOLATIONS}")
        self.source, self.in_grid, self.grid = source, in_grid, grid
        self.chain = chain
        self.interpolation = interpolation
        self.name = name
        self.background = float(background)
        self.targets = {self.KEY: target}
        self.dtype = np.dtype(target.dtype)
        self.in_dtype = np.dtype(source.dtype)
        to_index = index_affine(in_grid).inverse()
        ops = [index_affine(grid)] + list(chain.steps) + [to_index]
        self.ops = Chain(ops).simplified()
        #: fields read by windows, block by block (larger than memory)
        self.windowed = any(_windowed(op) for op in self.ops)
        self.n_xyz = np.array(in_grid.shape_xyz, dtype=np.int64)
        nx, ny, nz = grid.shape_xyz
        kinds = ", ".join(s.name for s in chain.steps) or "identity"
        self.what = (f"the resampling of {name} to {nx}x{ny}x{nz} voxels ({interpolation}; "
                     f"{kinds})")
        #: a label map's ids (resampled as labels), whose absence from the output is said
        self.label_ids = None

    def __getstate__(self):
        # (a task in another process writes through the executor's writers: the target
        # stays here)
        state = dict(self.__dict__)
        state["targets"] = {}
        state["output_name"] = self._output  # (what its casts' messages name)
        if self.label_ids is not None:  # (a task notes what it holds; the ids stay here:
            state["label_ids"] = np.empty(0, self.label_ids.dtype)  # 474,552 a task, slow)
        return state

    # -- regions -------------------------------------------------------------------------
    def _support(self, lo: np.ndarray, hi: np.ndarray) -> Box | None:
        """The input box (z, y, x) the interpolation reads for points in index box ``[lo, hi]``."""
        n = self.n_xyz
        lo = np.maximum(lo, -0.5)
        hi = np.minimum(hi, n - 0.5)
        if np.any(~(lo <= hi)):
            return None
        # one voxel more on each side: the kernels map each point on their own, and their
        # rounding may put a point a hair beyond the bound's corner
        if self.interpolation == "nearest":
            a, b = np.floor(lo + 0.5) - 1, np.floor(hi + 0.5) + 2
        elif self.interpolation == "linear":
            a, b = np.floor(lo) - 1, np.floor(hi) + 3
        else:
            a, b = np.floor(lo) - 2, np.floor(hi) + 4
            if a.min() < 0 or np.any(b > n):  # the mirrored indices' range
                a2, b2 = [], []
                for k in range(3):
                    m = _mirror(np.arange(int(a[k]), int(b[k])), int(n[k]))
                    a2.append(m.min())
                    b2.append(m.max() + 1)
                a, b = np.array(a2, float), np.array(b2, float)
        a = np.clip(a, 0, n).astype(int)
        b = np.clip(b, 0, n).astype(int)
        box = Box.from_xyz(tuple(a), tuple(b))
        return None if box.empty else box

    def _walk(self, box: Box):
        """``[(op, lo, hi)]``: each op with the box its points lie in for block ``box``.

        The boxes are the ops' own bounds (their ``box``), op by op; the last
        item is ``(None, lo, hi)``, the input index box.
        """
        (x0, y0, z0), (x1, y1, z1) = box.xyz()
        lo = np.array([x0, y0, z0], float)
        hi = np.array([x1 - 1, y1 - 1, z1 - 1], float)
        out = []
        for op in self.ops:
            out.append((op, lo, hi))
            lo, hi = op.box(lo, hi)
        out.append((None, lo, hi))
        return out

    def region(self, box: Box) -> Box | None:
        """A bound, before any sample is read, of the input box block ``box`` reads (None: none)."""
        _, ilo, ihi = self._walk(box)[-1]
        return self._support(ilo, ihi)

    def _local_ops(self, box: Box) -> list:
        """The ops, each field read by windows replaced by its window for block ``box``."""
        if not self.windowed:
            return self.ops
        return [op.window(lo, hi) if _windowed(op) else op for op, lo, hi in self._walk(box)[:-1]]

    def memory(self, box: Box) -> int:
        """The bytes of block ``box``, at its peak: its output, its region, its windows, scratch.

        Nearest and linear hold the region's samples (a copy in the input's
        type) while the parts are sampled. Cubic goes through three phases,
        the largest counted: the prefilter (:meth:`_coefficients`: two
        float64 arrays of the region grown by its halo, scipy's line
        buffers), the padded coefficients copied out of one of them
        (``np.pad`` copies its edge planes once more), then the sampling of
        the parts with only the padded coefficients held.
        """
        from . import parallel

        walk = self._walk(box)
        region = self._support(walk[-1][1], walk[-1][2])
        windows = sum(op.window_bytes(lo, hi) for op, lo, hi in walk[:-1] if _windowed(op))
        scratch = (min(box.size, PART_POINTS) * SCRATCH_PER_POINT
                   * max(1, min(parallel.threads(), 8)))
        held = 0
        if region is None:
            scratch = 0
        elif self.interpolation == "bspline":
            read, padded = self._prefilter_boxes(region)
            lines = 2 * 8 * max(_LINE_BUFFER_DOUBLES, max(read.shape) + 2 * PREFILTER_TAPS)
            pz, py, px = padded.shape
            pad_planes = 8 * CUBIC_PAD * max(py * px, pz * px, pz * py)  # (np.pad's copies)
            filtering = 16 * read.size + lines
            copying = 8 * read.size + 8 * padded.size + pad_planes
            held = max(filtering, copying, 8 * padded.size + scratch)
            scratch = 0
        else:
            held = region.size * self.in_dtype.itemsize
            promoted = self._sampled_type(self.in_dtype)
            if promoted != self.in_dtype:  # (a copy of the region in it: :meth:`compute`)
                held += region.size * promoted.itemsize
        return box.size * self.dtype.itemsize + windows + held + scratch + BLOCK_OVERHEAD

    def _sampled_type(self, dtype) -> np.dtype:
        """The type nearest samples in: the input's, unless the background does not fit it.

        Then the type both the input's and the output's fit in (-1000 for a
        uint8 scan's int16 output: int16).
        """
        dtype = np.dtype(dtype)
        if self.interpolation != "nearest" or holds_value(dtype, self.background):
            return dtype
        return np.promote_types(dtype, self.dtype)

    def block_shape(self, per_task: int, workers: int) -> tuple[int, int, int]:
        """Cubes as large as a task's memory allows (:meth:`memory` of one in the middle).

        A block's memory is not its voxels times a rate: its region's halo (the
        cubic prefilter's 15 voxels, the chain's reach) is fixed, so the edge
        doubles while a cube fits, then grows by eighths; two blocks a worker at least.
        """
        shape = self.grid.shape

        def cube(edge):
            size = [min(edge, n) for n in shape]
            lo = [max(0, min(n // 2 - e // 2, n - e)) for n, e in zip(shape, size, strict=True)]
            return Box(tuple(lo), tuple(a + e for a, e in zip(lo, size, strict=True)))

        def fits(edge):
            count = math.prod(-(-n // min(edge, n)) for n in shape)
            return self.memory(cube(edge)) <= per_task and (count >= 2 * workers or edge <= 8)

        edge = 8
        while edge < max(shape) and fits(edge * 2):
            edge *= 2
        step = max(1, edge // 8)
        while edge < max(shape) and fits(edge + step):
            edge += step
        return tuple(min(edge, n) for n in shape)

    # -- computing ---------------------------------------------------------------------
    def _parts(self, box: Box) -> list[Box]:
        ny, nx = box.shape[1], box.shape[2]
        planes = max(1, PART_POINTS // max(1, ny * nx))
        return [Box((z, box.lo[1], box.lo[2]), (min(z + planes, box.hi[0]), box.hi[1],
                                                   box.hi[2]))
                for z in range(box.lo[0], box.hi[0], planes)]

    def map_indices(self, part: Box, ops=None) -> np.ndarray:
        """The input's continuous indices (x, y, z) sampled by the voxels of ``part``, (N, 3).

        ``ops``: the block's (:meth:`_local_ops`; default the whole's).
        """
        from .transforms._applykernels import grid_points

        ops = self.ops if ops is None else ops
        first = ops[0]
        lo, hi = part.xyz()
        p = np.empty((part.size, 3))
        grid_points(np.array(lo, np.int64), np.array(hi, np.int64), first.matrix, first.offset,
                    p)
        rest = ops[1:]
        if (rest and isinstance(rest[0], DisplacementField)
                and rest[0].add_nodes(first, lo, hi, p)):  # (on the output's own grid)
            rest = rest[1:]
        for step in rest:
            p = step.map(p)
        return p

    def compute(self, box: Box, *, threads: int) -> dict:
        """``{"resampled": [z, y, x] of the output's type}`` of block ``box``.

        The region is :meth:`region`'s bound (exact for a linear chain), read
        once; the block's points are then mapped and sampled part by part
        over ``threads`` (no mapped points held: a 256^3 block's would be
        400 MB of fresh pages).
        """
        from . import parallel

        parts = self._parts(box)
        starts = np.cumsum([0] + [p.size for p in parts])
        out = np.empty(box.shape, dtype=self.dtype)
        flat = out.reshape(-1)
        region = self.region(box)
        from .samples import note_reached

        if region is None:  # (else its points tell: the bound of a rotated block, of a
            note_reached(self._inside, False)  # B-spline's reach, may meet the input alone)
            flat[:] = self._background_as(self.dtype)
            return {self.KEY: out}
        data, lo_xyz = self._region_samples(region)
        sampled = self._sampled_type(data.dtype)
        if sampled != data.dtype:  # (else the background would be clipped to the input's type)
            data = data.astype(sampled)
        ops = self._local_ops(box)
        spread = [0] * len(parts)  # (each part's count of output voxels a NaN reached)

        def part(k):
            coords = self.map_indices(parts[k], ops)
            note_reached(self._inside, lambda: _any_inside(coords, self.n_xyz))
            flat[starts[k]:starts[k + 1]] = self._sample(data, coords, lo_xyz, spread, k)

        parallel.run_blocks(part, range(len(parts)), threads)
        if any(spread):
            self._warn_spread(region, box, sum(spread))
        if self.label_ids is not None:
            from .samples import note_output_ids

            note_output_ids(self._output, out)
        return {self.KEY: out}

    def _warn_spread(self, region: Box, box: Box, count: int) -> None:
        """Say, once a run, that the input's NaN (or infinite) samples were interpolated.

        Linear and cubic interpolation blend a point's neighbours: one NaN
        sample makes NaN every output voxel whose support reaches it (up to 8
        for linear; for cubic, through the prefilter, a cube of about 34
        voxels a side). ITK's Resample does the same, silently; here the
        count in the first block that has them and one such sample's index
        are said. (The background is finite, so only the input's samples
        give a non-finite output.)
        """
        from .progress import log
        from .runscope import run_files

        key = ("input not finite", self._output)
        said = run_files().said
        if key in said:
            return
        said.add(key)
        read = self._prefilter_boxes(region)[0] if self.interpolation == "bspline" else region
        bad = np.argwhere(~np.isfinite(np.asarray(self.source[read.slices])))
        what = (f"NaN or infinite samples (one at index x y z = "
                f"{' '.join(str(int(v)) for v in bad[0][::-1] + read.xyz()[0])})"
                if len(bad) else "samples so large that their interpolation overflows")
        block = "" if box.size == math.prod(self.grid.shape_xyz) else " (its first block with them)"
        log.warning("warning: %s: %s, which %s interpolation blends into their neighbours: %d "
                    "voxels of %s%s are NaN or infinite (as ITK's Resample makes them); replace "
                    "those samples first, or use --interpolation nearest, to keep their "
                    "neighbours' values", self.name, what, self.interpolation, count,
                    self._output, block, extra={"once": key})

    def _background_as(self, dtype):
        from .samples import cast_samples

        return cast_samples(np.array([self.background]), dtype, what="--background-value")[0]

    def _region_samples(self, region: Box) -> tuple[np.ndarray, np.ndarray]:
        """The samples of ``region`` (nearest, linear) or their spline coefficients (bspline).

        With the global index (x, y, z) of their first element.
        """
        if self.interpolation != "bspline":
            return (np.ascontiguousarray(self.source[region.slices]),
                    np.array(region.xyz()[0], dtype=np.int64))
        coefficients, padded = self._coefficients(region)
        return coefficients, np.array(padded.xyz()[0], dtype=np.int64)

    def _prefilter_boxes(self, region: Box) -> tuple[Box, Box]:
        """The boxes (z, y, x) the prefilter reads and the padded coefficients cover."""
        n = tuple(int(v) for v in self.in_grid.shape)
        read = region.grow(PREFILTER_TAPS, within=Box.from_shape(n))
        lo = tuple(a - (CUBIC_PAD if a == 0 else 0) for a in region.lo)
        hi = tuple(b + (CUBIC_PAD if b == m else 0) for b, m in zip(region.hi, n, strict=True))
        return read, Box(lo, hi)

    def _coefficients(self, region: Box) -> tuple[np.ndarray, Box]:
        """Cubic B-spline coefficients of ``region``, padded, and the box they cover.

        The truncated prefilter (module notes) along each axis, on the
        samples of ``region`` grown by its halo within the input; beyond the
        input's edges scipy's ``mirror`` extension, ITK's. Then, where
        ``region`` meets an edge, the coefficients mirrored by
        :data:`CUBIC_PAD` indices beyond it, so that the kernel reads every
        point's 4x4x4 support without mirroring indices. Two float64 arrays
        of the read box at the most (:meth:`memory` counts them).
        """
        from scipy.ndimage import correlate1d

        read, padded = self._prefilter_boxes(region)
        a = np.array(self.source[read.slices], dtype=np.float64)  # (a copy: filtered in place)
        b = np.empty_like(a)
        w = _prefilter_weights()
        correlate1d(a, w, axis=0, output=b, mode="mirror")
        correlate1d(b, w, axis=1, output=a, mode="mirror")
        correlate1d(a, w, axis=2, output=b, mode="mirror")
        del a
        inner = b[region.relative_to(read).slices]
        pads = [(r0 - p0, p1 - r1) for r0, p0, r1, p1 in zip(region.lo, padded.lo, region.hi,
                                                              padded.hi, strict=True)]
        if not any(before or after for before, after in pads):
            return np.ascontiguousarray(inner), padded
        return np.pad(inner, pads, mode="reflect"), padded

    def _sample(self, data: np.ndarray, coords: np.ndarray, lo_xyz: np.ndarray,
                spread: list | None = None, k: int = 0) -> np.ndarray:
        """The samples at ``coords``, cast to the output's type.

        ``spread[k]`` (when given) is set to the count of samples that a
        non-finite input sample reached (linear and cubic of a float input).
        """
        from .samples import cast_samples
        from .transforms import _applykernels as kernels

        n = self.n_xyz
        if self.interpolation == "nearest":
            res = np.empty(len(coords), dtype=data.dtype)
            kernels.sample_nearest(data, coords, lo_xyz, n, self._background_as(data.dtype), res)
            return res if res.dtype == self.dtype else cast_samples(res, self.dtype,
                                                                     what=self._output)
        res = np.empty(len(coords))
        kernel = kernels.sample_linear if self.interpolation == "linear" else \
            kernels.sample_cubic
        kernel(data, coords, lo_xyz, n, self.background, res)
        if spread is not None and self.in_dtype.kind == "f" and not math.isfinite(res.sum()):
            # (the sum: one pass, no array; NaN or inf if any sample is, or if it overflows)
            spread[k] = len(res) - int(np.count_nonzero(np.isfinite(res)))
        return cast_samples(res, self.dtype, what=self._output)

    def expect_label_ids(self) -> None:
        """In a run, say at its end the label ids no output voxel holds (a map's resampling).

        Once its output is named (the blocks' notes name it too).
        """
        if self.label_ids is not None and len(self.label_ids):
            from .samples import expect_output_ids

            expect_output_ids(self._output, self.label_ids)

    def expect_inside(self) -> None:
        """In a run, say at its end if no output point mapped inside the input.

        Every voxel is then the background, exit 0: transforms in the wrong
        order or direction, or for another subject, or a reference grid far
        from the input. A block whose :meth:`region` is empty reaches nothing;
        in the others, the mapped points tell, as the kernels test them, until
        one is inside (a bound meets the input where its points may not: a
        rotated block's box, a B-spline's reach). A label map's missing ids
        are said already (:meth:`expect_label_ids`).
        """
        if self.label_ids is not None and len(self.label_ids):
            return
        from .samples import expect_reached

        corners = self.in_grid.index_to_world(self.in_grid.corner_indices())
        expect_reached(self._inside, (
            f"every voxel of {self._output} is the background ({self.background:g}): no output "
            f"point maps inside {self.name} (LPS "
            f"{_box_text(corners.min(axis=0), corners.max(axis=0))} mm); check the transforms' order (-t acts on "
            "the output's points in the order listed), their direction (an inverse: '[T,1]'?) "
            "and --reference"))

    @property
    def _inside(self) -> str:
        """The key of the note of whether any block's points reached the input."""
        return f"{self._output}: inside {self.name}"

    @property
    def _output(self) -> str:
        """The output, as a cast's messages name it (the API's has no path).

        (A task in another process has no target: the name it was sent with.)
        """
        target = self.targets.get(self.KEY)
        if target is None:
            return self.__dict__.get("output_name", "the resampled volume")
        return "the resampled volume" if target.path is None else str(target.path)

    def load(self) -> None:
        """What the resampling loads, so the budget counts it: scipy's filters for bspline.

        (The kernels are compiled C, loaded with the module: nothing to run.)
        """
        if self.interpolation == "bspline":
            import scipy.ndimage  # noqa: F401 - 25 MiB once imported


def _any_inside(coords: np.ndarray, n: np.ndarray) -> bool:
    """Whether a point of ``coords`` (N, 3 input indices) is inside, as the kernels test it.

    ``-0.5 <= i < n - 0.5`` on every axis (NaN: outside).
    """
    return bool(np.all((coords >= -0.5) & (coords < n - 0.5), axis=1).any())


def _windowed(op) -> bool:
    """Whether ``op`` is a displacement field read by windows."""
    return getattr(op, "source", None) is not None and getattr(op, "vectors", 0) is None


@dataclass(frozen=True)
class Sampling:
    """How an input's samples are taken (:func:`choose_sampling`): its values, interpolation, background.

    ``choice``: the label rule's :class:`~volwarp_cli.warp.defaults.ValuesChoice`;
    ``background_ruled``: the background is the input's border (not given);
    ``refusal``: why the interpolation asked for cannot be (a label map's ids
    would blend), raised by :func:`plan_resample` once the choice is said.
    """

    choice: object
    interpolation: str
    background: float
    background_ruled: bool
    refusal: str | None = None

    def say(self) -> None:
        """The choices, for ``-v`` (and the warning of labels asked on a scan, once)."""
        from .progress import log

        if self.choice.warning:
            log.warning("%s", self.choice.warning)
        log.info("%s", self.choice.describe())
        if self.background_ruled and self.refusal is None:
            log.info("background: %g (the input's border)", self.background)


def choose_sampling(source, *, interpolation: str | None = None, values: str | None = None,
                    background: float | None = None, name: str = "the input",
                    meta=None) -> Sampling:
    """How ``source``'s samples are resampled: read-only, the input alone decides it.

    Labels or intensities by ``values``, else by the label-map rule
    (:func:`volwarp_cli.warp.defaults.choose_values`): a label map is
    resampled by nearest neighbour (another interpolation is refused:
    :attr:`Sampling.refusal`); ``background`` by default the input's border
    (its most frequent label, or its median sample). Says nothing
    (:meth:`Sampling.say`): a command may run it beside its reading of the
    transforms. ``meta``: the input's key/values (a segmentation's ids are
    labels whatever the rule says).
    """
    from .warp.defaults import choose_values

    choice = choose_values(source, values, name=name, meta=meta)
    if choice.is_labels and interpolation not in (None, "nearest"):
        return Sampling(choice, interpolation, float("nan"), False,
                        label_interpolation_refusal(name, choice, interpolation))
    method = interpolation or ("nearest" if choice.is_labels else "linear")
    ruled = background is None
    if ruled:
        background = default_background(source, choice.is_labels)
    return Sampling(choice, method, float(background), ruled)


def plan_resample(header, source, chain: Chain, reference=None, *,
                  interpolation: str | None = None, values: str | None = None,
                  background: float | None = None, dtype=None, name: str = "the input",
                  sampling: Sampling | Callable[[], Sampling] | None = None,
                  outside_field: bool = False) -> ApplyOperation:
    """The resampling of an input through ``chain``, its defaults chosen (an operation).

    ``header``, ``source``: the input's :class:`~volwarp_cli.volume.Header`
    and its samples, sliceable; ``reference``: the output grid's Header (or
    Volume; default: the chain's own grid, an elastix file's, else the
    input's). ``interpolation``, ``values``, ``background``: as
    :func:`choose_sampling` (said at ``-v``; a label map given another
    interpolation than nearest is a :class:`~volwarp_cli.errors.BadUsage`),
    unless ``sampling`` is its result already, or the call that gives it
    (a command's thread's ``Future.result``: asked for after the coverage
    check, so the errors come in the same order); the output in the
    input's type unless ``dtype``. The field's coverage of the grid is
    checked here, before any work (``outside_field``: ITK's identity past a
    field's samples asked for, :func:`check_coverage`). The
    target is an output at no path (the input's header on the grid): the
    caller gives it its path and options.
    """
    from .execute import Target
    from .geometry import Geometry
    from .progress import log

    in_grid = Geometry.of(header)
    grid = Geometry.of(reference) if reference is not None else (
        in_grid if chain.grid is None else chain.grid)
    log.info("output grid: %s (%s)", "x".join(map(str, grid.shape[::-1])),
             "--reference" if reference is not None else
             f"{name}'s" if chain.grid is None else "the elastix file's fixed grid")
    check_coverage(chain, grid, allow=outside_field)
    if sampling is None:
        sampling = choose_sampling(source, interpolation=interpolation, values=values,
                                   background=background, name=name, meta=header.meta)
    elif (interpolation, values, background) != (None, None, None):
        raise ValueError("plan_resample: give interpolation, values and background to "
                         "choose_sampling, not beside its result")
    elif callable(sampling):
        sampling = sampling()
    sampling.say()
    if sampling.refusal is not None:
        raise BadUsage(sampling.refusal)
    out_dtype = np.dtype(dtype or source.dtype)
    if sampling.choice.is_labels:
        _check_label_output(sampling, dtype, out_dtype, name)
    out = header.replace(shape=grid.shape, dtype=out_dtype, spacing=np.array(grid.spacing),
                         origin=np.array(grid.origin), direction=np.array(grid.direction))
    from .labelmap import meta_as_taken

    # (a label map resampled as intensities, as asked: its keys would call the blend one;
    # labels asked of samples the rule takes for intensities: recorded)
    out = out.replace(meta=meta_as_taken(out.meta, sampling.choice.is_labels,
                                         sampling.choice.against_rule))
    # (the choice goes with the output: its pyramid's levels then take a label map's mode,
    # where the writer's own rule, on the resampled samples alone, took the mean)
    # (--values intensity too: asked for, the levels take the mean, never the mode)
    asked = values == "intensity" or sampling.choice.why == "given"
    labels = True if sampling.choice.is_labels else (False if asked else "auto")
    op = ApplyOperation(source, in_grid, chain, grid, interpolation=sampling.interpolation,
                        background=sampling.background,
                        target=Target(None, out, out_dtype, labels=labels), name=name)
    if sampling.choice.is_labels and sampling.choice.ids is not None:
        ids = np.asarray(sampling.choice.ids)  # (the background label: not missed)
        op.label_ids = ids[ids != sampling.background]
    return op


def _check_label_output(sampling: Sampling, dtype, out_dtype: np.dtype, name: str) -> None:
    """A label map's output type holds every id and the background (a label id too)."""
    from .labelmap import refuse_merged_ids

    b = sampling.background
    if not sampling.background_ruled:  # (the rule's background is a border label)
        if not float(b).is_integer():
            raise BadUsage(f"{name}: --background-value {b:g} is not a label id (an integer); "
                           "a label map's outside takes a label")
        if not holds_value(out_dtype, b):
            raise BadUsage(f"{name}: --background-value {b:g} does not fit the output's "
                           f"{out_dtype.name} ids (it would become another label); give a "
                           "--dtype that holds it")
    if dtype is not None and sampling.choice.ids is not None:
        refuse_merged_ids(sampling.choice.ids, dtype, name)


def label_interpolation_refusal(name: str, choice, interpolation: str) -> str:
    """The message refusing ``--interpolation`` other than nearest on labels (once said)."""
    if choice.ruled:
        n = "" if choice.labels is None else f" ({choice.labels} labels)"
        why = f"{name} looks like a label map{n}"
        way = "give --values intensity to resample it as intensities"
    else:
        why = f"{name} is resampled as labels (as asked)"
        way = "a label map is resampled by nearest neighbour"
    return f"{why}: --interpolation {interpolation} would blend its ids; {way}"


def default_background(source, labels: bool) -> float:
    """What the output gets outside the input: a label map's border label, a scan's border median."""
    from .border import border_label, border_value

    return float(border_label(source)) if labels else float(border_value(source))


def check_coverage(chain: Chain, grid, *, allow: bool = False) -> None:
    """Refuse a displacement field whose extent does not cover the output grid's points.

    Every field of the chain, with the output grid's points that reach it:
    its corners (exact through linear steps) and a lattice of its points
    (through non-linear steps before the field). Where some lie outside the
    field's extent it leaves them unmoved (ITK's rule), which silently
    resamples part of the output with another map than the rest; a field
    made for another reference or subject, or a chain in the wrong order,
    shows that way. One error naming the field, its size and the farthest
    point. (A B-spline transform's grid is ITK's to place: it is the
    identity outside by design.) ``allow`` (``--allow-outside-field``):
    ITK's rule is asked for, and the reach outside is said at ``-v`` instead.
    """
    from .errors import VolwarpError

    # the grid's corners (exact through linear steps: a parallelepiped's extremes) and a
    # lattice of its points (through a field or a B-spline before a later field)
    n_xyz = np.array(grid.shape_xyz, float)
    # (at most n of n - 1 steps: distinct; np.unique would import numpy.ma, 7 ms)
    axes = [np.linspace(0, n - 1, min(int(n), 9)) for n in n_xyz]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    reach = grid.index_to_world(np.vstack([grid.corner_indices(), lattice]))
    for step in chain.steps:
        if isinstance(step, DisplacementField):
            idx = step.frame.to_index(reach)
            n = np.asarray(step.frame.size, float)
            out = np.any((idx < -0.5 - 1e-3) | (idx > n - 0.5 + 1e-3), axis=1)
            if np.any(out) and allow:
                from .progress import log

                log.info("%s: %d of %d points checked lie outside its samples, where it is "
                         "the identity (--allow-outside-field)", step.name, int(out.sum()),
                         len(reach))
            elif np.any(out):
                far = reach[np.argmax(np.abs(idx - (n - 1) / 2).max(axis=1))]
                raise VolwarpError(
                    f"{step.name}: the output grid's points reach it outside its "
                    f"{'x'.join(str(int(v)) for v in n)} samples (at LPS "
                    f"{', '.join(f'{v:.4g}' for v in far)} mm; {int(out.sum())} of "
                    f"{len(reach)} points checked): a transform for another reference or "
                    "subject, or the chain in the wrong order (--reference sets the output "
                    "grid); --allow-outside-field takes it as the identity there, as ITK does")
        reach = step.map(reach)


def _box_text(lo, hi) -> str:
    return "[" + ", ".join(f"{a:.4g}..{b:.4g}" for a, b in zip(lo, hi, strict=True)) + "]"


# -- points and meshes: the other way, by the chain's inverse --------------------------------
def move_points(chain: Chain, points, path) -> None:
    """Write ``points`` (a :class:`~volwarp_cli.warp.export.PointsFile`) moved by ``T^-1`` to ``path``."""
    from .progress import timed
    from .warp.export import write_points

    with timed(f"invert the chain at {len(points.points)} points"):
        inv = chain.invert_points(points.points)
    _report(points.path, inv)
    with timed(f"write {path}"):
        write_points(points, inv.points, path)


def move_mesh(chain: Chain, mesh, source, path) -> None:
    """Write ``mesh`` with its vertices moved by ``T^-1``, its faces kept outward.

    (:func:`~volwarp_cli.surface.mesh.moved`: a chain that mirrors turns them
    back; its orientation is a linear chain's determinant's, else the
    Jacobian's at the moved points.)
    """
    from .progress import timed
    from .surface.mesh import map_orientation, moved
    from .surface.mesh_io import write_mesh

    with timed(f"invert the chain at {len(mesh.vertices)} vertices"):
        inv = chain.invert_points(mesh.vertices)
    _report(source, inv)
    if chain.linear:
        sign = 1 if np.linalg.det(chain.affine().matrix) >= 0 else -1
    else:
        sign = map_orientation(chain.map, inv.points)
    with timed(f"write {path}"):
        write_mesh(moved(mesh, inv.points, sign, source), path,
                   comments={"volwarp_command": "apply"})


def _report(what, inv) -> None:
    """The largest residual at -v; the points not solved, by row, in a warning."""
    from .progress import log

    worst = float(inv.residual.max()) if inv.residual.size else 0.0
    log.info("%s: %d points moved by the chain's inverse, largest residual %.3g mm", what,
             len(inv.residual), worst)
    if inv.unsolved.size:
        rows = ", ".join(str(int(i) + 1) for i in inv.unsolved[:20])
        more = "" if inv.unsolved.size <= 20 else f" and {inv.unsolved.size - 20} more"
        log.warning("warning: %s: %d points could not be solved (the chain folds or leaves "
                    "them; residual up to %.3g mm), written without a position (NaN; a "
                    "markups point 'undefined'): points %s%s", what, inv.unsolved.size,
                    float(np.nanmax(inv.residual[inv.unsolved])), rows, more)
