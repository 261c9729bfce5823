"""DICOM SEG (BINARY, FRACTIONAL, LABELMAP) as label maps, read and written with highdicom.

Reading (:func:`read_seg`). The label map lies in the SEG's own geometry: the
grid of its frames (highdicom's volume of the frame positions, as ITK/dcmqi
read it), in LPS with volwarp's axes (x the row cosine, y the column cosine, z
the slice normal row x column, as :func:`~volwarp_cli.io.dicom.read_dicom`
reads the series the SEG was made from). Frames a SEG leaves out because they
are empty are zeros, never missing slices. With ``reference`` (the image series)
the label map is on that series' whole grid instead, each frame placed on the
slice at its own position: the SEG needs no grid of its own then (frames on
some slices only, without the optional SpacingBetweenSlices, have none, and
read only this way). Values: BINARY and FRACTIONAL segments give their segment
numbers (a FRACTIONAL voxel is in its segment when its value is at least half
the maximum); a LABELMAP SEG gives its pixel values. ``segment=N`` gives segment N
as a 0/1 mask; overlapping segments without it are an error naming the option.

Speed (:func:`_fast_frames`). highdicom's ``segread`` builds a frame table from
every per-frame functional group item through pydicom's attribute access, and
``get_volume`` assembles the frames one by one: 2-3 s for a BINARY SEG of a few
thousand frames (highdicom #202: minutes for 98 segments). The common SEG, an
uncompressed multi-frame with a shared orientation and pixel spacing and one
plane position per frame, is read from pydicom's data set directly: the frame
positions by element tags, the grid by highdicom's own
:func:`highdicom.spatial.get_volume_positions` (the rule ``get_volume`` uses,
missing and repeated positions allowed, SpacingBetweenSlices as the hint), and
a BINARY SEG's bit-packed frames unpacked only where a byte is non-zero, all
frames at once. With a reference, compressed frames are read the same way once
highdicom has decoded them. Anything else (compressed frames without a
reference, tiled images, per-frame orientations) goes through highdicom; the
two give the same label map (``tests/test_dicom_seg_fast.py``,
``tests/test_dicom_seg_irregular.py``).

Writing (:func:`write_seg`): one segment per non-zero label of a label map
that lies on the reference series' grid, with new SOP and Series UIDs.

Each segment's label, codes, algorithm and colour are recorded in the label
map's key/values when it is read, and taken back from them when it is written
(:mod:`.segment_keys`).
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import BadUsage, FormatError, VolwarpError
from ..volume import LPS, Volume
from .common import make_volume
from .segment_keys import (
    NESTED_KEY,
    label_descriptions,
    nested_labels,
    seg_algorithm,
    seg_colour,
    seg_keys,
)

SEG_SOP = "1.2.840.10008.5.1.4.1.1.66.4"
LABELMAP_SEG_SOP = "1.2.840.10008.5.1.4.1.1.66.7"
SEG_SOPS = (SEG_SOP, LABELMAP_SEG_SOP)

#: position tolerance, in voxels, for a SEG frame to lie on a reference slice
_ON_GRID = 1e-2


def _one_line(exc) -> str:
    return " ".join(str(exc).split())[:300]


#: What reading a SEG holds, measured (peak less the process before: 5-108 MB files of
#: 700-12,544 frames): its pixel data as read, each frame's functional groups as pydicom
#: objects once parsed (about 7 KiB a frame), counted before the file is read; then the
#: label map, before it is made (:func:`_fast_frames`); each with :data:`READ_MARGIN`
READ_FRAME_BYTES = 8 << 10
READ_MARGIN = 16 << 20


def open_seg(path: str | os.PathLike):
    """The pydicom data set of the SEG at ``path`` (pixels included), or a FormatError.

    Its SOP class must be a SEG's and its SegmentSequence readable;
    :func:`as_highdicom` makes highdicom's Segmentation of it where needed.
    """
    import pydicom

    from ..memory import ensure_fits_in_memory, human_bytes

    force = str(path).lower().endswith(".dcm")
    try:
        head = pydicom.dcmread(str(path), force=force, stop_before_pixels=True)
        frames = int(head.get("NumberOfFrames", 1) or 1)
        del head
        size = os.path.getsize(path)
        ensure_fits_in_memory(size + frames * READ_FRAME_BYTES + READ_MARGIN,
                              f"reading {path} ({human_bytes(size)}, {frames} frames)")
        ds = pydicom.dcmread(str(path), force=force)
        uid = str(ds.get("SOPClassUID", ""))
        if uid not in SEG_SOPS:
            raise ValueError(f"SOPClassUID {uid or 'missing'} is not a SEG's")
        for item in ds.SegmentSequence:
            int(item.SegmentNumber)
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except Exception as exc:  # malformed SEGs raise many types in pydicom
        if isinstance(exc, VolwarpError):
            raise
        raise FormatError(f"{path}: not a readable DICOM SEG ({type(exc).__name__}: "
                          f"{_one_line(exc)})") from None
    return ds


def as_highdicom(ds, where: str):
    """The highdicom Segmentation of a SEG data set, or a FormatError naming the file."""
    import highdicom as hd

    if isinstance(ds, hd.seg.Segmentation):
        return ds
    try:
        return hd.seg.Segmentation.from_dataset(ds, copy=False)
    except Exception as exc:  # malformed SEGs raise many types in highdicom and pydicom
        raise FormatError(f"{where}: not a readable DICOM SEG ({type(exc).__name__}: "
                          f"{_one_line(exc)})") from None


def _code(seq) -> dict | None:
    if not seq:
        return None
    item = seq[0]
    return {"value": str(item.get("CodeValue", item.get("LongCodeValue", ""))),
            "scheme": str(item.get("CodingSchemeDesignator", "")),
            "meaning": str(item.get("CodeMeaning", ""))}


def describe_segments(seg) -> list[dict]:
    """Each segment's number, label and coded category and type (for ``volwarp info``)."""
    out = []
    for item in seg.SegmentSequence:
        out.append({"number": int(item.SegmentNumber),
                    "label": str(item.get("SegmentLabel", "")),
                    "category": _code(item.get("SegmentedPropertyCategoryCodeSequence")),
                    "type": _code(item.get("SegmentedPropertyTypeCodeSequence")),
                    "algorithm_type": str(item.get("SegmentAlgorithmType", ""))})
    return out


