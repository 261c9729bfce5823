"""Small PNG previews of a scan and of its outputs, for the HTML run report.

Run in a child process on the scan's worker, after its steps
(``python -m volwarp_cli.batch.thumbs FILE...``): a large or broken scan
costs that process, never the batch or the worker. Each file becomes at most
:data:`SIZE` pixels on its long side: a volume its middle axial slice (the
voxel spacing kept, windowed to the slice's 1st to 99th percentiles), an
image (a mesh step's render) scaled down. Standard output is one JSON list,
a base64 PNG or null (no preview) per file, in order.
"""

from __future__ import annotations

import base64
import json
import struct
import sys
import zlib
from pathlib import Path

#: the long side of a preview, in pixels
SIZE = 128
_IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")


def can_preview(path: str | Path) -> bool:
    """True for the outputs a preview is made of: volumes and images (not meshes)."""
    from ..errors import VolwarpError
    from ..io import volume_format

    name = str(path).lower()
    if name.endswith((".png", ".jpg", ".jpeg")):
        return True
    if name.endswith((".vwc", ".ply", ".stl", ".obj", ".vtp", ".vtk")):
        return False
    try:
        volume_format(path)
    except VolwarpError:
        return False
    return True


def command(files: list[str]) -> list[str]:
    """The child's command line for ``files``."""
    from .run import child_argv

    return child_argv(list(files), module="volwarp_cli.batch.thumbs")


def parse_output(out: bytes) -> list[bytes | None]:
    """The PNGs the child printed (None where a file has no preview)."""
    return [None if item is None else base64.b64decode(item) for item in json.loads(out)]


def png_bytes(image) -> bytes:
    """An 8-bit ``(H, W)`` or ``(H, W, 1..4)`` array as PNG bytes (gray, gray+alpha, RGB, RGBA)."""
    import numpy as np

    arr = np.asarray(image, dtype=np.uint8)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    h, w, c = arr.shape
    colour = {1: 0, 2: 4, 3: 2, 4: 6}[c]
    rows = np.concatenate([np.zeros((h, 1), np.uint8), arr.reshape(h, w * c)], axis=1)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    return (b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, colour, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6)) + chunk(b"IEND", b""))


def _resample(arr, height: int, width: int):
    """``arr`` (H, W, ...) sampled at ``height`` x ``width`` cell centres (nearest)."""
    import numpy as np

    ys = np.minimum(((np.arange(height) + 0.5) * arr.shape[0] / height).astype(int),
                    arr.shape[0] - 1)
    xs = np.minimum(((np.arange(width) + 0.5) * arr.shape[1] / width).astype(int),
                    arr.shape[1] - 1)
    return arr[ys][:, xs]


def _fit(height: float, width: float) -> tuple[int, int]:
    scale = SIZE / max(height, width, 1e-9)
    return max(1, round(height * scale)), max(1, round(width * scale))


def volume_preview(path: str | Path) -> bytes:
    """The middle axial slice of the volume at ``path``, windowed, as a PNG."""
    import numpy as np

    from ..io import read_volume

    vol = read_volume(path)
    data = np.asarray(vol.data)
    while data.ndim > 3:  # components: the first
        data = data[..., 0]
    plane = np.asarray(data[data.shape[0] // 2], dtype=np.float64)
    sx, sy = (float(v) for v in tuple(vol.spacing)[:2])
    h, w = _fit(plane.shape[0] * abs(sy or 1.0), plane.shape[1] * abs(sx or 1.0))
    plane = _resample(plane, h, w)
    finite = plane[np.isfinite(plane)]
    lo, hi = (np.percentile(finite, (1, 99)) if finite.size else (0.0, 1.0))
    if not hi > lo:
        lo, hi = lo - 0.5, lo + 0.5
    grey = np.clip((np.nan_to_num(plane, nan=lo) - lo) / (hi - lo), 0.0, 1.0)
    return png_bytes(np.rint(grey * 255.0).astype(np.uint8))


def image_preview(path: str | Path) -> bytes:
    """The image at ``path`` scaled to fit :data:`SIZE`, as a PNG."""
    import numpy as np

    from ..io.images import read_image

    img = read_image(path)  # float32 in [0, 1], (H, W, C)
    h, w = _fit(*img.shape[:2]) if max(img.shape[:2]) > SIZE else img.shape[:2]
    img = _resample(img, h, w)[:, :, :4]
    return png_bytes(np.rint(np.clip(img, 0.0, 1.0) * 255.0).astype(np.uint8))


def preview(path: str | Path) -> bytes | None:
    """The preview of ``path`` (a volume or an image), or None when it cannot be made."""
    try:
        if str(path).lower().endswith(_IMAGE_EXTENSIONS[:3]):
            return image_preview(path)
        return volume_preview(path)
    except Exception:  # a broken scan has no preview; its step says why  # noqa: BLE001
        return None


def main(argv: list[str]) -> int:
    """Print the previews of the files ``argv`` as one JSON list."""
    out = []
    for name in argv:
        png = preview(name)
        out.append(None if png is None else base64.b64encode(png).decode("ascii"))
    sys.stdout.write(json.dumps(out))
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
