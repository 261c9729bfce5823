"""Contact sheets: several pictures tiled into one."""

from __future__ import annotations

import math

import numpy as np

from ..errors import VolwarpError


def contact_sheet(images: list[np.ndarray], columns: int | None = None, *,
                  gap: int = 4, background: float | int = 255,
                  titles: list[str] | None = None) -> np.ndarray:
    """Tile ``images`` (each ``(H, W, C)``, same channels and type) row by row.

    ``columns`` defaults to a near-square layout. Every cell is as large as the
    largest picture; smaller ones are centred in theirs. Cells are separated by
    ``gap`` pixels of ``background``. ``titles`` (one per image) are written
    centred above each picture, in a strip of the background.
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
    if titles is not None:
        if len(titles) != n:
            raise VolwarpError(f"contact sheet: {len(titles)} titles for {n} images")
        w = max(im.shape[1] for im in images)
        images = [np.concatenate([title_strip(t, w, im, background), im]) for t, im in
                  zip(titles, _centred_columns(images, w, background), strict=True)]
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


def _centred_columns(images, width, background):
    """Each image padded left and right to ``width`` (its title centres on the cell)."""
    out = []
    for im in images:
        left = (width - im.shape[1]) // 2
        pad = ((0, 0), (left, width - im.shape[1] - left), (0, 0))
        out.append(np.pad(im, pad, constant_values=background))
    return out


def title_strip(text: str, width: int, like: np.ndarray, background) -> np.ndarray:
    """A ``(h, width, C)`` strip of ``background`` with ``text`` centred in it.

    ``like`` gives the channels and type. The text is drawn by OpenImageIO
    (its bundled font), dark on a light background and light on a dark one;
    where no font can be found the strip stays blank and a warning says so.
    """
    import OpenImageIO as oiio

    from ..progress import log

    height = max(16, min(width // 12, 40))
    channels = like.shape[2]
    colour = channels - 1 if channels in (2, 4) else channels  # the last of 2 or 4 is alpha
    scale = 255.0 if like.dtype == np.uint8 else (65535.0 if like.dtype == np.uint16 else 1.0)
    bg = float(background) / scale
    buf = oiio.ImageBuf(oiio.ImageSpec(width, height, colour, oiio.FLOAT))
    oiio.ImageBufAlgo.fill(buf, (bg,) * colour)
    ink = (0.1 if bg > 0.5 else 0.9,) * colour
    if text and not oiio.ImageBufAlgo.render_text(buf, width // 2, int(height * 0.75),
                                                  str(text), max(10, int(height * 0.6)), "",
                                                  ink, alignx="center"):
        log.warning("no font for contact sheet titles: %s", buf.geterror().strip())
    strip = np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(height, width, colour)
    if colour < channels:  # an opaque strip
        strip = np.concatenate([strip, np.ones((height, width, 1), np.float32)], axis=2)
    if like.dtype.kind in "ui":
        return np.clip(np.rint(strip * scale), 0, scale).astype(like.dtype)
    return strip.astype(like.dtype)
