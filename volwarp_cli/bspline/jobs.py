"""Typed calls into the warp's compiled kernels: one frozen dataclass per kernel.

The C kernels of ``_warpkernels.c`` take their arguments by position (the
scatter 19 of them, several of them triples of the same type); a triple in
the wrong place would run, on the wrong voxels. Each job here names its
fields, checks their types and shapes once, and calls its kernel in the
kernel's order, so a misplaced argument is a ``TypeError`` at construction.
``dataclasses.replace(job, block=..., clip=...)`` derives a job's parts (the
threads' slabs, a block's planes).

Regions are :class:`~volwarp_cli.box.Box` es (array order z, y, x) up to
here: a scatter's domain block and target window, a finalize's target block.
The ``run`` methods turn them into the kernels' integers, the one place those
are made (:func:`clip_ints` for the scatter's window, :meth:`Box.xyz` for the
blocks).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..box import Box
from . import _warpkernels

__all__ = ["ScatterJob", "SeparableJob", "TableJob", "SampleJob", "FinalizeJob", "replace"]


def _ints(name: str, value, n: int = 3) -> tuple[int, ...]:
    """``value`` as a tuple of ``n`` Python ints, or a TypeError naming the field."""
    try:
        items = tuple(value)
    except TypeError:
        raise TypeError(f"{name} must be {n} integers, got {value!r}") from None
    if len(items) != n or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool)
                                   for v in items):
        raise TypeError(f"{name} must be {n} integers, got {value!r}")
    return tuple(int(v) for v in items)


def _floats(name: str, value, n: int = 3) -> tuple[float, ...]:
    try:
        items = tuple(value)
    except TypeError:
        raise TypeError(f"{name} must be {n} numbers, got {value!r}") from None
    if len(items) != n or not all(isinstance(v, (int, float, np.integer, np.floating))
                                  and not isinstance(v, bool) for v in items):
        raise TypeError(f"{name} must be {n} numbers, got {value!r}")
    return tuple(float(v) for v in items)


def _array(name: str, value, ndim: int, dtypes: tuple) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        raise TypeError(f"{name} must be a numpy array, got {type(value).__name__}")
    if value.ndim != ndim or value.dtype not in dtypes:
        raise TypeError(f"{name} must be a {ndim}-D array of {'/'.join(map(str, dtypes))}, "
                        f"got {value.ndim}-D {value.dtype}")
    return value


def _box(name: str, value) -> Box:
    """``value`` if it is a :class:`~volwarp_cli.box.Box`, else a TypeError naming the field."""
    if not isinstance(value, Box):
        raise TypeError(f"{name} must be a Box (z, y, x), got {value!r}")
    return value


def _clip_box(value) -> Box:
    """The target window kept, as a Box (z, y, x).

    A Box as is; 6 integers are the kernel's own order ``(x0, x1, y0, y1, z0,
    z1)`` (a window with an end before its start keeps nothing: made empty).
    """
    if isinstance(value, Box):
        return value
    x0, x1, y0, y1, z0, z1 = _ints("clip", value, 6)
    return Box((z0, y0, x0), (max(z0, z1), max(y0, y1), max(x0, x1)))


def clip_ints(box: Box) -> tuple[int, int, int, int, int, int]:
    """The kernels' clip ``(x0, x1, y0, y1, z0, z1)`` of target window ``box`` (z, y, x)."""
    (z0, y0, x0), (z1, y1, x1) = box.lo, box.hi
    return (x0, x1, y0, y1, z0, z1)


_F32 = (np.dtype(np.float32),)
_FLOAT = (np.dtype(np.float32), np.dtype(np.float64))
_I64 = (np.dtype(np.int64),)


