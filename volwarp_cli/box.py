"""The one region type: a box of voxel indices in array order ``(z, y, x)``.

A :class:`Box` is three half-open index ranges ``[lo, hi)``, in the order of
the sample array's axes, so ``data[box.slices]`` is the block. Blocks, halos,
windows and tilings are all boxes; every operation's input-region rule
(:mod:`.regions`) takes an output box and returns an input box.

Geometry is written (x, y, z) elsewhere (specs, metadata, the warp's lattice
code): :meth:`Box.from_xyz` and :meth:`Box.xyz` convert, through
:func:`~.volume.xyz_to_zyx` and :func:`~.volume.zyx_to_xyz`, the one place the
two orders meet.

A box may reach below 0 (a halo grown past a volume's edge, before it is
clamped with ``within=``); :attr:`Box.slices` refuses such a box, since numpy
would read a negative start from the far end.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

from .volume import xyz_to_zyx, zyx_to_xyz

Ints3 = tuple[int, int, int]


def _ints3(values, name: str) -> Ints3:
    """Three ints from a sequence, or the same int three times from a scalar."""
    if type(values) is tuple and len(values) == 3 and all(type(v) is int for v in values):
        return values  # (the common case, as fast as can be: boxes are made in inner loops)
    if isinstance(values, int) or (hasattr(values, "__index__") and not hasattr(values, "__len__")):
        return (int(values),) * 3
    out = tuple(int(v) for v in values)
    if len(out) != 3:
        raise ValueError(f"{name} needs 3 values (z, y, x), got {len(out)}")
    return out


@dataclass(frozen=True)
class Box:
    """Half-open index ranges ``[lo, hi)`` per array axis ``(z, y, x)``.

    Parameters
    ----------
    lo, hi : 3 ints each
        First index and end (exclusive) per axis; ``hi >= lo`` (an axis with
        ``hi == lo`` makes the box empty).
    """

    lo: Ints3
    hi: Ints3

    def __post_init__(self):
        lo = _ints3(self.lo, "lo")
        hi = _ints3(self.hi, "hi")
        if any(b < a for a, b in zip(lo, hi, strict=True)):
            raise ValueError(f"a box needs hi >= lo on every axis, got lo={lo}, hi={hi}")
        object.__setattr__(self, "lo", lo)
        object.__setattr__(self, "hi", hi)

    # -- construction ---------------------------------------------------------------
    @classmethod
    def from_shape(cls, shape) -> Box:
        """The whole array of ``shape`` (z, y, x): ``[0, shape)``."""
        return cls((0, 0, 0), shape)

    @classmethod
    def from_xyz(cls, lo_xyz, hi_xyz) -> Box:
        """The box of (x, y, z) ranges ``[lo_xyz, hi_xyz)``."""
        return cls(xyz_to_zyx(_ints3(lo_xyz, "lo")), xyz_to_zyx(_ints3(hi_xyz, "hi")))

    def xyz(self) -> tuple[Ints3, Ints3]:
        """``(lo, hi)`` in (x, y, z) order."""
        return zyx_to_xyz(self.lo), zyx_to_xyz(self.hi)

    # -- sizes ----------------------------------------------------------------------
    @property
    def shape(self) -> Ints3:
        """Voxels per axis (z, y, x)."""
        return tuple(b - a for a, b in zip(self.lo, self.hi, strict=True))

    @property
    def size(self) -> int:
        """Number of voxels."""
        z, y, x = self.shape
        return z * y * x

    @property
    def empty(self) -> bool:
        """True when the box holds no voxel."""
        return self.size == 0

    @property
    def slices(self) -> tuple[slice, slice, slice]:
        """``data[box.slices]`` is the block (the box must not reach below 0)."""
        if min(self.lo) < 0:
            raise ValueError(f"{self} reaches below index 0: clamp it (grow(..., within=...) "
                             "or intersect) before indexing an array")
        return tuple(slice(a, b) for a, b in zip(self.lo, self.hi, strict=True))

    # -- algebra --------------------------------------------------------------------
    def intersect(self, other: Box) -> Box:
        """The voxels in both boxes (empty on an axis where they do not overlap)."""
        lo = tuple(max(a, b) for a, b in zip(self.lo, other.lo, strict=True))
        hi = tuple(max(s, min(a, b)) for s, a, b in zip(lo, self.hi, other.hi, strict=True))
        return Box(lo, hi)

    def union_hull(self, other: Box) -> Box:
        """The smallest box holding both.

        An empty box adds nothing; two empty boxes give the empty box at the origin,
        ``Box((0, 0, 0), (0, 0, 0))``.
        """
        if self.empty and other.empty:
            return Box((0, 0, 0), (0, 0, 0))
        if other.empty:
            return self
        if self.empty:
            return other
        return Box(tuple(min(a, b) for a, b in zip(self.lo, other.lo, strict=True)),
                   tuple(max(a, b) for a, b in zip(self.hi, other.hi, strict=True)))

    def contains(self, other) -> bool:
        """True when ``other`` (a Box, or one index (z, y, x)) lies inside.

        An empty box lies inside every box.
        """
        if isinstance(other, Box):
            if other.empty:
                return True
            return all(a <= c and d <= b for a, b, c, d in
                       zip(self.lo, self.hi, other.lo, other.hi, strict=True))
        p = _ints3(other, "index")
        return all(a <= v < b for a, b, v in zip(self.lo, self.hi, p, strict=True))

    def grow(self, n, within: Box | None = None) -> Box:
        """The box widened by ``n`` voxels on both sides (one int, or per axis (z, y, x)).

        Negative ``n`` shrinks it. ``within``: clamped to that enclosing box.
        """
        n = _ints3(n, "n")
        box = Box(tuple(a - k for a, k in zip(self.lo, n, strict=True)),
                  tuple(b + k for b, k in zip(self.hi, n, strict=True)))
        return box if within is None else box.intersect(within)

    def shift(self, offset) -> Box:
        """The box moved by ``offset`` voxels (one int, or per axis (z, y, x))."""
        d = _ints3(offset, "offset")
        return Box(tuple(a + k for a, k in zip(self.lo, d, strict=True)),
                   tuple(b + k for b, k in zip(self.hi, d, strict=True)))

    def relative_to(self, outer: Box) -> Box:
        """The box in the index frame of ``outer`` (whose ``lo`` becomes 0).

        That is where the block sits in the array ``data[outer.slices]``.
        """
        return self.shift(tuple(-v for v in outer.lo))

    # -- tilings --------------------------------------------------------------------
    def split(self, axis: int, parts: int) -> list[Box]:
        """``parts`` boxes cutting this one along array ``axis`` (0 = z), in order.

        Their lengths differ by at most one voxel; with more parts than voxels
        some are empty. Together they tile the box exactly.
        """
        if axis not in (0, 1, 2):
            raise ValueError(f"axis must be 0, 1 or 2 (z, y, x), got {axis}")
        if parts < 1:
            raise ValueError(f"parts must be at least 1, got {parts}")
        a, n = self.lo[axis], self.shape[axis]
        cuts = [a + n * i // parts for i in range(parts + 1)]
        out = []
        for c0, c1 in zip(cuts[:-1], cuts[1:], strict=True):
            lo, hi = list(self.lo), list(self.hi)
            lo[axis], hi[axis] = c0, c1
            out.append(Box(lo, hi))
        return out

    def blocks(self, block_shape) -> list[Box]:
        """Tiles of ``block_shape`` (z, y, x) covering the box exactly, in C order (x fastest).

        The last tile along an axis is cut short at the box's end.
        """
        step = _ints3(block_shape, "block_shape")
        if min(step) < 1:
            raise ValueError(f"block_shape must be positive, got {step}")
        if self.empty:
            return []
        starts = [range(a, b, s) for a, b, s in zip(self.lo, self.hi, step, strict=True)]
        return [Box(lo, tuple(min(v + s, b) for v, s, b in zip(lo, step, self.hi, strict=True)))
                for lo in product(*starts)]
