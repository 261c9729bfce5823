"""elastix's ``TransformParameters.N.txt``: one transform, and the chain before it.

The file is parenthesised key/values (``(Transform "EulerTransform")``,
``//`` comments). What volwarp reads, as transformix does:

- ``Transform``: ``EulerTransform`` (ITK's Euler3D: angles, translation,
  ``CenterOfRotationPoint``, ``ComputeZYX``), ``SimilarityTransform``
  (versor, translation, scale), ``AffineTransform`` (matrix row by row,
  translation), ``TranslationTransform``, ``BSplineTransform`` (order 3;
  ``GridSize``/``GridOrigin``/``GridSpacing``/``GridDirection``, the
  coefficients all x, then y, then z);
- ``Direction`` and ``GridDirection`` are written column by column (elastix
  flattens ITK's matrix that way), unlike ITK's FixedParameters;
- ``InitialTransformParameterFileName`` (elastix 4 spelled it
  ``InitialTransformParametersFileName``): the transform before this one,
  acting first on a fixed point (``HowToCombineTransforms "Compose"``; "Add"
  is refused). Its path is relative to where elastix ran: tried as written,
  then beside the file;
- ``Size``/``Spacing``/``Origin``/``Direction``/``Index``: the fixed grid,
  the output grid transformix resamples on (:func:`fixed_grid`);
- ``FinalBSplineInterpolationOrder``: transformix's final interpolation
  (:func:`final_interpolation`, reported to the user).

``(UseDirectionCosines "false")`` is refused: elastix then takes the
images' directions as identity, and its two front ends differ on which
(the command-line transformix reads both images so; itk-elastix 0.25's
TransformixFilter, given the moving image in memory, only the output grid).
"""

from __future__ import annotations

import dataclasses
import os
import re
import shlex

import numpy as np

from ..errors import VolwarpError
from .itk import itk_transform
from .model import check_dimension

_LINE = re.compile(r"^\(\s*([A-Za-z_]\w*)\s*(.*?)\s*\)\s*$")
_INITIAL = ("InitialTransformParameterFileName", "InitialTransformParametersFileName")
_CLASSES = {"EulerTransform": "Euler3DTransform", "SimilarityTransform": "Similarity3DTransform",
            "AffineTransform": "AffineTransform", "TranslationTransform": "TranslationTransform",
            "BSplineTransform": "BSplineTransform"}


def looks_like_elastix(text: str) -> bool:
    """Whether ``text`` is an elastix parameter file with a ``(Transform ...)`` entry."""
    return bool(re.search(r"^\s*\(\s*Transform\s+\"", text, re.M))


def parse(text: str, where: str) -> dict:
    """The key/values of an elastix parameter file: key -> list of str or float."""
    out: dict = {}
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("//", 1)[0].strip()
        if not line:
            continue
        m = _LINE.match(line)
        if m is None:
            raise VolwarpError(f"{where}: line {n}: expected (Key value ...), got {line[:40]!r}")
        key, rest = m.groups()
        try:
            words = shlex.split(rest)
        except ValueError:
            raise VolwarpError(f"{where}: line {n}: unbalanced quotes") from None
        values = []
        for w in words:
            try:
                values.append(float(w))
            except ValueError:
                values.append(w)
        out[key] = values
    return out


def _numbers(doc: dict, key: str, n: int | None, where: str, default=None, *,
             whole: bool = False) -> np.ndarray:
    """``(key ...)``'s ``n`` numbers; ``whole``: sizes, indices, orders (``22.5`` refused, not cut)."""
    if key not in doc:
        if default is not None:
            return np.asarray(default, float)
        raise VolwarpError(f"{where}: no ({key} ...)")
    vals = doc[key]
    if any(isinstance(v, str) for v in vals) or (n is not None and len(vals) != n):
        raise VolwarpError(f"{where}: ({key} ...) must be {n or 'some'} numbers")
    out = np.asarray(vals, float)
    if whole and not np.all(np.isfinite(out) & (out == np.round(out))):
        raise VolwarpError(f"{where}: ({key} ...) must be whole numbers, not "
                           f"{' '.join(repr(float(v)) for v in out)}")
    return out


def _word(doc: dict, key: str, default: str) -> str:
    """``(key "word" ...)``'s first word, as transformix reads it (more are ignored there too)."""
    vals = doc.get(key, [default])
    return str(vals[0]) if vals else default


def _column_major(values: np.ndarray) -> np.ndarray:
    return np.asarray(values, float).reshape(3, 3).T


