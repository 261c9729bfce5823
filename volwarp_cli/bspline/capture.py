"""A captured volume: the domain voxmap plus everything needed to warp it later.

:func:`capture_volume` is the ``volwarp capture`` core (paper §5
"Initialization"): it sets up the lattice, places the capture control points
and pulls the input back into the domain voxmap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..border import border_value, lower_median
from ..errors import VolwarpError
from ..memory import ensure_fits_in_memory
from ..progress import timed
from ..volume import Header, Volume
from .lattice import PLACEMENTS, Lattice, capture_offsets
from .pullback import SAMPLINGS, Sampler


@dataclass
class Capture:
    """Domain voxmap ``[Dz, Dy, Dx]`` and the capture set-up.

    ``geometry`` is the input volume's :class:`~volwarp_cli.volume.Header`
    (its shape, geometry, frame and ``meta``); ``input_dtype`` and ``stats`` (min, max, mean;
    the mean None when not asked for) describe the captured input. The
    domain's samples lie within the input's (min, max): each is one input
    sample (on a subdivision grid: its input voxel's; outside the input, the
    nearest edge voxel's, which the pushforward leaves out) or a convex
    combination of eight. A deferred capture has no
    ``domain`` array but a ``sampler`` that gathers its planes on demand.
    ``border``: the median of the input's border samples
    (:func:`~volwarp_cli.border.border_value`), the warp's default background; None
    when not known.
    """

    domain: np.ndarray | None
    grid: Lattice
    placement: str
    oversample: float
    sampling: str
    pad: tuple[int, int, int] | None
    geometry: Header
    input_dtype: np.dtype
    stats: tuple[float, float, float | None]
    sampler: Sampler | None = None
    border: float | None = None

    @property
    def voxmap(self) -> np.ndarray | Sampler:
        """The domain array, or for a deferred capture its sampler."""
        return self.domain if self.domain is not None else self.sampler

    @property
    def dq(self) -> np.ndarray:
        """Capture lattice offsets from the uniform lattice, (Cz, Cy, Cx, 3)."""
        return capture_offsets(self.grid, self.placement)

    def lattice_points_index(self) -> np.ndarray:
        """Capture control points in input voxel indices, (Cz, Cy, Cx, 3)."""
        return self.grid.uniform_positions() + self.dq


class NoSamples:
    """The domain of a capture without samples: only its shape (z, y, x).

    What a warp's lattice and scene need when no volume is computed (a label
    map's passes gather their own indicators; exports need the deformation
    only); anything that would gather samples is an error.
    """

    dtype = np.dtype(np.float32)

    def __init__(self, shape):
        self.shape = tuple(shape)

    def planes(self, *a, **k):  # pragma: no cover - nothing asks
        """Refused: there are no samples to gather."""
        raise VolwarpError("this capture has no samples (only its lattice)")

    whole = planes


def geometry_capture(header: Header, *, lattice=(9, 9, 9), placement: str = "uniform",
                     oversample: float = 2.0, sampling: str = "linear", pad=None) -> Capture:
    """A capture of ``header``'s geometry alone: its lattice and grid, no samples read.

    For what depends on the deformation only (moved points and meshes, the
    fields): the same grid and capture offsets as :func:`capture_volume`
    makes from the same settings, so the same lattice moves and maps.
    """
    if placement not in PLACEMENTS:
        raise VolwarpError(f"unknown placement {placement!r} (use uniform or tripled)")
    lattice = tuple(int(v) for v in np.broadcast_to(np.asarray(lattice), (3,)))
    grid = Lattice.create(header.shape_xyz, lattice, oversample, placement)
    ensure_fits_in_memory(int(np.prod(grid.lattice)) * 3 * 8 * LATTICE_ARRAYS,
                          f"the {'x'.join(map(str, grid.lattice))} control lattice")
    capture_offsets(grid, placement)
    if pad is not None:
        pad = tuple(int(v) for v in np.broadcast_to(np.asarray(pad), (3,)))
    return Capture(None, grid, placement, float(oversample), sampling, pad, header.replace(),
                   np.dtype(header.dtype), (0.0, 1.0, None),
                   NoSamples(tuple(grid.domain_shape[::-1])))


#: float64 (x, y, z) arrays of the control lattice's size held at a time (positions,
#: offsets, a move's old and new offsets, the scene's bounds): for the memory check.
LATTICE_ARRAYS = 8
#: How far above the bulk of the samples the largest may lie (see check_value_range):
#: the bulk then keeps at least 8 bits in the sums' 2**-40 of the largest.
MAX_VALUE_SPREAD = 2.0 ** 32
def check_value_range(data: np.ndarray, lo: float, hi: float, sample=None) -> None:
    """Refuse samples whose extremes would leave the warp's sums no precision for the rest.

    The box pushforward adds values as fixed-point integers scaled by the
    largest magnitude (exact, so local updates equal a full recomputation);
    they resolve about 2**-40 of it. A no-data marker such as -3.4e38, or a
    single spike, far above the bulk of the samples would then wipe the rest
    out. Refused: a largest magnitude over ``MAX_VALUE_SPREAD`` times the 99th
    percentile of the non-zero ``|value|`` in an evenly strided sample of the
    input (about 65000 samples, a millisecond or two). Non-zero: in a sparse
    volume (a small object in a field of zeros) the percentile of all the
    samples is 0, and a marker beside the object once went through, zeroing it.
    ``sample``: that sample, when already taken (:func:`scan_source`).
    """
    vmax = max(-lo, hi)
    if vmax <= 0:
        return
    sample = value_sample(data) if sample is None else sample
    mags = np.abs(sample, dtype=np.float64).ravel()
    mags = mags[mags > 0]
    if mags.size == 0:  # (nothing but zeros seen: no bulk to keep)
        return
    k = int(0.99 * (mags.size - 1))
    bulk = float(np.partition(mags, k)[k])  # (np.percentile's first call imports ~60 ms)
    if vmax > MAX_VALUE_SPREAD * bulk:
        raise VolwarpError(
            f"samples reach {lo if -lo > hi else hi:.3g}, over 2^{np.log2(MAX_VALUE_SPREAD):.0f} times "
            f"the bulk of the values (99% of the non-zero ones have |value| <= {bulk:.3g}): "
            f"the warp's exact sums resolve about {vmax * 2.0 ** -40:.2g}, too coarse for the "
            "rest; clip or "
            "mask those samples first (a no-data value?)")


def value_sample(data) -> np.ndarray:
    """The evenly strided sample :func:`check_value_range` looks at.

    16 planes, each on a 64 x 64 grid: about 1 MiB of a 256^3 input. ``data``
    may be any sliceable array (a zarr array, a lazy volume): the planes are
    read one by one.
    """
    steps = _sample_steps(data.shape)
    nz = data.shape[0]
    if isinstance(data, np.ndarray):
        return data[::steps[0], ::steps[1], ::steps[2]]
    return np.stack([np.asarray(data[z])[::steps[1], ::steps[2]]
                     for z in range(0, nz, steps[0])])


def _sample_steps(shape) -> tuple[int, int, int]:
    nz, ny, nx = shape
    return max(1, nz // 16), max(1, ny // 64), max(1, nx // 64)


@dataclass(frozen=True)
class SourceScan:
    """What one pass over an input's samples tells (:func:`scan_source`).

    ``lo``, ``hi``: its range; ``border``: its faces' samples, as
    :func:`~volwarp_cli.border.border_samples` reads them; ``sample``:
    :func:`value_sample`'s planes.
    """

    lo: float
    hi: float
    border: np.ndarray
    sample: np.ndarray


def scan_source(source, *, slab_bytes: int = 4 << 20) -> SourceScan:
    """One pass over a sliceable ``source``, slab by slab (never whole); NaN/inf refused.

    The range, and from the same slabs the faces and the value sample: a
    lazy source's x faces read on their own cost a read per row (17 ms of a
    256^3 warp's 0.6 s). Slabs of a few MiB: each is read, then passed over
    four times (min, max, faces, sample) while it is still in the cache, and
    the allocator hands the next slab the memory of the last; 64 MiB slabs,
    each fresh memory, took a 256^3 float32 scan 28-34 ms (60 ms the first
    time in a process) where 4 MiB slabs take 16, on one thread. (The whole
    warp is no faster: it then takes the fresh pages the scan took before;
    its peak is 6-7 MiB lower.)
    """
    from .. import parallel
    from ..memory import available_memory

    nz, ny, nx = source.shape
    threads = parallel.threads()
    # (within what the budget leaves: a slab, its copies and a reader's buffers, about
    # three slabs a thread; fixed 64 MiB slabs took a warp under 130M to 171 MiB)
    slab_bytes = min(slab_bytes, available_memory() // (3 * threads))
    step = max(1, min(slab_bytes // max(1, ny * nx * np.dtype(source.dtype).itemsize),
                      -(-nz // (2 * threads))))  # (two slabs a thread at least)
    sz, sy, sx = _sample_steps(source.shape)

    def slab(z0):
        part = np.asarray(source[z0:min(z0 + step, nz)])
        ends = [part[0].copy()] if z0 == 0 else []  # (the z faces: from their slabs only)
        if z0 + len(part) == nz:
            ends.append(part[-1].copy())
        sides = [part[:, 0].copy(), part[:, -1].copy(), part[:, :, 0].copy(),
                 part[:, :, -1].copy()]  # (y first, y last, x first, x last)
        planes = part[(-z0) % sz::sz, ::sy, ::sx].copy()
        return float(part.min()), float(part.max()), ends, sides, planes

    parts = parallel.run_blocks(slab, range(0, nz, step), threads)
    ranges = [p[:2] for p in parts]
    if not np.all(np.isfinite(ranges)):  # (each slab's: min() skips a NaN among numbers)
        raise VolwarpError("the volume has NaN or infinite samples; warping needs finite ones "
                           "(replace them first)")
    ends = [e.ravel() for p in parts for e in p[2]]
    sides = [np.concatenate([p[3][k] for p in parts]).ravel() for k in range(4)]
    return SourceScan(min(r[0] for r in ranges), max(r[1] for r in ranges),
                      np.concatenate(ends + sides), np.concatenate([p[4] for p in parts]))


def capture_source(header: Header, source, *, lattice=(9, 9, 9), placement: str = "uniform",
                   oversample: float = 2.0, sampling: str = "linear") -> Capture:
    """A deferred capture of an input that is not held (:class:`.pullback.BoxSampler`).

    ``header``: the input's :class:`~volwarp_cli.volume.Header` (its geometry
    and meta); ``source``: its samples, sliceable
    ``[z, y, x]``. The input's range comes from one pass over it, slab by
    slab; the gather runs later, box by box, in the blocks' tasks.
    """
    from .pullback import BoxSampler

    if placement not in PLACEMENTS:
        raise VolwarpError(f"unknown placement {placement!r} (use uniform or tripled)")
    if sampling not in SAMPLINGS:
        raise VolwarpError(f"unknown sampling {sampling!r} (use linear or nearest)")
    if tuple(source.shape) != tuple(header.shape):
        raise VolwarpError(f"samples of shape {tuple(source.shape)} do not match the volume's "
                           f"{tuple(header.shape)}")
    scan = scan_source(source)
    lo, hi = scan.lo, scan.hi
    check_value_range(source, lo, hi, scan.sample)
    lattice = tuple(int(v) for v in np.broadcast_to(np.asarray(lattice), (3,)))
    grid = Lattice.create(header.shape_xyz, lattice, oversample, placement)
    ensure_fits_in_memory(int(np.prod(grid.lattice)) * 3 * 8 * LATTICE_ARRAYS,
                          f"the {'x'.join(map(str, grid.lattice))} control lattice")
    capture_offsets(grid, placement)
    sampler = BoxSampler(source, grid, placement, sampling, domain_dtype(header.dtype))
    return Capture(None, grid, placement, float(oversample), sampling, None, header.replace(),
                   np.dtype(header.dtype), (lo, hi, None), sampler,
                   border=lower_median(scan.border))


def domain_dtype(dtype) -> np.dtype:
    """float64 where float32 would lose the input's precision, else float32."""
    dt = np.dtype(dtype)
    return np.dtype(np.float64) if dt in (np.float64, np.int32, np.uint32, np.int64,
                                          np.uint64) else np.dtype(np.float32)


