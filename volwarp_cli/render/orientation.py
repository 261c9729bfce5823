"""Anatomical orientation letters at the edges of a picture.

volwarp's world frame is LPS: +x points to the patient's Left, +y Posterior,
+z Superior (and -x Right, -y Anterior, -z Inferior). For each edge of a
picture (left, right, top, bottom) the letters name the world direction that
points towards that edge, as radiology viewers label their images:

* one letter when the direction lies within 22.5 degrees of an axis (the
  nearest of the 26 directions to the faces, edges and corners of a cube is
  a face's), e.g. ``"L"``;
* two or three letters for oblique directions, the axis with the largest
  component first, e.g. ``"LP"`` (mostly left, partly posterior) or ``"SRA"``
  for the ``iso`` view's top edge.

:func:`screen_letters` computes them from the camera (arrays in, letters
out); :func:`draw_orientation_labels` writes them onto a rendered picture
with a small built-in bitmap font (no font files, no OpenGL: the same
pixels on every machine).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import VolwarpError

#: (positive, negative) letters of the world axes x, y, z in LPS
AXIS_LETTERS = (("L", "R"), ("P", "A"), ("S", "I"))

#: file frames whose numbers are anatomical (the others are taken as LPS-like without a patient)
ANATOMICAL_FRAMES = ("left-posterior-superior", "right-anterior-superior",
                     "left-anterior-superior")


def direction_letters(v) -> str:
    """The orientation letters of the world direction ``v`` (LPS), see the module notes."""
    v = np.asarray(v, dtype=np.float64).reshape(3)
    length = float(np.linalg.norm(v))
    if not (length > 0 and math.isfinite(length)):
        raise VolwarpError(f"no direction: {v.tolist()}")
    a = np.abs(v) / length
    # by size, ties (to rounding) in the axis order x, y, z
    order = sorted(range(3), key=lambda i: (-round(float(a[i]), 9), i))
    best_k, best = 1, a[order[0]]
    for k in (2, 3):
        score = sum(a[i] for i in order[:k]) / math.sqrt(k)
        if score > best + 1e-9:  # the nearest of the 26 cube directions (fewer letters on ties)
            best_k, best = k, score
    return "".join(AXIS_LETTERS[i][0 if v[i] > 0 else 1] for i in order[:best_k])


def screen_letters(view_up, direction_of_projection) -> dict[str, str]:
    """Letters of the four picture edges for a camera: ``{"left", "right", "top", "bottom"}``.

    ``view_up`` (world direction of the picture's top; made orthogonal to the
    direction of projection, as VTK does) and ``direction_of_projection``
    (world direction from the viewer into the scene). Screen right is
    ``direction_of_projection x view_up``.
    """
    d = np.asarray(direction_of_projection, dtype=np.float64).reshape(3)
    u = np.asarray(view_up, dtype=np.float64).reshape(3)
    nd = float(np.linalg.norm(d))
    if not nd > 0:
        raise VolwarpError("the direction of projection is the zero vector")
    d = d / nd
    u = u - float(u @ d) * d
    nu = float(np.linalg.norm(u))
    if not nu > 1e-9:
        raise VolwarpError("view up is parallel to the direction of projection")
    u = u / nu
    r = np.cross(d, u)
    return {"left": direction_letters(-r), "right": direction_letters(r),
            "top": direction_letters(u), "bottom": direction_letters(-u)}


def view_letters(view) -> dict[str, str]:
    """:func:`screen_letters` of a named view or (azimuth, elevation) (see :mod:`.surface`)."""
    from .surface import view_axes

    _, up, back = view_axes(view)
    return screen_letters(up, -back)


def has_anatomical_frame(volume) -> bool:
    """Whether ``volume`` (a :class:`~volwarp_cli.volume.Volume`) was read with a patient frame.

    True for files that name an anatomical world frame (DICOM, NIfTI,
    MetaImage, a NRRD with ``space`` left-posterior-superior and the like);
    False for files without one (TIFF, raw, a NRRD without ``space`` or with
    ``scanner-xyz``/``3d-right-handed``) and for volumes volwarp made itself
    (sweeps), whose axes are LPS by convention but belong to no patient.
    """
    return (getattr(volume, "space", None) is not None
            and getattr(volume, "file_space", None) in ANATOMICAL_FRAMES)


# -- drawing ------------------------------------------------------------------

_GLYPHS = {
    "L": ("X....", "X....", "X....", "X....", "X....", "X....", "XXXXX"),
    "R": ("XXXX.", "X...X", "X...X", "XXXX.", "X.X..", "X..X.", "X...X"),
    "A": (".XXX.", "X...X", "X...X", "XXXXX", "X...X", "X...X", "X...X"),
    "P": ("XXXX.", "X...X", "X...X", "XXXX.", "X....", "X....", "X...."),
    "S": (".XXXX", "X....", "X....", ".XXX.", "....X", "....X", "XXXX."),
    "I": (".XXX.", "..X..", "..X..", "..X..", "..X..", "..X..", ".XXX."),
}
_GLYPH_H, _GLYPH_W = 7, 5


def text_mask(text: str, k: int) -> np.ndarray:
    """A boolean mask of ``text`` (letters of ``L R A P S I``), each font pixel k x k."""
    cols = []
    for n, ch in enumerate(text):
        if ch not in _GLYPHS:
            raise VolwarpError(f"no glyph for {ch!r}")
        if n:
            cols.append(np.zeros((_GLYPH_H, 1), dtype=bool))
        cols.append(np.array([[c == "X" for c in row] for row in _GLYPHS[ch]]))
    mask = np.concatenate(cols, axis=1)
    return np.kron(mask, np.ones((k, k), dtype=bool)).astype(bool)


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` grown by ``r`` pixels (a square), padded by ``r`` on every side."""
    h, w = mask.shape
    out = np.zeros((h + 2 * r, w + 2 * r), dtype=bool)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out[dy:dy + h, dx:dx + w] |= mask
    return out


