"""ITK's transform files: text ``.tfm``/``.txt``, HDF5 ``.h5``, MATLAB v4 ``.mat``.

Each holds transforms by ITK class name (``AffineTransform_double_3_3``),
with ``Parameters`` and ``FixedParameters``; a ``CompositeTransform`` is
followed by its components in queue order, and ITK applies the *last*
component first to a point (``CompositeTransform::TransformPoint``), so
:func:`itk_transform` returns a composite's steps reversed: the order they
act on a point. The classes and their parameters (ITK's definitions):

- ``AffineTransform``, ``MatrixOffsetTransformBase``, ``Rigid3DTransform``:
  the 3x3 matrix (row by row) then the translation; fixed: the centre;
- ``Euler3DTransform``: angles x, y, z (rad) and the translation; fixed: the
  centre and ITK 5's ComputeZYX flag (rotation ``Rz Rx Ry``, or ``Rz Ry Rx``);
- ``VersorRigid3DTransform``: the versor's vector part and the translation;
  ``Similarity3DTransform``: the same and the scale; fixed: the centre;
- ``TranslationTransform``: the offset;
- ``BSplineTransform``: the coefficients, all x then all y then all z (x
  fastest); fixed: grid size, origin, spacing, direction (row by row);
  ``BSplineDeformableTransform`` (ITK 3's, older ANTs'): the same grid and
  coefficients, but its ``InsideValidRegion`` has no far-face exception: a
  point at grid index ``n - 2`` is outside, not moved;
- ``DisplacementFieldTransform``: the vectors interleaved (x fastest); fixed
  as the B-spline's.

ANTs' ``0GenericAffine.mat`` is the MATLAB v4 form of the first group: a
variable named after the class and ``fixed``, the centre.

As ITK, a centre of fewer than 3 values (a file cut short) is refused; a
text file without a FixedParameters line, which ITK reads as the identity
(dropping its Parameters), is refused too.
"""

from __future__ import annotations

import re

import numpy as np

from ..errors import VolwarpError
from .model import Affine, BSplineGrid, DisplacementField, check_dimension, grid_frame

_NAME = re.compile(r"^(\w+?)_(double|float)_(\d+)_(\d+)$")
_MATRIX = ("AffineTransform", "MatrixOffsetTransformBase", "Rigid3DTransform",
           "ScalableAffineTransform")
#: the classes whose FixedParameters begin with the centre (ITK refuses fewer than 3)
_CENTRED = (*_MATRIX, "Euler3DTransform", "VersorRigid3DTransform", "Similarity3DTransform",
            "ScaleTransform")


def split_name(name: str, where: str) -> str:
    """The class of an ITK transform name (``Euler3DTransform_double_3_3``), its dimension checked."""
    m = _NAME.match(name.strip())
    if m is None:
        order = re.match(r"^(\w*BSpline\w*?)_(?:double|float)_3_3_(\d+)$", name.strip())
        if order is not None and order.group(2) != "3":  # (ITK names a non-cubic spline so)
            raise VolwarpError(f"{where}: {order.group(1)} of spline order {order.group(2)} "
                               "is not supported (cubic B-splines only, as ANTs and elastix "
                               "write them)")
        raise VolwarpError(f"{where}: {name.strip()!r} is not an ITK transform name")
    cls, _, d_in, d_out = m.groups()
    if d_in != d_out:
        raise VolwarpError(f"{where}: {name.strip()} maps {d_in}-D points to {d_out}-D ones; "
                           "the images are 3-D")
    check_dimension(name.strip(), int(d_in), where)
    return cls


def _rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def versor_matrix(v) -> np.ndarray:
    """The rotation of a versor's vector part ``v`` (ITK's Versor, w >= 0).

    As ITK's ``SetParameters`` (VersorRigid3D, Similarity3D): a vector part
    whose norm is not below ``1 - 1e-10`` (a rounded or hand-edited file) is
    divided by ``norm (1 + 1e-10)``, a rotation near a half turn, not refused.
    """
    x, y, z = (float(t) for t in v)
    norm = np.sqrt(x * x + y * y + z * z)  # (ITK's order of operations: w is ill-conditioned)
    if norm >= 1.0 - 1e-10:
        x, y, z = (t / (norm + 1e-10 * norm) for t in (x, y, z))
        norm = np.sqrt(x * x + y * y + z * z)
    w = np.sqrt(max(1.0 - norm * norm, 0.0))
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _need(params, n: int, what: str, where: str, cls: str):
    if len(params) < n:
        raise VolwarpError(f"{where}: {cls} has {len(params)} {what}, expected {n}")
    return np.asarray(params[:n], dtype=float)