def seg_type(seg) -> str:
    """BINARY, FRACTIONAL or LABELMAP."""
    return str(seg.SegmentationType)


def _label_dtype(top: int) -> np.dtype:
    for t in (np.uint8, np.uint16, np.uint32):
        if top <= np.iinfo(t).max:
            return np.dtype(t)
    raise VolwarpError(f"label {top} does not fit uint32")


def _frames_array(seg, where: str, segment: int | None,
                  reference=None) -> tuple[np.ndarray, np.ndarray]:
    """(samples [slice, row, column], highdicom's affine) of the SEG's own grid.

    Frames with no regular grid of their own are an error that names
    ``--reference SERIES`` when no ``reference`` was given (it reads them),
    unless the frames lie on a gantry-tilted stack, which no reference read as
    stored is (:func:`_tilt_drift`).
    """
    kind = seg_type(seg)
    numbers = [int(s.SegmentNumber) for s in seg.SegmentSequence]
    if segment is not None and segment not in numbers:
        raise BadUsage(f"{where}: --segment {segment}: the SEG has segments "
                       f"{' '.join(map(str, numbers))}")
    seg = as_highdicom(seg, where)
    try:
        if kind == "LABELMAP":
            vol = seg.get_volume(combine_segments=True)
            arr = np.asarray(vol.array)
            if segment is not None:
                arr = (arr == segment).astype(np.uint8)
            else:
                arr = arr.astype(_label_dtype(max(numbers, default=0)), copy=False)
        elif kind == "FRACTIONAL":
            arr, vol = _fractional(seg, numbers if segment is None else [segment], where)
            if segment is not None:
                arr = (arr > 0).astype(np.uint8)
        else:  # BINARY
            if segment is not None:
                vol = seg.get_volume(segment_numbers=[segment])
                arr = np.asarray(vol.array)[..., 0].astype(np.uint8)
            else:
                vol = seg.get_volume(combine_segments=True,
                                     dtype=_label_dtype(max(numbers, default=0)))
                arr = np.asarray(vol.array)
    except RuntimeError as exc:
        if "overlap" in str(exc):
            raise _overlap_error(where, numbers) from None
        if "regularly-spaced" in str(exc) and reference is None:
            drift = _tilt_drift(seg)
            if drift > 0.01:
                raise FormatError(
                    f"{where}: its frames lie on a gantry-tilted stack (their positions move "
                    f"{drift:.3g} mm within the slice plane), so the SEG has no grid of its own, "
                    "and the series it was drawn on would be resampled for the tilt, which "
                    "--reference does not do: volwarp cannot place these frames") from None
            raise FormatError(
                f"{where}: {_one_line(exc).rstrip('.')} (its frames lie on some slices only and "
                "no SpacingBetweenSlices gives their spacing, or they are irregular), so the SEG "
                "has no grid of its own: --reference SERIES (the series it was drawn on) reads "
                "it on that series' grid, each frame on its slice") from None
        raise FormatError(f"{where}: {_one_line(exc)}") from None
    except (ValueError, KeyError, AttributeError) as exc:
        raise FormatError(f"{where}: cannot assemble the SEG's frames into a volume "
                          f"({type(exc).__name__}: {_one_line(exc)})") from None
    if arr.ndim == 4:  # (a one-channel highdicom volume)
        arr = arr[..., 0]
    return np.ascontiguousarray(arr), np.asarray(vol.affine, dtype=np.float64)


def _tilt_drift(seg) -> float:
    """How far (mm) the frames' positions move within the slice plane; 0 if unknown.

    Frames of an untilted stack differ along the normal only; a SEG drawn on a
    gantry-tilted series carries that series' sheared positions.
    """
    from .dicom._geometry import inplane_offsets

    try:
        frames = seg.PerFrameFunctionalGroupsSequence
        shared = seg.SharedFunctionalGroupsSequence[0]
        plane = shared if "PlaneOrientationSequence" in shared else frames[0]
        iop = np.array([float(v) for v in
                        plane.PlaneOrientationSequence[0].ImageOrientationPatient])
        pos = np.array([[float(v) for v in f.PlanePositionSequence[0].ImagePositionPatient]
                        for f in frames])
    except (AttributeError, IndexError, KeyError, TypeError, ValueError):
        return 0.0
    normal = np.cross(iop[:3], iop[3:])
    if len(pos) < 2 or not np.linalg.norm(normal) > 0 or not np.all(np.isfinite(pos)):
        return 0.0
    return float(np.linalg.norm(inplane_offsets(pos, normal / np.linalg.norm(normal)),
                                axis=1).max())


# tags of the per-frame functional groups read by _fast_frames
_PLANE_POSITION = 0x00209113
_IMAGE_POSITION = 0x00200032
_SEGMENT_IDENTIFICATION = 0x0062000A
_REFERENCED_SEGMENT = 0x0062000B


