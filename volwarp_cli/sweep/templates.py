"""Sweeping templates: images (and image stacks) on the normalised square [0, 1]^2.

Winter & Chen §3 map an ``nx x ny`` image onto ``m(x, y)``, 0 <= x, y <= 1,
with an interpolation function; §5.4 stacks several images into a volume
template ``w(x, y, z)`` whose ``z`` is picked by an image-path association
function ``f(u)``. Here:

* pixel centres sit at ``((i + 0.5) / W, 1 - (j + 0.5) / H)`` for column ``i``,
  row ``j`` (row 0 is the top of the picture, so ``y`` points up the image);
  between centres values are bilinear, beyond the outer centres they are
  clamped (the square's border keeps the edge pixels' values); outside the
  square there is no template (the paper's constant ``c``, 0);
* a volume template's slice coordinate ``f(u)`` is fractional: the two
  neighbouring slices are interpolated linearly, and coordinates outside
  ``[0, n - 1]`` are clamped. Without ``path``, ``f`` runs from slice 0 to the
  last slice along each segment.

Images are read with :func:`volwarp_cli.io.images.read_image` (OpenImageIO,
alpha left unassociated so colour is not darkened by opacity): 8- and
16-bit images are scaled to [0, 1], float images are kept as they are.
Image stacks come from a glob pattern (its files in natural order: ``f_2``
before ``f_10``, ``t_0.25`` before ``t_0.5``; :func:`natural_order`), a list of files (in its
order), or one volume file (NRRD, multi-page TIFF, NIfTI: its z slices are
the frames, scaled as images are: an integer type's largest value is 1.0, a
float kept; the same frames as PNG files or as one TIFF stack give one
template).
"""

from __future__ import annotations

import glob as globmod
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import OutOfMemoryError, VolwarpError
from ..io.images import normalized, read_image
from ..io.inputs import declare_input, declare_input_glob
from ..spec.functions import Function, spec_error


@dataclass
class Template:
    """One field's template: ``data`` is ``(n_slices, H, W)`` float32."""

    name: str
    data: np.ndarray
    path_fn: Function | None = None
    key: tuple = ()

    @property
    def n_slices(self) -> int:
        """The template's number of slices (1 for a single image)."""
        return int(self.data.shape[0])

    def slice_coords(self, seg, s: np.ndarray) -> np.ndarray:
        """Fractional slice index at normalised parameters ``s`` of segment ``seg``."""
        s = np.asarray(s, dtype=np.float64)
        if self.n_slices == 1:
            return np.zeros_like(s)
        if self.path_fn is None:
            return np.clip(s, 0.0, 1.0) * (self.n_slices - 1)
        # (clamped as the samplers clamp them: a path far beyond the stack, u * 1e300, asks
        # for no templates between slices that are all the last one)
        return np.clip(self.path_fn(seg.u_of(s)), 0.0, self.n_slices - 1)


def natural_order(name: str) -> tuple:
    """A sort key taking numbers as numbers: ``f_2`` before ``f_10``, ``t_0.25`` before ``t_0.5``.

    (``sorted`` put ``f_10`` first, so a stack of unpadded frame numbers played
    out of order along the trajectory.) Equal numbers (``f_1``, ``f_01``) go
    by the name itself, so the order never depends on the folder's listing.
    """
    from decimal import Decimal

    parts = re.split(r"(\d+(?:\.\d+)?)", name)
    return [Decimal(p) if i % 2 else p for i, p in enumerate(parts)], name


def sample_template(data: np.ndarray, x: np.ndarray, y: np.ndarray,
                    sl: np.ndarray | None = None) -> np.ndarray:
    """Bilinear (and linear-between-slices) sample of ``data[n, H, W]`` at (x, y[, slice]).

    The numpy reference of the voxeliser's C sampler (same conventions).
    """
    n, h, w = data.shape
    cx = np.clip(np.asarray(x, dtype=np.float64) * w - 0.5, 0.0, w - 1)
    cy = np.clip((1.0 - np.asarray(y, dtype=np.float64)) * h - 0.5, 0.0, h - 1)
    x0 = np.floor(cx).astype(np.int64)
    y0 = np.floor(cy).astype(np.int64)
    fx = cx - x0
    fy = cy - y0
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    if sl is None or n == 1:
        z0 = np.zeros_like(x0)
        z1 = z0
        fz = np.zeros_like(fx)
    else:
        cz = np.clip(np.asarray(sl, dtype=np.float64), 0.0, n - 1)
        z0 = np.floor(cz).astype(np.int64)
        fz = cz - z0
        z1 = np.minimum(z0 + 1, n - 1)

    def plane(z):
        return ((data[z, y0, x0] * (1 - fx) + data[z, y0, x1] * fx) * (1 - fy)
                + (data[z, y1, x0] * (1 - fx) + data[z, y1, x1] * fx) * fy)

    out = plane(z0)
    if np.any(fz > 0):
        out = out * (1 - fz) + plane(z1) * fz
    return out