def itk_transform(cls: str, params, fixed, where: str):
    """The step for ITK class ``cls`` with its parameters (module notes)."""
    try:
        params = np.asarray(params, dtype=float).ravel()
        fixed = np.asarray(fixed, dtype=float).ravel()
    except (TypeError, ValueError):  # (text where numbers belong: a damaged file)
        raise VolwarpError(f"{where}: {cls} has parameters that are not numbers") from None
    if not (np.all(np.isfinite(params)) and np.all(np.isfinite(fixed))):
        raise VolwarpError(f"{where}: {cls} has parameters that are not finite numbers")
    name = f"{where} ({cls})"
    if cls in _CENTRED:  # (a centre cut short would be taken about another point)
        center = _need(fixed, 3, "fixed parameters (its centre)", where, cls)
    if cls in _MATRIX:
        p = _need(params, 12, "parameters", where, cls)
        return Affine.centred(p[:9], p[9:12], center, name)
    if cls == "Euler3DTransform":
        p = _need(params, 6, "parameters", where, cls)
        zyx = len(fixed) >= 4 and fixed[3] != 0
        rx, ry, rz = _rot_x(p[0]), _rot_y(p[1]), _rot_z(p[2])
        m = rz @ ry @ rx if zyx else rz @ rx @ ry
        return Affine.centred(m, p[3:6], center, name)
    if cls == "VersorRigid3DTransform":
        p = _need(params, 6, "parameters", where, cls)
        return Affine.centred(versor_matrix(p[:3]), p[3:6], center, name)
    if cls == "Similarity3DTransform":
        p = _need(params, 7, "parameters", where, cls)
        return Affine.centred(p[6] * versor_matrix(p[:3]), p[3:6], center, name)
    if cls == "ScaleTransform":
        p = _need(params, 3, "parameters", where, cls)
        return Affine.centred(np.diag(p), np.zeros(3), center, name)
    if cls == "TranslationTransform":
        p = _need(params, 3, "parameters", where, cls)
        return Affine(np.eye(3), p.copy(), name)
    if cls == "IdentityTransform":
        return Affine(np.eye(3), np.zeros(3), name)
    if cls in ("BSplineTransform", "BSplineDeformableTransform", "DisplacementFieldTransform"):
        f = _need(fixed, 18, "fixed parameters", where, cls)
        frame = grid_frame(f[0:3], f[3:6], f[6:9], f[9:18].reshape(3, 3), where)
        nx, ny, nz = frame.size
        count = nx * ny * nz
        if cls == "DisplacementFieldTransform":
            if len(params) != 3 * count:
                raise VolwarpError(f"{where}: {cls} has {len(params)} parameters, expected "
                                   f"{3 * count} (3 per voxel of {nx}x{ny}x{nz})")
            return DisplacementField(frame, params.reshape(nz, ny, nx, 3), name)
        if len(params) != 3 * count:
            raise VolwarpError(f"{where}: {cls} has {len(params)} parameters, expected "
                               f"{3 * count} (3 per control point of {nx}x{ny}x{nz})")
        coef = np.ascontiguousarray(np.moveaxis(params.reshape(3, nz, ny, nx), 0, -1))
        # (ITK's older class: the same grid, its valid region [1, n - 2) to the letter)
        return BSplineGrid(frame, coef, name, far_face=cls == "BSplineTransform")
    raise VolwarpError(f"{where}: ITK transform {cls} is not supported (supported: "
                       "AffineTransform, MatrixOffsetTransformBase, Rigid3DTransform, "
                       "ScalableAffineTransform, Euler3DTransform, Similarity3DTransform, "
                       "VersorRigid3DTransform, TranslationTransform, ScaleTransform, "
                       "BSplineTransform, DisplacementFieldTransform, CompositeTransform)")


def _assemble(items, where: str) -> list:
    """Steps in the order they act on a point, from ``(class, params, fixed)`` in file order.

    A composite's components follow it in the file; ITK applies the last first.
    """
    steps, composite = [], False
    for k, (cls, params, fixed) in enumerate(items):
        if cls == "CompositeTransform":
            if k != 0:
                raise VolwarpError(f"{where}: a CompositeTransform inside a composite is not "
                                   "supported")
            composite = True
            continue
        steps.append(itk_transform(cls, params, fixed, where))
    if not steps:
        raise VolwarpError(f"{where}: holds no transform")
    if len(steps) > 1 and not composite:
        raise VolwarpError(f"{where}: holds {len(steps)} transforms without a "
                           "CompositeTransform; ITK reads the first only")
    return steps[::-1]


