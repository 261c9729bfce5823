"""One entry point for signed distance fields: shape by iso level, metric, surface mode.

Conventions (the same for every metric): the shape is the set of samples at
or above the iso level ``V`` (``inside="above"``) or below it (``"below"``), as
``volwarp mesh`` has it (a sample equal to ``V`` counts as above); NaN samples
are outside. Inside voxels always get a negative value (at least 1e-6 of the
finest spacing in magnitude, for a sample lying exactly on ``V``), so the sign
alone tells the side. Distances are in world units (each
axis' spacing), **negative inside, positive outside**.

Metrics
-------
``euclidean``
    Binary inputs (two distinct sample values): the exact distance between
    voxel centres (:mod:`.exact`). Smooth inputs: the distance to the
    sub-voxel iso-surface (:mod:`.subvoxel`). ``surface`` forces either.
``minnorm``
    The paper's shift-and-min scheme (:mod:`.minnorm`); it equals the
    spacing-weighted taxicab distance between voxel centres.
``taxicab``, ``chessboard``
    Per-line passes between voxel centres (:mod:`._line_kernels`: a sweep
    each way for taxicab, Meijster et al.'s lower envelope for chessboard),
    the values of ``scipy.ndimage.distance_transform_cdt``; voxel steps, so
    isotropic spacing only.

Every metric but the sub-voxel field is an operation in passes
(:mod:`.passes`), in memory here as by blocks.
"""

from __future__ import annotations

import numpy as np

from ..errors import BadUsage, VolwarpError

METRICS = ("euclidean", "minnorm", "chessboard", "taxicab")
#: the narrowest band a field may be clamped to (``--max-distance``, a morph's
#: ``max_distance``): float32's smallest normal number. A band of 1e-300 is 0 in float32:
#: every distance became 0 and the shape was lost, with exit 0.
MIN_BAND = float(np.finfo(np.float32).tiny)


def band_problem(max_distance: float) -> str | None:
    """Why ``max_distance`` cannot be a band (:data:`MIN_BAND`), or None."""
    if not max_distance >= MIN_BAND:
        return (f"{max_distance:g} is below {MIN_BAND:.3g}, the smallest band a float32 "
                "field holds (every distance would be 0)")
    return None
SURFACES = ("auto", "voxel", "subvoxel")


def inside_mask(data: np.ndarray, iso: float, inside: str = "above") -> np.ndarray:
    """The shape: samples at or above (or below) ``iso``; NaN is outside."""
    if inside == "above":
        return data >= iso
    if inside == "below":
        return data < iso
    raise VolwarpError(f"inside must be 'above' or 'below', got {inside!r}")


def is_binary(data: np.ndarray) -> bool:
    """True when the samples take at most two distinct values (NaN samples aside: outside)."""
    if data.dtype == bool:
        return True
    lo, hi = data.min(), data.max()
    nans = 0
    if np.isnan(lo) or np.isnan(hi):  # (min and max carry a NaN: only then counted)
        nans = int(np.count_nonzero(np.isnan(data)))
        if nans == data.size:
            return True
        lo, hi = np.nanmin(data), np.nanmax(data)
    if lo == hi:
        return True
    return int(np.count_nonzero((data == lo) | (data == hi))) == data.size - nans


def check_method(metric: str, surface: str) -> None:
    """Refuse an unknown metric or surface mode, or a sub-voxel surface of another metric.

    Usage errors (:class:`~volwarp_cli.errors.BadUsage`, exit 2): the options
    contradict each other whatever the input.
    """
    if metric not in METRICS:
        raise BadUsage(f"unknown metric {metric!r} (known: {', '.join(METRICS)})")
    if surface not in SURFACES:
        raise BadUsage(f"unknown surface mode {surface!r} (known: {', '.join(SURFACES)})")
    if surface == "subvoxel" and metric != "euclidean":
        raise BadUsage(f"sub-voxel surfaces need the euclidean metric, not {metric!r}")


def check_isotropic(metric: str, spacing_zyx) -> None:
    """Refuse anisotropic spacing for the voxel-step metrics (taxicab, chessboard)."""
    if metric not in ("taxicab", "chessboard"):
        return
    spacing_zyx = tuple(float(s) for s in spacing_zyx)
    if not np.allclose(spacing_zyx, spacing_zyx[0], rtol=1e-6):
        raise VolwarpError(f"the {metric} metric counts voxel steps and needs isotropic "
                           f"spacing, got {list(spacing_zyx[::-1])} (x, y, z); use euclidean "
                           "or minnorm (spacing-weighted taxicab)")


