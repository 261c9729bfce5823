"""Contact sheets: several equally sized pictures tiled into one."""

from __future__ import annotations

import math

import numpy as np

from ..errors import VolwarpError


def contact_sheet(images: list[np.ndarray], columns: int | None = None, *,
                  gap: int = 4, background: float | int = 255) -> np.ndarray:
    """Tile ``images`` (each ``(H, W, C)``, same shape and type) row by row.

    ``columns`` defaults to a near-square layout. Cells are separated by
    ``gap`` pixels of ``background``.
    """
    if not images:
        raise VolwarpError("a contact sheet needs at least one image")
    first = np.asarray(images[0])
    if first.ndim == 2:
        images = [np.asarray(im)[:, :, None] for im in images]
        first = images[0]
    for i, im in enumerate(images):
        if np.asarray(im).shape != first.shape or np.asarray(im).dtype != first.dtype:
            raise VolwarpError(f"contact sheet: image {i} has shape {np.asarray(im).shape}, "
                               f"image 0 has {first.shape}")
    n = len(images)
    cols = columns or math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    h, w, c = first.shape
    sheet = np.full((rows * h + (rows + 1) * gap, cols * w + (cols + 1) * gap, c),
                    background, dtype=first.dtype)
    for idx, im in enumerate(images):
        r, q = divmod(idx, cols)
        y = gap + r * (h + gap)
        x = gap + q * (w + gap)
        sheet[y:y + h, x:x + w] = im
    return sheet