@dataclass(frozen=True, kw_only=True, eq=False)
class ScatterJob:
    """The box (or nearest) pushforward of the domain voxels ``block`` into ``acc``.

    See :func:`.pushforward.scatter` for the meaning of each field; ``block``
    (domain voxels) and ``clip`` (the target window kept) are
    :class:`~volwarp_cli.box.Box` es (z, y, x; 6 integers ``(x0, x1, y0, y1,
    z0, z1)`` are taken as a clip), ``acc`` holding the window's plane
    ``clip.lo[0]`` first (or, with ``ring``, plane z at ``z % len(acc)``).

    ``values`` and ``acc`` may hold some columns and rows of their planes
    only (an out-of-core block's): ``values_xy`` and ``acc_xy`` are the (x, y)
    of their ``[:, 0, 0]``, and ``domain_xy`` the domain's columns and rows
    (default: the values' own, whole planes). The block and the window must
    lie inside them.
    """

    u: np.ndarray
    u_new: np.ndarray | None
    origin: tuple[int, int, int]
    values: np.ndarray
    planes: tuple[int, int]
    offset: tuple[float, float, float]
    scale: tuple[float, float, float]
    block: Box
    sign: int
    inv_vmax: float
    box: bool
    acc: np.ndarray
    clip: Box
    ring: bool = False
    bounds: bool = False
    still: np.ndarray | None = None
    granularity: tuple[int, int, int] = (1, 1, 1)
    values_xy: tuple[int, int] = (0, 0)
    domain_xy: tuple[int, int] | None = None
    acc_xy: tuple[int, int] = (0, 0)

    def __post_init__(self):
        s = object.__setattr__
        _array("u", self.u, 4, _F32)
        if self.u_new is not None:
            _array("u_new", self.u_new, 4, _F32)
        _array("values", self.values, 3, _FLOAT)
        _array("acc", self.acc, 4, _I64)
        if self.still is not None:
            _array("still", self.still, 4, (np.dtype(np.uint8),))
        s(self, "origin", _ints("origin", self.origin))
        s(self, "planes", _ints("planes", self.planes, 2))
        s(self, "offset", _floats("offset", self.offset))
        s(self, "scale", _floats("scale", self.scale))
        _box("block", self.block)
        s(self, "clip", _clip_box(self.clip))
        s(self, "granularity", _ints("granularity", self.granularity))
        s(self, "values_xy", _ints("values_xy", self.values_xy, 2))
        if self.domain_xy is not None:
            s(self, "domain_xy", _ints("domain_xy", self.domain_xy, 2))
        s(self, "acc_xy", _ints("acc_xy", self.acc_xy, 2))
        if self.sign not in (1, -1):
            raise TypeError(f"sign must be +1 or -1, got {self.sign!r}")
        for name in ("box", "ring", "bounds"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise TypeError(f"{name} must be a bool, got {getattr(self, name)!r}")
        s(self, "inv_vmax", float(self.inv_vmax))

    def run(self) -> np.ndarray:
        """Scatter; returns the touched target box ``[x0, y0, z0, x1, y1, z1]``.

        The box is inclusive; x1 < 0 when nothing landed or ``bounds`` is off.
        """
        two = self.u_new is not None
        lo, hi = self.block.xyz()
        return np.array(_warpkernels.scatter(
            self.u, self.u_new if two else self.u, 2 if two else 1, self.origin, self.values,
            self.planes, self.offset, self.scale, lo, hi, self.sign, self.inv_vmax,
            bool(self.box), self.acc, clip_ints(self.clip), bool(self.ring), bool(self.bounds),
            self.still, self.granularity, self.values_xy,
            (-1, -1) if self.domain_xy is None else self.domain_xy, self.acc_xy))


@dataclass(frozen=True, kw_only=True, eq=False)
class SeparableJob:
    """The separable spline evaluator on domain voxels [x0, x1) x [y0, y1) x [z0, z1)."""

    dq: np.ndarray
    weights: tuple[np.ndarray, np.ndarray, np.ndarray]  # x, y, z: (granularity, 4)
    x: tuple[int, int]
    y: tuple[int, int]
    z: tuple[int, int]
    out: np.ndarray
    origin: tuple[int, int, int]

    def __post_init__(self):
        _array("dq", self.dq, 4, (np.dtype(np.float64),))
        if len(self.weights) != 3:
            raise TypeError("weights must be the x, y and z tables")
        for name, w in zip("xyz", self.weights, strict=True):
            _array(f"weights {name}", w, 2, (np.dtype(np.float64),))
        _array("out", self.out, 4, _FLOAT)
        for name in ("x", "y", "z"):
            object.__setattr__(self, name, _ints(name, getattr(self, name), 2))
        object.__setattr__(self, "origin", _ints("origin", self.origin))

    def run(self) -> None:
        """Evaluate the offsets into ``out`` (the compiled kernel of ``_warpkernels.c``)."""
        wx, wy, wz = self.weights
        _warpkernels.separable(self.dq, wx, wy, wz, *self.x, *self.y, *self.z, self.out,
                               *self.origin)


@dataclass(frozen=True, kw_only=True, eq=False)
class TableJob:
    """The papers' 64-term table evaluator (numba) on the same ranges as :class:`SeparableJob`."""

    dq: np.ndarray
    table: np.ndarray
    x: tuple[int, int]
    y: tuple[int, int]
    z: tuple[int, int]
    out: np.ndarray
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3, np.int64))

    def __post_init__(self):
        _array("dq", self.dq, 4, (np.dtype(np.float64),))
        _array("table", self.table, 6, (np.dtype(np.float64),))
        _array("out", self.out, 4, _FLOAT)
        for name in ("x", "y", "z"):
            object.__setattr__(self, name, _ints(name, getattr(self, name), 2))
        object.__setattr__(self, "origin", np.asarray(_ints("origin", self.origin), np.int64))

    def run(self) -> None:
        """Evaluate the offsets into ``out`` (the numba table kernel)."""
        from .basis import table_kernel

        table_kernel()(self.dq, self.table, *self.x, *self.y, *self.z, self.out, self.origin)