class TemplateLoader:
    """Loads the ``fields`` of a spec, reading each image file once."""

    def __init__(self, doc):
        self.doc = doc
        self._images: dict[str, np.ndarray] = {}

    def _err(self, path, message):
        return spec_error(self.doc, path, message)

    def _image(self, name: str, path: tuple, resolved: bool = False) -> np.ndarray:
        file = self.doc.resolve(name) if self.doc is not None and not resolved else name
        declare_input(file)  # no output of the run may replace it
        key = str(file)
        if key not in self._images:
            try:
                if not Path(file).is_file():
                    raise self._err(path, f"template image {str(file)!r} does not exist")
                self._images[key] = read_image(file)
            except OutOfMemoryError:
                raise  # (the budget's refusal, exit 1: not the spec's fault, exit 2)
            except VolwarpError as exc:
                if getattr(exc, "key", None):
                    raise
                raise self._err(path, f"cannot read template image: {exc}") from None
        return self._images[key]

    def _channel(self, img: np.ndarray, channel: int, path: tuple, file: str) -> np.ndarray:
        if channel >= img.shape[2]:
            raise self._err(path, f"channel {channel} does not exist in {file!r} "
                            f"({img.shape[2]} channel{'s' if img.shape[2] != 1 else ''})")
        return np.ascontiguousarray(img[:, :, channel], dtype=np.float32)

    def load(self, name: str, spec: dict, path: tuple, path_fn: Function | None) -> Template:
        """A :class:`Template` for field ``name`` from its spec mapping at key ``path``."""
        channel = int(spec.get("channel", 0))
        if "value" in spec:
            value = float(spec["value"])
            if not abs(value) <= np.finfo(np.float32).max:  # (was "has non-finite values")
                raise self._err(path, f"value {value:g} is beyond float32's range (the "
                                "fields are float32, at most 3.4e+38)")
            data = np.full((1, 1, 1), value, dtype=np.float32)
        elif "image" in spec:
            img = self._image(spec["image"], path + ("image",))
            data = self._channel(img, channel, path + ("channel",), spec["image"])[None]
        else:
            data = self._frames(spec["frames"], channel, path)
        if not np.all(np.isfinite(data)):
            raise self._err(path, f"template of field {name!r} has non-finite values")
        if path_fn is not None and data.shape[0] == 1:
            raise self._err(path + ("path",), "'path' (f(u)) needs a stack of frames; "
                            "this template has one image")
        return Template(name, np.ascontiguousarray(data, dtype=np.float32), path_fn, path)

    def _frames(self, frames, channel: int, path: tuple) -> np.ndarray:
        fpath = path + ("frames",)
        if isinstance(frames, str) and any(c in frames for c in "*?["):
            pattern = str(self.doc.resolve(frames)) if self.doc is not None else frames
            declare_input_glob(pattern)  # (an output it matches would be a frame next time)
            files = sorted(globmod.glob(pattern), key=natural_order)
            if not files:
                raise self._err(fpath, f"no files match {frames!r}")
            resolved = True
        elif isinstance(frames, str):
            from ..io import VOLUME_EXTENSIONS, read_volume

            resolved = True
            file = self.doc.resolve(frames) if self.doc is not None else Path(frames)
            declare_input(file)
            lower = str(file).lower()
            if not any(lower.endswith(ext) for ext in VOLUME_EXTENSIONS):
                files = [str(file)]
            else:
                if not file.is_file():
                    raise self._err(fpath, f"template volume {str(file)!r} does not exist")
                from ..io.tiff import samples_only

                try:
                    with samples_only():  # (placed by the sweep: no calibration to say)
                        vol = read_volume(file)
                except VolwarpError as exc:
                    raise self._err(fpath, f"cannot read template volume: {exc}") from None
                return normalized(vol.data)  # (as its slices would be as image files)
        else:
            files = list(frames)
            resolved = False
        slices = []
        for i, f in enumerate(files):
            p = fpath + (i,) if isinstance(frames, list) else fpath
            img = self._image(f, p, resolved)
            sl = self._channel(img, channel, path + ("channel",), f)
            if slices and sl.shape != slices[0].shape:
                raise self._err(p, f"frame {f!r} is {sl.shape[1]}x{sl.shape[0]}, the first "
                                f"frame is {slices[0].shape[1]}x{slices[0].shape[0]}; "
                                "all frames must have the same size")
            slices.append(sl)
        return np.stack(slices)