def capture_volume(vol: Volume, *, lattice=(9, 9, 9), placement: str = "uniform",
                   oversample: float = 2.0, sampling: str = "linear", pad=None,
                   mean: bool = True, defer: bool = False) -> Capture:
    """Capture ``vol`` into a domain voxmap (see :mod:`.pullback`).

    ``mean``: also find the input's mean for ``stats`` (a capture file keeps
    it; a one-shot warp has no use for that extra pass). ``defer``: set the
    gather up without running it (the one-shot warp gathers the planes as it
    streams them; ``vol`` must then stay valid).
    """
    if placement not in PLACEMENTS:
        raise VolwarpError(f"unknown placement {placement!r} (use uniform or tripled)")
    if sampling not in SAMPLINGS:
        raise VolwarpError(f"unknown sampling {sampling!r} (use linear or nearest)")
    data = vol.data
    lo, hi = float(data.min()), float(data.max())
    if not (np.isfinite(lo) and np.isfinite(hi)):  # NaN and inf reach min or max
        raise VolwarpError("the volume has NaN or infinite samples; warping needs finite ones "
                           "(replace them first)")
    check_value_range(data, lo, hi)
    lattice = tuple(int(v) for v in np.broadcast_to(np.asarray(lattice), (3,)))
    grid = Lattice.create(vol.shape_xyz, lattice, oversample, placement)
    # the lattice's own arrays (positions, offsets, the scene's bounds and masks) come
    # before the domain's: a lattice finer than the input can outgrow it
    ensure_fits_in_memory(int(np.prod(grid.lattice)) * 3 * 8 * LATTICE_ARRAYS,
                          f"the {'x'.join(map(str, grid.lattice))} control lattice")
    capture_offsets(grid, placement)  # validates the placement for this lattice
    dt = domain_dtype(vol.dtype)
    if not defer:
        ensure_fits_in_memory(int(np.prod(grid.domain_shape)) * dt.itemsize * 2,
                              f"the {'x'.join(map(str, grid.domain_shape))} domain voxmap")
    elif np.dtype(vol.dtype) != dt:  # the sampler's copy of the input in the domain's type
        ensure_fits_in_memory(data.size * dt.itemsize, "the input's samples as floats")
    sampler = Sampler(vol.data, grid, placement, sampling, dt)
    domain = None
    if not defer:
        with timed("capture (pullback)"):
            domain, _ = sampler.whole()
        sampler = None
    stats = (lo, hi, float(data.mean(dtype=np.float64)) if mean else None)
    if pad is not None:
        pad = tuple(int(v) for v in np.broadcast_to(np.asarray(pad), (3,)))
    return Capture(domain, grid, placement, float(oversample), sampling, pad, vol.header,
                   np.dtype(vol.dtype), stats, sampler, border=border_value(data))


