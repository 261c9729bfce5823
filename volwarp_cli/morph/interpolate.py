"""Implicit morph frames: the zero level set of ``(1 - t) d_source + t d_target``.

Dinh & Carvalho (2004), §0.3.1 (after Payne & Toga): the signed distance
fields of source and target are cross-dissolved, ``d = (1 - t) dist(A) + t
dist(B)``, and the frame at time ``t`` is where ``d`` is zero; at ``t = 0`` it is
the source, at ``t = 1`` the target, and shapes of different topology morph
without special handling. The paper does this per pixel with texture
combiners; volwarp does it per voxel with numpy, writing every frame.

How the two fields reach one grid (§0.4):

1. Each field is computed once, on its own input's grid.
2. It is resampled (trilinear) through the inverse of its alignment onto the
   frame grid (:mod:`.grid`), its values multiplied by the alignment's scale.
   Where the frame grid lies outside the input's grid (beyond its outer
   voxel centres by more than :data:`~volwarp_cli.geometry.COVER_TOLERANCE`, a rounding's margin)
   the field does not exist; it is filled by the paper's shift-and-increment propagation
   (§0.5.1, :func:`volwarp_cli.distance.update.fill_uncovered`).
3. A landmark warp (:mod:`.landmarks`) is applied to the distance fields, as
   in the paper's dependent textures and Cohen-Or et al.:

   * ``static`` (the paper): the source field is pulled back through the warp
     ``V`` fitted from the target landmarks to the source landmarks, so the
     source's landmarks sit on the target's before the morph starts. Frame 0
     is then the *warped* source.
   * ``progressive``: with ``u_b = V - id`` and ``u_f = W - id`` (``W`` fitted from
     source to target landmarks), frame ``t`` interpolates
     ``d_s(x + t u_b(x))`` and ``d_t(x + (1 - t) u_f(x))``: the source warps
     forward as the target warps back from the source's landmarks, so frame 0
     is exactly the source and frame 1 exactly the target.

   Warped samples falling outside the frame grid take the nearest border
   value (the paper clamps texture coordinates the same way).

Attributes (colour or other volumes of each input) go through the same maps
and are interpolated ``(1 - t) a_s + t a_t``.
"""

from __future__ import annotations

import numpy as np

from ..box import Box
from ..errors import VolwarpError
from ..geometry import Geometry, beyond_grid
from .landmarks import LandmarkWarp


def _perm() -> np.ndarray:
    p = np.zeros((4, 4))
    p[0, 2] = p[1, 1] = p[2, 0] = p[3, 3] = 1.0
    return p


def _index_map(values_i2w: np.ndarray, matrix: np.ndarray, grid: Geometry) -> np.ndarray:
    """Grid voxel (z, y, x) -> values voxel (z, y, x), homogeneous 4x4."""
    m_idx = np.linalg.inv(values_i2w) @ np.linalg.inv(matrix) @ grid.index_to_world_matrix
    p = _perm()
    return p @ m_idx @ p


def lands_on_grid(shape_zyx, values_i2w: np.ndarray, matrix: np.ndarray,
                  grid: Geometry) -> bool:
    """Whether samples of ``shape_zyx`` on ``values_i2w``, moved by ``matrix``, are ``grid``'s.

    Then they are the grid's samples as they are (no interpolation).
    """
    return (tuple(shape_zyx) == tuple(grid.shape)
            and np.allclose(_index_map(values_i2w, matrix, grid), np.eye(4), atol=1e-9))


#: The interpolation of every resampling onto the frame grid (trilinear) and its support:
#: a coordinate ``c`` reads samples ``floor(c)`` .. ``floor(c) + SUPPORT`` on each axis
ORDER = 1
SUPPORT = ORDER


def index_map(values_i2w: np.ndarray, matrix: np.ndarray, grid: Geometry) -> np.ndarray:
    """Frame grid voxel (z, y, x) -> values voxel (z, y, x), homogeneous 4x4."""
    return _index_map(values_i2w, matrix, grid)


