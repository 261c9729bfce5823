"""The one grid geometry: a :class:`~.volume.Volume` without samples, type, frame or key/values.

(A :class:`~.volume.Header` is a Volume without samples: a Geometry with a
sample type, a frame and key/values; :meth:`Geometry.header` makes one.)

A :class:`Geometry` is where a grid of samples lies in the world: its
``shape`` in array order (z, y, x) and, as a Volume has them, ``spacing``,
``origin`` and ``direction`` in (x, y, z). The voxel with index
``(i, j, k)`` (x, y, z) has its centre at::

    world = origin + direction @ (spacing * (i, j, k))

(DESIGN.md, "World coordinates"; LPS for volumes with an anatomical frame).
:meth:`Geometry.sub` is the geometry of a block (a :class:`~.box.Box`): the
block's shape, and the origin moved to the block's first voxel through the
direction matrix, so that every voxel of the block keeps its world point (as
SimpleITK's ``image[x0:x1, y0:y1, z0:z1]`` and RegionOfInterestImageFilter
have it).

It is every sampling grid's one type: a volume's, a block's, the morph's frame
grid (:mod:`.morph.grid`) and the sweep's output grid (:func:`.sweep.model.fit_grid`,
always with the identity direction). The B-spline lattice's layout is another
concept (:class:`.bspline.lattice.Lattice`).

:func:`check_placement` is the one rule every grid's placement obeys (finite,
positive and bounded spacing, a finite and bounded origin, a non-singular
direction): Volume and Geometry apply it, and every reader calls it with the
names of its file's own fields, so that a refusal says which field is wrong.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .box import Box
from .errors import FormatError, VolwarpError
from .volume import xyz_to_zyx, zyx_to_xyz

Floats3 = tuple[float, float, float]
_IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

#: Bound on a grid's spacing (1/LIMIT..LIMIT) and world coordinates (|x| <= LIMIT), in the
#: file's units. volwarp writes distances and mesh vertices in float32 and squares
#: distances in it (edt): a spacing of 1e20 gives distances of inf, one of 1e-40 of 0.
#: Within the bound the squares of every distance stay normal float32 numbers.
PLACEMENT_LIMIT = 1e15

#: How far a direction's column may be off a unit vector, and the cosine of two columns
#: off a right angle, for a grid to count as not sheared (:attr:`Geometry.right_angled`):
#: a DICOM series' cosines, written to six decimals, stay off by a few millionths.
AXIS_TOLERANCE = 1e-4

_AXES = "xyz"


#: How far (in voxels) beyond an input's outer voxel centres a frame voxel still lies on the
#: input, taking its border's value: grids that coincide but for rounding (a NIfTI's float32
#: spacing beside a NRRD's, a matrix inverted, a quarter turn, a DICOM series' positions in
#: decimal strings) put border voxels 1e-7 voxel outside, and the fill then took them for
#: outside the shape (a mask stored RAS-flipped in a NIfTI and LPS in a NRRD turned 155
#: inside voxels of a morph's frame 0 positive). Every resampling that marks samples off its
#: input's grid (NaN, a fill) follows it: :func:`beyond_grid`, :func:`snap_to_samples`.
COVER_TOLERANCE = 1e-3


def beyond_grid(coords: np.ndarray, values_shape) -> np.ndarray:
    """Where coordinates (3, ...) lie beyond the voxel centres of ``values_shape`` (a bool array).

    Beyond by more than :data:`COVER_TOLERANCE`: nearer, a coordinate is on
    the grid, and an interpolation with ``mode="nearest"`` gives it the border's value.
    """
    out = np.zeros(coords.shape[1:], bool)
    for axis, n in enumerate(values_shape):
        out |= coords[axis] < -COVER_TOLERANCE
        out |= coords[axis] > n - 1 + COVER_TOLERANCE
    return out


def snap_to_samples(coords) -> np.ndarray:
    """Coordinates within :data:`COVER_TOLERANCE` of a whole number made that number.

    Coordinates in voxels: shifts, offsets, interpolation weights. A sample a
    rounding off another is that sample, for the resamplings that cannot clamp
    (a fill outside, NaN carried on): there, one a hair off the border's sample
    read the fill beside it, or blended it in.
    """
    coords = np.asarray(coords, dtype=np.float64)
    whole = np.rint(coords)
    return np.where(np.abs(coords - whole) <= COVER_TOLERANCE, whole, coords)


def check_placement(spacing, origin, direction, shape_xyz=None, *, where: str | None = None,
                    fields: dict | None = None, error=FormatError):
    """``(spacing, origin, direction)`` as float64 arrays, or an error naming the bad field.

    The one rule for where a grid may lie (finite numbers, a positive spacing
    and a non-singular direction, all within :data:`PLACEMENT_LIMIT`; with
    ``shape_xyz``, the grid's corners too), so that no command meets an
    infinity or a division by zero later. ``fields`` maps ``spacing``, ``origin``
    and ``direction`` to the file's own names (``spacing`` may give one name
    per axis); with ``where`` (the file) the error is ``error`` (a FormatError:
    the file's fault) ``where: field: what``, else a VolwarpError.
    """
    names = {"spacing": None, "origin": None, "direction": None, **(fields or {})}

    def fail(key, message, axis=None):
        name = names[key]
        if isinstance(name, list | tuple):
            name = name[axis if axis is not None else 0]
        text = f"{name}: {message}" if name else message
        if where is None:
            raise VolwarpError(text)
        raise error(f"{where}: {text}")

    spacing = _vector3(spacing, "spacing", fail)
    _check_spacing(spacing, fail)
    origin = _vector3(origin, "origin", fail)
    _check_bounded(origin, "origin", fail)
    direction = np.asarray(direction, dtype=np.float64)
    if direction.shape != (3, 3) or not np.all(np.isfinite(direction)):
        fail("direction", f"direction must be a finite 3x3 matrix, got {direction.tolist()}")
    _check_direction(direction, spacing, fail)
    if shape_xyz is not None and min(int(n) for n in shape_xyz) > 0:
        _check_corners(spacing, origin, direction, shape_xyz, fail)
    return spacing, origin, direction


def _vector3(value, key, fail) -> np.ndarray:
    """Three finite numbers (a scalar stands for all three)."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        fail(key, f"{key} must be 3 numbers (x, y, z), got {value!r}")
    if arr.shape == ():
        arr = np.full(3, float(arr))
    if arr.shape != (3,):
        fail(key, f"{key} must have 3 values (x, y, z), got {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        fail(key, f"{key} must be finite, got {arr.tolist()}", int(np.argmax(bad)))
    return arr


def _check_spacing(spacing, fail) -> None:
    """Positive, and within 1/LIMIT..LIMIT (else float32 distances under- or overflow)."""
    for a, s in enumerate(spacing):
        if not s > 0:
            fail("spacing", f"spacing must be positive, got {spacing.tolist()}", a)
        if not 1.0 / PLACEMENT_LIMIT <= s <= PLACEMENT_LIMIT:
            fail("spacing", f"spacing {s:.6g} along {_AXES[a]} is outside "
                 f"{1 / PLACEMENT_LIMIT:g}..{PLACEMENT_LIMIT:g} (volwarp's float32 distances "
                 "and mesh vertices would overflow or vanish)", a)


def _check_bounded(values, key, fail) -> None:
    for a, v in enumerate(values):
        if abs(v) > PLACEMENT_LIMIT:
            fail(key, f"{key} {v:.6g} along {_AXES[a]} is beyond {PLACEMENT_LIMIT:g} in "
                 "magnitude (volwarp's float32 mesh vertices and distances would overflow)", a)


def _check_direction(direction, spacing, fail) -> None:
    """Every axis a non-zero vector (its step within the bound), the three not in one plane."""
    scale = np.abs(direction).max(axis=0)
    if np.any(scale == 0):
        a = int(np.argmin(scale))
        fail("direction", f"direction matrix is singular: its axis {_AXES[a]} is zero "
             f"({direction[:, a].tolist()})")
    norms = scale * np.linalg.norm(direction / scale[None, :], axis=0)  # (no overflow)
    for a, step in enumerate(norms * spacing):
        if not 1.0 / PLACEMENT_LIMIT <= step <= PLACEMENT_LIMIT:
            fail("direction", f"direction axis {_AXES[a]} ({direction[:, a].tolist()}) times "
                 f"the spacing {spacing[a]:.6g} is a step of {step:.6g}, outside "
                 f"{1 / PLACEMENT_LIMIT:g}..{PLACEMENT_LIMIT:g}")
    if abs(np.linalg.det(direction / norms[None, :])) < 1e-9:
        fail("direction", "direction matrix is singular (its axes lie in one plane)")


def _check_corners(spacing, origin, direction, shape_xyz, fail) -> None:
    """The farthest voxel centre within LIMIT of 0 along each world axis."""
    lengths = spacing * (np.asarray(shape_xyz, dtype=np.float64) - 1)
    steps = np.abs(direction) * lengths[None, :]
    reach = np.abs(origin) + steps.sum(axis=1)
    if reach.max() > PLACEMENT_LIMIT:
        w = int(np.argmax(reach))
        a = int(np.argmax(steps[w]))
        size = "x".join(str(int(n)) for n in shape_xyz)
        fail("spacing", f"the grid ({size} voxels of spacing {spacing.tolist()}) reaches "
             f"{reach[w]:.6g} along world {_AXES[w]}, beyond {PLACEMENT_LIMIT:g} in magnitude "
             "(volwarp's float32 mesh vertices and distances would overflow)", a)


@dataclass(frozen=True)
class Geometry:
    """Shape (z, y, x) and the placement of a grid; spacing, origin, direction (x, y, z).

    Stored as tuples (so two geometries compare and hash exactly); the
    ``*_array`` properties give numpy arrays. ``direction``'s *columns* are
    the unit vectors of the index axes in world space (rows of the tuple are
    the matrix's rows), as in :class:`~.volume.Volume`.
    """

    shape: tuple[int, int, int]
    spacing: Floats3 = (1.0, 1.0, 1.0)
    origin: Floats3 = (0.0, 0.0, 0.0)
    direction: tuple[Floats3, Floats3, Floats3] = _IDENTITY

    def __post_init__(self):
        shape = tuple(int(v) for v in self.shape)
        if len(shape) != 3 or min(shape) < 0:
            raise VolwarpError(f"a grid shape is 3 non-negative sizes (z, y, x), got {shape}")
        spacing, origin, direction = check_placement(self.spacing, self.origin,
                                                     self.direction, zyx_to_xyz(shape))
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "spacing", tuple(float(v) for v in spacing))
        object.__setattr__(self, "origin", tuple(float(v) for v in origin))
        object.__setattr__(self, "direction", tuple(tuple(float(v) for v in row)
                                                    for row in direction))

    @classmethod
    def of(cls, volume) -> Geometry:
        """The geometry of a :class:`~.volume.Volume`, a :class:`~.volume.Header` or anything alike.

        That is anything with ``data`` or ``shape`` (z, y, x), ``spacing``, ``origin``
        and ``direction``.
        """
        shape = volume.data.shape if hasattr(volume, "data") else volume.shape
        return cls(tuple(shape), volume.spacing, volume.origin, volume.direction)

    @classmethod
    def from_xyz(cls, shape_xyz, spacing=1.0, origin=0.0, direction=None) -> Geometry:
        """A geometry from a size written (x, y, z), as specs and metadata have it."""
        return cls(xyz_to_zyx(tuple(int(v) for v in shape_xyz)), spacing, origin,
                   np.eye(3) if direction is None else direction)

    # -- sizes ----------------------------------------------------------------------
    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """The size written (x, y, z), as specs and metadata have it."""
        return tuple(zyx_to_xyz(self.shape))

    @property
    def size(self) -> int:
        """Number of voxels (exact: :attr:`.box.Box.size` of :attr:`box`)."""
        return self.box.size

    @property
    def box(self) -> Box:
        """Every voxel: ``Box.from_shape(shape)``."""
        return Box.from_shape(self.shape)

    @property
    def spacing_zyx(self) -> Floats3:
        """Spacing along the array axes, as the numeric cores take it."""
        return tuple(xyz_to_zyx(self.spacing))

    # -- coordinates ----------------------------------------------------------------
    @property
    def spacing_array(self) -> np.ndarray:
        """Spacing (x, y, z) as a numpy array."""
        return np.array(self.spacing)

    @property
    def origin_array(self) -> np.ndarray:
        """Origin (x, y, z) as a numpy array."""
        return np.array(self.origin)

    @property
    def direction_array(self) -> np.ndarray:
        """Direction as a 3x3 numpy array (columns: the index axes x, y, z)."""
        return np.array(self.direction)

    @property
    def identity_direction(self) -> bool:
        """True when ``direction`` is exactly the identity (index axes along world x, y, z).

        Then a voxel's centre is ``origin + spacing * (i, j, k)``, the form the
        axis-aligned samplers (the sweep's) take.
        """
        return self.direction == _IDENTITY

    @property
    def right_angled(self) -> bool:
        """Whether the index axes are at right angles in the world (the grid is not sheared).

        Within :data:`AXIS_TOLERANCE` of a right angle's cosine.
        """
        d = self.direction_array
        d = d / np.linalg.norm(d, axis=0)
        return bool(np.allclose(d.T @ d, np.eye(3), atol=AXIS_TOLERANCE))

    @property
    def orthonormal(self) -> bool:
        """Whether the direction's columns are unit vectors at right angles (:data:`AXIS_TOLERANCE`).

        Only then is the spacing the world step along each axis, as whatever
        measures along the axes (a distance field's passes) takes it: every
        reader but MetaImage's (ITK's ``TransformMatrix``, kept as it stands)
        gives unit columns.
        """
        lengths = np.linalg.norm(self.direction_array, axis=0)
        return bool(np.abs(lengths - 1).max() <= AXIS_TOLERANCE) and self.right_angled

    @property
    def matrix(self) -> np.ndarray:
        """3x3 ``direction @ diag(spacing)``: index steps (x, y, z) to world vectors."""
        return self.direction_array * self.spacing_array[None, :]

    @property
    def index_to_world_matrix(self) -> np.ndarray:
        """4x4 homogeneous matrix taking (i, j, k, 1) to world (x, y, z, 1)."""
        m = np.eye(4)
        m[:3, :3] = self.matrix
        m[:3, 3] = self.origin
        return m

    def index_to_world(self, ijk) -> np.ndarray:
        """World points of (fractional) indices (i, j, k) = (x, y, z), shape (..., 3)."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return ijk @ self.matrix.T + self.origin_array

    def world_to_index(self, xyz) -> np.ndarray:
        """Fractional indices (i, j, k) = (x, y, z) of world points, shape (..., 3)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        return (xyz - self.origin_array) @ np.linalg.inv(self.matrix).T

    def corner_indices(self, *, voxel_boxes: bool = False) -> np.ndarray:
        """The 8 corner indices (i, j, k) = (x, y, z) of the grid, shape (8, 3), float.

        The first and last voxel centre along each axis (``0`` and ``n - 1``),
        x varying slowest and z fastest; with ``voxel_boxes`` the corners of the
        voxels' boxes (``-0.5`` and ``n - 0.5``). :meth:`index_to_world` of them
        (or ``index_to_world_matrix`` of them with a 1 appended) are the world corners.
        """
        if min(self.shape) == 0:
            raise VolwarpError(f"a grid of shape {self.shape} has no voxels, hence no corners")
        n = np.array(self.shape_xyz, dtype=np.float64) - 1
        a, b = (-0.5, n + 0.5) if voxel_boxes else (0.0, n)
        lo = np.broadcast_to(a, 3)
        return np.array([[x, y, z] for x in (lo[0], b[0]) for y in (lo[1], b[1])
                         for z in (lo[2], b[2])])

    def bounds_world(self, *, voxel_boxes: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned world bounding box ``(min, max)`` of the voxel centres.

        With ``voxel_boxes``: of the voxels' boxes (half a voxel beyond the centres).
        """
        if min(self.shape) == 0:
            raise VolwarpError(f"a grid of shape {self.shape} has no voxels, hence no bounds")
        pts = self.index_to_world(self.corner_indices(voxel_boxes=voxel_boxes))
        return pts.min(axis=0), pts.max(axis=0)

    def same_grid(self, other: Geometry, atol: float = 1e-6) -> bool:
        """True when both grids sample the same world points (as :meth:`.volume.Volume.same_grid`).

        The same shape, and spacing, origin and direction equal within ``atol``
        (``numpy.allclose``); ``other`` may be anything :meth:`of` takes.
        """
        other = other if isinstance(other, Geometry) else Geometry.of(other)
        return (self.shape == other.shape
                and np.allclose(self.spacing, other.spacing, atol=atol)
                and np.allclose(self.origin, other.origin, atol=atol)
                and np.allclose(self.direction, other.direction, atol=atol))

    # -- blocks ---------------------------------------------------------------------
    def sub(self, box: Box) -> Geometry:
        """The geometry of block ``box`` (array order).

        Its shape, and the origin at its first voxel,
        ``origin + direction @ (spacing * lo_xyz)``; spacing and direction unchanged.
        The box may reach beyond the grid (a halo): the grid's lattice simply continues.
        """
        lo_xyz, _ = box.xyz()
        return Geometry(box.shape, self.spacing, self.index_to_world(lo_xyz), self.direction)

    def volume(self, data: np.ndarray, **kwargs):
        """A :class:`~.volume.Volume` of ``data`` (its shape must be ``shape``) on this grid.

        ``kwargs`` (meta, ...) pass through (a ``space`` other than LPS would move it).
        """
        from .volume import Volume

        data = np.asarray(data)
        if tuple(data.shape) != self.shape:
            raise VolwarpError(f"samples of shape {data.shape} do not fit a grid of shape "
                               f"{self.shape}")
        return Volume(data, spacing=self.spacing_array, origin=self.origin_array,
                      direction=self.direction_array, **kwargs)

    def header(self, dtype, **kwargs):
        """A :class:`~.volume.Header` of samples of ``dtype`` on this grid (none held).

        ``kwargs`` (meta, ...) pass through (a ``space`` other than LPS would move it).
        """
        from .volume import Header

        return Header(self.shape, dtype, spacing=self.spacing_array, origin=self.origin_array,
                      direction=self.direction_array, **kwargs)
