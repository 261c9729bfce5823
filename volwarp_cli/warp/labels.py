"""Warping label maps (segmentations): the forward counterpart of ITK's label interpolators.

The intensity warp averages sample values, which on a label map writes ids
that occur nowhere near the voxel. Here every label ``L`` gets a weight per
output voxel instead, and the output voxel takes the label of largest weight:

- ``L``'s weight is the box pushforward's accumulated weight of its indicator
  (1 inside ``L``, 0 elsewhere): the exact fixed-point sums of the intensity
  warp (:meth:`~volwarp_cli.bspline.scene.Scene.contribute`), read before the ``v / w``
  normalisation. One pass per label, over the domain block of its bounding
  box, into a rolling accumulator that covers only the target block the
  label's image can reach (bounded from the lattice alone, region by region:
  :meth:`~volwarp_cli.bspline.reach.Reach.rebuild_block`), so memory does not grow with the
  number of labels: the output holds the best weight and label so far.
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
- Ties go to the smaller label, deterministically. Every output value is an
  input label, and ids keep the input's type end to end (only the weights
  are numbers): integer ids above 2^24 survive. Float samples are a label
  map when every one is an integer (nibabel's and MONAI's segmentations):
  their ids are compared as the floats they are (exact for integers), and
  the output has the input's float type.

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

import copy
import threading
from dataclasses import dataclass, field

import numpy as np

from .. import parallel
from ..box import Box
from ..bspline.capture import Capture, geometry_capture
from ..bspline.lattice import PLACEMENTS
from ..bspline.pushforward import QUANTUM, HeldPlanes
from ..bspline.reach import STREAM_PLANES, ring_planes
from ..bspline.scene import Scene
from ..errors import VolwarpError
from ..memory import ensure_fits_in_memory
from ..progress import log, timed
from ..volume import Volume

_Q = int(QUANTUM)


def capture_labels(vol: Volume, *, lattice=(9, 9, 9), placement: str = "uniform",
                   oversample: float = 2.0, sampling: str = "linear", pad=None) -> Capture:
    """A :class:`Capture` of a label map (no float voxmap: the label passes gather their own).

    Refuses samples that cannot be ids (not integers or floats; a float's
    values are checked by the label passes, which read them all) and the
    spanning grid (a non-integer oversample or the tripled placement: its
    capture would blend ids). The returned capture keeps the labels as
    ``labels`` (``vol.data``, not copied).
    """
    data = vol.data
    if np.dtype(data.dtype).kind not in "iuf":
        raise VolwarpError(f"a label map needs integer samples, got {data.dtype} (convert it "
                           "with --dtype, or warp it without --labels)")
    if placement not in PLACEMENTS:
        raise VolwarpError(f"unknown placement {placement!r} (use uniform or tripled)")
    k = float(oversample)
    if placement != "uniform" or not (k >= 1 and k.is_integer()):
        raise VolwarpError("a label map is warped on the subdivision grid, where each domain "
                           "voxel takes one input voxel's label: use an integer oversample "
                           f"(1, 2, ...) and the uniform placement (got oversample {oversample:g}, "
                           f"placement {placement})")
    cap = geometry_capture(vol, lattice=lattice, placement=placement, oversample=k,
                           sampling=sampling, pad=pad)
    cap.labels = data
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


class LabelStream:
    """One share of the target (z planes [t_lo, t_hi)): what :func:`label_passes` fills.

    ``labels_in``: the label map, any sliceable ``[z, y, x]``; ``best_w``,
    ``best_l``: the best weight and label so far of the share's planes (or
    of more: see :func:`label_passes`); ``background``: the map's background
    label. Its buffers, and one label pass at a time streamed into a rolling
    accumulator of its target block.
    """

    def __init__(self, scene: Scene, dq, labels_in: np.ndarray, t_lo: int, t_hi: int,
                 best_w: np.ndarray, best_l: np.ndarray, background: int = 0):
        self.scene, self.dq, self.data = scene, dq, labels_in  # (any sliceable map)
        self.background = background
        self.t_lo, self.t_hi = t_lo, t_hi
        self.best_w, self.best_l = best_w, best_l
        grid = scene.grid
        self.k = grid.subdivision
        self.lead = np.array(grid.lead)
        self.chunk = max(1, int(STREAM_PLANES * self.k))  # domain planes per step
        # each domain plane's reach, from its own layer of the lattice (as the stream's)
        self.reach = scene._plane_reach([dq])
        self.planes = ring_planes(self.reach, self.chunk)
        dz, dy, dx = grid.domain_shape[::-1]
        self.values = np.zeros((self.chunk, dy, dx), dtype=np.float32)
        self.acc = np.zeros(0, dtype=np.int64)
        from ..bspline.scene import Scratch
        self.scratch = Scratch()

    def run(self, label, box: Box, on_planes) -> None:
        """Scatter label ``label``'s indicator (None: the background's) over input box ``box``.

        The background's indicator is ``label != background``: the weight of the
        model's other labels, from which its own is found.

        ``box``: a :class:`~volwarp_cli.box.Box` (z y x) of the input.

        ``on_planes(target, weights)`` is called for the finished target planes of its
        block in this thread's share: ``weights[k, y, x, 2]`` of the target voxels
        ``target`` (a :class:`~volwarp_cli.box.Box`, z y x).
        """
        sc, k = self.scene, self.k
        box_lo, box_hi = (np.array(v, np.int64) for v in box.xyz())
        vlo = self.lead + k * box_lo
        vhi = self.lead + k * box_hi
        voxels = Box.from_xyz(vlo.tolist(), vhi.tolist())  # the domain's
        bounds = sc._offset_bounds(self.dq)
        block = sc.reach.rebuild_block(bounds, bounds, voxels)
        if block is None:
            return
        (tz0, y0, x0), (tz1, y1, x1) = block.target.lo, block.target.hi
        z_lo, z_hi = max(tz0, self.t_lo), min(tz1, self.t_hi)
        if z_lo >= z_hi:
            return
        wx, wy = x1 - x0, y1 - y0
        # target coordinates relative to the block's corner in x and y: a small ring
        sub = copy.copy(sc)
        sub.offset = sc.offset - np.array([x0, y0, 0.0])
        sub.scratch = self.scratch
        need = self.planes * wy * wx * 2
        if self.acc.size < need:
            self.acc = np.zeros(need + need // 4, dtype=np.int64)
        acc = self.acc[:need].reshape(self.planes, wy, wx, 2)
        acc.fill(0)
        g_lo, g_hi = self.reach.domain_window(z_lo, z_hi)
        g_lo, g_hi = max(g_lo, int(vlo[2])), min(g_hi, int(vhi[2]))
        base = z_lo
        planes = self.planes

        def flush(upto):
            nonlocal base
            while base < upto:
                s0 = base % planes
                n = min(upto - base, planes - s0)
                on_planes(Box((base, y0, x0), (base + n, y1, x1)), acc[s0:s0 + n])
                acc[s0:s0 + n] = 0
                base += n

        (_, by0, bx0), (_, by1, bx1) = box.lo, box.hi
        xs = slice(int(vlo[0]), int(vhi[0]))
        ys = slice(int(vlo[1]), int(vhi[1]))
        for g0 in range(g_lo, g_hi, self.chunk):
            g1 = min(g0 + self.chunk, g_hi)
            r_lo, r_hi = self.reach.target_reach(g0, g1)  # r_lo: of every plane from g0 on
            flush(min(max(r_lo, base), z_hi))
            if min(r_hi, z_hi) - base > planes:  # pragma: no cover - cannot happen
                raise AssertionError("rolling accumulator too small")
            # the indicator of the label on domain planes [g0, g1) (the box's voxels;
            # the rest of the buffer stays 0): each domain voxel takes its input voxel's
            zi = (np.arange(g0, g1) - self.lead[2]) // k
            # (one contiguous read of the input planes, then repeated: the map may be a
            # file read by boxes, which takes no index arrays)
            src = np.asarray(self.data[int(zi[0]):int(zi[-1]) + 1, by0:by1, bx0:bx1])[
                zi - zi[0]]
            ind = (src != self.background) if label is None else (src == label)
            view = self.values[:g1 - g0, ys, xs].reshape(g1 - g0, by1 - by0, k, bx1 - bx0, k)
            np.copyto(view, ind[:, :, None, :, None])
            sub.contribute([self.dq], Box((g0, *voxels.lo[1:]), (g1, *voxels.hi[1:])), 1,
                           acc=acc, held=HeldPlanes(base, min(base + planes, z_hi), ring=True),
                            parallel=False,
                            scratch=self.scratch, values=(self.values[:g1 - g0], g0),
                            window=((0, wx), (0, wy)))
            self.values[:g1 - g0, ys, xs] = 0
        flush(z_hi)


def warp_labels(labels_in: np.ndarray, scene: Scene, frames=(), *, preserve: bool = False,
                spacing=(1.0, 1.0, 1.0), background: int | None = None) -> LabelWarp:
    """Warp the label map ``labels_in`` ``[z, y, x]`` (integer ids) with ``scene``'s lattice.

    ``scene``: from :func:`.prepare.prepare` on a :func:`capture_labels` capture;
    the last of ``frames`` (if any) is the lattice applied. ``spacing``
    (x y z, mm) scales the report's volumes. ``background``: the label
    written where nothing lands (None: :func:`~volwarp_cli.border.border_label`, the
    most frequent on the map's border). Returns the target labels (padded
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
    ensure_fits_in_memory(tx * ty * tz * (8 + labels_in.dtype.itemsize)
                          + workers * stream_bytes(scene, dq, labels_in.dtype),
                          "the warped labels")
    with timed("labels: bounding boxes"):
        labels, nvox, boxes, _ = _bounding_boxes(labels_in, b)
    best_w = np.empty((tz, ty, tx), dtype=np.int64)
    best_l = np.full((tz, ty, tx), b, dtype=labels_in.dtype)
    # the background's weight where nothing of the model lands: all of it
    best_w.fill(_Q)
    cuts = parallel.cuts(0, tz, workers)
    vol_voxel = float(np.prod(spacing))
    predicted = {L: 0 for L in labels}  # exact integer sums: the same for any thread count
    peak = {L: (0, None) for L in labels}  # (weight, target index z y x)
    lock = threading.Lock()

    def share(i):
        st = LabelStream(scene, dq, labels_in, cuts[i], cuts[i + 1], best_w, best_l, b)
        got, top = label_passes(st, labels, boxes, preserve=preserve)
        with lock:
            merge_passes(predicted, peak, got, top)

    with timed(f"labels: {len(labels)} label passes + background ({workers} threads)"):
        parallel.run_blocks(share, range(len(cuts) - 1), workers)
    best_w = None  # (freed before the counts)
    out_counts = _counts(best_l, labels, b)

    def label_at(at):
        return best_l[at]

    def set_label(at, L):
        best_l[at] = L

    report = label_report(labels, nvox, predicted, peak, out_counts, vol_voxel,
                          preserve=preserve, label_at=label_at, set_label=set_label)
    report["background"] = b
    return LabelWarp(best_l, report)


def stream_bytes(scene: Scene, dq, dtype) -> int:
    """Memory one share of :func:`label_passes` holds beside its target planes (an upper bound).

    A label pass's rolling accumulator (whole target planes, for the
    background's), its domain planes, the input planes they read, and the
    deformation's buffers.
    """
    grid = scene.grid
    k = grid.subdivision
    chunk = max(1, int(STREAM_PLANES * k))
    planes = ring_planes(scene._plane_reach([dq]), chunk)  # as LabelStream's
    tx, ty, _ = scene.target_shape
    dx, dy, _ = grid.domain_shape
    nx, ny, _ = grid.input_shape
    inputs = (chunk // max(1, k) + 1) * ny * nx * (np.dtype(dtype).itemsize + 1)
    return (planes * ty * tx * 16 + chunk * dy * dx * 4 + inputs
            + 2 * scene.chunk_bytes)


def label_passes(st: LabelStream, labels, boxes, *, preserve: bool = False, z_base: int = 0):
    """The background's and every label's pass over the target planes of share ``st``.

    Into its ``best_w``/``best_l``, whose plane 0 is target plane ``z_base`` (the
    whole target, or one slab of it: the result does not depend on the cut);
    ``best_l`` holds the ``background`` label where no label wins.
    ``labels``/``boxes``: the map's labels but ``background`` and their input
    bounding boxes (:func:`_bounding_boxes`). Returns ``(predicted, peak)``:
    per label, its total weight in these planes and (with ``preserve``) its
    voxel of largest weight ``(w, (z, y, x))`` (target indices).
    """
    best_w, best_l = st.best_w, st.best_l
    full = Box.from_xyz((0, 0, 0), st.scene.grid.input_shape)
    predicted = {}
    peak = {}

    def on_background(target, acc):
        w_all, w_fg = acc[..., 0], acc[..., 1]
        best_w[target.shift((-z_base, 0, 0)).slices] = np.maximum(w_all, _Q) - w_fg

    st.run(None, full, on_background)
    # the labels below the background first, descending, winning ties (>=: the smaller id
    # wins), then those above it ascending, losing ties: the smallest label wins a tie
    b = st.background
    order = [L for L in labels if L < b][::-1] + [L for L in labels if L > b]
    where = {L: i for i, L in enumerate(labels)}
    for L in order:
        total = [0]
        top = [0, None]

        def keep(target, acc, L=L, total=total, top=top):
            w = acc[..., 1]
            here = target.shift((-z_base, 0, 0)).slices
            bw, bl = best_w[here], best_l[here]
            better = (w >= bw) if L < b else (w > bw)
            np.copyto(bw, w, where=better)
            np.copyto(bl, L, where=better, casting="unsafe")
            total[0] += int(w.sum(dtype=np.int64))  # < 2^63: a few planes of 2^40 each
            if preserve:
                j = int(np.argmax(w))
                kz, ky, kx = np.unravel_index(j, w.shape)
                at = tuple(a + int(b) for a, b in zip(target.lo, (kz, ky, kx), strict=True))
                if _stronger(int(w.flat[j]), at, *top):
                    top[0], top[1] = int(w.flat[j]), at

        st.run(L, boxes[where[L]], keep)
        predicted[L] = total[0]
        peak[L] = (top[0], top[1])
    return predicted, peak


def merge_passes(predicted: dict, peak: dict, got: dict, top: dict) -> None:
    """Add one share's :func:`label_passes` result to the totals (in place)."""
    for L, total in got.items():
        predicted[L] = predicted.get(L, 0) + total
    for L, (w, at) in top.items():
        if at is not None and _stronger(w, at, *peak.get(L, (0, None))):
            peak[L] = (w, at)


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


def _counts(target: np.ndarray, labels, background: int = 0) -> dict:
    """Voxels of each label in ``target`` (a few planes at a time: no whole-size copy).

    ``target`` holds ``labels`` and the ``background`` label only.
    """
    if not labels:
        return {}
    lo, hi = min(min(labels), background), max(max(labels), background)
    if hi - lo >= 1 << 24:
        values, counts = np.unique(target, return_counts=True)
        have = dict(zip(values.tolist(), counts.tolist(), strict=True))
        return {L: int(have.get(L, 0)) for L in labels}
    counts = np.zeros(hi - lo + 1, dtype=np.int64)
    step = max(1, (1 << 20) // max(1, target[0].size))
    for z in range(0, len(target), step):
        part = target[z:z + step].ravel().astype(np.int64) - lo
        counts += np.bincount(part, minlength=hi - lo + 1)
    return {L: int(counts[L - lo]) for L in labels}


def prepare_labels(vol: Volume, doc, spec, *, method=None, evaluator=None, background=None,
                   source: str = "input", allow_growth: bool = False, grid: str | None = None):
    """``(cap, scene, frames)`` for warping the label map ``vol`` with a checked spec.

    The spec: ``doc``, ``spec``. Returned: the :func:`capture_labels` capture of
    ``vol`` and :func:`.prepare.prepare`'s scene and frames (the frames' lattices are
    applied by :func:`warp_labels`). ``grid``: the output's, as
    :func:`.prepare.prepare` takes it.
    """
    from .prepare import capture_as_spec, prepare

    if background not in (None, 0, 0.0):
        raise VolwarpError("--background does not apply to a label map (its background is "
                           "its most frequent border label)")
    cap = capture_as_spec(capture_labels, spec.capture, source, vol)
    if spec.background not in (None, 0):
        raise doc.error(("background",), "does not apply to a label map (its background is "
                        "its most frequent border label)")
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
