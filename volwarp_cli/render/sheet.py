"""Contact sheets: several pictures tiled into one."""

from __future__ import annotations

import math

import numpy as np

from ..errors import VolwarpError


def contact_sheet(images: list[np.ndarray], columns: int | None = None, *,
                  gap: int = 4, background: float | int = 255) -> np.ndarray:
    """Tile ``images`` (each ``(H, W, C)``, same channels and type) row by row.

    ``columns`` defaults to a near-square layout. Every cell is as large as the
    largest picture; smaller ones are centred in theirs. Cells are separated by
    ``gap`` pixels of ``background``.
    """
    if not images:
        raise VolwarpError("a contact sheet needs at least one image")
    images = [np.asarray(im) for im in images]
    images = [im[:, :, None] if im.ndim == 2 else im for im in images]
    first = images[0]
    for i, im in enumerate(images):
        if im.ndim != 3 or im.shape[2] != first.shape[2] or im.dtype != first.dtype:
            raise VolwarpError(f"contact sheet: image {i} is {im.shape} {im.dtype}, "
                               f"image 0 is {first.shape} {first.dtype}")
    n = len(images)
    cols = columns or math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    h = max(im.shape[0] for im in images)
    w = max(im.shape[1] for im in images)
    c = first.shape[2]
    sheet = np.full((rows * h + (rows + 1) * gap, cols * w + (cols + 1) * gap, c),
                    background, dtype=first.dtype)
    for idx, im in enumerate(images):
        r, q = divmod(idx, cols)
        y = gap + r * (h + gap) + (h - im.shape[0]) // 2
        x = gap + q * (w + gap) + (w - im.shape[1]) // 2
        sheet[y:y + im.shape[0], x:x + im.shape[1]] = im
    return sheet