def label_scale(width: int, height: int) -> int:
    """Font pixel size for a picture: 7-pixel letters at 64x64, 28 at 800x600."""
    return max(1, int(min(width, height) / 160 + 0.5))


def draw_orientation_labels(image: np.ndarray, letters: dict[str, str], *,
                            background=None) -> np.ndarray:
    """Write ``letters`` (see :func:`screen_letters`) at the edges of ``image``, in place.

    ``image`` is ``(H, W, 3 or 4)`` uint8. Each label is centred on its edge,
    dark on a light ``background`` (an RGB triple 0..255; default: the median
    of the corner pixels) and light on a dark one, with a halo of the
    background colour so that it reads over the object too. A picture too
    small to hold the labels (under about 24 pixels) is left as it is.
    Returns ``image``.
    """
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.dtype != np.uint8:
        raise VolwarpError(f"orientation labels need an (H, W, 3|4) uint8 picture, got "
                           f"{image.shape} {image.dtype}")
    h, w = image.shape[:2]
    k = label_scale(w, h)
    if background is None:
        corners = image[[0, 0, -1, -1], [0, -1, 0, -1], :3].astype(np.float64)
        background = np.median(corners, axis=0)
    bg = np.asarray(background, dtype=np.float64).reshape(3)
    luminance = 0.2126 * bg[0] + 0.7152 * bg[1] + 0.0722 * bg[2]
    ink = np.array([20, 20, 20] if luminance > 127.5 else [240, 240, 240], dtype=np.uint8)
    halo_colour = np.clip(np.rint(bg), 0, 255).astype(np.uint8)
    halo = max(1, k // 2)
    margin = max(2, 2 * k)
    masks = {edge: text_mask(text, k) for edge, text in letters.items() if text}
    if not masks:
        return image
    tallest = max(m.shape[0] for m in masks.values())
    widest = max(m.shape[1] for m in masks.values())
    if w < 2 * widest + 2 * margin + k or h < 2 * tallest + 2 * margin + k:
        return image
    for edge, mask in masks.items():
        mh, mw = mask.shape
        if edge == "left":
            y, x = (h - mh) // 2, margin
        elif edge == "right":
            y, x = (h - mh) // 2, w - margin - mw
        elif edge == "top":
            y, x = margin, (w - mw) // 2
        elif edge == "bottom":
            y, x = h - margin - mh, (w - mw) // 2
        else:
            raise VolwarpError(f"unknown picture edge {edge!r}")
        ring = _dilate(mask, halo)
        y0, x0 = y - halo, x - halo
        ys, xs = np.nonzero(ring)
        ys, xs = ys + y0, xs + x0
        keep = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
        image[ys[keep], xs[keep], :3] = halo_colour
        ys, xs = np.nonzero(mask)
        image[ys + y, xs + x, :3] = ink
    return image
