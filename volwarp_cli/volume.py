"""The Volume type: a ``[z, y, x]`` sample array plus its place in the world.

A :class:`Header` is the same without the samples (their shape and type):
what an output is before it is computed, what a file holds before it is read.

Geometry (sizes, spacing, origin, points, indices) is always written (x, y, z);
samples are indexed ``[z, y, x]``. :func:`xyz_to_zyx` and :func:`zyx_to_xyz`
are the one place where the two orders meet: every module that turns a
geometric tuple into an array axis (or back) calls them.

The voxel with index ``(i, j, k)`` (x, y, z) has its centre at::

    world = origin + direction @ (spacing * (i, j, k))

``direction`` is a 3x3 matrix whose *columns* are the unit vectors of the
index axes in world space, as ITK and NRRD's ``space directions`` have them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .errors import VolwarpError

#: NRRD's names of world frames, and the short forms accepted on input.
SPACE_NAMES = {
    "right-anterior-superior": "right-anterior-superior",
    "ras": "right-anterior-superior",
    "left-anterior-superior": "left-anterior-superior",
    "las": "left-anterior-superior",
    "left-posterior-superior": "left-posterior-superior",
    "lps": "left-posterior-superior",
    "scanner-xyz": "scanner-xyz",
    "3d-right-handed": "3d-right-handed",
    "3d-left-handed": "3d-left-handed",
}


#: volwarp's world frame (ITK's, DICOM's, 3D Slicer's files')
LPS = "left-posterior-superior"

#: For each anatomical frame a file may store, the signs that take its world (x, y, z)
#: to LPS. ``scanner-xyz`` and ``3d-right-handed`` are taken as LPS-like, and
#: ``3d-left-handed`` as it stands, as ITK's NrrdImageIO does (their numbers are kept).
_TO_LPS_SIGNS = {
    "right-anterior-superior": (-1.0, -1.0, 1.0),
    "left-anterior-superior": (1.0, -1.0, 1.0),
    "left-posterior-superior": (1.0, 1.0, 1.0),
    "scanner-xyz": (1.0, 1.0, 1.0),
    "3d-right-handed": (1.0, 1.0, 1.0),
    "3d-left-handed": (1.0, 1.0, 1.0),
}


def frame_to_lps(space: str | None) -> np.ndarray | None:
    """The 3x3 matrix taking world vectors of the file frame ``space`` to LPS.

    None when ``space`` names no frame (a file without one: its numbers are
    used as they stand, and the volume has no anatomical frame). An unknown
    frame name raises: guessing would place the anatomy somewhere else.
    """
    if space is None:
        return None
    name = SPACE_NAMES.get(str(space).lower())
    if name is None:
        known = ", ".join(sorted(_TO_LPS_SIGNS))
        raise VolwarpError(f"unknown world frame {space!r} (known: {known})")
    return np.diag(_TO_LPS_SIGNS[name])


def xyz_to_zyx(values):
    """Reverse a per-axis (x, y, z) sequence to array order [z, y, x]."""
    return tuple(values)[::-1]


def zyx_to_xyz(values):
    """Reverse a per-axis array-order [z, y, x] sequence to (x, y, z)."""
    return tuple(values)[::-1]


@dataclass(kw_only=True, eq=False)
class _Placed:
    """What :class:`Volume` and :class:`Header` share: a grid of ``shape`` (z, y, x) in the world.

    The placement's fields (keywords after a subclass's own), the one
    implementation of the checks and the frame conversion every volume's
    geometry goes through (:meth:`_place`), and of the geometry methods; a
    subclass has ``shape``.
    """

    spacing: np.ndarray = field(default_factory=lambda: np.ones(3))
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.eye(3))
    space: str | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    #: the world frame the file itself used (its readers converted it to ``space``)
    file_space: str | None = None

    def _place(self, shape_zyx) -> None:
        """Check the placement for a grid of ``shape_zyx`` and convert the file's frame to LPS.

        Spacing, origin and direction obey
        :func:`volwarp_cli.geometry.check_placement`; a frame other than LPS
        (``space``) has its origin and direction converted to LPS here, once,
        and is kept as ``file_space``.
        """
        from .geometry import check_placement  # (geometry imports this module)

        self.spacing, self.origin, self.direction = check_placement(
            self.spacing, self.origin, self.direction, zyx_to_xyz(shape_zyx))
        to_lps = frame_to_lps(self.space)
        if to_lps is not None:  # the one conversion of a file's frame to LPS
            frame = SPACE_NAMES[str(self.space).lower()]
            if self.file_space is None:
                self.file_space = frame
            if frame != LPS:
                self.origin = to_lps @ self.origin + 0.0  # + 0.0: no negative zeros
                self.direction = to_lps @ self.direction + 0.0
            self.space = LPS
        self.meta = dict(self.meta)

    def replace(self, **changes):
        """A copy with ``changes`` (geometry, frame, meta, ...); meta kept (a copy) by default."""
        changes.setdefault("meta", dict(self.meta))
        return replace(self, **changes)

    # -- sizes --------------------------------------------------------------
    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """Number of samples along x, y, z."""
        return tuple(int(n) for n in zyx_to_xyz(self.shape))

    # -- coordinates ----------------------------------------------------------
    @property
    def index_to_world_matrix(self) -> np.ndarray:
        """4x4 matrix taking homogeneous (i, j, k, 1) indices to world (x, y, z, 1)."""
        m = np.eye(4)
        m[:3, :3] = self.direction * self.spacing[None, :]
        m[:3, 3] = self.origin
        return m

    def index_to_world(self, ijk) -> np.ndarray:
        """World coordinates of (fractional) voxel indices, shape (..., 3) in (x, y, z)."""
        ijk = np.asarray(ijk, dtype=np.float64)
        return ijk @ (self.direction * self.spacing[None, :]).T + self.origin

    def world_to_index(self, xyz) -> np.ndarray:
        """Fractional voxel indices (i, j, k) of world points, shape (..., 3)."""
        xyz = np.asarray(xyz, dtype=np.float64)
        inv = np.linalg.inv(self.direction * self.spacing[None, :])
        return (xyz - self.origin) @ inv.T

    def world_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned world bounding box (min, max) of the voxel centres."""
        n = np.array(self.shape_xyz) - 1
        corners = np.array([[a, b, c] for a in (0, n[0]) for b in (0, n[1]) for c in (0, n[2])])
        pts = self.index_to_world(corners)
        return pts.min(axis=0), pts.max(axis=0)

    def same_grid(self, other: _Placed, atol: float = 1e-6) -> bool:
        """True when both sample the same world points (a Volume's or a Header's grid)."""
        return (
            self.shape_xyz == other.shape_xyz
            and np.allclose(self.spacing, other.spacing, atol=atol)
            and np.allclose(self.origin, other.origin, atol=atol)
            and np.allclose(self.direction, other.direction, atol=atol)
        )


