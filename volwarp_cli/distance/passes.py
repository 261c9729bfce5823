"""The exact field and the line metrics: operations in passes over whole lines.

**Exact** (:class:`ExactDistance`): the exact Euclidean transform of
:mod:`.exact` is three separable passes (x, y, z), each setting a value from
the whole line through it along its axis and nothing else
(:func:`~volwarp_cli.regions.distance_pass_input`). The x and y passes run
together on slabs of whole planes (where a plane fits a block's budget;
otherwise x on whole x lines, then y on whole y lines), their float32
squared distances kept in a scratch array with the mask riding along as
their sign (a squared distance to the other side is never 0, and negating is
exact); the z pass, on whole z lines, takes the mask back from the sign, adds
the z terms and takes the signed square root.

**Line metrics** (:class:`LineMetricDistance`): ``minnorm``, ``taxicab`` and
``chessboard`` are per-axis passes too, elementwise along the lines of each
axis (:func:`.minnorm.line_metric_pass`): the outside and the inside fields
go through the x, y and z passes in two scratch arrays, and the z pass
combines them into the signed field.

Both are :class:`volwarp_cli.passes.Passes`: in memory, the whole's passes on
the calling threads (a block a view of the scratch, the kernels in place); by
blocks, the same pass functions on blocks of the same lines, the scratch in
files. The same arithmetic on the same lines: the same bytes. The whole's
checks (an empty or full shape, NaNs) are folded into the first pass
(:func:`.scan.block_stats` as the samples are read), not a read of their own.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError
from ..execute import Target
from ..passes import Pass, Passes
from .exact import x_pass, y_pass, z_pass
from .field import check_isotropic, finish_field, inside_mask
from .scan import block_stats, check_shape, merge_stats

#: Bytes per voxel a block of a pass holds besides its input samples, by blocks: a
#: float32 field, a float32 copy, the mask and the stats' boolean temporaries; in memory
#: (the field a view of the scratch array) the mask and the stats' temporaries. (Measured
#: in memory, 256^3 uint8: 10 bytes a voxel with the scratch, against 11 counted.)
PASS_BYTES_PER_VOXEL = 13
PASS_BYTES_IN_MEMORY = 6

#: Bytes per voxel of a line-metric block besides its samples, by blocks: the mask, the
#: outside and inside float32 fields, the shift scratch and a read copy; in memory: the
#: mask, a float32 temporary and the shift scratch. (Measured in memory, minnorm 256^3
#: uint8: 14 bytes a voxel with both scratch arrays, against 18 counted.)
LINE_BYTES_PER_VOXEL = 17
LINE_BYTES_IN_MEMORY = 9


# -- the shape, box by box -----------------------------------------------------------------
class MaskSource:
    """The shape's mask of any box of a sliceable source (an array or a lazy reader; picklable).

    ``check``: whether the first pass gathers the samples' statistics for the
    whole's checks (:meth:`box_and_stats`).
    """

    def __init__(self, source, iso: float, inside: str, *, check: bool = True,
                 name: str = ""):
        self.source, self.iso, self.inside, self.check = source, float(iso), inside, check
        self.name = name  # (the input's file: its checks' errors name it)
        self.shape = tuple(int(n) for n in source.shape)
        self.itemsize = np.dtype(source.dtype).itemsize
        self.is_bool = np.dtype(source.dtype) == bool

    def box(self, box) -> np.ndarray:
        """uint8 mask (1 inside) of ``box`` (z, y, x)."""
        return self._mask(np.asarray(self.source[box.slices]))

    def _mask(self, data: np.ndarray) -> np.ndarray:
        if self.is_bool and self.inside == "above" and 0 < self.iso <= 1:
            return data.view(np.uint8)  # the mask itself (no copy)
        return inside_mask(data, self.iso, self.inside).view(np.uint8)

    def box_and_stats(self, box):
        """:meth:`box` and, with ``check``, the box's :func:`.scan.block_stats`."""
        data = np.asarray(self.source[box.slices])
        return self._mask(data), block_stats(data, self.iso, self.inside) if self.check else None

    def after_first(self, values) -> None:
        """The whole's checks from the first pass's stats (an empty or full shape; NaNs)."""
        if self.check:
            nans, count, lo, hi, _ = merge_stats(values, self.is_bool)
            check_shape(nans, count, int(np.prod(self.shape)), lo, hi, self.iso, self.inside,
                        self.name)