@dataclass(frozen=True, kw_only=True, eq=False)
class SampleJob:
    """The capture's gather of domain planes [g0, g1) into ``out``.

    The first plane of ``out`` is g0 when ``relative``, else plane 0 of the domain.
    """

    data: np.ndarray
    x: tuple[np.ndarray, np.ndarray, np.ndarray]  # lower index, upper index, weight
    y: tuple[np.ndarray, np.ndarray, np.ndarray]
    z: tuple[np.ndarray, np.ndarray, np.ndarray]
    out: np.ndarray
    g0: int
    g1: int

    def __post_init__(self):
        if not isinstance(self.data, np.ndarray) or self.data.ndim != 3:
            raise TypeError("data must be a 3-D numpy array")
        for name in ("x", "y", "z"):
            axis = getattr(self, name)
            if len(axis) != 3:
                raise TypeError(f"{name} must be (lower index, upper index, weight)")
            _array(f"{name} lower", axis[0], 1, (np.dtype(np.int32),))
            _array(f"{name} upper", axis[1], 1, (np.dtype(np.int32),))
            _array(f"{name} weight", axis[2], 1, (np.dtype(np.float64),))
        _array("out", self.out, 3, _FLOAT)
        object.__setattr__(self, "g0", int(self.g0))
        object.__setattr__(self, "g1", int(self.g1))

    def run(self) -> tuple[float, float]:
        """Gather; returns the (min, max) of the samples written."""
        return _warpkernels.sample(self.data, *self.x, *self.y, *self.z, self.out, self.g0,
                                   self.g1)


@dataclass(frozen=True, kw_only=True, eq=False)
class FinalizeJob:
    """``out = v / w`` (blended with the background on the silhouette) on target ``block``.

    ``block``: a :class:`~volwarp_cli.box.Box` (z, y, x) of ``acc`` and ``out``;
    ``clear`` zeroes the block's accumulators in the same pass.
    """

    acc: np.ndarray
    vmax: float
    block: Box
    out: np.ndarray
    background: float = 0.0
    clear: bool = False

    def __post_init__(self):
        _array("acc", self.acc, 4, _I64)
        _array("out", self.out, 3, _FLOAT)
        _box("block", self.block)
        object.__setattr__(self, "vmax", float(self.vmax))
        object.__setattr__(self, "background", float(self.background))
        if not isinstance(self.clear, (bool, np.bool_)):
            raise TypeError(f"clear must be a bool, got {self.clear!r}")

    def run(self) -> None:
        """Finalize the block into ``out`` (and clear its accumulators if asked)."""
        lo, hi = self.block.xyz()
        _warpkernels.finalize(self.acc, self.vmax, lo, hi, self.out, self.background,
                              bool(self.clear))