def read_text(path: str, text: str) -> list:
    """An ITK text transform file's steps (``#Insight Transform File V1.0``)."""
    items, cur = [], None
    for n, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if line.replace(" ", "").lower() == "#volwarp_field:forward":
            raise VolwarpError(f"{path}: volwarp's --transform-to map is the forward "
                               "(modelling) map, for points: resample with the warp's "
                               "--displacement-to field instead")
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise VolwarpError(f"{path}: line {n}: expected 'Key: value', got {line[:40]!r}")
        key = key.strip()
        if key == "Transform":
            cur = [split_name(value, path), [], None]
            items.append(cur)
        elif key in ("Parameters", "FixedParameters"):
            if cur is None:
                raise VolwarpError(f"{path}: line {n}: {key} before any Transform")
            try:
                numbers = [float(v) for v in value.split()]
            except ValueError:
                raise VolwarpError(f"{path}: line {n}: {key} are not numbers") from None
            cur[1 if key == "Parameters" else 2] = numbers
        else:
            raise VolwarpError(f"{path}: line {n}: unknown key {key!r}")
    for cls, params, fixed in items:
        if fixed is None and params:
            raise VolwarpError(f"{path}: {cls} has Parameters but no FixedParameters line: "
                               "ITK reads such a file as the identity (it drops the Parameters)")
    return _assemble([(cls, params, fixed or []) for cls, params, fixed in items], path)


def read_hdf5(path: str) -> list:
    """An ITK HDF5 transform file's steps (``/TransformGroup/N``)."""
    from ..runscope import stop_if_dry_run

    stop_if_dry_run(path)  # (it may hold a displacement field: batch's checks end here)
    try:
        import h5py
    except ImportError:  # pragma: no cover - a dependency
        raise VolwarpError(f"{path}: reading ITK .h5 transforms needs h5py") from None
    try:
        with h5py.File(path, "r") as f:
            if "TransformGroup" not in f:
                raise VolwarpError(f"{path}: an HDF5 file without ITK's TransformGroup: not a "
                                   "transform")
            group = f["TransformGroup"]
            if not isinstance(group, h5py.Group):
                raise VolwarpError(f"{path}: its TransformGroup is not a group: not an ITK "
                                   "transform file")
            keys = list(group)
            # (ITK reads 0, 1, ... N-1 and refuses a gap: a component left out of a composite
            # was skipped, the chain applied without it)
            if sorted(keys, key=lambda k: (len(k), k)) != [str(i) for i in range(len(keys))]:
                raise VolwarpError(f"{path}: its TransformGroup holds {sorted(keys)}, not the "
                                   f"transforms 0 to {len(keys) - 1} ITK reads (one missing or "
                                   "misnamed)")
            items = []
            for key in (str(i) for i in range(len(keys))):
                g = group[key]
                if not isinstance(g, h5py.Group) or "TransformType" not in g:
                    raise VolwarpError(f"{path}: transform {key} has no TransformType")
                kind = g["TransformType"][()]
                kind = kind[0] if np.ndim(kind) else kind
                kind = kind.decode() if isinstance(kind, bytes) else str(kind)
                cls = split_name(kind, path)
                params = g["TransformParameters"][()] if "TransformParameters" in g else []
                fixed = (g["TransformFixedParameters"][()] if "TransformFixedParameters" in g
                         else [])
                items.append((cls, params, fixed))
    except OSError as exc:
        raise VolwarpError(f"{path}: cannot read HDF5 ({exc})") from None
    return _assemble(items, path)


def read_matlab(path: str) -> list:
    """An ITK/ANTs MATLAB v4 ``.mat`` transform's steps (one affine)."""
    import scipy.io

    try:
        doc = scipy.io.loadmat(path)
    except Exception as exc:  # noqa: BLE001 - scipy raises many types for non-MATLAB files
        raise VolwarpError(f"{path}: not a transform file (not MATLAB either: "
                           f"{str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
                           ) from None
    names = [k for k in doc if _NAME.match(k)]
    if len(names) != 1:
        raise VolwarpError(f"{path}: a MATLAB file without one ITK transform variable "
                           f"(AffineTransform_double_3_3, ...): not a transform")
    cls = split_name(names[0], path)
    # (ITK: "fixed" required; the numbers are checked as every file's are)
    return [itk_transform(cls, doc[names[0]], doc.get("fixed", []), path)]