def _step(doc: dict, where: str):
    kind = _word(doc, "Transform", "")
    dims = int(_numbers(doc, "FixedImageDimension", 1, where, [3], whole=True)[0])
    check_dimension(f"an elastix {kind}", dims, where)
    if kind not in _CLASSES:
        raise VolwarpError(f"{where}: elastix transform {kind!r} is not supported (supported: "
                           f"{', '.join(_CLASSES)})")
    if _word(doc, "UseDirectionCosines", "true").lower() == "false":
        raise VolwarpError(f'{where}: (UseDirectionCosines "false") is not supported: elastix '
                           "then takes the images' directions as identity (the command-line "
                           "transformix both images', itk-elastix's TransformixFilter the "
                           "output grid's only); resample with transformix, or make it "
                           '"true" where both images\' directions are the identity')
    params = _numbers(doc, "TransformParameters", None, where)
    center = _numbers(doc, "CenterOfRotationPoint", 3, where, [0, 0, 0])
    fixed = list(center)
    if kind == "EulerTransform":
        fixed.append(1.0 if _word(doc, "ComputeZYX", "false").lower() == "true" else 0.0)
    if kind == "BSplineTransform":
        order = int(_numbers(doc, "BSplineTransformSplineOrder", 1, where, [3], whole=True)[0])
        if order != 3:
            raise VolwarpError(f"{where}: a B-spline of order {order}: only cubic (3) is "
                               "supported")
        if _word(doc, "UseCyclicTransform", "false").lower() == "true":
            raise VolwarpError(f"{where}: a cyclic B-spline transform is not supported")
        spacing = _numbers(doc, "GridSpacing", 3, where)
        direction = _column_major(_numbers(doc, "GridDirection", 9, where, np.eye(3).ravel()))
        # (transformix's coefficients start at GridIndex of a grid whose index 0 lies at
        # GridOrigin: ITK's grid origin is that node's point; a non-zero index, 3 mm off when
        # ignored, comes from files other tools or hands wrote)
        index = _numbers(doc, "GridIndex", 3, where, [0, 0, 0], whole=True)
        origin = _numbers(doc, "GridOrigin", 3, where) + direction @ (spacing * index)
        size = _numbers(doc, "GridSize", 3, where, whole=True)
        fixed = [*size, *origin, *spacing, *direction.ravel()]
    step = itk_transform(_CLASSES[kind], params, fixed, where)
    # (elastix's valid region is [1, n - 2) to the letter: its far face is outside, not ITK's)
    return dataclasses.replace(step, far_face=False) if kind == "BSplineTransform" else step


def _initial(doc: dict, path: str, folder: str | None = None) -> str | None:
    """The initial transform ``path`` names: where elastix ran, else beside ``path``.

    Where elastix ran: ``folder``, default the run's
    (:attr:`~volwarp_cli.runscope.RunFiles.folder`), else this process's.
    """
    for key in _INITIAL:
        if key in doc:
            name = _word(doc, key, "NoInitialTransform")
            break
    else:
        return None
    if name in ("NoInitialTransform", ""):
        return None
    if folder is None:
        from ..runscope import run_files

        folder = run_files().folder
    there = name if folder is None else os.path.join(folder, name)  # (absolute: itself)
    if os.path.isfile(there):
        return there
    beside = os.path.join(os.path.dirname(path), os.path.basename(name))
    if os.path.isfile(beside):
        return beside
    raise VolwarpError(f"{path}: its initial transform {name} is neither there (relative to "
                       f"where elastix ran) nor beside it ({beside})")


def read_elastix(path: str, text: str, _seen: tuple = ()) -> tuple[list, dict]:
    """The steps of ``path`` and of its initial transforms (first acting first), and its doc."""
    if os.path.realpath(path) in _seen:
        raise VolwarpError(f"{path}: its initial transforms loop back to it")
    doc = parse(text, path)
    how = _word(doc, "HowToCombineTransforms", "Compose")
    steps: list = []
    initial = _initial(doc, path)
    if initial is not None:
        if how != "Compose":
            raise VolwarpError(f"{path}: HowToCombineTransforms {how!r}: only \"Compose\" is "
                               "supported")
        from ..io.inputs import declare_input

        declare_input(initial)
        with open(initial, encoding="utf-8", errors="replace") as fh:
            steps, _ = read_elastix(initial, fh.read(), _seen + (os.path.realpath(path),))
    steps.append(_step(doc, path))
    return steps, doc


def initial_files(path: str, folder: str | None = None) -> list[str]:
    """The initial transforms an elastix parameter file names, nearest first ([] for another file).

    What reading ``path`` reads besides it (``volwarp batch`` hashes them
    with a scan's own transform), a relative name taken from ``folder`` (as
    :func:`_initial`).
    """
    from . import sniff

    out: list[str] = []
    seen = {os.path.realpath(path)}
    while True:
        if sniff(path) != "elastix":
            return out
        with open(path, encoding="utf-8", errors="replace") as fh:
            text = fh.read()
        if not looks_like_elastix(text):
            return out
        initial = _initial(parse(text, path), path, folder)
        if initial is None or os.path.realpath(initial) in seen:
            return out
        seen.add(os.path.realpath(initial))
        out.append(initial)
        path = initial


def fixed_grid(doc: dict, where: str):
    """The fixed grid a parameter file states (transformix's output grid), a Geometry."""
    from ..geometry import Geometry

    size = _numbers(doc, "Size", 3, where, whole=True)
    spacing = _numbers(doc, "Spacing", 3, where)
    origin = _numbers(doc, "Origin", 3, where)
    direction = _column_major(_numbers(doc, "Direction", 9, where, np.eye(3).ravel()))
    index = _numbers(doc, "Index", 3, where, [0, 0, 0], whole=True)
    origin = origin + direction @ (spacing * index)
    return Geometry.from_xyz(tuple(int(v) for v in size), spacing, origin, direction)


def final_interpolation(doc: dict) -> str | None:
    """The final interpolation transformix would use, as the file says (for the user), or None."""
    kind = _word(doc, "ResampleInterpolator", "")
    if not kind:
        return None
    order = doc.get("FinalBSplineInterpolationOrder")
    return f"{kind}" + (f" of order {int(order[0])}" if order else "")