def signed_distance(data: np.ndarray, spacing_zyx=(1.0, 1.0, 1.0), *, iso: float,
                    inside: str = "above", metric: str = "euclidean",
                    surface: str = "auto") -> tuple[np.ndarray, dict]:
    """Signed distance field of the shape ``data`` {above|below} ``iso``.

    Parameters
    ----------
    data : (Z, Y, X) array
    spacing_zyx : 3 floats
        Spacing along the array axes.
    iso, inside : the shape's definition (module doc).
    metric : {"euclidean", "minnorm", "chessboard", "taxicab"}
    surface : {"auto", "voxel", "subvoxel"}
        Euclidean only: voxel-centre distances (binary) or sub-voxel surface.

    Returns
    -------
    field : (Z, Y, X) float32 array
    info : dict
        ``{"metric", "surface", "passes"}`` (passes for ``minnorm``).
    """
    check_method(metric, surface)
    data = np.asarray(data)
    if data.dtype.kind == "c" or data.dtype.kind not in "biuf":
        raise VolwarpError(f"cannot take the distance of samples of type {data.dtype}")
    from ..memory import ensure_fits_once_loaded

    # An explicit budget is the whole process's: where it is tight, what the work loads
    # (numba, scipy: about 80 MiB; the sub-voxel kernels' code another 60 MiB) is loaded
    # before the check, so that what the process holds counts it
    sub = metric == "euclidean" and (surface == "subvoxel"
                                     or (surface == "auto" and not is_binary(data)))
    # mask + float32 field (+ seed ids, a second id buffer and float32 samples, sub-voxel)
    ensure_fits_once_loaded(
        data.size * (18 if metric == "euclidean" else 13),
        f"the distance field of {data.size} samples",
        None if data.size <= _WARM_SIZE ** 3 else  # (the small field itself: loads them)
        lambda: warm_kernels(metric, "subvoxel" if sub else "voxel", data.dtype, iso, inside))
    # (the whole's checks, an empty or full shape and NaNs, are the passes' or the scan's)
    spacing_zyx = tuple(float(s) for s in spacing_zyx)
    info = {"metric": metric, "surface": "voxel", "passes": 0}
    if sub:
        from .scan import scan_shape
        from .subvoxel import subvoxel_signed_distance

        scan_shape(data, iso, inside, box_voxels=data.size or 1)  # its checks
        info["surface"] = "subvoxel"
        return subvoxel_signed_distance(data, iso, inside=inside, spacing_zyx=spacing_zyx), info
    from .passes import MaskSource, field_in_memory

    field = field_in_memory(MaskSource(data, iso, inside), spacing_zyx, metric=metric)
    if metric == "minnorm":
        from .minnorm import signed_pass_count

        info["passes"] = signed_pass_count(data.shape)
    return field, info


#: The side of the ball the field's kernels run on to load (:func:`warm_kernels`).
_WARM_SIZE = 8


def warm_kernels(metric: str, surface: str, dtype, iso: float, inside: str) -> None:
    """Run the field's kernels once on a small ball of ``dtype`` (a surface between its samples).

    Loads their modules, libraries and compiled code, as the real input's field will.
    """
    n = _WARM_SIZE
    z, y, x = np.ogrid[:n, :n, :n]
    r2 = ((x - n / 2) ** 2 + (y - n / 2) ** 2 + (z - n / 2) ** 2).astype(np.float64)
    up = inside == "above"
    hi, lo = (iso + 1.0, iso - 1.0) if up else (iso - 1.0, iso + 1.0)
    ball = np.where(r2 < (n / 4) ** 2, hi, lo)
    if surface == "subvoxel":  # smooth samples, crossing the level between voxel centres
        ball = iso + (1.0 if up else -1.0) * ((n / 4) ** 2 - r2) / (n / 4) ** 2
    ball = ball.astype(dtype) if np.dtype(dtype).kind == "f" else ball.round().astype(dtype)
    from ..errors import OutOfMemoryError

    try:
        signed_distance(ball, iso=iso, inside=inside, metric=metric, surface=surface)
    except OutOfMemoryError:  # (numba does not fit the budget: said now, with the whole
        raise                 # budget, not by a block task against its share, after work)
    except VolwarpError:  # (a level the dtype cannot hold around it: the real input tells)
        pass


def field_note(metric: str, surface: str, rule, unsigned: bool = False,
               max_distance: float | None = None) -> str:
    """How a field was defined, for its ``volwarp_distance`` key.

    The same however it was computed, in memory or by blocks (the samples are
    the same); ``rule``'s part says labels or intensity, and why
    (:meth:`.labels.ShapeRule.note`).
    """
    return (f"metric={metric} surface={surface} {rule.note()}"
            + (" unsigned" if unsigned else "")
            + (f" max_distance={max_distance:g} (exact inside the band, clamped outside)"
               if max_distance is not None else ""))


def finish_field(field: np.ndarray, *, unsigned: bool = False,
                 max_distance: float | None = None) -> np.ndarray:
    """Apply ``--unsigned`` (distance to the shape, 0 inside) and ``--max-distance``, in place."""
    if unsigned:
        np.maximum(field, 0, out=field)
    if max_distance is not None:
        if band_problem(max_distance):
            raise VolwarpError(f"max distance: {band_problem(max_distance)}")
        np.clip(field, -max_distance, max_distance, out=field)
    return field