def _fast_frames(ds, where: str, segment: int | None, reference=None):
    """``(data [z, y, x], spacing, origin, direction)`` of a common SEG, or None (use highdicom).

    The module docstring says which SEGs, and why; the values and the grid are
    those of :func:`_frames_array` and :func:`_to_volwarp_axes`. With
    ``reference``, the data lie on the reference grid, each frame on the slice at
    its own position (:func:`_reference_slices`), whatever the spacing of the
    frames: the same label map as :func:`_onto_reference` of the SEG's own grid
    where the SEG has one. Compressed frames are then decoded by highdicom.
    """
    from pydicom.uid import UID

    kind = seg_type(ds)
    numbers = [int(s.SegmentNumber) for s in ds.SegmentSequence]
    if segment is not None and segment not in numbers:
        raise BadUsage(f"{where}: --segment {segment}: the SEG has segments "
                       f"{' '.join(map(str, numbers))}")
    syntax = UID(str(getattr(ds, "file_meta", {}).get("TransferSyntaxUID", "")))
    if kind not in ("BINARY", "FRACTIONAL", "LABELMAP") or not syntax or \
            (syntax.is_compressed and reference is None) or "PixelData" not in ds or \
            "TotalPixelMatrixRows" in ds or int(ds.get("SamplesPerPixel", 1)) != 1:
        return None
    try:
        shared = ds.SharedFunctionalGroupsSequence[0]
        orientation = [float(v) for v in
                       shared.PlaneOrientationSequence[0].ImageOrientationPatient]
        measures = shared.PixelMeasuresSequence[0]
        pixel_spacing = [float(v) for v in measures.PixelSpacing]
        hint = measures.get("SpacingBetweenSlices")
        hint = float(hint) if hint not in (None, "") and float(hint) > 0 else None
        per_frame = ds.PerFrameFunctionalGroupsSequence
        n_frames = int(ds.get("NumberOfFrames", 1))
        if len(per_frame) != n_frames or len(orientation) != 6 or len(pixel_spacing) != 2:
            return None
        positions = np.empty((n_frames, 3))
        seg_of = np.zeros(n_frames, np.int64)
        # A SEG of one segment may name it once, in the shared functional groups.
        # Read here with a reference only: without one, highdicom's grid is kept (the
        # same grid, but its spacing differs in the last bit, and outputs are bytes).
        one = shared[_SEGMENT_IDENTIFICATION] if reference is not None and \
            _SEGMENT_IDENTIFICATION in shared else None
        for i, item in enumerate(per_frame):
            positions[i] = [float(v) for v in item[_PLANE_POSITION].value[0][_IMAGE_POSITION].value]
            if kind != "LABELMAP":
                ident = item[_SEGMENT_IDENTIFICATION] if _SEGMENT_IDENTIFICATION in item else one
                if ident is None:
                    return None
                seg_of[i] = int(ident.value[0][_REFERENCED_SEGMENT].value)
    except (AttributeError, IndexError, KeyError, TypeError, ValueError):
        return None  # (something less common: highdicom reads it, or says what is wrong)
    rows, cols = int(ds.Rows), int(ds.Columns)
    bits = int(ds.BitsAllocated)
    if (kind == "BINARY") != (bits == 1) or bits not in (1, 8, 16) or not np.all(
            np.isfinite(positions)):
        return None
    import highdicom as hd

    row_cos, col_cos = np.array(orientation[:3]), np.array(orientation[3:])
    row_cos /= np.linalg.norm(row_cos)
    col_cos /= np.linalg.norm(col_cos)
    normal = np.cross(row_cos, col_cos)
    normal /= np.linalg.norm(normal)
    direction = np.column_stack([row_cos, col_cos, normal])
    off_grid = ()
    if reference is not None:
        g = reference.grid
        index, off_grid = _reference_slices(
            ds, positions, (rows, cols), np.array([pixel_spacing[1], pixel_spacing[0]]),
            direction, kind, reference, where)
        n = g.shape[0] + len(off_grid)  # (a scratch slice for each frame off the grid)
        spacing, first, direction = g.spacing, g.origin, g.direction
    else:
        spacing_z, index = hd.spatial.get_volume_positions(
            positions, orientation, allow_missing_positions=True,
            allow_duplicate_positions=kind != "LABELMAP", spacing_hint=hint)
        if index is None:
            return None  # (highdicom's get_volume says why these are not a volume)
        index = np.asarray(index, np.int64)
        n = int(index.max()) + 1
        along = positions @ normal
        if n > 1 and along[index == index.max()][0] < along[index == 0][0]:
            index = (n - 1) - index  # volwarp's z runs along the normal
        first = positions[index == 0][0]
        spacing = np.array([pixel_spacing[1], pixel_spacing[0],
                            spacing_z if n > 1 else _single_spacing(ds)], dtype=np.float64)
    npix = rows * cols
    from ..memory import ensure_fits_in_memory

    item = 1 if segment is not None else _label_dtype(max(numbers, default=0)).itemsize
    # (compressed: highdicom's decoded frames, a byte a pixel at least, and their bytes)
    decoded = n_frames * npix * max(1, bits // 8) + -(-n_frames * npix * bits // 8) \
        if syntax.is_compressed else 0
    ensure_fits_in_memory(n * npix * item + decoded + READ_MARGIN,
                          f"{where}: its frames as a {cols}x{rows}x{n} label map")
    raw = _decoded(ds, kind, bits, where) if syntax.is_compressed else ds.PixelData
    need = -(-n_frames * npix * bits // 8)  # (BINARY: bits run on across frames)
    if len(raw) < need:
        raise FormatError(f"{where}: the pixel data is truncated: {n_frames} frames of "
                          f"{cols}x{rows} {kind} pixels need {need} bytes, the file holds "
                          f"{len(raw)}")
    if kind == "BINARY":
        data = _binary_labels(raw, n_frames, npix, n, index, seg_of, segment, numbers, where)
    else:
        dtype = np.dtype(f"<u{bits // 8}")
        frames = np.frombuffer(raw, dtype, n_frames * npix).reshape(n_frames, npix)
        if kind == "LABELMAP":
            data = np.zeros((n, npix), _label_dtype(max(numbers, default=0)))
            data[index] = frames
            if segment is not None:
                data = (data == segment).astype(np.uint8)
        else:
            data = _fractional_labels(ds, frames, n, index, seg_of, segment, numbers, where)
    if reference is not None:
        nz = reference.grid.shape[0]
        for j, (f, ijk) in enumerate(off_grid):
            if data[nz + j].any():  # (a frame with nothing in the map may lie anywhere)
                raise VolwarpError(f"{where}: its frame {f + 1} at {_xyz(positions[f])} mm is "
                                   f"not a slice of the reference series in {reference.path} "
                                   f"(index {_xyz(ijk)})")
        data, n = data[:nz], nz
    return data.reshape(n, rows, cols), spacing, first, direction


def _reference_slices(ds, positions, shape_yx, spacing_xy, direction, kind, reference,
                      where: str):
    """``(index, off_grid)``: the reference slice of each frame, by its own position.

    The frame of reference and the images (size, pixel spacing, orientation) must
    be the reference's, as :func:`_onto_reference` checks. A frame within
    ``_ON_GRID`` voxel of a slice's pixel (0, 0) goes to that slice; each other
    frame gets a scratch slice after the grid's (``off_grid`` lists them as
    ``(frame, fractional index)``), an error only if it puts something in the map.
    Two frames of a LABELMAP SEG on one slice are an error (one frame a slice).
    """
    check_frame_of_reference(where, str(ds.get("FrameOfReferenceUID", "")), reference)
    _check_images(where, shape_yx, spacing_xy, direction, reference)
    g = reference.grid
    nz = g.shape[0]
    ijk = g.world_to_index(positions).reshape(-1, 3)
    rk = np.rint(ijk)
    on = (np.abs(ijk - rk).max(axis=1) <= _ON_GRID) & (rk[:, 0] == 0) & (rk[:, 1] == 0) & \
        (rk[:, 2] >= 0) & (rk[:, 2] < nz)
    index = np.where(on, rk[:, 2], 0).astype(np.int64)
    off = np.flatnonzero(~on)
    index[off] = nz + np.arange(off.size)
    if kind == "LABELMAP":
        slices, count = np.unique(index[on], return_counts=True)
        if np.any(count > 1):
            k = int(slices[count > 1][0])
            frames = np.flatnonzero(index == k) + 1
            raise FormatError(f"{where}: frames {frames[0]} and {frames[1]} of the LABELMAP SEG "
                              f"are both on slice {k} of the reference series in "
                              f"{reference.path} (a LABELMAP SEG has one frame a slice)")
    return index, tuple((int(f), ijk[f]) for f in off)


def _decoded(ds, kind: str, bits: int, where: str) -> bytes:
    """The frames of a compressed SEG as uncompressed PixelData (BINARY: bit-packed)."""
    seg = as_highdicom(ds, where)
    try:
        frames = np.asarray(seg.get_stored_frames())
    except Exception as exc:  # (the codecs raise many types)
        raise FormatError(f"{where}: cannot decode the SEG's frames ({type(exc).__name__}: "
                          f"{_one_line(exc)})") from None
    if kind == "BINARY":
        return np.packbits(frames.reshape(-1) != 0, bitorder="little").tobytes()
    return np.ascontiguousarray(frames, f"<u{bits // 8}").tobytes()


def _binary_labels(raw: bytes, n_frames: int, npix: int, n: int, index, seg_of, segment,
                   numbers, where: str) -> np.ndarray:
    """A BINARY SEG's label map [slice, pixel] from its bit-packed frames.

    The frames' bits run on from frame to frame, the first pixel in the lowest
    bit of a byte (PS3.5 8.1.1). Frames of whole bytes (rows x columns a multiple
    of 8, the usual case) are unpacked one by one over the span of their bytes
    holding a set bit; others at once, only their bytes with a set bit.
    """
    buf = np.frombuffer(raw, np.uint8, -(-n_frames * npix // 8))
    top = max(numbers, default=0)
    out = np.zeros((n, npix), np.uint8 if segment is not None else _label_dtype(top))
    if npix % 8 == 0:
        frames = buf.reshape(n_frames, npix // 8)
        for f in range(n_frames):
            if segment is not None and seg_of[f] != segment:
                continue
            hit = np.flatnonzero(frames[f])
            if not hit.size:
                continue
            lo, hi = int(hit[0]), int(hit[-1]) + 1
            bits = np.unpackbits(frames[f, lo:hi], bitorder="little").view(bool)
            target = out[index[f], lo * 8:hi * 8]
            value = 1 if segment is not None else seg_of[f]
            if segment is None:
                was = target[bits]
                if np.any((was != 0) & (was != value)):  # a voxel two segments set
                    raise _overlap_error(where, numbers)
            target[bits] = value
        return out
    hit = np.flatnonzero(buf)
    bits = np.unpackbits(buf[hit], bitorder="little").reshape(-1, 8)
    byte, bit = np.nonzero(bits)
    g = hit[byte] * 8 + bit
    g = g[g < n_frames * npix]
    frame = g // npix
    flat = index[frame] * npix + (g - frame * npix)
    out = out.reshape(-1)
    if segment is not None:
        out[flat[seg_of[frame] == segment]] = 1
        return out.reshape(n, npix)
    label = seg_of[frame].astype(out.dtype)
    out[flat] = label
    if np.any(out[flat] != label):  # a voxel two segments set
        raise _overlap_error(where, numbers)
    return out.reshape(n, npix)


def _fractional_labels(ds, frames, n: int, index, seg_of, segment, numbers,
                       where: str) -> np.ndarray:
    """A FRACTIONAL SEG's label map [slice, pixel]: a segment where its value >= half the maximum."""
    top = int(ds.get("MaximumFractionalValue", 255))
    inside = frames.astype(np.int64) * 2 >= top
    if segment is not None:
        out = np.zeros((n, frames.shape[1]), np.uint8)
        for f in np.flatnonzero(seg_of == segment):
            out[index[f]] |= inside[f]
        return out
    out = np.zeros((n, frames.shape[1]), _label_dtype(max(numbers, default=0)))
    for f in range(len(frames)):
        m = inside[f]
        row = out[index[f]]
        if np.any((row[m] != 0) & (row[m] != seg_of[f])):
            raise _overlap_error(where, numbers)
        row[m] = seg_of[f]
    return out


class SegmentsOverlap(VolwarpError):
    """Segments share a voxel: no one label map holds them (``info`` still lists them)."""


def _overlap_error(where: str, numbers) -> SegmentsOverlap:
    return SegmentsOverlap(f"{where}: segments overlap (a voxel in two segments), so one label map "
                        "cannot hold them: read one segment as a 0/1 mask with --segment N "
                        f"(segments {' '.join(map(str, numbers))})")


def _fractional(seg, numbers, where: str):
    """A FRACTIONAL SEG's segments, each thresholded at half the maximum, combined."""
    out = None
    vol = None
    for n in numbers:
        vol = seg.get_volume(segment_numbers=[n], rescale_fractional=True)
        inside = np.asarray(vol.array)[..., 0] >= 0.5
        if out is None:
            out = np.zeros(inside.shape, _label_dtype(max(numbers)))
        if np.any(out[inside]):
            raise _overlap_error(where, [int(s.SegmentNumber) for s in seg.SegmentSequence])
        out[inside] = n
    return out, vol


def _to_volwarp_axes(arr: np.ndarray, affine: np.ndarray, single_spacing: float):
    """The [z, y, x] samples and geometry of highdicom's (slice, row, column) array and affine.

    z runs along the slice normal (row cosine x column cosine), as the series
    reader orders slices, so a SEG lies on the grid its source series is read on.
    """
    col_step, row_step, slice_step = affine[:3, 2], affine[:3, 1], affine[:3, 0]
    row_cos = col_step / np.linalg.norm(col_step)   # along a row: the x index
    col_cos = row_step / np.linalg.norm(row_step)   # down a column: the y index
    normal = np.cross(row_cos, col_cos)
    normal /= np.linalg.norm(normal)
    origin = affine[:3, 3].copy()
    n = arr.shape[0]
    if n > 1:
        if float(slice_step @ normal) < 0:
            arr = arr[::-1]
            origin = origin + (n - 1) * slice_step
        sz = float(np.linalg.norm(slice_step))
    else:
        sz = single_spacing
    spacing = np.array([np.linalg.norm(col_step), np.linalg.norm(row_step), sz])
    return np.ascontiguousarray(arr), spacing, origin, np.column_stack([row_cos, col_cos, normal])


def _pixel_measure(seg, keyword: str) -> float | None:
    """A positive value of the SEG's shared PixelMeasuresSequence (None: none, or not one)."""
    try:
        v = seg.SharedFunctionalGroupsSequence[0].PixelMeasuresSequence[0].get(keyword)
        return float(v) if v not in (None, "") and float(v) > 0 else None
    except (AttributeError, IndexError, KeyError, ValueError, TypeError):
        return None


def _single_spacing(seg) -> float:
    return _pixel_measure(seg, "SpacingBetweenSlices") or _pixel_measure(seg, "SliceThickness") \
        or 1.0


def _warn_gapped(seg, spacing_z: float, n_slices: int, where: str) -> None:
    """Say when frames placed without SpacingBetweenSlices lie k >= 2 slice thicknesses apart.

    A SEG may leave out its empty frames: frames on slices 1, 3 and 5 of a
    2.5 mm series then give a grid of 5 mm, every other slice of the series
    missing, and nothing in the SEG tells that from a gapped acquisition
    (which is why this is not refused).
    """
    thickness = _pixel_measure(seg, "SliceThickness")
    if n_slices < 2 or thickness is None or _pixel_measure(seg, "SpacingBetweenSlices"):
        return
    ratio = spacing_z / thickness
    k = round(ratio)
    if k >= 2 and abs(ratio - k) <= 1e-3 * k:
        from ..progress import log

        log.warning("warning: %s: its frames lie %g mm apart, %d times its SliceThickness of "
                    "%g mm, and no SpacingBetweenSlices gives the series' spacing: if it left "
                    "out empty frames between them, the label map's slices are %g mm apart "
                    "where the series' are %g mm; --reference SERIES places each frame on its "
                    "slice exactly", where, spacing_z, k, thickness, spacing_z, thickness)


def _meta(seg, keep_phi: bool) -> dict:
    from .dicom._scan import PHI_TAGS

    keys = ("Modality", "SeriesDescription", "SeriesNumber", "StudyInstanceUID",
            "SeriesInstanceUID", "FrameOfReferenceUID", "SOPClassUID", "SegmentationType",
            "ContentLabel") + (PHI_TAGS if keep_phi else ())
    meta = {f"DICOM_{k}": str(seg.get(k)) for k in keys if seg.get(k) not in (None, "")}
    refs = referenced_series(seg)
    if refs:
        meta["DICOM_ReferencedSeriesInstanceUID"] = "\\".join(refs)
    return meta


def referenced_series(ds) -> tuple[str, ...]:
    """The SeriesInstanceUIDs a SEG's ReferencedSeriesSequence names."""
    return tuple(str(item.SeriesInstanceUID) for item in ds.get("ReferencedSeriesSequence", [])
                 if "SeriesInstanceUID" in item)


def read_seg(path: str | os.PathLike, *, segment: int | None = None, reference=None,
             keep_phi: bool = False, seg=None) -> Volume:
    """A SEG as a label map (or segment ``segment`` as a 0/1 mask); rules: the module docstring.

    ``reference``: a :class:`~volwarp_cli.io.dicom.ReferenceSeries` whose grid the
    result lies on (its frame of reference must be the SEG's). ``seg``: the file's
    highdicom Segmentation, when the caller has opened it.
    """
    where = str(path)
    seg = open_seg(path) if seg is None else seg
    fast = _fast_frames(seg, where, segment, reference)
    if fast is not None:  # (with a reference: on its grid already)
        data, spacing, origin, direction = fast
    else:
        arr, affine = _frames_array(seg, where, segment, reference)
        data, spacing, origin, direction = _to_volwarp_axes(arr, affine, _single_spacing(seg))
        if reference is not None:
            data = _onto_reference(data, spacing, origin, direction, seg, reference, where)
            g = reference.grid
            spacing, origin, direction = g.spacing, g.origin, g.direction
    if reference is None:
        _warn_gapped(seg, float(spacing[2]), data.shape[0], where)
    meta = _meta(seg, keep_phi)
    if segment is not None:
        meta["DICOM_Segment"] = str(segment)
    meta.update(seg_keys(seg, segment))  # (what each label is: written back by build_seg)
    return make_volume(where, data, spacing=spacing, origin=origin, direction=direction,
                       space=LPS, file_space=LPS, meta=meta)


def check_frame_of_reference(where: str, own: str, reference) -> None:
    """The segmentation and its reference series must share a frame of reference."""
    if own and reference.frame_of_reference_uid and own != reference.frame_of_reference_uid:
        raise VolwarpError(f"{where}: its frame of reference {own} is not that of the "
                           f"reference series {reference.series_uid} in {reference.path} "
                           f"({reference.frame_of_reference_uid}): give the series it was "
                           "drawn on with --reference")


def _onto_reference(data, spacing, origin, direction, seg, reference, where) -> np.ndarray:
    """The SEG's slices placed on the reference grid (zeros elsewhere)."""
    check_frame_of_reference(where, str(seg.get("FrameOfReferenceUID", "")), reference)
    _check_images(where, data.shape[1:], spacing[:2], direction, reference)
    g = reference.grid
    nz, ny, nx = g.shape
    out = np.zeros((nz, ny, nx), data.dtype)
    for k in range(data.shape[0]):
        ijk = g.world_to_index(origin + direction[:, 2] * spacing[2] * k)
        rk = np.rint(ijk)
        if np.abs(ijk - rk).max() > _ON_GRID or not 0 <= rk[2] < nz or rk[0] != 0 or rk[1] != 0:
            if not data[k].any():
                continue  # an empty slice of the SEG's own grid: nothing to place
            raise VolwarpError(f"{where}: its slice at {_xyz(origin + direction[:, 2] * spacing[2] * k)}"
                               f" mm is not a slice of the reference series in {reference.path} "
                               f"(index {_xyz(ijk)})")
        out[int(rk[2])] = data[k]
    return out


def _check_images(where: str, shape_yx, spacing_xy, direction, reference) -> None:
    """A SEG's frames must be the reference's images: size, pixel spacing, orientation."""
    g = reference.grid
    _, ny, nx = g.shape
    mine = f"{shape_yx[1]}x{shape_yx[0]} pixels of {spacing_xy[0]:g}x{spacing_xy[1]:g} mm"
    theirs = f"{nx}x{ny} pixels of {g.spacing[0]:g}x{g.spacing[1]:g} mm"
    if tuple(shape_yx) != (ny, nx) or not np.allclose(spacing_xy, g.spacing[:2], rtol=1e-4) \
            or not np.allclose(direction[:, :2], g.direction[:, :2], atol=1e-4):
        raise VolwarpError(f"{where}: its frames ({mine}) are not the images of the reference "
                           f"series in {reference.path} ({theirs}, or another orientation)")


def _xyz(v) -> str:
    return " ".join(f"{float(x):.4g}" for x in v)


# -- writing -----------------------------------------------------------------------------

def _grid_text(shape_xyz, spacing, origin, direction) -> str:
    return (f"{'x'.join(str(int(n)) for n in shape_xyz)} voxels, spacing {_xyz(spacing)}, "
            f"origin {_xyz(origin)}, direction "
            + "; ".join(_xyz(r) for r in np.asarray(direction)))


def check_on_reference_grid(vol: Volume, reference, where: str) -> None:
    """A label map written against ``reference`` must lie on its grid (within 1e-3 voxel)."""
    g = reference.grid
    same = vol.data.shape == g.shape
    if same:
        corners = np.array([[0, 0, 0], np.array(vol.shape_xyz) - 1], dtype=np.float64)
        corners = np.vstack([corners, [[1, 0, 0], [0, 1, 0], [0, 0, 1]]])
        off = g.world_to_index(vol.index_to_world(corners)) - g.world_to_index(
            g.index_to_world(corners))
        same = float(np.abs(off).max()) <= 1e-3
    if not same:
        raise VolwarpError(
            f"{where}: the label map's grid ({_grid_text(vol.shape_xyz, vol.spacing, vol.origin, vol.direction)}) "
            f"is not the grid of the reference series in {reference.path} "
            f"({_grid_text(g.shape_xyz, g.spacing, g.origin, g.direction)}): resample it onto "
            "the reference first")


def slice_labels(vol: Volume, where: str) -> tuple[np.ndarray, list[set[int]]]:
    """The non-zero labels of an integer-valued label map (0 is background), and each plane's.

    Sorted int64, and the set of labels of each z plane (what a SEG's frames
    and an RTSTRUCT's contours are made of). Plane by plane: the distinct
    values by a table pass for 8- and 16-bit ids, a float map's test of whole
    numbers on a plane's copies; no whole-size copy beside the map (np.unique
    sorts one).
    """
    from ..samples import distinct_values

    data = vol.data
    if data.dtype.kind not in "iuf":
        raise VolwarpError(f"{where}: cannot write samples of type {data.dtype} as labels")
    per_plane = []
    for plane in data:
        if data.dtype.kind == "f" and (not np.all(np.isfinite(plane))
                                       or not np.array_equal(plane, np.rint(plane))):
            raise VolwarpError(f"{where}: a segmentation is written from a label map: its "
                               "samples must be whole numbers")
        per_plane.append(distinct_values(plane))
    values = np.unique(np.concatenate(per_plane)) if per_plane else np.zeros(0, data.dtype)
    if values.size and values[0] < 0:
        raise VolwarpError(f"{where}: label {values[0]:g} is negative (labels are 0..65535)")
    values = values[values != 0].astype(np.int64)
    if values.size and values[-1] > 65535:
        raise VolwarpError(f"{where}: label {values[-1]} is above 65535 (a DICOM segment "
                           "number is 16 bits)")
    if not values.size:
        raise VolwarpError(f"{where}: the label map has no label (every voxel is 0): nothing "
                           "to write")
    return values, [set(p.astype(np.int64).tolist()) - {0} for p in per_plane]


def check_names(names: dict[int, str], values, names_from: str) -> None:
    """Warn of ``--segments`` rows naming no label of the map (0, or a label it lacks).

    They name nothing: a label id mistyped, or the CSV of another map, would
    otherwise leave the segments it meant with the default names, silently.
    """
    unused = sorted(set(names) - {int(v) for v in values})
    if unused:
        from ..progress import log

        log.warning("warning: %s: label%s %s name%s nothing: the label map has no such "
                    "label%s (0 is its background); check the label column against the map's "
                    "labels (volwarp info)", names_from, "s" if len(unused) > 1 else "",
                    " ".join(map(str, unused)), "" if len(unused) > 1 else "s",
                    "s" if len(unused) > 1 else "")


def read_names(path: str | os.PathLike) -> dict[int, str]:
    """``label,name`` rows of a CSV file (a header row ``label,name`` is skipped)."""
    import csv

    names: dict[int, str] = {}
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except OSError as exc:
        raise BadUsage(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise BadUsage(f"{path}: not a UTF-8 text file (--segments wants label,name rows)") from None
    for n, row in enumerate(rows, 1):
        if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
            continue
        if n == 1 and row[0].strip().lower() == "label":
            continue
        if len(row) < 2 or not row[0].strip().isdigit() or not row[1].strip():
            raise BadUsage(f"{path}:{n}: want 'label,name' (a whole number and a name), got "
                           f"{','.join(row)!r}")
        label = int(row[0])
        if label in names:
            raise BadUsage(f"{path}:{n}: label {label} is named twice")
        names[label] = row[1].strip()
    return names


def _stamp(reference) -> tuple[str, str]:
    """The reference's content (else series, study) date and time: no clock in the output."""
    import pydicom

    ds = pydicom.dcmread(reference.files[0], stop_before_pixels=True)
    for d, t in (("ContentDate", "ContentTime"), ("SeriesDate", "SeriesTime"),
                 ("StudyDate", "StudyTime")):
        if ds.get(d):
            return str(ds.get(d)), str(ds.get(t) or "000000")
    return "19700101", "000000"


def new_uid(*sources) -> str:
    """A new UID made from what the output is made of (the same inputs, the same UID)."""
    from pydicom.uid import generate_uid

    return str(generate_uid(entropy_srcs=[str(s) for s in sources]))


def _content_key(vol: Volume, reference, kind: str, names: dict, described=None) -> str:
    import hashlib

    h = hashlib.sha256(memoryview(np.ascontiguousarray(vol.data)).cast("B"))  # (no copy)
    h.update(repr((str(vol.data.dtype), reference.series_uid, kind, sorted(names.items()))).encode())
    if described:  # (the labels' descriptions from the key/values)
        h.update(repr(sorted(described.items())).encode())
    return h.hexdigest()


def make_timeless(ds, date: str, time: str, uid) -> None:
    """Replace the clock's values and random UIDs highdicom put in ``ds`` (deterministic bytes)."""
    for d, t in (("InstanceCreationDate", "InstanceCreationTime"), ("ContentDate", "ContentTime"),
                 ("SeriesDate", "SeriesTime")):
        if d in ds:
            setattr(ds, d, date)
        if t in ds:
            setattr(ds, t, time)
    for item in ds.get("ContributingEquipmentSequence", []):
        if "ContributionDateTime" in item:
            item.ContributionDateTime = date + time
    mapping = {}
    for seq in ("DimensionOrganizationSequence", "DimensionIndexSequence"):
        for item in ds.get(seq, []):
            old = item.get("DimensionOrganizationUID")
            if old is not None:
                item.DimensionOrganizationUID = mapping.setdefault(str(old),
                                                                   uid(f"dim{len(mapping)}"))


def build_seg(vol: Volume, reference, *, labelmap: bool = False,
              names: dict[int, str] | None = None, where: str = "SEG",
              source: str | None = None, names_from: str | None = None):
    """The highdicom Segmentation of a label map on ``reference``'s grid.

    BINARY (``labelmap`` False): one segment per label, numbered 1..K in
    ascending label order as the standard requires; LABELMAP: the segment
    numbers are the label values. Each segment is named from ``names``, else
    the map's key/values (:mod:`.segment_keys`: also its colour, property
    category and type, and algorithm), else ``label N`` (coded SCT Tissue /
    Tissue, MANUAL, no colour). An outer label of the map's
    ``DICOM_ROI_nested`` is its voxels and those of the labels inside it (a
    BINARY SEG's segments then overlap; a LABELMAP SEG cannot, and warns). SOP
    Instance and Series UIDs are new (never
    copied), made from the label map, its descriptions, the reference series
    and the options. ``source``: the label map's file, named in errors;
    ``names_from``: the file ``names`` came from, named when a row names no
    label (:func:`check_names`).
    """
    import highdicom as hd
    from pydicom.sr.codedict import codes

    from .. import __version__

    check_on_reference_grid(vol, reference, where)
    values, in_slice = slice_labels(vol, where)
    names = dict(names or {})
    check_names(names, values, names_from or where)
    described = label_descriptions(vol.meta, values, source or where)
    key = _content_key(vol, reference, "labelmap" if labelmap else "seg", names, described)

    def uid(what):
        return new_uid(key, what)
    inside = nested_labels(vol.meta, values, source or where)
    from ..memory import ensure_fits_in_memory, human_bytes

    need, frames = seg_memory(vol, values, in_slice, inside, labelmap, reference)
    ensure_fits_in_memory(need, f"{where}: a {'LABELMAP' if labelmap else 'BINARY'} SEG of "
                                f"{frames} frames of {vol.shape_xyz[0]}x{vol.shape_xyz[1]} "
                                f"(beside the {human_bytes(vol.data.nbytes)} label map)")
    if labelmap:
        numbers = [int(v) for v in values]
        pixels = vol.data.astype(_label_dtype(int(values[-1])), copy=False)
        if inside:
            from ..progress import log

            held = "; ".join(f"{o} holds {' '.join(map(str, i))}" for o, i in inside.items())
            log.warning("warning: %s: %s (%s), but a LABELMAP SEG has one segment a voxel: "
                        "the outer segments keep their inner labels' holes; --dicom-type seg "
                        "or rtstruct writes them whole", where, held, NESTED_KEY)
    elif inside:
        pixels = _overlapping_segments(vol.data, values, inside, where)
        numbers = list(range(1, len(values) + 1))
    else:
        numbers = list(range(1, len(values) + 1))
        lut = np.zeros(int(values[-1]) + 1, _label_dtype(len(values)))
        lut[values] = numbers
        ids = vol.data
        if _cast_for_table(ids.dtype):
            ids = ids.astype(_label_dtype(int(values[-1])))
        pixels = lut[ids]
    def description(n: int, v: int):
        d = described.get(v)
        name = names.get(v) or (d and (d.seg_label or d.roi_name)) or f"label {v}"
        algorithm, ident = seg_algorithm(d)
        category = hd.sr.CodedConcept(d.category[1], d.category[0], d.category[2]) \
            if d and d.category else codes.SCT.Tissue
        kind = hd.sr.CodedConcept(d.type[1], d.type[0], d.type[2]) \
            if d and d.type else codes.SCT.Tissue
        return hd.seg.SegmentDescription(
            segment_number=n, segment_label=name[:64], segmented_property_category=category,
            segmented_property_type=kind, algorithm_type=algorithm,
            algorithm_identification=ident, display_color=seg_colour(d))
    try:
        descs = [description(n, int(v)) for n, v in zip(numbers, values, strict=True)]
    except (ValueError, TypeError) as exc:
        raise VolwarpError(f"{source or where}: a segment's description from its key/values "
                           f"is refused by highdicom ({_one_line(exc)})") from None
    sources, pixels = _sources_and_frames(reference, pixels, where)
    try:
        seg = hd.seg.Segmentation(
            source_images=sources, pixel_array=np.ascontiguousarray(pixels),
            segmentation_type="LABELMAP" if labelmap else "BINARY",
            segment_descriptions=descs, series_instance_uid=uid("series"), series_number=901,
            sop_instance_uid=uid("sop"), instance_number=1, manufacturer="volwarp",
            manufacturer_model_name="volwarp", software_versions=str(__version__),
            device_serial_number="0", content_label="VOLWARP", omit_empty_frames=True)
    except (ValueError, TypeError, AttributeError) as exc:
        raise VolwarpError(f"{where}: highdicom refused the segmentation "
                           f"({type(exc).__name__}: {_one_line(exc)})") from None
    make_timeless(seg, *_stamp(reference), uid)
    return seg


#: What building and encoding a SEG adds beyond the arrays :func:`seg_memory` counts:
#: highdicom loads the standard's module table on its first SEG (a JSON file held as 60 MiB
#: of Python objects, more while it is parsed), a byte a voxel of its own copies, and the
#: frames twice (its list of encoded frames and their join). Measured (peak less the
#: process before the build) for 5-42 million voxels, 1-343 labels, 8- and 16-bit maps:
#: 113-136 MiB up to 21 million voxels, 195-271 MiB for 512x512x160, 457 MiB for 256^3
#: of 343 labels (12,544 frames: each frame's functional groups are pydicom objects of
#: about 8 KiB); counted as 112 MiB, those terms and :data:`SEG_FRAME_BYTES` a frame
#: (129-175, 233-354, 503 MiB).
SEG_FIXED_BYTES = 112 << 20
SEG_FRAME_BYTES = 12 << 10


def _cast_for_table(dtype) -> bool:
    """Whether ids of ``dtype`` are cast before they index a table of segment numbers.

    8- and 16-bit unsigned ids index it as they are (numpy casts an index array
    in buffered pieces: no 8-byte copy of the map); others are cast to the
    smallest unsigned type first (:func:`slice_labels`: all in 0..65535).
    """
    return np.dtype(dtype).kind != "u" or np.dtype(dtype).itemsize > 2


def seg_memory(vol: Volume, values, in_slice, inside: dict, labelmap: bool,
               reference) -> tuple[int, int]:
    """The bytes a SEG of ``vol`` needs beside it, and its number of frames.

    Its frames are those :func:`build_seg` writes (empty ones omitted): a frame
    a plane holding any label (LABELMAP), a frame a segment a plane holding it
    or a label nested in it (BINARY, a bit a pixel). Counted: the pixels
    handed to highdicom (a cast of the map or its segment numbers; overlapping
    segments' masks), a multi-frame reference's frame array, the frames twice,
    their functional groups and :data:`SEG_FIXED_BYTES`' part.
    """
    plane = vol.data.shape[1] * vol.data.shape[2]
    n = vol.data.size
    ids = _label_dtype(int(values[-1]))  # (the type the map's ids are cast to)
    if labelmap:
        frames = sum(1 for held in in_slice if held)
        item = ids.itemsize
        pixels = n * item if vol.data.dtype != ids else 0
        encoded = frames * plane * item
    else:
        frames = sum(sum(1 for held in in_slice if not held.isdisjoint([v, *inside.get(v, ())]))
                     for v in values.tolist())
        item = 1 if inside else _label_dtype(len(values)).itemsize
        pixels = n * (len(values) if inside else item)
        if not inside and _cast_for_table(vol.data.dtype):
            pixels += n * ids.itemsize  # (the ids cast first)
        encoded = -(-frames * plane // 8)
    if reference.multi_frame:  # (the pixels placed in the file's frames: one more array)
        pixels += n * (len(values) if inside and not labelmap else item)
    return SEG_FIXED_BYTES + n + pixels + 2 * encoded + SEG_FRAME_BYTES * frames, frames


def _overlapping_segments(data: np.ndarray, values, inside: dict, where: str) -> np.ndarray:
    """Each label's mask [z, y, x, segment], an outer label's holding its nested labels' voxels.

    highdicom takes overlapping BINARY segments as one bool plane a segment, so
    this needs a byte a voxel a label (:func:`seg_memory` counts it).
    """
    masks = np.zeros(data.shape + (len(values),), bool)
    for n, v in enumerate(int(x) for x in values):
        members = [v, *inside.get(v, ())]
        for k, plane in enumerate(data):  # (a plane at a time: isin's copies are the plane's)
            masks[k, ..., n] = np.isin(plane, members)
    return masks


def _sources_and_frames(reference, pixels: np.ndarray, where: str):
    """The ``source_images`` and ``pixel_array`` highdicom takes for a label map on ``reference``.

    A series of single-frame images: each slice's data set (headers only), the
    pixels as they are. An enhanced (multi-frame) image: highdicom takes that
    one data set, and the pixels frame by frame in the file's frame order (which
    need not be volwarp's z order: frames are stored in any order), a frame of
    the file that is no slice of the grid (another stack) empty.
    """
    import pydicom

    if not reference.multi_frame:
        return [pydicom.dcmread(p, stop_before_pixels=True) for p in reference.files], pixels
    files = sorted(set(reference.files))
    if len(files) > 1 or None in reference.frame_numbers:
        raise VolwarpError(f"{where}: the reference series in {reference.path} is made of "
                           f"{len(files)} files holding several frames each: a SEG written "
                           "against a multi-frame image references one file")
    source = pydicom.dcmread(files[0], stop_before_pixels=True)
    frames = np.zeros((int(source.get("NumberOfFrames", 1)),) + pixels.shape[1:], pixels.dtype)
    frames[np.array(reference.frame_numbers, np.int64) - 1] = pixels
    return [source], frames


def write_seg(vol: Volume, path: str | os.PathLike, reference, *, labelmap: bool = False,
              names: dict[int, str] | None = None, source: str | None = None,
              names_from: str | None = None) -> None:
    """Write :func:`build_seg`'s SEG to ``path`` atomically."""
    from .atomic import atomic_output, check_output_path

    check_output_path(path)
    seg = build_seg(vol, reference, labelmap=labelmap, names=names, where=str(path),
                    source=source, names_from=names_from)
    with atomic_output(path) as tmp:
        seg.save_as(tmp)