class CapturedInput:
    """The input's samples as a subdivision capture holds them: a sliceable ``[z, y, x]`` view.

    On the subdivision grid (the uniform placement, an integer oversample k)
    every domain voxel inside the input holds exactly its input voxel's value
    (either sampling), so input voxel ``i`` is domain voxel ``lead + k i``
    (per axis), cast back to the input's type: a capture file gives back the
    volume it was made from, which the label rule, the border value and a
    label warp read. ``domain``: the domain, sliceable ``[z, y, x]`` (an
    array, or a capture file's payload read box by box: picklable when it is).
    """

    def __init__(self, domain, grid: Lattice, dtype):
        if not grid.subdivision:
            raise ValueError("only a subdivision capture holds its input's samples")
        self.domain = domain
        self.k = int(grid.subdivision)
        self.lead = tuple(grid.lead[::-1])  # z, y, x
        self.shape = tuple(int(n) for n in grid.input_shape[::-1])
        self.dtype = np.dtype(dtype)
        self.ndim = 3

    def __getitem__(self, key) -> np.ndarray:
        from ..io.filearray import box_of_key

        box, pick = box_of_key(key, self.shape)
        k = self.k
        if any(hi <= lo for lo, hi in box):
            part = np.empty(tuple(max(0, hi - lo) for lo, hi in box), dtype=self.dtype)
            return part[pick]
        index = tuple(slice(d + k * lo, d + k * (hi - 1) + 1, k)
                      for d, (lo, hi) in zip(self.lead, box, strict=True))
        part = np.asarray(self.domain[index])
        return part.astype(self.dtype)[pick]


