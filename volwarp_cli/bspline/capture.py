"""A captured volume: the domain voxmap plus everything needed to warp it later.

:func:`capture_volume` is the ``volwarp capture`` core (paper §5
"Initialization"): it sets up the lattice, places the capture control points
and pulls the input back into the domain voxmap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import VolwarpError
from ..io.common import ensure_fits_in_memory
from ..progress import timed
from ..volume import Volume
from .lattice import PLACEMENTS, Grid, capture_offsets
from .pullback import SAMPLINGS, Sampler


@dataclass
class Capture:
    """Domain voxmap ``[Dz, Dy, Dx]`` and the capture set-up.

    ``geometry`` is the input volume's geometry with a 1-voxel placeholder
    array (its ``meta`` kept); ``input_dtype`` and ``stats`` (min, max, mean;
    the mean None when not asked for) describe the captured input. The
    domain's samples lie within the input's (min, max): each is one input
    sample or a convex combination of eight. A deferred capture has no
    ``domain`` array but a ``sampler`` that gathers its planes on demand.
    """

    domain: np.ndarray | None
    grid: Grid
    placement: str
    oversample: float
    sampling: str
    pad: tuple[int, int, int] | None
    geometry: Volume
    input_dtype: np.dtype
    stats: tuple[float, float, float | None]
    sampler: Sampler | None = None

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
    lattice = tuple(int(v) for v in np.broadcast_to(np.asarray(lattice), (3,)))
    grid = Grid.create(vol.shape_xyz, lattice, oversample)
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
    geometry = vol.with_data(np.zeros((1, 1, 1), dtype=vol.dtype))
    if pad is not None:
        pad = tuple(int(v) for v in np.broadcast_to(np.asarray(pad), (3,)))
    return Capture(domain, grid, placement, float(oversample), sampling, pad, geometry,
                   np.dtype(vol.dtype), stats, sampler)