@dataclass(eq=False)
class Header(_Placed):
    """A volume without its samples: ``shape`` (z, y, x), ``dtype``, and its place in the world.

    What an output is before it is computed, what a file holds before it is
    read: everything a :class:`Volume` has but ``data`` (spacing, origin,
    direction, frame and key/values, the same checks and the same one
    conversion of a file's frame to LPS). :meth:`with_data` gives the Volume
    of samples on it; :meth:`Volume.header` the Header of a Volume. It pickles
    small, whatever the grid's size.
    """

    shape: tuple[int, int, int]
    dtype: np.dtype

    def __post_init__(self):
        shape = tuple(int(n) for n in self.shape)
        if len(shape) != 3 or min(shape) < 0:
            raise VolwarpError(f"a volume has 3 axes, got a shape {shape}")
        self.shape = shape
        self.dtype = np.dtype(self.dtype)
        self._place(shape)

    def with_data(self, data: np.ndarray, **changes) -> Volume:
        """A Volume of ``data`` (and optionally new geometry or meta) on this header; meta kept."""
        changes.setdefault("meta", dict(self.meta))
        kept = {k: getattr(self, k) for k in ("spacing", "origin", "direction", "space",
                                               "file_space")}
        return Volume(data, **{**kept, **changes})


@dataclass
class Volume(_Placed):
    """Samples ``data[z, y, x]`` with spacing, origin and direction, all (x, y, z).

    ``meta`` holds the file format's other key/value pairs (strings), carried
    from input to output so that a pipeline does not lose them.

    ``space`` is the world frame of origin and direction: LPS
    (``left-posterior-superior``) for every file with an anatomical frame, or
    None for files that name none (TIFF, raw, a NRRD without ``space``). A
    Volume made with another frame (a reader passes the file's own, e.g. a
    NRRD's ``right-anterior-superior``) converts its origin and direction to
    LPS here, once, and keeps the file's frame in ``file_space``: no other
    code converts frames, and every writer starts from LPS.

    Spacing, origin and direction obey :func:`volwarp_cli.geometry.check_placement`
    (finite, positive, non-singular and within its bound): the readers call it
    first with their files' own field names, so that a refusal names the field.
    The same without samples is a :class:`Header` (:attr:`header`).
    """

    data: np.ndarray

    def __post_init__(self):
        data = np.asarray(self.data)
        if data.ndim != 3:
            raise VolwarpError(f"a volume has 3 axes, got an array of shape {data.shape}")
        self.data = data
        self._place(data.shape)

    # -- sizes --------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        """The shape (z, y, x) of ``data``."""
        return tuple(self.data.shape)

    @property
    def dtype(self) -> np.dtype:
        """The sample type of ``data``."""
        return self.data.dtype

    @property
    def header(self) -> Header:
        """The volume without its samples: its shape, type, geometry, frame and key/values."""
        return Header(self.data.shape, self.data.dtype, spacing=self.spacing,
                      origin=self.origin, direction=self.direction, space=self.space,
                      meta=dict(self.meta), file_space=self.file_space)

    def with_data(self, data: np.ndarray, **changes) -> Volume:
        """A copy with new samples (and optionally new geometry or meta); meta kept by default."""
        return self.replace(data=data, **changes)