class LabelMaskSource(MaskSource):
    """A label map's shape of any box (:func:`.labels.label_mask`): its voxels, never its ids.

    ``label``: one label's voxels; None: every non-zero id's. Its checks are
    made before the passes (:func:`.labels.choose_shape`).
    """

    def __init__(self, source, label: int | None = None):
        self.source, self.label, self.check, self.name = source, label, False, ""
        self.shape = tuple(int(n) for n in source.shape)
        self.itemsize = np.dtype(source.dtype).itemsize
        self.is_bool = False

    def box(self, box) -> np.ndarray:
        """uint8 mask (1 on the label's voxels) of ``box``."""
        from .labels import label_mask

        return label_mask(np.asarray(self.source[box.slices]), self.label).view(np.uint8)

    def box_and_stats(self, box):
        """:meth:`box`, and None for the stats (checked before)."""
        return self.box(box), None


def mask_source(source, rule) -> MaskSource:
    """The :class:`MaskSource` of ``rule``'s shape (:class:`.labels.ShapeRule`) in ``source``."""
    if rule.labels:
        return LabelMaskSource(source, rule.label)
    return MaskSource(source, rule.iso, rule.inside, name=rule.name)


def _field_target(target):
    # the array API's output: float32 arrays, no file
    return target if target is not None else Target(None, None, np.dtype(np.float32))


class _FieldPasses(Passes):
    """What both fields share: the grid, the output, how a block's field is finished."""

    label = "distance"

    def __init__(self, masks: MaskSource, grid, *, target=None, unsigned: bool = False,
                 max_distance: float | None = None, what: str | None = None):
        self.masks, self.grid = masks, grid
        self.spacing_zyx = tuple(float(s) for s in grid.spacing_zyx)
        self.targets = {"field": _field_target(target)}
        self.dtype = np.dtype(self.targets["field"].dtype)
        self.unsigned, self.max_distance = unsigned, max_distance
        self.what = what or f"the distance field of {grid.size} samples"

    #: bytes a voxel of a pass's block holds besides its samples: (by blocks, in memory)
    block_bytes_per_voxel = (PASS_BYTES_PER_VOXEL, PASS_BYTES_IN_MEMORY)

    def passes(self, block_bytes):
        """The passes: x and y on slabs (x, then y, where a plane does not fit), then z.

        Each pass's block is ``_xy``, ``_x``, ``_y`` or ``_z`` of the subclass.
        """
        by_blocks, in_memory = self.block_bytes_per_voxel
        per = (in_memory if block_bytes is None else by_blocks) + self._extra()
        nz, ny, nx = self.grid.shape
        if block_bytes is None or ny * nx * per <= block_bytes:
            first = [Pass("xy", (1, 2), per, self._xy, self.masks.after_first)]
        else:  # a plane does not fit: x on whole x lines, then y on whole y lines
            first = [Pass("x", (2,), per, self._x, self.masks.after_first),
                     Pass("y", (1,), per, self._y)]
        return [*first, Pass("z", (0,), per, self._z)]

    def load(self) -> None:
        """The kernels on a small ball, so that the budget counts their loaded code."""
        from .field import warm_kernels

        warm_kernels(getattr(self, "metric", "euclidean"), "voxel", np.dtype(bool), 0.5,
                     "above")

    def _finish(self, field: np.ndarray) -> np.ndarray:
        # --unsigned, --max-distance (in place), then the output's type
        finish_field(field, unsigned=self.unsigned, max_distance=self.max_distance)
        if self.dtype == field.dtype:
            return field
        from ..samples import cast_samples

        return cast_samples(field, self.dtype, what=str(self.targets["field"].path))

    def _extra(self) -> int:
        # a block's input samples and, where the output's type differs, its cast
        cast = 0 if self.dtype == np.float32 else self.dtype.itemsize
        return self.masks.itemsize + cast


class ExactDistance(_FieldPasses):
    """The exact signed Euclidean field between voxel centres, in passes (module notes).

    ``masks``: the shape (:class:`MaskSource`); ``grid``: the output
    :class:`~volwarp_cli.geometry.Geometry`; ``target``: the output file
    (None: the array API's float32 array). ``unsigned``, ``max_distance``:
    applied to each finished block.
    """

    scratch = {"xy": np.float32}
    aliases = {"field": "xy"}

    def _x(self, box, stores, *, and_y: bool = False):
        mask, stats = self.masks.box_and_stats(box)
        out = stores["xy"].empty(box)
        x_pass(mask, self.spacing_zyx[2], out)
        if and_y:  # (negates inside)
            y_pass(out, mask, self.spacing_zyx[1])
        else:
            np.negative(out, out=out, where=mask.view(bool))
        stores["xy"].write(box, out)
        return stats

    def _xy(self, box, stores):
        return self._x(box, stores, and_y=True)

    def _y(self, box, stores):
        field = stores["xy"].read(box)
        mask = np.signbit(field)
        np.abs(field, out=field)
        y_pass(field, mask.view(np.uint8), self.spacing_zyx[1])
        stores["xy"].write(box, field)

    def _z(self, box, stores):
        field = stores["xy"].read(box)
        z_pass(field, self.spacing_zyx[0])
        stores["field"].write(box, self._finish(field))


