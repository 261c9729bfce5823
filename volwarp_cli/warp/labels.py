"""Warping label maps (segmentations): the forward counterpart of ITK's label interpolators.

The intensity warp averages sample values, which on a label map writes ids
that occur nowhere near the voxel. Here every label ``L`` gets a weight per
output voxel instead, and the output voxel takes the label of largest weight:

- ``L``'s weight is the box pushforward's accumulated weight of its indicator
  (1 inside ``L``, 0 elsewhere): the exact fixed-point sums of the intensity
  warp (:meth:`~volwarp_cli.bspline.scene.Scene.contribute`), read before the ``v / w``
  normalisation. Every label's at once, in one pass over the domain whatever
  the number of labels (:class:`LabelStream`): each domain voxel is pushed
  forward once (``scatter_labels`` of ``bspline/_warpkernels.c``, the intensity
  scatter's numbers to the bit, from the same helpers)
  and adds each contribution to the weight of its own label at the target
  voxel, held in a few (label, weight) slots beside it (a chain of more
  where more labels reach it: exact for any count); integer sums do not
  depend on their order, so these are the weights one pass per label gave.
  The target is streamed through a rolling window of planes, each resolved
  as soon as no later domain plane can reach it (bounded from the lattice
  alone, region by region: :meth:`~volwarp_cli.bspline.reach.Reach.rebuild_block`),
  so memory does not grow with the number of labels either. Only the target
  block the labels' images can reach (:func:`label_window`) is computed,
  the rest is the background, and in it only the voxels of tiles that can
  reach a target voxel some label's voxel can reach (:func:`needed_tiles`):
  elsewhere the background wins whatever else lands there.
- The background label ``b`` is the map's most frequent label on its border
  (:func:`~volwarp_cli.border.border_label`: 0 in the usual map), what surrounds the
  anatomy. It competes like any label: its weight is that of the input's
  ``b`` voxels plus the empty space around the model, ``max(w, 1) - w_fg``
  (``w`` all the model's weight, ``w_fg`` that of its voxels of other
  labels; one full pass of the indicator ``label != b``), so labels do not
  grow into empty space: a label is kept on the model's silhouette only
  where it covers more than the space around it, and where nothing lands
  the output is ``b``. Why not always 0: a map whose ids are 1 to 4 (1
  around the anatomy) gained 1,093 voxels of an id 0 it does not have; 0,
  when the map has it and it is not ``b``, is a label like the others.
- Ties go to the smaller label, deterministically (the background included,
  at its id). Every output value is an
  input label, and ids keep the input's type end to end (only the weights
  are numbers): integer ids above 2^24 survive. Float samples are a label
  map when every one is an integer (nibabel's and MONAI's segmentations):
  their ids are compared as the floats they are (exact for integers), and
  the output has the input's float type.

Every box is computed in the target's own coordinates, as the intensity
warp computes them. (The former per-label passes computed each label's in
coordinates relative to its block's corner: where a box side is not exact
in binary, an oversample of 3 or offsets far below a voxel, that rounded a
few contributions differently by 2**-40 of a voxel's weight, so a label's
weights depended on how far its other voxels reached.)

Labels need the subdivision grid (an integer oversample with the uniform
placement, see :mod:`volwarp_cli.bspline.lattice`): there every domain voxel lies inside one
input voxel and takes its label, with no blend of ids. The spanning grid
(non-integer oversample, tripled placement) is refused.

``preserve``: a label that would vanish (no output voxel) keeps its voxel of
largest weight (where two such labels want the same voxel, the larger weight,
then the smaller label). :func:`warp_labels` also reports, per label, the
input and output volume and the volume the deformation predicts: the total
weight the label deposits, i.e. the sum of its domain voxels' Jacobian
volumes (the box filter scales every voxel's overlaps to it), in mm^3.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from .. import parallel
from ..box import Box
from ..bspline.capture import Capture, geometry_capture
from ..bspline.lattice import PLACEMENTS
from ..bspline.pushforward import QUANTUM
from ..bspline.reach import STREAM_PLANES, TargetBlock, ring_planes
from ..bspline.scene import Scene
from ..errors import VolwarpError
from ..memory import ensure_fits_in_memory
from ..progress import log, timed
from ..volume import Header, Volume

_Q = int(QUANTUM)


def capture_labels(vol: Volume | Header, *, lattice=(9, 9, 9), placement: str = "uniform",
                   oversample: float = 2.0, sampling: str = "linear", pad=None) -> Capture:
    """A :class:`Capture` of a label map (no float voxmap: the label passes gather their own).

    ``vol``: the map, or its :class:`~volwarp_cli.volume.Header` (its
    samples read elsewhere, by slabs). Refuses samples that cannot be ids
    (not integers or floats; a float's values are checked by the label
    passes, which read them all) and the spanning grid (a non-integer
    oversample or the tripled placement: its capture would blend ids). The
    capture of a Volume keeps its labels as ``labels`` (``vol.data``, not copied).
    """
    dtype = np.dtype(vol.dtype)
    if dtype.kind not in "iuf":
        raise VolwarpError(f"a label map needs integer samples, got {dtype} (convert it "
                           "with --dtype, or warp it without --labels)")
    if placement not in PLACEMENTS:
        raise VolwarpError(f"unknown placement {placement!r} (use uniform or tripled)")
    k = float(oversample)
    if placement != "uniform" or not (k >= 1 and k.is_integer()):
        raise VolwarpError("a label map is warped on the subdivision grid, where each domain "
                           "voxel takes one input voxel's label: use an integer oversample "
                           f"(1, 2, ...) and the uniform placement (got oversample {oversample:g}, "
                           f"placement {placement})")
    header = vol.header if isinstance(vol, Volume) else vol
    cap = geometry_capture(header, lattice=lattice, placement=placement, oversample=k,
                           sampling=sampling, pad=pad)
    if isinstance(vol, Volume):
        cap.labels = vol.data
    return cap


@dataclass
class LabelWarp:
    """The result of :func:`warp_labels`: the target labels and the per-label report.

    The target labels are ``[z, y, x]``, of the input's dtype.
    """

    target: np.ndarray
    report: dict = field(default_factory=dict)


def check_ids(data, name: str = "the label map") -> None:
    """Refuse float samples that are not all integers (:class:`VolwarpError`); read by slabs.

    Integer samples pass unread. A fraction, a NaN or an infinity is no id.
    """
    from ..border import not_ids
    from ..labelmap import integer_samples

    if np.dtype(data.dtype).kind in "iu":
        return
    step = max(1, (1 << 20) // max(1, int(np.prod(data.shape[1:]))))
    for z in range(0, len(data), step):
        if integer_samples(np.asarray(data[z:z + step])) is None:
            raise not_ids(name, data.dtype)


def _label_counts(data: np.ndarray, background: int = 0, tile: int = 0):
    """``(labels, counts, hull, tiles)`` of the label map's labels other than ``background``.

    The distinct labels (sorted) but ``background``, their voxel counts, and
    the bounding box of all their voxels (a :class:`~volwarp_cli.box.Box`, z y
    x; None when there is none): what :func:`warp_labels` needs of the map
    (:func:`_bounding_boxes` also finds each label's box). With ``tile``,
    ``tiles``: uint8, 1 for each tile of ``tile`` voxels a side (z y x, from
    voxel 0) holding one of those voxels (:func:`label_tiles`); else None. A
    few planes at a time, numpy only. Float samples must hold integers
    (:func:`check_ids`).
    """
    check_ids(data)
    nz = len(data)
    step = max(1, (1 << 20) // max(1, data[0].size))
    if tile:
        step = tile * max(1, step // tile)
    z_any = np.zeros(nz, bool)
    yx_any = np.zeros(data.shape[1:], bool)
    tiles = np.zeros([-(-n // tile) for n in data.shape], np.uint8) if tile else None
    lo, hi = (int(data.min()), int(data.max())) if data.size else (0, 0)
    table = hi - lo < 1 << 24
    counts = np.zeros(hi - lo + 1 if table else 0, dtype=np.int64)
    for z in range(0, nz, step):
        part = data[z:z + step]
        if table:
            counts += np.bincount(part.ravel().astype(np.int64) - lo, minlength=hi - lo + 1)
        fg = part != background
        z_any[z:z + step] = fg.any(axis=(1, 2))
        yx_any |= fg.any(axis=0)
        if tile:
            part_tiles = label_tiles(fg, tile)
            tiles[z // tile:z // tile + len(part_tiles)] |= part_tiles
    if table:
        present = np.flatnonzero(counts)
        values, counts = present + lo, counts[present]
    else:
        values, counts = np.unique(data, return_counts=True)
    keep = values != background
    labels = [int(v) for v in values[keep]]
    hull = None
    if labels:
        bounds = [np.flatnonzero(v) for v in (z_any, yx_any.any(axis=1), yx_any.any(axis=0))]
        hull = Box(tuple(int(b[0]) for b in bounds), tuple(int(b[-1]) + 1 for b in bounds))
    return labels, [int(c) for c in counts[keep]], hull, tiles


def label_tiles(mask: np.ndarray, tile: int) -> np.ndarray:
    """uint8 ``[ceil(z / tile), ...]``: 1 for each tile of ``mask`` (bool z y x) holding a True."""
    out = mask.view(np.uint8)
    for axis in range(3):
        out = np.maximum.reduceat(out, np.arange(0, out.shape[axis], tile), axis=axis)
    return out


def needed_tiles(scene: Scene, dq, labelled: np.ndarray, tile: int) -> np.ndarray:
    """uint8, per tile of ``tile`` input voxels: whether its voxels can add to a weight that counts.

    ``labelled``: the tiles holding a voxel of a label other than the
    background (:func:`label_tiles`). A target voxel no label's voxel can
    reach takes the background whatever the rest of the map adds there; the
    tiles whose voxels can reach none where a label's can (both bounded from
    lattice ``dq`` alone, tile by tile, as
    :meth:`~volwarp_cli.bspline.reach.Reach.rebuild_block` bounds a block:
    the convex hull of the regions' control points, the box filter's half
    voxel) are left out, exactly. A map whose labels fill a small part of
    its box (the frog's 26 tissues: 3.6% of it) is warped at the cost of that
    part and its surroundings.
    """
    grid = scene.grid
    k, lead = grid.subdivision, grid.lead
    lo_u, hi_u = scene._offset_bounds(dq)  # [Rz, Ry, Rx, 3]: x y z components
    tshape = scene.target_shape  # x y z
    ntiles = labelled.shape  # z y x
    ends = []
    for axis in range(3):  # x, y, z; the array axis 2 - axis
        n_in, g, r = grid.input_shape[axis], grid.granularity[axis], grid.regions[axis]
        j = np.arange(ntiles[2 - axis])
        first = lead[axis] + k * tile * j  # each tile's first and last domain voxel
        last = lead[axis] + k * np.minimum(tile * (j + 1), n_in) - 1
        r0, r1 = np.clip(first // g, 0, r - 1), np.clip(last // g, 0, r - 1)
        # the offset bounds over the regions of each tile's voxels, along this axis
        lo_b = hi_b = None
        for d in range(int((r1 - r0).max()) + 1):
            rr = np.minimum(r0 + d, r1)
            lo_d, hi_d = np.take(lo_u, rr, axis=2 - axis), np.take(hi_u, rr, axis=2 - axis)
            lo_b = lo_d if lo_b is None else np.minimum(lo_b, lo_d)
            hi_b = hi_d if hi_b is None else np.maximum(hi_b, hi_d)
        lo_u, hi_u = lo_b, hi_b
        ends.append((first, last))
    # per tile and axis: the target voxels [a, b) its voxels' boxes can reach (as rebuild_block)
    boxes = []
    for axis in range(3):
        first, last = ends[axis]
        shape = [1, 1, 1]
        shape[2 - axis] = -1
        s, o = float(scene.scale[axis]), float(scene.offset[axis])
        a = np.floor(o + s * first.reshape(shape) + lo_u[..., axis] - 0.5 * s - 0.5)
        b = np.ceil(o + s * last.reshape(shape) + hi_u[..., axis] + 0.5 * s + 0.5) + 1
        a = np.clip(a, 0, tshape[axis]).astype(np.int64)
        b = np.clip(b, 0, tshape[axis]).astype(np.int64)
        boxes.append((a // tile, -(-b // tile), b > a))  # in target tiles
    (ax0, ax1, okx), (ay0, ay1, oky), (az0, az1, okz) = boxes
    ok = okx & oky & okz
    grid_t = [-(-n // tile) for n in tshape[::-1]]  # target tiles, z y x
    # the target tiles a label can land in: the union of the labelled tiles' boxes
    diff = np.zeros([n + 1 for n in grid_t], np.int64)
    hit = ok & (labelled > 0)
    hit_lo = [v[hit] for v in (az0, ay0, ax0)]
    hit_hi = [v[hit] for v in (az1, ay1, ax1)]
    for corner in range(8):
        idx = tuple(hit_hi[i] if corner >> i & 1 else hit_lo[i] for i in range(3))
        np.add.at(diff, idx, -1 if bin(corner).count("1") % 2 else 1)
    landing = diff.cumsum(0).cumsum(1).cumsum(2)[:-1, :-1, :-1] > 0
    # every tile whose box meets one of them (a summed-area table of them)
    sat = np.zeros([n + 1 for n in grid_t], np.int64)
    sat[1:, 1:, 1:] = landing.cumsum(0).cumsum(1).cumsum(2)
    box_lo, box_hi = (az0, ay0, ax0), (az1, ay1, ax1)
    total = np.zeros(ntiles, np.int64)
    for corner in range(8):
        idx = tuple(box_hi[i] if corner >> i & 1 else box_lo[i] for i in range(3))
        sign = 1 if bin(corner ^ 7).count("1") % 2 == 0 else -1
        total += sign * sat[idx]
    return (ok & (total > 0)).astype(np.uint8)


def _bounding_boxes(data: np.ndarray, background: int = 0):
    """``(labels, counts, boxes)`` of the label map's labels other than ``background``.

    The distinct labels (sorted) but ``background``, their voxel counts and
    input bounding boxes (:class:`~volwarp_cli.box.Box` es, z y x); and the
    count of ``background``. Float samples must hold integers (:func:`check_ids`).
    """
    from scipy import ndimage

    check_ids(data)
    lo, hi = int(data.min()), int(data.max())
    if hi - lo < 1 << 24:
        # a count table and a compact index (1..n), a few planes at a time: no
        # whole-size int64 temporaries
        step = max(1, (1 << 20) // max(1, data[0].size))
        counts = np.zeros(hi - lo + 1, dtype=np.int64)
        for z in range(0, len(data), step):
            counts += np.bincount(data[z:z + step].ravel().astype(np.int64) - lo,
                                  minlength=hi - lo + 1)
        present = np.flatnonzero(counts)
        values = present + lo
        itype = np.uint8 if len(present) < 255 else (np.uint16 if len(present) < 65535
                                                     else np.int32)
        lut = np.zeros(hi - lo + 1, dtype=itype)
        lut[present] = np.arange(1, len(present) + 1)
        index = np.empty(data.shape, dtype=itype)
        for z in range(0, len(data), step):
            part = data[z:z + step]
            index[z:z + step] = lut[part.astype(np.intp) - lo]  # (not in part's own type)
        counts = counts[present]
    else:
        values, inverse, counts = np.unique(data, return_inverse=True, return_counts=True)
        index = (inverse.reshape(data.shape) + 1).astype(np.int32)
    objects = ndimage.find_objects(index)
    kept = int(counts[values == background].sum())
    labels, nvox, boxes = [], [], []
    for v, c, sl in zip(values, counts, objects, strict=True):
        if v == background or sl is None:
            continue
        labels.append(int(v))
        nvox.append(int(c))
        boxes.append(Box(tuple(s.start for s in sl), tuple(s.stop for s in sl)))
    return labels, nvox, boxes, kept


#: (label, weight) pairs held beside each target voxel of a stream's ring; a voxel that
#: more labels reach chains blocks of as many from a shared pool (exact, only slower).
#: One: the frog's 250x235x136 warp took the same time with 1 and 2 (the few voxels
#: where labels meet chain a block each; 100 touching labels: 7% longer with 1), and the
#: ring is 12 bytes a voxel smaller.
SLOTS = 1
#: the chains' pool as first made: a block (of ``SLOTS`` pairs) per this many ring voxels,
#: at least ``POOL_BLOCKS_MIN``; it doubles when a row might not fit (rare: a voxel that
#: more than ``SLOTS`` labels reach)
POOL_SHARE = 16
POOL_BLOCKS_MIN = 64
#: edge (input voxels) of the tiles by which a label warp leaves out the voxels that can
#: reach no target voxel where a label lands (:func:`needed_tiles`)
TILE = 8
#: id ranges up to this (or 16 per label) map ids to codes through a table, wider ones
#: by a sorted search (the same codes)
_TABLE_IDS = 1 << 16


class LabelCodes:
    """A label map's ids as the label kernels' codes (``_warpkernels.scatter_labels``), and back.

    Code 0 is the ``background`` label, codes 1..n the map's other
    ``labels`` (ascending): comparing codes compares ids, and a code below
    ``below`` is a label whose id lies below the background's. ``table[code]``
    is the id, in the map's ``dtype``.
    """

    def __init__(self, labels, background, dtype):
        self.labels = list(labels)
        self.background = background
        self.table = np.array([background, *self.labels], dtype=dtype)
        self.below = 1 + sum(1 for L in self.labels if L < background)
        ids = [background, *self.labels]
        lo, hi = min(ids), max(ids)
        self._lo, self._lut, self._sorted = lo, None, None
        if hi - lo < max(_TABLE_IDS, 16 * len(ids)):
            self._lut = np.zeros(hi - lo + 1, np.int32)
            self._lut[np.array(self.labels, np.int64) - lo] = np.arange(1, len(self.labels) + 1)
        else:
            self._sorted = self.table[1:]

    def codes(self, ids: np.ndarray, out: np.ndarray) -> None:
        """Write the codes of ``ids`` (samples of the map: its labels and background) to ``out``.

        ``out``: int32, C-contiguous, of ``ids``' shape.
        """
        if self._lut is not None:
            index = ids.astype(np.intp)
            if self._lo:
                index -= self._lo
            np.take(self._lut, index, out=out, mode="clip")
        else:
            out[...] = np.searchsorted(self._sorted, ids) + 1
            out[ids == self.background] = 0


def label_window(scene: Scene, dq, hull: Box | None) -> TargetBlock | None:
    """Where the map's labels (but the background) matter: a :class:`~volwarp_cli.bspline.reach.TargetBlock`.

    Its target: every target voxel the image of the input box ``hull`` (z y
    x, holding every voxel of those labels) can reach, from lattice ``dq``
    alone; its domain: every domain voxel of the model whose image can reach
    that block. Outside the target block no label lands and the background
    wins; inside, the domain block holds every voxel that adds to a weight
    there. None when there is no label (``hull`` None) or none can reach the
    target.
    """
    if hull is None:
        return None
    grid = scene.grid
    k, lead = grid.subdivision, np.array(grid.lead)
    lo, hi = (np.array(v, np.int64) for v in hull.xyz())
    voxels = Box.from_xyz((lead + k * lo).tolist(), (lead + k * hi).tolist())  # the domain's
    bounds = scene._offset_bounds(dq)
    block = scene.reach.rebuild_block(bounds, bounds, voxels)
    if block is None or block.domain.empty:
        return None
    return TargetBlock(block.target, block.domain.intersect(scene._data_box))


@dataclass
class LabelTotals:
    """A share's totals per label id (every label but the background).

    ``predicted``: its total weight (2**-40 units); ``peak``: its largest
    weight and the first target voxel (z, y, x) with it (``(0, None)`` where
    it has none); ``counts``: the output voxels it won.
    """

    predicted: dict = field(default_factory=dict)
    peak: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)

    def add(self, other: LabelTotals) -> None:
        """Add another share's totals (in place): the same whatever the cut."""
        for L, total in other.predicted.items():
            self.predicted[L] = self.predicted.get(L, 0) + total
        for L, n in other.counts.items():
            self.counts[L] = self.counts.get(L, 0) + n
        for L, (w, at) in other.peak.items():
            if at is not None and _stronger(w, at, *self.peak.get(L, (0, None))):
                self.peak[L] = (w, at)
            else:
                self.peak.setdefault(L, (0, None))


class LabelStream:
    """One share of the target, z planes [t_lo, t_hi): every label's weight in one pass.

    ``source``: the label map, any sliceable ``[z, y, x]`` (read a few planes at
    a time); ``out``: the share's output labels, ``out[0]`` plane ``t_lo``;
    ``codes``: the map's :class:`LabelCodes`; ``window``: :func:`label_window`
    (None: no label reaches the target); ``need``: :func:`needed_tiles` (None:
    every voxel). :meth:`run` streams the domain
    planes that can reach the share through a ring of its target planes
    (:func:`~volwarp_cli.bspline.reach.ring_planes`), each domain voxel pushed
    once (``scatter_labels`` of ``bspline/_warpkernels.c``), each plane resolved
    as soon as no later domain plane can reach it (its ``resolve_planes``).
    ``slots``: (label, weight) pairs beside each ring voxel (:data:`SLOTS`;
    more labels reaching a voxel chain blocks of as many: any count is exact).
    """

    def __init__(self, scene: Scene, dq, source, t_lo: int, t_hi: int, out, codes, *,
                 window: TargetBlock | None = None, need: np.ndarray | None = None,
                 slots: int = SLOTS):
        if int(slots) < 1:
            raise ValueError(f"slots must be at least 1, got {slots}")
        self.scene, self.dq, self.source = scene, dq, source
        self.t_lo, self.t_hi = t_lo, t_hi
        self.out, self.codes, self.window = out, codes, window
        self.slots = int(slots)
        grid = scene.grid
        if need is None:  # (every voxel)
            need = np.ones([-(-n // TILE) for n in grid.input_shape[::-1]], np.uint8)
        self.need = np.ascontiguousarray(need, np.uint8)
        self.k = grid.subdivision
        self.chunk = max(1, int(STREAM_PLANES * self.k))  # domain planes per step
        # each domain plane's reach, from the deformation itself (a share's halo is that)
        self.reach = scene.tight_plane_reach(dq)
        self.planes = ring_planes(self.reach, self.chunk)
        #: the scatter's value scale (1: a label map's scene, whose range is (0, 1))
        self.inv_vmax = 1.0 / scene.vmax if scene.vmax > 0 else 0.0
        from ..bspline.scene import Scratch
        self.scratch = Scratch()

    def run(self) -> LabelTotals:
        """Fill ``out`` (the background where no label wins); the share's :class:`LabelTotals`."""
        from ..bspline._warpkernels import resolve_planes

        codes, win = self.codes, self.window
        n = len(codes.labels) + 1
        counts, total_hi, total_lo, peak_w = (np.zeros(n, np.int64) for _ in range(4))
        peak_at = np.zeros((n, 3), np.int64)
        self.out[...] = codes.background
        z_lo = z_hi = 0
        if win is not None:
            z_lo, z_hi = max(win.target.lo[0], self.t_lo), min(win.target.hi[0], self.t_hi)
        if z_lo >= z_hi:
            return self._totals(counts, total_hi, total_lo, peak_w, peak_at)
        (_, y0, x0), (_, y1, x1) = win.target.lo, win.target.hi
        planes, k, slots = self.planes, self.k, self.slots
        size = planes * (y1 - y0) * (x1 - x0)
        ring = [np.zeros(size, np.int64), np.zeros(size * slots, np.int32),
                np.zeros(size * slots, np.int64), np.full(size, -1, np.int32)]
        self.pool = np.zeros(max(POOL_BLOCKS_MIN, size // POOL_SHARE) * (2 * slots + 1),
                             np.int64)
        # the pool's free list, blocks used, blocks ever taken, blocks free
        self.state = np.array([-1, 0, 0, 0], np.int64)
        won = np.empty((min(planes, STREAM_PLANES), y1 - y0, x1 - x0), np.int32)
        base = z_lo

        def flush(upto):
            nonlocal base
            while base < upto:
                m = min(upto - base, len(won))
                resolve_planes(base, base + m, planes, (y0, x0), (y1 - y0, x1 - x0), *ring,
                               self.pool, self.state, slots, codes.below, won, counts,
                               total_hi, total_lo, peak_w, peak_at)
                self.out[base - self.t_lo:base - self.t_lo + m, y0:y1, x0:x1] = \
                    codes.table[won[:m]]
                base += m

        dom = win.domain
        g_lo, g_hi = self.reach.domain_window(z_lo, z_hi)
        g_lo, g_hi = max(g_lo, dom.lo[0]), min(g_hi, dom.hi[0])
        lead = self.scene.grid.lead
        # the input rows and columns the domain block lies in
        (_, iy0, ix0), (_, iy1, ix1) = dom.lo, dom.hi
        iy0, ix0 = (iy0 - lead[1]) // k, (ix0 - lead[0]) // k
        iy1, ix1 = (iy1 - 1 - lead[1]) // k + 1, (ix1 - 1 - lead[0]) // k + 1
        buf = np.empty((self.chunk // k + 2, iy1 - iy0, ix1 - ix0), np.int32)
        for g0 in range(g_lo, g_hi, self.chunk):
            g1 = min(g0 + self.chunk, g_hi)
            r_lo, r_hi = self.reach.target_reach(g0, g1)  # r_lo: of every plane from g0 on
            flush(min(max(r_lo, base), z_hi))
            if min(r_hi, z_hi) - base > planes:  # pragma: no cover - cannot happen
                raise AssertionError("rolling accumulator too small")
            iz0, iz1 = (g0 - lead[2]) // k, (g1 - 1 - lead[2]) // k + 1
            part = buf[:iz1 - iz0]
            codes.codes(np.asarray(self.source[iz0:iz1, iy0:iy1, ix0:ix1]), part)
            self._scatter(Box((g0, *dom.lo[1:]), (g1, *dom.hi[1:])), part, (ix0, iy0, iz0),
                          (x0, x1, y0, y1, base, min(base + planes, z_hi)), ring)
        flush(z_hi)
        return self._totals(counts, total_hi, total_lo, peak_w, peak_at)

    def _scatter(self, block: Box, part, part_xyz, clip, ring) -> None:
        """Push domain voxels ``block`` (z y x) into the ring, the deformation evaluated by chunks.

        ``part``: the codes of the input voxels from ``part_xyz`` on; ``clip``:
        the target voxels kept ``(x0, x1, y0, y1, z0, z1)``. The deformation
        as :meth:`~volwarp_cli.bspline.scene.Scene.contribute` evaluates it
        (the same chunks' buffers, the still regions left out): the offsets
        the C scatter reads, here read by the label kernel.
        """
        from ..bspline import basis
        from ..bspline._warpkernels import scatter_labels
        from ..bspline.pushforward import domain_faces, fill_halo, with_planes
        from ..bspline.scene import _to_evaluate

        sc, grid = self.scene, self.scene.grid
        dshape = grid.domain_shape
        ext = block.grow(1, within=sc._domain_box)  # and the voxels' neighbours
        _, ny, nx = ext.shape
        cz = int(max(4, sc.chunk_bytes // ((nx + 2) * (ny + 2) * 12)))
        evaluate = basis.EVALUATORS[sc.evaluator]
        regions = sc._still([self.dq])  # (None, or uint8 [1, Rz, Ry, Rx])
        still = np.zeros((0, 0, 0), np.uint8) if regions is None else regions[0]
        box = sc.method == "box"
        fixed = (part_xyz, self.k, tuple(int(v) for v in grid.lead),
                 tuple(float(v) for v in sc.offset), tuple(float(v) for v in sc.scale))
        win_lo, win_shape = (clip[2], clip[0]), (clip[3] - clip[2], clip[1] - clip[0])
        for z0 in range(block.lo[0], block.hi[0], cz):
            chunk = with_planes(block, z0, min(z0 + cz, block.hi[0]))
            z1 = chunk.hi[0]
            e0, e1 = max(z0 - 1, 0), min(z1 + 1, dshape[2])
            planar = self.scratch.arrays((3, e1 - e0 + 2, ny + 2, nx + 2), 1)[0]
            ub = np.moveaxis(planar, 0, -1)
            origin = (ext.lo[2], ext.lo[1], e0)
            sub = _to_evaluate(regions, grid, chunk, ext)
            if sub is not None:
                evaluate(self.dq, grid, ub[1:-1, 1:-1, 1:-1], x=sub[0], y=sub[1], z=(e0, e1),
                         origin=origin, parallel=False)
                faces = domain_faces(e0, e1, ext, dshape)
                fill_halo(ub, faces)
            (cz0, cy0, cx0), (cz1, cy1, cx1) = chunk.lo, chunk.hi
            start = (cy0, cz0)
            while True:  # (again from the row it stopped at, when the pool had to grow)
                start = scatter_labels(
                    planar, tuple(int(v) for v in origin), part, *fixed,
                    (cx0, cx1, cy0, cy1, cz0, cz1), box, self.inv_vmax, still,
                    tuple(int(v) for v in grid.granularity), tuple(int(v) for v in dshape),
                    tuple(int(v) for v in clip), self.planes,
                    win_lo, win_shape, *ring, self.pool, self.state, self.slots, self.need,
                    TILE, start)
                if start[0] < 0:
                    break
                self.pool = np.concatenate([self.pool, np.zeros_like(self.pool)])

    def _totals(self, counts, total_hi, total_lo, peak_w, peak_at) -> LabelTotals:
        totals = LabelTotals()
        hi, lo, pw = total_hi.tolist(), total_lo.tolist(), peak_w.tolist()
        # the nearest pushforward weighs each domain voxel 1, the box its share of a target
        # voxel: in input voxels, the nearest's totals are the oversample^3 too large
        per = 1 if self.scene.method == "box" else max(1, self.scene.grid.subdivision) ** 3
        for c, L in enumerate(self.codes.labels, start=1):
            total = (hi[c] << 32) + lo[c]
            totals.predicted[L] = total if per == 1 else total / per
            totals.counts[L] = int(counts[c])
            totals.peak[L] = (pw[c], tuple(peak_at[c].tolist())) if pw[c] > 0 else (0, None)
        return totals


def warp_labels(labels_in: np.ndarray, scene: Scene, frames=(), *, preserve: bool = False,
                spacing=(1.0, 1.0, 1.0), background: int | None = None,
                slots: int = SLOTS) -> LabelWarp:
    """Warp the label map ``labels_in`` ``[z, y, x]`` (integer ids) with ``scene``'s lattice.

    ``scene``: from :func:`.prepare.prepare` on a :func:`capture_labels` capture;
    the last of ``frames`` (if any) is the lattice applied. ``spacing``
    (x y z, mm) scales the report's volumes. ``background``: the label
    written where nothing lands (None: :func:`~volwarp_cli.border.border_label`, the
    most frequent on the map's border). ``slots``: :class:`LabelStream`'s (the
    same output for any). Returns the target labels (padded
    like the intensity warp's target: crop with :func:`.prepare.output_volume`)
    and a report::

        {"labels": {L: {"input_voxels", "output_voxels", "input_mm3",
                        "output_mm3", "predicted_mm3", "preserved"}},
         "vanished": [...], "preserved": [...], "background": b}

    (every label but the background ``b``).
    """
    from ..border import border_label

    grid = scene.grid
    if not grid.subdivision:
        raise VolwarpError("label maps are warped on the subdivision grid (integer oversample, "
                           "uniform placement)")
    if np.dtype(labels_in.dtype).kind not in "iuf":
        raise VolwarpError(f"a label map needs integer samples, got {labels_in.dtype}")
    if tuple(labels_in.shape[::-1]) != tuple(grid.input_shape):
        raise VolwarpError("the label map does not match the lattice's input")
    if scene.background != 0:
        raise VolwarpError("a label map's background is one of its labels (no --background)")
    b = border_label(labels_in) if background is None else int(background)
    if frames:
        scene.set_lattice(frames[-1].dq)
    dq = scene.dq
    tx, ty, tz = scene.target_shape
    workers = max(1, min(parallel.threads(), tz // 4))
    ensure_fits_in_memory(tx * ty * tz * labels_in.dtype.itemsize
                          + workers * stream_bytes(scene, dq, labels_in.dtype, slots),
                          "the warped labels")
    with timed("labels: counts"):
        labels, nvox, hull, tiles = _label_counts(labels_in, b, TILE)
    codes = LabelCodes(labels, b, labels_in.dtype)
    window = label_window(scene, dq, hull)
    need = needed_tiles(scene, dq, tiles, TILE)
    best_l = np.empty((tz, ty, tx), dtype=labels_in.dtype)
    # the threads' shares: the planes labels can reach, cut evenly (the rest: the background)
    z0, z1 = (window.target.lo[0], window.target.hi[0]) if window is not None else (tz, tz)
    best_l[:z0] = b
    best_l[z1:] = b
    cuts = parallel.cuts(z0, z1, workers)
    totals = LabelTotals()
    lock = threading.Lock()

    def share(i):
        got = LabelStream(scene, dq, labels_in, cuts[i], cuts[i + 1], best_l[cuts[i]:cuts[i + 1]],
                          codes, window=window, need=need, slots=slots).run()
        with lock:
            totals.add(got)

    with timed(f"labels: {len(labels)} labels + background, one pass ({workers} threads)"):
        parallel.run_blocks(share, range(len(cuts) - 1), workers)

    def label_at(at):
        return best_l[at]

    def set_label(at, L):
        best_l[at] = L

    report = label_report(labels, nvox, totals.predicted, totals.peak, totals.counts,
                          float(np.prod(spacing)), preserve=preserve, label_at=label_at,
                          set_label=set_label)
    report["background"] = b
    return LabelWarp(best_l, report)


def stream_bytes(scene: Scene, dq, dtype, slots: int = SLOTS) -> int:
    """Memory one :class:`LabelStream` holds beside its output planes (an upper bound).

    Its ring of target planes (whole planes: the window's at most) with each
    voxel's total weight, ``slots`` (label, weight) pairs and chain, the
    winning codes of a step's planes, and the chains' pool as first made (it
    grows only where more than ``slots`` labels reach a voxel, by doubling);
    the codes of the input planes a step reads, with the samples read and the
    index made from them; the deformation's buffers.
    """
    grid = scene.grid
    k = grid.subdivision
    chunk = max(1, int(STREAM_PLANES * k))
    # (the hull's reach: LabelStream's own, Scene.tight_plane_reach, lies within it)
    planes = ring_planes(scene._plane_reach([dq]), chunk)
    tx, ty, _ = scene.target_shape
    nx, ny, _ = grid.input_shape
    ring = planes * ty * tx
    pool = max(POOL_BLOCKS_MIN, ring // POOL_SHARE) * (2 * slots + 1) * 8
    won = min(planes, STREAM_PLANES) * ty * tx * (4 + np.dtype(dtype).itemsize)
    inputs = (chunk // max(1, k) + 2) * ny * nx * (4 + np.dtype(dtype).itemsize + 8)
    return ring * (8 + slots * 12 + 4) + pool + won + inputs + 2 * scene.chunk_bytes


def label_report(labels, nvox, predicted, peak, out_counts, vol_voxel: float, *,
                 preserve: bool, label_at, set_label) -> dict:
    """The per-label report, after keeping (``preserve``) the labels that would vanish.

    ``out_counts``: output voxels per label (updated in place);
    ``label_at(at)``/``set_label(at, L)``: read and change one target voxel,
    for the labels kept at their voxel of largest weight (``peak``).
    """
    vanished = [L for L in labels if out_counts[L] == 0]
    preserved = []
    if preserve and vanished:
        # the strongest first: a voxel wanted by two vanishing labels goes to the larger weight
        for L in sorted(vanished, key=lambda L: (-peak[L][0], L)):
            w, at = peak[L]
            if at is None or w <= 0:
                continue
            old = label_at(at)
            if old in vanished and old in preserved:
                continue
            set_label(at, L)
            preserved.append(L)
            if old in out_counts:  # (not the background: it is no reported label)
                out_counts[old] -= 1
            out_counts[L] = 1
        for L in preserved:
            log.info("label %d would vanish: kept at its voxel of largest weight", L)
        # a label whose only voxels were taken by a preserved one vanishes in turn
        vanished = [L for L in labels if out_counts[L] == 0]
    report = {"labels": {}, "vanished": vanished, "preserved": sorted(preserved)}
    for L, n in zip(labels, nvox, strict=True):
        report["labels"][L] = {
            "input_voxels": n, "output_voxels": int(out_counts[L]),
            "input_mm3": n * vol_voxel, "output_mm3": int(out_counts[L]) * vol_voxel,
            "predicted_mm3": predicted[L] / _Q * vol_voxel,
            "preserved": L in preserved}
    for L in vanished:
        log.warning("label %d vanished in the warp (%d input voxels)%s", L,
                    report["labels"][L]["input_voxels"],
                    "" if preserve else ": --preserve-labels keeps one voxel of it")
    return report


def _stronger(w: int, at, w_best: int, at_best) -> bool:
    """Whether weight ``w`` at voxel ``at`` beats the best so far.

    It does when larger, or as large and first in (z, y, x) order, so the winner does
    not depend on the blocks' order.
    """
    return w > w_best or (w == w_best and at_best is not None and at < at_best)


def prepare_labels(vol: Volume | Header, doc, spec, *, method=None, evaluator=None,
                   source: str = "input", allow_growth: bool = False,
                   grid: str | None = None):
    """``(cap, scene, frames)`` for warping the label map ``vol`` (or its Header) by a spec.

    The spec: ``doc``, ``spec``. Returned: the :func:`capture_labels` capture of
    ``vol`` and :func:`.prepare.prepare`'s scene and frames (the frames' lattices are
    applied by :func:`warp_labels`). ``grid``: the output's, as
    :func:`.prepare.prepare` takes it. (The map's background label, given
    or its border's, is :func:`.run.background_label`'s: the scene's
    background value is unused by labels.)
    """
    from .prepare import capture_as_spec, prepare

    cap = capture_as_spec(capture_labels, spec.capture, source, vol)
    scene, frames = prepare(cap, doc, spec, method=method, evaluator=evaluator, background=0.0,
                            allow_growth=allow_growth, grid=grid)
    return cap, scene, frames


def format_report(report: dict) -> str:
    """The per-label report as text lines (``warp --labels -v``)."""
    lines = ["label  input_mm3  output_mm3  predicted_mm3  output/predicted"]
    for L, r in report["labels"].items():
        ratio = r["output_mm3"] / r["predicted_mm3"] if r["predicted_mm3"] > 0 else float("nan")
        mark = "  (preserved)" if r["preserved"] else ("  (vanished)" if L in report["vanished"]
                                                       else "")
        lines.append(f"{L:>5}  {r['input_mm3']:>9.6g}  {r['output_mm3']:>10.6g}  "
                     f"{r['predicted_mm3']:>13.6g}  {ratio:>16.4f}{mark}")
    return "\n".join(lines)