def sample_coordinates(m: np.ndarray, box: Box) -> np.ndarray:
    """Values-grid coordinates (3, *box.shape) float64 of the target voxels of ``box``.

    Each voxel's coordinate is computed from its integer index alone, by the
    same float operations wherever the box lies (``m[i, 0] z + m[i, 1] y +
    m[i, 2] x + m[i, 3]``, left to right): a box of the grid gets exactly the
    coordinates the whole grid gets there.
    """
    return _coordinates(m, *(np.arange(a, b, dtype=np.float64)
                             for a, b in zip(box.lo, box.hi, strict=True)))


def _coordinates(m: np.ndarray, z: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """:func:`sample_coordinates` of the voxels at indices ``z x y x x`` (1-D float64 each)."""
    z, y, x = z[:, None, None], y[None, :, None], x[None, None, :]
    out = np.empty((3, z.shape[0], y.shape[1], x.shape[2]), np.float64)
    for i in range(3):
        out[i] = m[i, 0] * z
        out[i] += m[i, 1] * y
        out[i] += m[i, 2] * x
        out[i] += m[i, 3]
    return out


def needed_box(m: np.ndarray, box: Box, values_shape) -> Box:
    """The box of values samples that resampling target ``box`` through ``m`` reads.

    The image of a box under an affine map is the hull of its corners'
    images: their min/max coordinates, floored, widened by the
    interpolation's support (:data:`SUPPORT`), clipped to the values' grid
    (never empty: a box wholly outside keeps the nearest border sample, which
    ``outside="nearest"`` reads). The corners' coordinates are computed as
    :func:`sample_coordinates` computes them, and a voxel's coordinate, an
    affine combination of the corners', lies within their hull up to
    rounding: a relative slack of 1e-9 covers that.
    """
    c = _coordinates(m, *(np.array([a, b - 1], dtype=np.float64)
                          for a, b in zip(box.lo, box.hi, strict=True))).reshape(3, 8).T
    slack = 1e-9 * np.maximum(1.0, np.abs(c).max(axis=0))
    first = np.floor(c.min(axis=0) - slack)
    last = np.floor(c.max(axis=0) + slack) + SUPPORT
    return clip_box(first, last, values_shape)


def coordinates_box(coords: np.ndarray, values_shape) -> Box:
    """The values box sampled at ``coords`` (3, ...): exact min/max, floored, plus the support."""
    flat = coords.reshape(3, -1)
    return clip_box(np.floor(flat.min(axis=1)), np.floor(flat.max(axis=1)) + SUPPORT,
                    values_shape)


def clip_box(first, last, values_shape) -> Box:
    """``[first, last]`` (inclusive, per axis) clipped to ``values_shape``, at least one sample."""
    n = np.asarray(values_shape, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        lo = np.clip(np.nan_to_num(first, nan=0.0), 0, n - 1)
        hi = np.clip(np.nan_to_num(last, nan=0.0) + 1, lo + 1, n)
    return Box(tuple(int(v) for v in lo), tuple(int(v) for v in hi))


def resample_box(values, values_box: Box, m: np.ndarray, box: Box, *, values_shape,
                 outside: str = "nan") -> np.ndarray:
    """Target ``box`` of the frame grid sampled from the values in ``values_box`` through ``m``.

    ``values``: the samples of ``values_box`` of the whole values grid (an
    array of its shape; the whole grid when ``values_box`` is all of it),
    which must hold every sample the box's coordinates read
    (:func:`needed_box`) and end only where the values grid ends or where no
    coordinate reaches. The result is then that of the whole grid's: the
    coordinates are the whole grid's (:func:`sample_coordinates`), shifted
    by whole voxels (exact), so the trilinear weights and the samples
    weighed, hence every float operation, are the same. ``values_shape``: the
    whole values grid's; ``outside``: ``"nan"`` (voxels :func:`beyond_grid` are
    NaN) or ``"nearest"`` (the border sample).
    """
    from scipy import ndimage

    coords = sample_coordinates(m, box)
    src = np.asarray(values, dtype=np.float32)
    if tuple(src.shape) != tuple(values_box.shape):
        raise VolwarpError(f"resample_box: samples of shape {src.shape} for a box of "
                           f"shape {values_box.shape}")
    beyond = beyond_grid(coords, values_shape) if outside == "nan" else None
    for axis in range(3):
        if values_box.lo[axis]:
            coords[axis] -= values_box.lo[axis]  # exact: a whole number off a coordinate
    out = ndimage.map_coordinates(src, coords, order=ORDER, output=np.float32, mode="nearest")
    if beyond is not None:
        out[beyond] = np.nan
    return out


def warp_on_grid(values: np.ndarray, grid: Geometry, displacement: np.ndarray,
                 fraction: float = 1.0) -> np.ndarray:
    """``values(x + fraction * displacement(x))`` on ``grid`` (world displacement, [3,Z,Y,X] xyz)."""
    from scipy import ndimage

    if fraction == 0.0:
        return values.copy()
    inv = np.linalg.inv(grid.matrix)  # world offset -> index offset
    nz, ny, nx = values.shape
    out = np.empty_like(values, dtype=np.float32)
    base = np.mgrid[0:ny, 0:nx].astype(np.float32)
    for z in range(nz):  # one slice at a time keeps the coordinate arrays small
        d = displacement[:, z] * np.float32(fraction)  # (3, ny, nx), xyz world
        di = np.tensordot(inv.astype(np.float32), d, axes=1)  # index offsets (i, j, k)
        coords = np.stack([z + di[2], base[0] + di[1], base[1] + di[0]])
        out[z] = ndimage.map_coordinates(values, coords, order=1, mode="nearest")
    return out


def displacement_field(warp: LandmarkWarp, grid: Geometry) -> np.ndarray:
    """The warp's world displacement at every grid voxel, (3, Z, Y, X) float32, x first."""
    nz, ny, nx = grid.shape
    out = np.empty((3, nz, ny, nx), np.float32)
    j, i = np.mgrid[0:ny, 0:nx]
    m = grid.index_to_world_matrix
    for z in range(nz):
        ijk = np.stack([i.ravel(), j.ravel(), np.full(i.size, z)], axis=1).astype(np.float64)
        world = ijk @ m[:3, :3].T + m[:3, 3]
        out[:, z] = warp.displacement(world).T.reshape(3, ny, nx)
    return out


class Morph:
    """Source and target fields on one grid; :meth:`field` gives the frame at ``t``.

    Parameters
    ----------
    source, target : (Z, Y, X) float32 arrays on ``grid`` (already aligned).
    grid : Geometry
        The frame grid.
    warp_back, warp_fwd : LandmarkWarp or None
        ``V`` (target landmarks -> source landmarks) and ``W`` (source -> target),
        in the frame grid's world coordinates.
    mode : {"static", "progressive"}
    """

    def __init__(self, source: np.ndarray, target: np.ndarray, grid: Geometry, *,
                 warp_back: LandmarkWarp | None = None, warp_fwd: LandmarkWarp | None = None,
                 mode: str = "static"):
        if source.shape != grid.shape or target.shape != grid.shape:
            raise VolwarpError("morph fields must lie on the frame grid")
        if mode not in ("static", "progressive"):
            raise VolwarpError(f"unknown warp mode {mode!r} (static or progressive)")
        self.grid = grid
        self.mode = mode
        self.back = self.fwd = None
        if warp_back is not None and mode == "static":
            source = warp_on_grid(source, grid, displacement_field(warp_back, grid))
        elif warp_back is not None:
            self.back = displacement_field(warp_back, grid)
            self.fwd = displacement_field(warp_fwd, grid)
        self.source = source
        self.target = target

    def _pair(self, t: float, a: np.ndarray, b: np.ndarray):
        if self.back is None:
            return a, b
        return warp_on_grid(a, self.grid, self.back, t), warp_on_grid(b, self.grid, self.fwd, 1 - t)

    def field(self, t: float, out: np.ndarray | None = None) -> np.ndarray:
        """``(1 - t) d_s + t d_t`` (float32; negative inside the frame's shape)."""
        check_time(t)
        a, b = self._pair(t, self.source, self.target)
        return blend(a, b, t, out)

    def attribute(self, t: float, a_source: np.ndarray, a_target: np.ndarray) -> np.ndarray:
        """An attribute pair (on the grid, static warp already applied) at ``t``."""
        check_time(t)
        a, b = self._pair(t, a_source, a_target)
        return blend(a, b, t)

    def static_source(self, values: np.ndarray, warp_back: LandmarkWarp | None) -> np.ndarray:
        """Apply the static warp to an attribute of the source (identity otherwise)."""
        if warp_back is None or self.mode != "static":
            return values
        return warp_on_grid(values, self.grid, displacement_field(warp_back, self.grid))


def check_time(t: float) -> None:
    """Refuse a morph time outside [0, 1] (a VolwarpError)."""
    if not (0.0 <= t <= 1.0):
        raise VolwarpError(f"time t = {t:g} is outside [0, 1]")


def blend(a: np.ndarray, b: np.ndarray, t: float, out: np.ndarray | None = None) -> np.ndarray:
    """``(1 - t) a + t b`` in float32, exactly ``a`` at t = 0 and ``b`` at t = 1."""
    if out is None:
        out = np.empty(a.shape, np.float32)
    if t == 0.0:
        np.copyto(out, a)
    elif t == 1.0:
        np.copyto(out, b)
    else:
        np.multiply(a, np.float32(1.0 - t), out=out)
        out += np.float32(t) * b
    return out


def density(field: np.ndarray, width: float) -> np.ndarray:
    """Smooth occupancy ``clip(0.5 - d / width, 0, 1)``: 1 inside, 0.5 on the surface."""
    occ = np.float32(0.5) - field * np.float32(1.0 / width)
    np.clip(occ, 0.0, 1.0, out=occ)
    return occ


def occupancy_to_range(occ: np.ndarray, lo: float, iso: float, hi: float, inside: str,
                       dtype) -> np.ndarray:
    """Map occupancy to the source's value range so that 0.5 falls on ``iso``.

    ``inside = "above"``: 0 -> lo, 0.5 -> iso, 1 -> hi; ``"below"`` the reverse.
    Integer types are rounded and clipped. Every voxel with occupancy above 0.5
    (inside the frame) gets a value inside the source's shape (``>= iso`` for
    ``above``, ``< iso`` for ``below``) and every other voxel one outside it, so
    ``volwarp distance``/``mesh`` at the source's iso level see the frame's shape.
    """
    from ..samples import cast_samples

    dt = np.dtype(dtype)
    a, b = (lo, hi) if inside == "above" else (hi, lo)
    occ64 = occ.astype(np.float64)
    vals = np.where(occ64 >= 0.5, iso + (occ64 - 0.5) * 2.0 * (b - iso),
                    iso - (0.5 - occ64) * 2.0 * (iso - a))
    if dt.kind in "iu":
        at_or_above = float(np.ceil(iso))  # smallest integer >= iso
        below = at_or_above - 1.0           # largest integer < iso
        vals = np.rint(vals)
    else:
        at_or_above = float(iso)
        below = float(np.nextafter(dt.type(iso), dt.type(-np.inf)))
    inner = occ64 > 0.5
    if inside == "above":
        vals = np.where(inner, np.maximum(vals, at_or_above), np.minimum(vals, below))
    else:
        vals = np.where(inner, np.minimum(vals, below), np.maximum(vals, at_or_above))
    return cast_samples(vals, dt.name, what="density frame")


def frame_times(frames: int | None = None, times=None) -> list[float]:
    """``frames`` evenly spaced times from 0 to 1, or the given ``times`` (checked)."""
    if times is not None:
        out = [float(t) for t in times]
        for t in out:
            check_time(t)
        if not out:
            raise VolwarpError("times is empty")
        return out
    if frames is None or frames < 2:
        raise VolwarpError("a morph needs at least 2 frames (or a list of times)")
    return [i / (frames - 1) for i in range(frames)]
