"""What the whole input says before any block of its field: the shape's size, NaNs, two values.

Global values, not regions (:mod:`volwarp_cli.regions`' notes): a field of an
empty shape, or of one filling the grid, is refused; NaN samples are warned
about; and under ``surface="auto"`` the euclidean field is the sub-voxel one
unless the samples take two values. A block cannot tell any of these from its
own samples, so they are read once from the whole, box by box
(:func:`scan_shape`), before the field runs: the same answer however the
field then runs (one block in memory, many by blocks). The exact passes fold
the same per-box statistics into their first pass
(:func:`.chunked.staged_check`) instead of reading the samples twice.
"""

from __future__ import annotations

import numpy as np

from ..errors import VolwarpError
from .field import inside_mask


def block_stats(block, iso: float, inside: str):
    """``(NaNs, inside count, nanmin, nanmax, binary, lo, hi)`` of one box of samples."""
    b = np.asarray(block)
    if b.size == 0:
        return 0, 0, np.nan, np.nan, True, None, None
    nans = int(np.count_nonzero(np.isnan(b))) if b.dtype.kind == "f" else 0
    count = int(np.count_nonzero(inside_mask(b, iso, inside)))
    if b.dtype == bool:
        return nans, count, float(b.min()), float(b.max()), True, bool(b.min()), bool(b.max())
    if nans == b.size:  # (NaN samples count as outside: they make no value of the shape's)
        return nans, count, np.nan, np.nan, True, None, None
    lo, hi = (np.nanmin(b), np.nanmax(b)) if nans else (b.min(), b.max())
    fmin, fmax = float(lo), float(hi)
    # (two values and some NaN samples are still binary: a NaN turned a 0/1 mask's
    # voxel-centre distances into the sub-voxel surface's, half a voxel off everywhere)
    binary = bool(lo == hi) or int(np.count_nonzero((b == lo) | (b == hi))) == b.size - nans
    return nans, count, fmin, fmax, binary, lo.item(), hi.item()


def merge_stats(stats, is_bool: bool = False):
    """The boxes' :func:`block_stats` as the whole's ``(nans, count, lo, hi, binary)``."""
    nans = sum(s[0] for s in stats)
    count = sum(s[1] for s in stats)
    mins = [s[2] for s in stats if not np.isnan(s[2])]
    maxs = [s[3] for s in stats if not np.isnan(s[3])]
    values = {v for s in stats for v in s[5:] if v is not None}
    binary = is_bool or (all(s[4] for s in stats) and len(values) <= 2)
    return (nans, count, min(mins) if mins else np.nan, max(maxs) if maxs else np.nan,
            binary)


def check_shape(nans: int, count: int, size: int, lo, hi, iso: float, inside: str,
                name: str = "") -> None:
    """The whole's refusals and warning, in :func:`.field.signed_distance`'s words.

    NaN samples are warned about; an empty shape, or one filling the grid, refused
    (the error naming ``name``, the input's file, where given).
    """
    whose = f"{name}: " if name else ""
    if nans:
        from ..progress import log
        from ..runscope import first_said

        # (said once a run: the scan and the passes both check one shape; another shape,
        # a morph's second, has its own count inside or range, and is said too)
        key = ("nan-outside", nans, count, size, float(lo), float(hi))
        if first_said(key):
            log.warning("%d NaN samples (%.2g%%) count as outside the shape", nans,
                        100.0 * nans / size, extra={"once": key})
    if count == 0:
        raise VolwarpError(f"{whose}the shape is empty: no sample is {inside} the iso level "
                           f"{iso:g} "
                           f"(samples range {float(lo):g} to {float(hi):g})")
    if count == size:
        raise VolwarpError(f"{whose}the shape fills the whole grid: every sample is {inside} "
                           "the iso "
                           f"level {iso:g}, so there is no surface")


#: Voxels of one box of a scan: small boxes cost nothing more (a 256^3 scan takes 40 to 75 ms
#: at 2^18 to 2^22 voxels a box, fastest small) and hold little (about 16 bytes a voxel each).
BOX_VOXELS = 1 << 20


def scan_box_voxels() -> int:
    """Voxels of one box of a scan: :data:`BOX_VOXELS`, fewer where the memory budget is tight."""
    from ..memory import memory_limit

    return max(1 << 16, min(BOX_VOXELS, memory_limit() // 16))


def scan_shape(source, iso: float, inside: str, *, box_voxels: int, name: str = ""):
    """The whole's ``(nans, count, lo, hi, binary)``, read box by box over the threads.

    ``source``: an array or a sliceable lazy source; ``box_voxels``: about the
    voxels of one box. Checked (:func:`check_shape`) before it returns.
    """
    from .. import parallel
    from ..labelmap import scan_boxes

    dtype = np.dtype(source.dtype)
    if dtype.kind not in "biuf":
        raise VolwarpError(f"cannot take the distance of samples of type {dtype}")
    shape = tuple(int(n) for n in source.shape)
    stats = parallel.run_blocks(lambda box: block_stats(source[box.slices], iso, inside),
                                scan_boxes(shape, box_voxels))
    merged = merge_stats(stats, dtype.kind == "b")
    check_shape(*merged[:2], int(np.prod(shape)), *merged[2:4], iso, inside, name)
    return merged


def field_surface(source, rule, *, metric: str, surface: str, max_distance: float | None,
                  box_voxels: int) -> str:
    """The surface ``rule``'s field is computed on: ``"voxel"`` or ``"subvoxel"``.

    A label rule's is the voxel surface (its checks made by
    :func:`.labels.choose_shape`), and so is every metric's but the
    euclidean. An intensity rule's euclidean field, where it runs as
    overlapping blocks (:mod:`.band`: ``max_distance``, or a sub-voxel
    surface), scans the whole first (:func:`scan_shape`: its checks and,
    under ``"auto"``, binary samples give ``"voxel"``, others
    ``"subvoxel"``); so does ``"auto"`` without a band. The exact passes and
    the other metrics check the samples themselves.
    """
    if rule.labels or metric != "euclidean" or (surface == "voxel" and max_distance is None):
        return "voxel"
    *_, binary = scan_shape(source, rule.iso, rule.inside, box_voxels=box_voxels,
                            name=rule.name)
    return "subvoxel" if surface == "subvoxel" or not binary else "voxel"
