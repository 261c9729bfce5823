"""Other tools' transforms, read into one chain of point maps (fixed/output -> moving/input).

Modules:

- :mod:`.model`: the transforms (affine, ITK B-spline grid, displacement
  field), the :class:`~.model.Chain` and its inverse for points;
- :mod:`.itk`: ITK text ``.tfm``/``.txt``, HDF5 ``.h5``, MATLAB v4 ``.mat``;
- :mod:`.fields`: displacement-field images (NIfTI, NRRD, MetaImage);
- :mod:`.elastix`: elastix ``TransformParameters`` files and their initial transforms;
- :mod:`._applykernels`: the sampling kernels, in C (fields, B-splines, images).

:func:`read_chain` reads ``-t`` arguments in antsApplyTransforms' order: the
transforms act on an output point in the order listed (``-t A -t B``: the
input is sampled at ``B(A(p))``), and ``[FILE,1]`` is a linear file's
inverse. A file is recognised by its content, not its name.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from ..errors import VolwarpError
from .model import Affine, Chain

__all__ = ["TransformSpec", "parse_spec", "read_transform", "read_chain", "refuse_folder",
           "Chain", "Affine"]

_SPEC = re.compile(r"^\[\s*(.+?)\s*,\s*([01])\s*\]$")


@dataclass(frozen=True)
class TransformSpec:
    """A ``-t`` argument: the file, and whether its inverse is asked for (``[FILE,1]``)."""

    path: str
    invert: bool = False


def parse_spec(text: str) -> TransformSpec:
    """``FILE`` or ``[FILE,0]`` or ``[FILE,1]`` (antsApplyTransforms' spelling)."""
    text = str(text).strip()
    m = _SPEC.match(text)
    if m:
        return TransformSpec(m.group(1), m.group(2) == "1")
    if text.startswith("["):
        raise VolwarpError(f"{text!r}: expected FILE or [FILE,0] or [FILE,1]")
    return TransformSpec(text)


#: names of the transform files registrations leave in their folders (named in the refusal)
_TRANSFORM_NAMES = re.compile(r"(?i)^(TransformParameters\.\d+\.txt|.*\.(tfm|h5|mat)|"
                              r".*Warp\.nii(\.gz)?)$")


def refuse_folder(path: str) -> None:
    """A folder given as a transform: one error naming it (and the transform files in it).

    Checked before the folder is declared an input (an output inside it
    would otherwise be refused as overwriting an input folder).
    """
    import os

    if not os.path.isdir(path):
        return
    try:
        names = sorted(n for n in os.listdir(path) if _TRANSFORM_NAMES.match(n))
    except OSError:
        names = []
    hint = ""
    if names:
        shown = ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")
        hint = f" (transform files in it: {shown})"
    raise VolwarpError(f"{path}: is a folder, not a transform file{hint}")


def sniff(path: str) -> str:
    """What the file at ``path`` holds, by its first bytes.

    ``itk-text``, ``hdf5``, ``elastix``, ``image:FMT`` (nifti, nrrd,
    metaimage), ``matlab`` (a ``.mat`` file: MATLAB v4 has no magic), or
    ``unknown``.
    """
    import gzip

    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
    except FileNotFoundError:
        raise VolwarpError(f"{path}: no such transform file") from None
    except IsADirectoryError:
        refuse_folder(path)
        raise
    except OSError as exc:
        raise VolwarpError(f"{path}: cannot open ({exc.strerror})") from None
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        return "hdf5"
    if head.lstrip().startswith(b"#Insight Transform File"):
        return "itk-text"
    if head.lstrip().startswith(b"(") or b"(Transform " in head:
        return "elastix"
    if head.startswith(b"NRRD000"):
        return "image:nrrd"
    if head.startswith(b"\x1f\x8b"):
        try:
            with gzip.open(path, "rb") as fh:
                inner = fh.read(352)
        except (OSError, EOFError):
            inner = b""
        if inner[344:348] in (b"n+1\0", b"n+2\0") or inner[4:8] == b"n+2\0":
            return "image:nifti"
        return "unknown"
    if head[344:348] in (b"n+1\0", b"ni1\0") or head[4:8] == b"n+2\0":
        return "image:nifti"
    from ..io.metaimage import looks_like_metaimage

    if looks_like_metaimage(head):
        return "image:metaimage"
    if str(path).lower().endswith(".mat"):
        return "matlab"
    return "unknown"


def read_transform(spec: TransformSpec, chain: Chain | None = None) -> list:
    """The steps of one ``-t`` argument, in the order they act on a point.

    ``chain``: the chain being read, given the first file's grid and notes.
    """
    from . import itk

    path = spec.path
    kind = sniff(path)
    if kind in ("itk-text", "elastix"):
        with open(path, encoding="utf-8", errors="replace") as fh:
            text = fh.read()
    if kind == "itk-text":
        steps = itk.read_text(path, text)
    elif kind == "elastix":
        from . import elastix

        if not elastix.looks_like_elastix(text):
            raise VolwarpError(f"{path}: an elastix parameter file without (Transform ...): "
                               "not a transform (a registration's parameter map?)")
        steps, doc = elastix.read_elastix(path, text)
        if chain is not None and not chain.steps and not spec.invert:
            chain.grid = elastix.fixed_grid(doc, path)
            final = elastix.final_interpolation(doc)
            if final:
                chain.notes.append(f"{path}: transformix's final interpolation is {final}; "
                                   "volwarp uses --interpolation")
    elif kind == "hdf5":
        steps = itk.read_hdf5(path)
    elif kind == "matlab":
        steps = itk.read_matlab(path)
    elif kind.startswith("image:"):
        from .fields import read_field

        steps = [read_field(path, kind.split(":", 1)[1])]
    else:
        raise VolwarpError(f"{path}: not a transform file (not ITK text, HDF5, MATLAB or "
                           "elastix, nor a displacement-field image)")
    if spec.invert:
        if not all(s.linear for s in steps):
            raise VolwarpError(f"[{path},1]: only a linear transform can be inverted here; "
                               "give the inverse field (ANTs' 1InverseWarp.nii.gz)")
        return [Chain(steps).affine().inverse()]
    return steps


def read_chain(specs) -> Chain:
    """The chain of ``-t`` arguments (strings or :class:`TransformSpec`), in the order given."""
    chain = Chain()
    for spec in specs:
        spec = spec if isinstance(spec, TransformSpec) else parse_spec(spec)
        chain.steps += read_transform(spec, chain)
    return chain
