"""TIFF stacks (one page per z slice, or an ImageJ hyperstack) via tifffile.

Spacing is read the way ImageJ/Fiji store it: x and y from the resolution
tags (pixels per unit), z from the ImageJ description's ``spacing``, the unit
from its ``unit``. Plain TIFFs with a ResolutionUnit of inch or centimetre
are converted to millimetres. volwarp also stores its exact spacing, origin
and direction (keys ``volwarp_spacing``, ``volwarp_origin``,
``volwarp_direction``) so that a round trip keeps the geometry to the bit,
since TIFF resolutions are rationals.

ImageJ can only hold uint8, int16, uint16 and float32 stacks; other types are
written as plain multi-page TIFFs with the same resolution tags and the
geometry in tifffile's JSON description.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import FormatError
from ..volume import Volume
from .atomic import atomic_output
from .common import check_dtype, ensure_fits_in_memory, native, voxel_count, with_byte_order

_IMAGEJ_TYPES = ("uint8", "int16", "uint16", "float32")
_UNIT_TO_MM = {"inch": 25.4, "centimeter": 10.0, "millimeter": 1.0, "micrometer": 1e-3}


def _floats(value, n, where, name):
    if isinstance(value, str):
        value = value.replace(",", " ").split()
    try:
        out = [float(v) for v in value]
    except (TypeError, ValueError):
        raise FormatError(f"{where}: cannot read {name} {value!r}") from None
    if len(out) != n:
        raise FormatError(f"{where}: {name} must have {n} values")
    return out


def read_tiff(path: str | os.PathLike) -> Volume:
    import tifffile

    where = str(path)
    try:
        tif = tifffile.TiffFile(path)
    except (OSError, ValueError, tifffile.TiffFileError) as exc:
        raise FormatError(f"{where}: not a readable TIFF ({exc})") from None
    with tif:
        pages = tif.pages
        if len(pages) == 0:
            raise FormatError(f"{where}: TIFF has no pages")
        first = pages.first
        shape0, dtype0 = first.shape, first.dtype
        if first.samplesperpixel > 1:
            raise FormatError(f"{where}: TIFF has {first.samplesperpixel} samples per pixel; "
                              "volwarp reads one-channel stacks")
        for i, page in enumerate(pages):
            if page.shape != shape0 or page.dtype != dtype0:
                raise FormatError(f"{where}: page {i} has shape {page.shape} {page.dtype}, "
                                  f"page 0 has {shape0} {dtype0}; all slices must match")
        if dtype0 is None:
            raise FormatError(f"{where}: unsupported TIFF sample format")
        check_dtype(dtype0, where)
        ny, nx = shape0[-2], shape0[-1]
        nz = len(pages)
        ensure_fits_in_memory(voxel_count((nx, ny, nz)) * dtype0.itemsize,
                              f"{where} ({nx}x{ny}x{nz} {dtype0.name})")
        try:
            data = tif.asarray(key=range(nz)) if nz > 1 else first.asarray()
        except Exception as exc:  # tifffile raises many types for damaged files
            raise FormatError(f"{where}: cannot read TIFF data ({exc})") from None
        data = np.asarray(data).reshape(nz, ny, nx)
        meta: dict = {}
        spacing = [1.0, 1.0, 1.0]
        origin = [0.0, 0.0, 0.0]
        direction = np.eye(3)
        extra = {}
        ij = tif.imagej_metadata
        if ij:
            extra = ij
            for key in ("channels", "frames"):
                if int(ij.get(key, 1)) > 1:
                    raise FormatError(f"{where}: ImageJ hyperstack has {ij[key]} {key}; "
                                      "volwarp reads single-channel, single-frame stacks")
            if ij.get("unit"):
                meta["unit"] = str(ij["unit"])
            if "spacing" in ij:
                spacing[2] = float(ij["spacing"])
        elif tif.shaped_metadata:
            extra = tif.shaped_metadata[0]
            if "unit" in extra:
                meta["unit"] = str(extra["unit"])
        scale = 1.0
        tags = first.tags
        if not ij and "ResolutionUnit" in tags:
            unit = {2: "inch", 3: "centimeter"}.get(int(tags["ResolutionUnit"].value))
            if unit and "volwarp_spacing" not in extra:
                scale = _UNIT_TO_MM[unit]
                meta["unit"] = "mm"
        for axis, tag in ((0, "XResolution"), (1, "YResolution")):
            if tag in tags:
                num, den = tags[tag].value
                if num > 0 and den > 0:
                    spacing[axis] = scale * den / num
        if "volwarp_spacing" in extra:
            spacing = _floats(extra["volwarp_spacing"], 3, where, "volwarp_spacing")
        elif "spacing" in extra and not ij and not isinstance(extra["spacing"], (int, float)):
            spacing = _floats(extra["spacing"], 3, where, "spacing")
        if "volwarp_origin" in extra:
            origin = _floats(extra["volwarp_origin"], 3, where, "volwarp_origin")
        if "volwarp_direction" in extra:
            direction = np.array(_floats(extra["volwarp_direction"], 9, where,
                                         "volwarp_direction")).reshape(3, 3)
        space = extra.get("volwarp_space") or None
        if "volwarp_spacing" in extra:
            # written by volwarp: its key/values are exactly the volume's meta
            try:
                meta = dict(json.loads(extra.get("volwarp_meta", "{}")))
            except (TypeError, ValueError):
                raise FormatError(f"{where}: volwarp_meta is not valid JSON") from None
    try:
        return Volume(native(data), spacing=spacing, origin=origin, direction=direction,
                      space=space, meta=meta)
    except Exception as exc:
        raise FormatError(f"{where}: {exc}") from None


def write_tiff(vol: Volume, path: str | os.PathLike, *, compress: bool = False,
               byte_order: str = "little") -> None:
    import tifffile

    path = Path(path)
    dtype = check_dtype(vol.data.dtype, str(path))
    meta = dict(vol.meta)
    unit = str(meta.get("unit", "mm"))
    geometry = {
        "volwarp_spacing": " ".join(repr(float(v)) for v in vol.spacing),
        "volwarp_origin": " ".join(repr(float(v)) for v in vol.origin),
        "volwarp_direction": " ".join(repr(float(v)) for v in vol.direction.ravel()),
    }
    if vol.space:
        geometry["volwarp_space"] = vol.space
    if meta:
        geometry["volwarp_meta"] = json.dumps(meta, sort_keys=True, default=str)
    data = with_byte_order(vol.data, byte_order)
    kwargs = dict(
        byteorder="<" if byte_order == "little" else ">",
        resolution=(1.0 / vol.spacing[0], 1.0 / vol.spacing[1]),
        compression="zlib" if compress else None,
        software="volwarp",
    )
    with atomic_output(path) as tmp:
        if dtype.name in _IMAGEJ_TYPES:
            tifffile.imwrite(tmp, data, imagej=True,
                             metadata={"axes": "ZYX", "spacing": float(vol.spacing[2]),
                                       "unit": unit, **geometry}, **kwargs)
        else:
            tifffile.imwrite(tmp, data, metadata={"axes": "ZYX", "unit": unit, **geometry},
                             resolutionunit="NONE", **kwargs)