def captured_input(cap: Capture) -> CapturedInput | None:
    """The input's samples held in ``cap`` (:class:`CapturedInput`), or None.

    None on the spanning grid (a non-integer oversample, the tripled
    placement: each domain voxel blends input voxels) and for a capture
    without samples.
    """
    if not cap.grid.subdivision:
        return None
    if cap.domain is not None:
        return CapturedInput(cap.domain, cap.grid, cap.input_dtype)
    source = getattr(cap.sampler, "stored", None)  # a capture file's payload, read by boxes
    return None if source is None else CapturedInput(source, cap.grid, cap.input_dtype)


def capture_border(cap: Capture) -> float:
    """The input's border value (:func:`~volwarp_cli.border.border_value`) from what ``cap`` holds.

    A subdivision capture holds the input's samples (:class:`CapturedInput`);
    on the spanning grid the domain's faces are the input's faces,
    interpolated (rounded for an integer input).
    """
    view = captured_input(cap)
    if view is not None:
        return border_value(view)
    if cap.domain is not None:
        value = border_value(cap.domain)
    elif getattr(cap.sampler, "stored", None) is not None:
        value = border_value(cap.sampler.stored)
    else:
        return 0.0
    return float(np.rint(value)) if cap.input_dtype.kind in "iu" else value