class LineMetricDistance(_FieldPasses):
    """The signed ``minnorm``, ``taxicab`` or ``chessboard`` field, in per-axis line passes.

    The outside field (0 on the shape, +inf off it) and the inside one go
    through the passes along x, y and z (x and y together on slabs of whole
    planes where a plane fits), then combine: ``-inside`` on the shape; taxicab
    and chessboard (integer voxel steps) scaled by the isotropic spacing.
    ``minnorm`` runs :func:`.minnorm.axis_pass`, the paper's shift-and-min
    passes; ``taxicab`` :func:`.minnorm.taxicab_axis_pass` (a sweep each way,
    scipy's ``distance_transform_cdt`` values); ``chessboard``
    :func:`.minnorm.chessboard_axis_pass`.
    """

    scratch = {"outside": np.float32, "inside": np.float32}
    aliases = {"field": "outside"}
    block_bytes_per_voxel = (LINE_BYTES_PER_VOXEL, LINE_BYTES_IN_MEMORY)

    def __init__(self, masks: MaskSource, grid, *, metric: str, **kwargs):
        if metric not in ("minnorm", "taxicab", "chessboard"):
            raise VolwarpError(f"no per-line passes for the {metric!r} metric")
        super().__init__(masks, grid, **kwargs)
        check_isotropic(metric, self.spacing_zyx)
        self.metric = metric
        self.scale = (None if metric == "minnorm" or self.spacing_zyx[0] == 1.0
                      else self.spacing_zyx[0])

    def _lines(self, fields, axes):
        from .minnorm import line_metric_pass

        scratch = np.empty(fields[0].size, np.float32) if self.metric == "minnorm" else None
        for f in fields:
            for axis in axes:
                line_metric_pass(self.metric, f, axis, self.spacing_zyx[axis], scratch)

    def _x(self, box, stores, axes=(2,)):
        mask, stats = self.masks.box_and_stats(box)
        m = mask.view(bool)
        out, inn = stores["outside"].empty(box), stores["inside"].empty(box)
        np.copyto(out, np.where(m, np.float32(0), np.float32(np.inf)))
        np.copyto(inn, np.where(m, np.float32(np.inf), np.float32(0)))
        del mask, m
        self._lines((out, inn), axes)
        stores["outside"].write(box, out)
        stores["inside"].write(box, inn)
        return stats

    def _xy(self, box, stores):
        return self._x(box, stores, axes=(2, 1))

    def _y(self, box, stores):
        out, inn = stores["outside"].read(box), stores["inside"].read(box)
        self._lines((out, inn), (1,))
        stores["outside"].write(box, out)
        stores["inside"].write(box, inn)

    def _z(self, box, stores):
        out, inn = stores["outside"].read(box), stores["inside"].read(box)
        self._lines((out, inn), (0,))
        # the shape is where the outside field is 0 (every other value is a step at least)
        np.negative(inn, out=inn)
        np.copyto(out, inn, where=out == 0)
        if self.scale is not None:
            out *= np.float32(self.scale)
        stores["field"].write(box, self._finish(out))


def field_passes(masks: MaskSource, spacing_zyx, *, metric: str = "euclidean",
                 **kwargs) -> _FieldPasses:
    """The operation in passes of ``metric``'s field of ``masks``' shape, on a grid of spacing_zyx.

    For the array API (no output file, the grid at the origin): ``kwargs``
    as :class:`ExactDistance`'s.
    """
    from ..geometry import Geometry
    from ..volume import zyx_to_xyz

    grid = Geometry.from_xyz(zyx_to_xyz(masks.shape), zyx_to_xyz(spacing_zyx))
    if metric == "euclidean":
        return ExactDistance(masks, grid, **kwargs)
    return LineMetricDistance(masks, grid, metric=metric, **kwargs)


def field_in_memory(masks: MaskSource, spacing_zyx, *, metric: str = "euclidean") -> np.ndarray:
    """The float32 signed field of ``masks``' shape: the passes in memory, on the threads."""
    from .. import parallel

    op = field_passes(masks, spacing_zyx, metric=metric)
    return op.compute(op.grid.box, threads=parallel.threads())["field"]
