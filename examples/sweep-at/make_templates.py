"""Draw the sweep templates of the Winter & Chen figures with numpy (no downloads).

    python make_templates.py OUTDIR [--frames N]

writes into OUTDIR:

* ``at_opacity.png``, ``at_colour.png``, ``at_geometry.png``: the '@' of Fig. 3
  (a-c): a translucent outer ring (cyan) around an opaque inner 'a' (red), and
  a smoothed geometry template for shading normals;
* ``bottle_opacity.png``, ``bottle_colour.png``, ``bottle_geometry.png``: the
  milk-bottle profile of Fig. 1 (b-d), drawn with the bottle's axis on the
  template's right edge (x = 1), ready for a rotational sweep of radius
  half the template width;
* ``flame_000.png`` ... (RGBA, ``--frames`` of them, default 256): a flickering
  flame, the "video" template of the ring of fire (Fig. 8).

Images are written with OpenImageIO through volwarp's ``write_image``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from volwarp_cli.io.images import write_image

AT_SIZE = 128
BOTTLE_SIZE = (96, 160)  # width, height
FLAME_SIZE = (32, 48)


def _grid(w: int, h: int):
    """Template coordinates of pixel centres: x right, y up, both in [0, 1]."""
    x = (np.arange(w) + 0.5) / w
    y = 1.0 - (np.arange(h) + 0.5) / h
    return np.meshgrid(x, y)


def _smooth(a: np.ndarray, passes: int = 3) -> np.ndarray:
    out = a.astype(np.float32)
    for _ in range(passes):
        p = np.pad(out, 1, mode="edge")
        out = (p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] + 2 * p[1:-1, 1:-1]) / 6
    return out


def at_templates(size: int = AT_SIZE):
    """(opacity, colour RGB, geometry) of the '@' as float32 arrays (H, W[, 3])."""
    x, y = _grid(size, size)
    dx, dy = x - 0.5, y - 0.5
    r = np.hypot(dx, dy)
    ang = np.degrees(np.arctan2(dy, dx))
    # outer ring with the opening of the '@' at the lower right
    ring = (r > 0.36) & (r < 0.47) & ~((ang > -40) & (ang < 5))
    # the inner 'a': a bowl and a stem on its right that runs into the ring's tail
    bowl = (np.hypot(dx + 0.03, dy) > 0.09) & (np.hypot(dx + 0.03, dy) < 0.19)
    stem = (dx > 0.13) & (dx < 0.22) & (dy > -0.20) & (dy < 0.19)
    # the tail: from the stem's foot a quarter-ellipse curling up into the ring's end
    # at the right (5 degrees), which makes the 'a' and the ring one '@' stroke
    t = np.linspace(0.0, np.pi / 2, 64)
    cx, cy = 0.175 + 0.24 * np.sin(t), 0.036 - 0.236 * np.cos(t)
    tail = np.min(np.hypot(dx[..., None] - cx, dy[..., None] - cy), axis=-1) < 0.045
    inner = bowl | stem | tail
    opacity = np.where(inner, 1.0, np.where(ring, 0.06, 0.0)).astype(np.float32)
    colour = np.zeros((size, size, 3), dtype=np.float32)
    colour[ring] = (0.1, 0.9, 0.95)
    colour[inner] = (0.95, 0.1, 0.1)
    geometry = _smooth((ring | inner).astype(np.float32), 4)
    return opacity, colour, geometry


def bottle_templates(size=BOTTLE_SIZE):
    """(opacity, colour RGB, geometry) of the milk-bottle profile (axis at x = 1)."""
    w, h = size
    x, y = _grid(w, h)
    rad = 1.0 - x  # distance from the axis, in template widths
    # outer radius along the height: body, shoulder, neck, lip
    body = 0.62
    neck = 0.27
    shoulder = np.clip((y - 0.50) / 0.25, 0, 1)
    outer = body + (neck - body) * (3 * shoulder ** 2 - 2 * shoulder ** 3)
    outer = np.where(y > 0.9, neck + 0.06, outer)  # the lip
    inside_shape = (rad <= outer) & (y > 0.04) & (y < 0.95)
    glass = inside_shape & ((rad > outer - 0.06) | (y < 0.08))
    milk = inside_shape & ~glass & (y < 0.62)
    cap = inside_shape & (y > 0.90)
    opacity = np.zeros((h, w), dtype=np.float32)
    opacity[glass] = 0.25
    opacity[milk] = 0.9
    opacity[cap] = 1.0
    colour = np.zeros((h, w, 3), dtype=np.float32)
    colour[glass] = (0.75, 0.85, 0.95)
    colour[milk] = (0.97, 0.97, 0.93)
    colour[cap] = (0.1, 0.3, 0.9)
    geometry = _smooth(inside_shape.astype(np.float32), 8)
    return opacity, colour, geometry


def flame_frame(k: int, n: int, size=FLAME_SIZE) -> np.ndarray:
    """RGBA flame number ``k`` of ``n``: a tongue whose height and sway flicker with k.

    The flicker mixes several frequencies (whole numbers of cycles over the n
    frames, so the video loops), so neighbouring frames differ a little and
    frames far apart a lot: swept along the ring it gives a row of tongues of
    different heights, as in the paper's Fig. 8.
    """
    w, h = size
    x, y = _grid(w, h)
    phase = 2 * np.pi * k / n
    height = (0.68 + 0.14 * np.sin(9 * phase) + 0.10 * np.sin(17 * phase + 1.0)
              + 0.06 * np.sin(29 * phase + 2.0))
    sway = (0.06 * np.sin(5 * phase + 5 * y) + 0.04 * np.sin(13 * phase + 9 * y)) * y
    yy = np.clip(y / height, 0, None)
    half_width = 0.30 * np.sqrt(np.clip(yy, 0, 1)) * np.clip(1 - yy, 0, 1) * 1.7
    d = np.abs(x - 0.5 - sway) / np.maximum(half_width, 1e-6)
    inten = np.clip(1 - d, 0, 1) * (yy < 1) * (y > 0.02)
    inten = _smooth(inten, 1)
    # red at the fringe, orange, yellow in the core; faint (it glows)
    rgba = np.stack([np.clip(4.0 * inten, 0, 1), np.clip(1.1 * inten ** 1.2, 0, 1),
                     np.clip(0.6 * inten ** 4, 0, 1), np.clip(0.4 * inten, 0, 1)], axis=-1)
    return rgba.astype(np.float32)


def write_rgba_png(path: Path, rgba: np.ndarray) -> None:
    """An RGBA PNG with the colour stored as given (unassociated alpha).

    volwarp's ``write_image`` hands RGBA to OpenImageIO as associated
    (premultiplied) alpha, so the PNG writer divides the colour by alpha and a
    faint flame (alpha 0.2) comes out white; ``read_image`` reads PNG alpha
    unassociated. Write the samples as they are, as the spec's channels expect.
    """
    import OpenImageIO as oiio

    arr = np.rint(np.clip(rgba, 0.0, 1.0) * 255.0).astype(np.uint8)
    h, w, c = arr.shape
    spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    tmp = path.with_name(path.name + ".tmp.png")
    png = oiio.ImageOutput.create(str(tmp))
    if png is None or not png.open(str(tmp), spec) or not png.write_image(arr):
        raise SystemExit(f"make_templates.py: cannot write {path}: {oiio.geterror()}")
    png.close()
    tmp.replace(path)


def make_all(outdir, frames: int = 256) -> list[Path]:
    """Write every template into ``outdir`` (created); return the files written."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    written = []

    def put(name, arr):
        if arr.ndim == 3 and arr.shape[2] == 4:
            write_rgba_png(out / name, arr)
        else:
            write_image(out / name, np.ascontiguousarray(arr))
        written.append(out / name)

    o, c, g = at_templates()
    put("at_opacity.png", o[:, :, None])
    put("at_colour.png", c)
    put("at_geometry.png", g[:, :, None])
    o, c, g = bottle_templates()
    put("bottle_opacity.png", o[:, :, None])
    put("bottle_colour.png", c)
    put("bottle_geometry.png", g[:, :, None])
    for k in range(frames):
        put(f"flame_{k:03d}.png", flame_frame(k, frames))
    return written


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("outdir")
    ap.add_argument("--frames", type=int, default=256)
    args = ap.parse_args(argv)
    files = make_all(args.outdir, args.frames)
    print(f"wrote {len(files)} templates to {args.outdir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
