"""DICOM RTSTRUCT (planar contours) as label maps on a reference series' grid, read with pydicom.

Reading (:func:`read_rtstruct`). Every ROI is rasterised on the grid of the
image series the structure set was drawn on (``reference``), its voxels taking
the ROI Number (an ROI with contours numbered 0, the background, or less is an
error naming ``--structure``: never lost from the map); ``structure=NAME`` gives
one ROI as a 0/1 mask. ROIs that
overlap (:func:`combine`): one lying wholly inside another (organs inside the
BODY or External contour, a GTV inside its CTV inside its PTV) is *nested*,
and a voxel takes the ROI Number of the smallest ROI holding it, so every
ROI's own voxels keep its number and the outer one gets the rest; ROIs that
overlap only in part (a PTV reaching into the rectum), or two ROIs with the
same voxels, cannot share one label map: an error lists every such pair, with
their shared voxels, and names ``--structure``. The rule (:func:`rasterize`),
slice by slice:

- a contour lies in the slice whose plane it is in (every point within 0.05
  voxel of it, else an error naming the ROI); a contour outside the series'
  slices, or on an image it does not hold, is an error too (its image is
  missing: dropping it would lose the ROI's voxels there);
- even-odd: a voxel centre is inside when a ray from it crosses the slice's
  closed contours of the ROI an odd number of times, so holes and islands are
  what the contours make them, whichever way round they are drawn;
- a voxel centre on a closed contour (within 1e-3 voxel, measured in voxel
  units of the slice) is inside: contours drawn through the boundary voxels'
  centres (rt-utils' habit) give exactly the voxels they pass through;
- a 1-point contour (POINT, or one vertex) gives the voxel holding it (rint of
  its index), and a polyline (OPEN_PLANAR, or a 2-point contour) the voxels it
  passes through, one per step along its major axis (:func:`_mark_nearest`):
  a marker or a line off the voxel centres is not lost.

An ROI with contours that still holds no voxel (a closed contour round no
voxel centre) is said in a warning naming it: its key/value lists it.
"""

from __future__ import annotations

import os
import shlex
from dataclasses import dataclass

import numpy as np

from ..errors import BadUsage, FormatError, VolwarpError
from ..progress import log
from ..volume import LPS, Volume
from .common import make_volume
from .segment_keys import (
    label_descriptions,
    nested_keys,
    nested_labels,
    roi_colour,
    roi_colours,
    roi_keys,
)

RTSTRUCT_SOP = "1.2.840.10008.5.1.4.1.1.481.3"


class ReferenceNeeded(BadUsage, FormatError):
    """An RTSTRUCT read without the series it lies on: a usage error (exit 2), and not an image."""

#: a voxel centre this close to a contour (voxels) is inside
ON_CONTOUR = 1e-3
#: a contour's points must lie this close to one slice plane (voxels)
IN_PLANE = 0.05


def _one_line(exc) -> str:
    return " ".join(str(exc).split())[:300]


#: What reading an RTSTRUCT holds, measured (peak less the process before: 2.3-6.4 MB files,
#: 10-80 MiB maps of 12-343 ROIs, 10-80 MiB): pydicom's objects of its contours, counted
#: at 12 bytes a byte of file before it is read, then the map and the ROIs' masks (a byte a
#: voxel at most: each is cut to its ROI's box) before they are made, each with
#: :data:`READ_MARGIN` for the work of a slab
READ_BYTES_PER_FILE_BYTE = 12
READ_MARGIN = 16 << 20
#: what rasterising a ROI holds beside its mask (a byte a voxel of its box): a slab's
#: crossing counts and their running sums (:data:`_FILL_CELLS` of 8 bytes each), and its
#: edges' arrays, a few numbers a contour point
RASTER_MARGIN = 24 << 20
RASTER_BYTES_PER_POINT = 96


def open_rtstruct(path: str | os.PathLike):
    """The pydicom data set of an RTSTRUCT file, or a FormatError naming it."""
    import pydicom

    from ..memory import ensure_fits_in_memory, human_bytes

    try:
        size = os.path.getsize(path)
        ensure_fits_in_memory(READ_BYTES_PER_FILE_BYTE * size + READ_MARGIN,
                              f"reading {path} ({human_bytes(size)} of contours)")
        ds = pydicom.dcmread(str(path), force=str(path).lower().endswith(".dcm"))
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except Exception as exc:  # damaged files raise many types in pydicom
        if isinstance(exc, VolwarpError):
            raise
        raise FormatError(f"{path}: not a readable RTSTRUCT ({type(exc).__name__}: "
                          f"{_one_line(exc)})") from None
    if str(ds.get("SOPClassUID", "")) != RTSTRUCT_SOP:
        raise FormatError(f"{path}: not an RTSTRUCT (SOPClassUID {ds.get('SOPClassUID')})")
    return ds


def referenced_series(ds) -> tuple[str, ...]:
    """The SeriesInstanceUIDs an RTSTRUCT's ReferencedFrameOfReferenceSequence names."""
    out = []
    for fr in ds.get("ReferencedFrameOfReferenceSequence", []):
        for st in fr.get("RTReferencedStudySequence", []):
            for se in st.get("RTReferencedSeriesSequence", []):
                if "SeriesInstanceUID" in se:
                    out.append(str(se.SeriesInstanceUID))
    return tuple(dict.fromkeys(out))


def frames_of_reference(ds) -> tuple[str, ...]:
    """The FrameOfReferenceUIDs of an RTSTRUCT (its referenced frames, its ROIs')."""
    out = [str(fr.FrameOfReferenceUID) for fr in ds.get("ReferencedFrameOfReferenceSequence", [])
           if "FrameOfReferenceUID" in fr]
    out += [str(r.ReferencedFrameOfReferenceUID) for r in ds.get("StructureSetROISequence", [])
            if "ReferencedFrameOfReferenceUID" in r]
    return tuple(dict.fromkeys(out))


def roi_frames(ds) -> dict[int, str]:
    """Each ROI's ReferencedFrameOfReferenceUID (ROIs that give one), by ROI Number."""
    return {int(r.ROINumber): str(r.ReferencedFrameOfReferenceUID)
            for r in ds.get("StructureSetROISequence", [])
            if "ROINumber" in r and r.get("ReferencedFrameOfReferenceUID")}


def _check_roi_frame(roi_frame: str | None, reference, where: str, label: str) -> None:
    """An ROI's contours lie in its own frame of reference: it must be the reference's."""
    own = reference.frame_of_reference_uid
    if roi_frame and own and roi_frame != own:
        raise VolwarpError(f"{where}: {label} lies in frame of reference {roi_frame}, not that "
                           f"of --reference {reference.path} ({own}): its contours are in "
                           "another coordinate system; read the ROIs on this one with "
                           "--structure NAME, or give that frame's series with --reference")


def describe_structures(ds) -> list[dict]:
    """Each ROI's number, name and number of contours (for ``volwarp info``)."""
    contours = {int(c.ReferencedROINumber): len(c.get("ContourSequence", []))
                for c in ds.get("ROIContourSequence", []) if "ReferencedROINumber" in c}
    return [{"number": int(r.ROINumber), "name": str(r.get("ROIName", "")),
             "contours": contours.get(int(r.ROINumber), 0)}
            for r in ds.get("StructureSetROISequence", [])]


def _structure_number(rois: list[dict], structure: str, where: str) -> int:
    """The ROI Number of the one ROI named ``structure`` (``rois``: :func:`describe_structures`)."""
    hits = [r["number"] for r in rois if r["name"] == structure]
    names = ", ".join(repr(r["name"]) for r in rois) or "none"
    if not hits:
        raise BadUsage(f"{where}: no structure named {structure!r} (--structure; the ROIs: "
                       f"{names})")
    if len(hits) > 1:
        raise BadUsage(f"{where}: {len(hits)} structures are named {structure!r} (ROI numbers "
                       f"{' '.join(map(str, hits))}): the name does not choose one")
    return hits[0]


def check_reference(ds, reference, where: str) -> None:
    """The reference must be the series the RTSTRUCT names (or, naming none, its frame).

    Each ROI's own frame is checked as it is read (:func:`_check_roi_frame`):
    an ROI of another frame is refused, ``--structure`` of one on this frame reads.
    """
    wanted = referenced_series(ds)
    if wanted and reference.series_uid not in wanted:
        raise VolwarpError(f"{where}: drawn on series {' '.join(wanted)}, but --reference "
                           f"{reference.path} holds series {reference.series_uid}")
    frames = frames_of_reference(ds)
    if frames and reference.frame_of_reference_uid and \
            reference.frame_of_reference_uid not in frames:
        raise VolwarpError(f"{where}: its frame of reference {' '.join(frames)} is not that of "
                           f"--reference {reference.path} ({reference.frame_of_reference_uid})")


def read_rtstruct(path: str | os.PathLike, reference, *, structure: str | None = None,
                  series=None, irregular: str = "error", duplicates: str = "error",
                  keep_phi: bool = False) -> Volume:
    """An RTSTRUCT rasterised on its reference series' grid (rules: the module docstring).

    ``reference``: the image series' path (a folder, DICOMDIR or file);
    ``series``, ``irregular`` and ``duplicates`` choose how it is read.
    """
    where = str(path)
    if reference is None:
        raise ReferenceNeeded(f"{where}: an RTSTRUCT holds contours, no PixelData: give the image "
                       "series it was drawn on with --reference CT_DIR")
    from .dicom import read_reference

    ds = open_rtstruct(path)
    ref = read_reference(reference, series=series, irregular=irregular, duplicates=duplicates,
                         want_series=referenced_series(ds))
    check_reference(ds, ref, where)
    structures = describe_structures(ds)
    numbers = [r["number"] for r in structures]
    only = _structure_number(structures, structure, where) if structure is not None else None
    grid = ref.grid
    names = {r["number"]: r["name"] for r in structures}
    frames = roi_frames(ds)
    dtype = np.uint8 if only is not None else _label_dtype(max(numbers, default=0), where)
    from ..memory import ensure_fits_in_memory

    voxels = int(np.prod(grid.shape))
    ensure_fits_in_memory(voxels * (np.dtype(dtype).itemsize + 1) + READ_MARGIN,
                          f"{where}: its contours as a {'x'.join(map(str, grid.shape_xyz))} "
                          "label map")
    out = np.zeros(grid.shape, dtype)
    rois = []
    images: dict = {}  # ContourImageSequence bytes -> the UIDs they name
    for roi in ds.get("ROIContourSequence", []):
        number = int(roi.get("ReferencedROINumber", -1))
        if only is not None and number != only:
            continue
        label = f"ROI {number} {names.get(number, '')!r}"
        if roi.get("ContourSequence"):
            _check_roi_frame(frames.get(number), ref, where, label)
        contours = _contours_in_index(roi, ref, where, label, images)
        if contours and only is None:
            _check_label(number, names, where)
        mask = RoiMask.of(number, names.get(number, ""), contours, grid.shape)
        if contours and not mask.count:
            log.warning("warning: %s: %s has %d contour(s) but holds no voxel centre of "
                        "--reference %s (drawn smaller than a voxel?): it has no voxels in "
                        "the output", where, label, len(contours), ref.path)
        if only is not None:
            out[mask.slices()][mask.mask] = 1
            continue
        rois.append(mask)
    nested = [] if only is not None else combine(rois, out, where)
    meta = _meta(ds, keep_phi, ref)
    colours = roi_colours(ds)
    if only is not None:
        meta["DICOM_Structure"] = f"{only} {names[only]}"
        # (the mask's label 1 is that ROI: its name and colour, written back by build_rtstruct)
        meta.update(roi_keys({1: names[only]},
                             {1: colours[only]} if only in colours else {}))
    else:
        meta.update(roi_keys({n: names[n] for n in numbers}, colours))
        meta.update(nested_keys(nested))
    return make_volume(where, out, spacing=grid.spacing, origin=grid.origin,
                       direction=grid.direction, space=LPS, file_space=LPS, meta=meta)


@dataclass(frozen=True)
class RoiMask:
    """One ROI's voxels: its number and name, its bounding box and its mask within it."""

    number: int
    name: str
    box: tuple  # (z0, y0, x0), (z1, y1, x1): the box [start, stop) of its voxels
    mask: np.ndarray  # bool, the box's shape
    count: int

    @classmethod
    def of(cls, number: int, name: str, contours, shape_zyx) -> RoiMask:
        """The ROI of ``contours`` (:func:`rasterize`'s) on a grid of ``shape_zyx``.

        Rasterised in the box of the contours' points (widened by the on-contour
        tolerance, within the grid): the voxels outside it cannot be inside.
        """
        if not contours:
            return cls(number, name, ((0, 0, 0), (0, 0, 0)), np.zeros((0, 0, 0), bool), 0)
        ks = [k for k, _, _ in contours]
        pts = np.concatenate([p for _, p, _ in contours])
        lo = np.array([min(ks), *np.floor(pts.min(axis=0)[::-1] - 1)], np.int64)
        hi = np.array([max(ks) + 1, *np.ceil(pts.max(axis=0)[::-1] + 2)], np.int64)
        lo = np.clip(lo, 0, shape_zyx)
        hi = np.clip(hi, lo, shape_zyx)
        shift = lo[:0:-1].astype(np.float64)  # (x0, y0)
        from ..memory import ensure_fits_in_memory

        # (a speckled ROI's box is the whole grid: ten such masks held ten bytes a voxel,
        # beyond the map's charge)
        voxels = int(np.prod(hi - lo))
        ensure_fits_in_memory(voxels + RASTER_BYTES_PER_POINT * len(pts) + RASTER_MARGIN,
                              f"ROI {number} {name!r}: its mask of {voxels} voxels")
        mask = rasterize([(k - lo[0], p - shift, c) for k, p, c in contours], tuple(hi - lo))
        return cls(number, name, (tuple(map(int, lo)), tuple(map(int, hi))), mask,
                   int(np.count_nonzero(mask)))

    def slices(self) -> tuple:
        """The grid's slices of its box."""
        return tuple(slice(a, b) for a, b in zip(*self.box, strict=True))

    def shared(self, other: RoiMask) -> int:
        """How many voxels this ROI and ``other`` share."""
        lo = np.maximum(self.box[0], other.box[0])
        hi = np.minimum(self.box[1], other.box[1])
        if np.any(hi <= lo):
            return 0
        mine = self.mask[tuple(slice(a - b, c - b) for a, b, c in
                               zip(lo, self.box[0], hi, strict=True))]
        theirs = other.mask[tuple(slice(a - b, c - b) for a, b, c in
                                  zip(lo, other.box[0], hi, strict=True))]
        return int(np.count_nonzero(mine & theirs))

    def title(self) -> str:
        """``NUMBER 'NAME'``, for messages."""
        return f"{self.number} {self.name!r}"


def combine(rois: list[RoiMask], out: np.ndarray, where: str) -> list[tuple[int, int]]:
    """Paint ``rois`` into the label map ``out``, nested ROIs over the ROIs holding them.

    Every pair that shares voxels must be nested: one ROI's voxels all inside
    the other's (the smaller is then painted after the larger, so a voxel
    takes the smallest ROI holding it). A pair overlapping only in part, or two
    ROIs with the same voxels, is an error listing every such pair with the
    voxels it shares and naming ``--structure``. Returns the nested pairs
    ``(inner ROI Number, outer ROI Number)``.
    """
    nested, clashes = [], []
    for i, j in _box_pairs(rois):
        a, b = rois[i], rois[j]
        common = a.shared(b)
        if not common:
            continue
        if common == a.count and a.count < b.count:
            nested.append((a.number, b.number))
        elif common == b.count and b.count < a.count:
            nested.append((b.number, a.number))
        else:
            clashes.append(f"{a.title()} and {b.title()} share {common} voxels"
                           + (" (the same voxels)" if common == a.count == b.count else ""))
    if clashes:
        shown = "; ".join(clashes[:6]) + (f"; and {len(clashes) - 6} more pairs"
                                          if len(clashes) > 6 else "")
        raise VolwarpError(f"{where}: ROIs overlap without one lying inside the other, so one "
                           f"label map cannot hold them ({shown}): read each as a 0/1 mask "
                           "with --structure NAME")
    for roi in sorted(rois, key=lambda r: (-r.count, r.number)):  # outer ROIs first
        out[roi.slices()][roi.mask] = roi.number
    return sorted(nested)


def _box_pairs(rois: list[RoiMask]) -> list[tuple[int, int]]:
    """The pairs ``(i, j)``, i < j, of ROIs whose boxes overlap (only they can share voxels).

    In the order of the loop over every pair (so the error lists pairs as it always did).
    """
    if len(rois) < 2:
        return []
    lo = np.array([r.box[0] for r in rois], np.int64)
    hi = np.array([r.box[1] for r in rois], np.int64)
    overlap = np.all(np.minimum(hi[:, None], hi[None]) > np.maximum(lo[:, None], lo[None]),
                     axis=2)
    i, j = np.nonzero(np.triu(overlap, 1))
    return list(zip(i.tolist(), j.tolist(), strict=True))


def _check_label(number: int, names: dict[int, str], where: str) -> None:
    """An ROI with contours is a label of the map when listed and numbered 1 or more.

    ``names``: the structure set's ROIs, number -> name; 0 is the map's background.
    """
    if number not in names:
        listed = " ".join(map(str, names)) or "none"
        raise FormatError(f"{where}: contours of ROI Number {number}, which "
                          f"StructureSetROISequence does not list (ROIs {listed}): no ROI to "
                          "label them with; read a listed ROI with --structure NAME")
    if number < 1:
        why = "0 is the background" if number == 0 else "a label is not negative"
        raise VolwarpError(f"{where}: ROI {number} {names[number]!r} cannot be a label of the "
                           f"map of every ROI ({why}): read it as a 0/1 mask with --structure "
                           f"{shlex.quote(names[number])}")


def _label_dtype(top: int, where: str):
    for t in (np.uint8, np.uint16, np.uint32):
        if top <= np.iinfo(t).max:
            return t
    raise VolwarpError(f"{where}: ROI Number {top} does not fit uint32")


def _meta(ds, keep_phi: bool, ref) -> dict:
    from .dicom._scan import PHI_TAGS

    keys = ("Modality", "SeriesDescription", "SeriesNumber", "StudyInstanceUID",
            "SeriesInstanceUID", "SOPClassUID", "StructureSetLabel") + \
        (PHI_TAGS if keep_phi else ())
    meta = {f"DICOM_{k}": str(ds.get(k)) for k in keys if ds.get(k) not in (None, "")}
    meta["DICOM_FrameOfReferenceUID"] = ref.frame_of_reference_uid
    meta["DICOM_ReferencedSeriesInstanceUID"] = ref.series_uid
    return meta


def _contours_in_index(roi, ref, where: str, label: str,
                       images: dict) -> list[tuple[int, np.ndarray, bool]]:
    """``(slice k, points (n, 2) as continuous (x, y) indices, closed)`` of one ROI's contours.

    Each must lie on an image of the reference ``ref`` (a ReferenceSeries): one it
    holds, when its ContourImageSequence names it, and one of its grid's slices.
    A contour whose image is missing (or was skipped as unreadable) is an error:
    dropping it would lose the ROI's voxels there without a word. ``images``:
    :func:`_contour_images`' cache.
    """
    out = []
    grid = ref.grid
    nz = grid.shape[0]
    for m, c in enumerate(roi.get("ContourSequence", [])):
        items = _contour_data(c)
        if not items:
            continue
        try:
            pts = np.array([float(v) for v in items], dtype=np.float64)
        except (TypeError, ValueError):
            raise FormatError(f"{where}: {label} contour {m + 1}: ContourData is not "
                              "numeric") from None
        if pts.size % 3 or not np.all(np.isfinite(pts)):
            raise FormatError(f"{where}: {label} contour {m + 1}: ContourData must be finite "
                              f"x y z triples, got {pts.size} values")
        for uid in _contour_images(c, images):
            if uid and uid not in ref.image_uids:
                raise FormatError(f"{where}: {label} contour {m + 1} lies on image {uid}, which "
                                  f"--reference {ref.path} does not hold (missing, or skipped "
                                  "as unreadable)")
        ijk = grid.world_to_index(pts.reshape(-1, 3))
        k = np.rint(ijk[:, 2])
        if np.abs(ijk[:, 2] - k).max() > IN_PLANE or k.min() != k.max():
            at = float(np.median(ijk[:, 2]))
            raise FormatError(f"{where}: {label} contour {m + 1} does not lie in a slice plane "
                              f"of the reference series (at slice index {at:.3f}, "
                              f"{np.ptp(ijk[:, 2]):.3g} across)")
        k = int(k[0])
        if not 0 <= k < nz:
            raise FormatError(f"{where}: {label} contour {m + 1} lies at slice index {k}, "
                              f"outside the slices 0..{nz - 1} of --reference {ref.path} (its "
                              "image missing, or skipped as unreadable?)")
        kind = str(c.get("ContourGeometricType", "CLOSED_PLANAR")).upper()
        out.append((k, ijk[:, :2], kind == "CLOSED_PLANAR"))
    return out


#: the tag of Contour Data (3006,0050)
_CONTOUR_DATA = 0x30060050
#: the tag of Contour Image Sequence (3006,0016)
_CONTOUR_IMAGES = 0x30060016


def _contour_images(item, cache: dict) -> tuple[str, ...]:
    """The SOP Instance UIDs a contour item's ContourImageSequence names (() if none).

    pydicom parses a sequence when it is first read, about 50 us a contour (a
    quarter of reading a large RTSTRUCT); the contours on one image hold the same
    bytes, so each distinct sequence is parsed once, ``cache`` keeping its UIDs.
    """
    if _CONTOUR_IMAGES not in item:
        return ()
    raw = item.get_item(_CONTOUR_IMAGES).value
    key = bytes(raw) if isinstance(raw, (bytes, bytearray)) else None
    if key in cache:
        return cache[key]
    uids = tuple(str(i.get("ReferencedSOPInstanceUID", "")) for i in item[_CONTOUR_IMAGES].value)
    if key is not None:
        cache[key] = uids
    return uids


def _contour_data(item) -> list:
    """A contour item's ContourData as its list of values (strings or numbers; [] if none).

    An element read from a file is still its bytes: they are split here as
    pydicom decodes a DS value (latin-1, the padding stripped, split at the
    backslashes), and ``float`` of each item gives the number pydicom's
    ``DSfloat`` would, without building one object per number (pydicom spends
    about 3 us a value there: two thirds of reading a large RTSTRUCT). An
    element already decoded is taken as it is.
    """
    if _CONTOUR_DATA not in item:
        return []
    value = item.get_item(_CONTOUR_DATA).value
    if isinstance(value, (bytes, bytearray)):
        text = bytes(value).decode("latin-1").strip().rstrip(" \x00")
        return text.split("\\") if text else []
    if value is None:
        return []
    if isinstance(value, (str, bytes, float, int)):
        return [value] if str(value).strip() else []
    return list(value)


def rasterize(contours, shape_zyx, *, tol: float = ON_CONTOUR) -> np.ndarray:
    """A bool mask [z, y, x] of contours ``(k, points (n, 2) in (x, y) voxel indices, closed)``.

    Even-odd over each slice's closed contours, plus every voxel centre within
    ``tol`` voxel of any contour (its closing edge included when closed). The
    slice index ``k`` must be one of the mask's (0 <= k < nz). Slices are
    rasterised a slab at a time (:data:`_FILL_CELLS`): every contour of the slab
    in a few array passes, rather than a few passes per contour, with scratch
    memory bounded by the slab's size and its contours' lengths.
    """
    nz, ny, nx = shape_zyx
    mask = np.zeros(shape_zyx, dtype=bool)
    step = max(1, _FILL_CELLS // (ny * (nx + 1)))  # slices in a slab
    slabs: dict[int, list] = {}
    for k, pts, closed in contours:
        slabs.setdefault(int(k) // step, []).append((int(k), pts, closed))
    for slab, items in slabs.items():
        z0 = slab * step
        _rasterize_slab(mask[z0:z0 + step], [(k - z0, pts, closed) for k, pts, closed in items],
                        tol)
    return mask


#: cells (rows x (columns + 1)) of a slab :func:`rasterize` fills at once (8 MiB of counts)
_FILL_CELLS = 1 << 20


def _rasterize_slab(mask: np.ndarray, contours, tol: float) -> None:
    """:func:`rasterize` into ``mask`` (all False), its contours' ``k`` counted from its first slice."""
    rings, lines = [], []  # (k, a, b): slice and end points of edges a -> b
    for k, pts, closed in contours:
        pts = np.asarray(pts, np.float64)
        if bool(closed) and len(pts) >= 3:
            rings.append((k, pts, np.roll(pts, -1, axis=0)))
        elif len(pts) == 1:  # (a point: a segment of no length, its nearest centre)
            lines.append((k, pts, pts))
        else:
            lines.append((k, pts[:-1], pts[1:]))
    if rings:
        ring_edges = _stacked(rings)
        _even_odd(mask, *ring_edges)
        _mark_on_segments(mask, *ring_edges, tol)
    if lines:
        _mark_nearest(mask, *_stacked(lines))


def _stacked(parts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(k, a, b)`` of a list of edge runs ``(k, a, b)``, as arrays: one row per edge."""
    k = np.concatenate([np.full(len(a), k, np.int64) for k, a, _ in parts])
    return (k, np.concatenate([a for _, a, _ in parts]),
            np.concatenate([b for _, _, b in parts]))


def _even_odd(mask: np.ndarray, k: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """Set the voxel centres of ``mask`` [z, y, x] an odd number of edges lie to the left of.

    Edge ``e`` runs from ``a[e]`` to ``b[e]`` ((x, y) = (i, j) voxel indices) on
    slice ``k[e]``; ``mask`` is all False on entry.
    """
    nz, ny, nx = mask.shape
    y0, y1 = a[:, 1], b[:, 1]
    lo, hi = np.minimum(y0, y1), np.maximum(y0, y1)
    # a row j crosses an edge when lo <= j < hi (half open: a vertex on the row counts once)
    j0 = np.clip(np.ceil(lo), 0, ny).astype(np.int64)
    j1 = np.clip(np.ceil(hi), 0, ny).astype(np.int64)
    count = np.maximum(j1 - j0, 0)
    keep = count > 0
    if not keep.any():
        return
    edge = np.repeat(np.flatnonzero(keep), count[keep])
    first = np.repeat(j0[keep], count[keep])
    offs = np.arange(edge.size) - np.repeat(np.cumsum(count[keep]) - count[keep], count[keep])
    j = first + offs
    xa, ya, xb, yb = a[edge, 0], a[edge, 1], b[edge, 0], b[edge, 1]
    x = xa + (j - ya) * (xb - xa) / (yb - ya)
    start = np.clip(np.floor(x).astype(np.int64) + 1, 0, nx)  # centres strictly right of x
    cell = (k[edge] * ny + j) * (nx + 1) + start  # the crossing's cell, rows of every slice
    toggles = np.bincount(cell, minlength=nz * ny * (nx + 1)).reshape(nz, ny, nx + 1)
    mask[...] = (np.cumsum(toggles[:, :, :nx], axis=2) & 1).astype(bool)


def _mark_on_segments(mask: np.ndarray, k: np.ndarray, a: np.ndarray, b: np.ndarray,
                      tol: float) -> None:
    """Set the voxel centres of ``mask`` [z, y, x] within ``tol`` of a segment a->b on slice k."""
    seg, c = _step_centres(mask.shape, a, b, tol)
    # exact distance from the candidate centre to the segment
    ds = (b - a)[seg]
    dd = np.einsum("ij,ij->i", ds, ds)
    p = np.where(dd > 0, np.einsum("ij,ij->i", c - a[seg], ds) / np.where(dd > 0, dd, 1.0), 0.0)
    p = np.clip(p, 0.0, 1.0)
    near = a[seg] + p[:, None] * ds
    ok = np.hypot(*(near - c).T) <= tol
    mask[k[seg[ok]], c[ok, 1].astype(np.int64), c[ok, 0].astype(np.int64)] = True


def _mark_nearest(mask: np.ndarray, k: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """Set the voxels of ``mask`` [z, y, x] a segment a->b on slice k passes through, one per step.

    Nearest-centre rasterisation (a DDA line): along the segment's major axis
    (x when |dx| >= |dy|), every index t from rint of one end to rint of the
    other gets the voxel holding the segment's point at t (the end point where
    t lies beyond it), i.e. minor index rint of that point's. A segment of no
    length (a POINT) gives the voxel holding it. Voxels off the grid are left out.
    """
    seg, c = _step_centres(mask.shape, a, b, None)
    mask[k[seg], c[:, 1].astype(np.int64), c[:, 0].astype(np.int64)] = True


def _step_centres(shape_zyx, a: np.ndarray, b: np.ndarray,
                  tol: float | None) -> tuple[np.ndarray, np.ndarray]:
    """``(segment, centre (x, y))``: each segment's voxel centre nearest it at each step t.

    The steps are the whole indices t along the segment's major axis (x when
    |dx| >= |dy|) from ``ceil(start - tol)`` to ``floor(end + tol)``, or with
    ``tol`` None from rint of one end to rint of the other; the centre is
    ``(t, rint of the segment's minor coordinate at t)``, the end point's
    where t lies beyond it. Centres off the grid are left out.
    """
    _, ny, nx = shape_zyx
    d = b - a
    major = (np.abs(d[:, 1]) > np.abs(d[:, 0])).astype(np.int64)  # 0: x, 1: y
    idx = np.arange(len(a))
    am, bm = a[idx, major], b[idx, major]
    lo, hi = np.minimum(am, bm), np.maximum(am, bm)
    lo, hi = (np.rint(lo), np.rint(hi)) if tol is None else (np.ceil(lo - tol), np.floor(hi + tol))
    size = np.where(major == 0, nx, ny)
    t0 = np.maximum(np.clip(lo, -1, size).astype(np.int64), 0)  # (the grid's steps only)
    t1 = np.minimum(np.clip(hi, -1, size).astype(np.int64), size - 1)
    count = np.maximum(t1 - t0 + 1, 0)
    seg = np.repeat(idx, count)
    offs = np.arange(seg.size) - np.repeat(np.cumsum(count) - count, count)
    t = (t0[seg] + offs).astype(np.float64)
    mj = major[seg]
    dm = d[seg, mj]
    s = np.clip(np.where(dm != 0, (t - a[seg, mj]) / np.where(dm != 0, dm, 1.0), 0.0), 0.0, 1.0)
    c = np.empty((seg.size, 2))
    c[np.arange(seg.size), mj] = t
    c[np.arange(seg.size), 1 - mj] = np.rint(a[seg, 1 - mj] + s * d[seg, 1 - mj])
    ok = (c[:, 0] >= 0) & (c[:, 0] < nx) & (c[:, 1] >= 0) & (c[:, 1] < ny)
    return seg[ok], c[ok]


# -- writing -----------------------------------------------------------------------------

#: how far (voxels) contours on voxel edges are moved into the voxels they outline
NUDGE = 0.01


def mask_outlines(mask: np.ndarray, *, nudge: float = NUDGE) -> list[np.ndarray]:
    """Closed outlines (n, 2) of a 2-D bool mask [y, x] on its voxel edges, in (x, y) indices.

    Each loop keeps the voxels it outlines on its right (y down), so outer
    boundaries and holes run opposite ways; at a corner shared by two voxels
    that touch only there the loop turns to stay with its voxel, so diagonal
    neighbours get loops of their own. Every vertex is moved ``nudge`` voxel
    into the outlined voxels (each edge's inward offset), so no loop touches
    another and none passes through a voxel centre: the even-odd rule gives the
    mask back exactly.
    """
    m = np.pad(np.asarray(mask, dtype=bool), 1)
    out_edges = {}
    # horizontal edges at corner row cy (between pixel rows cy - 1 and cy of the mask)
    below, above = m[1:, 1:-1], m[:-1, 1:-1]
    for cy, i in zip(*np.nonzero(below & ~above), strict=True):
        out_edges.setdefault((int(i), int(cy)), []).append((1, 0))      # +x
    for cy, i in zip(*np.nonzero(above & ~below), strict=True):
        out_edges.setdefault((int(i) + 1, int(cy)), []).append((-1, 0))  # -x
    left, right = m[1:-1, :-1], m[1:-1, 1:]
    for j, cx in zip(*np.nonzero(left & ~right), strict=True):
        out_edges.setdefault((int(cx), int(j)), []).append((0, 1))      # +y
    for j, cx in zip(*np.nonzero(right & ~left), strict=True):
        out_edges.setdefault((int(cx), int(j) + 1), []).append((0, -1))  # -y
    loops = []
    for start in sorted(out_edges):
        while out_edges.get(start):
            v, d = start, out_edges[start].pop(0)
            pts, dirs = [], []
            while True:
                pts.append(v)
                dirs.append(d)
                v = (v[0] + d[0], v[1] + d[1])
                choices = out_edges.get(v)
                if not choices:
                    break
                right_turn = (-d[1], d[0])
                d = right_turn if right_turn in choices else choices[0]
                choices.remove(d)
            loops.append(_corners(np.array(pts, float), np.array(dirs, float), nudge))
    return loops


#: the contour styles :func:`build_rtstruct` writes
CONTOUR_STYLES = ("edges", "smooth")
#: margin (voxels) around a slice's mask where its distance field is computed
_FIELD_MARGIN = 2


def smooth_outlines(mask: np.ndarray) -> list[np.ndarray]:
    """Closed outlines (n, 2) of a 2-D bool mask [y, x] from its sub-voxel distance field.

    The field is the exact Euclidean distance between voxel centres, in voxels
    (``scipy.ndimage.distance_transform_edt``), signed and moved half a voxel:
    ``0.5 - d_in`` at a voxel of the mask (``d_in``: to the nearest centre
    outside it), ``d_out - 0.5`` elsewhere, so its zero level runs along the
    voxel faces where the boundary is straight and cuts across its staircases.
    The outlines are that level by marching squares (scikit-image's
    ``find_contours``, elements above the level fully connected, so voxels
    touching only at a corner get loops of their own), with collinear vertices
    dropped (``approximate_polygon``, tolerance 1e-3 voxel). Every voxel centre
    lies at least 0.35 voxel from them, inside them exactly when its voxel is in
    the mask: the even-odd rule reads the mask back exactly.

    References
    ----------
    W. E. Lorensen and H. E. Cline, "Marching cubes: a high resolution 3D surface
    construction algorithm", SIGGRAPH 1987, doi:10.1145/37402.37422 (its 2-D case).
    """
    from scipy import ndimage
    from skimage.measure import approximate_polygon, find_contours

    mask = np.asarray(mask, dtype=bool)
    ys, xs = np.nonzero(mask)
    if not ys.size:
        return []
    y0, x0 = ys.min() - _FIELD_MARGIN, xs.min() - _FIELD_MARGIN
    crop = np.zeros((ys.max() - y0 + 1 + _FIELD_MARGIN, xs.max() - x0 + 1 + _FIELD_MARGIN),
                    bool)
    crop[ys - y0, xs - x0] = True  # (the margin is outside: every loop closes inside it)
    d_in = ndimage.distance_transform_edt(crop)
    d_out = ndimage.distance_transform_edt(~crop)
    field = np.where(crop, 0.5 - d_in, d_out - 0.5)
    loops = []
    for c in find_contours(field, 0.0, fully_connected="high"):
        c = approximate_polygon(c, tolerance=1e-3)  # (closed: its first point is its last)
        loops.append(c[:-1, ::-1] + (x0, y0))
    return loops


def _corners(pts: np.ndarray, dirs: np.ndarray, nudge: float) -> np.ndarray:
    """The loop's turning vertices, moved inward, in voxel-centre (x, y) indices."""
    prev = np.roll(dirs, 1, axis=0)
    turn = np.any(prev != dirs, axis=1)
    inward = np.column_stack([-dirs[:, 1], dirs[:, 0]]) + np.column_stack([-prev[:, 1], prev[:, 0]])
    return (pts[turn] - 0.5) + nudge * inward[turn]


def _ds(values) -> list[str]:
    return [f"{v:.6f}".rstrip("0").rstrip(".") if abs(v) < 1e9 else f"{v:.6e}" for v in values]


#: (3006,0050) Contour Data
CONTOUR_DATA = 0x30060050


def _contour_item(values):
    """A contour's item holding ``values`` (x, y, z, ...) as its Contour Data, encoded.

    The bytes pydicom writes for the :func:`_ds` strings, kept as a raw element
    in an item marked explicit VR little endian (pydicom's documented way to
    write an element as it is): assigned as numbers, each would be a ``DSfloat``
    of about 400 bytes until written, 300 MiB for a 512x512x160 map's 40 labels.
    Its elements set after this are encoded by pydicom as they are written.
    """
    from pydicom.dataelem import RawDataElement
    from pydicom.dataset import Dataset
    from pydicom.tag import Tag

    text = "\\".join(_ds(values)).encode("ascii")
    if len(text) % 2:
        text += b" "
    item = Dataset()
    item.set_original_encoding(False, True, "iso8859")
    item[CONTOUR_DATA] = RawDataElement(Tag(CONTOUR_DATA), "DS", len(text), text, 0, False, True)
    return item


def build_rtstruct(vol: Volume, reference, *, names: dict[int, str] | None = None,
                   where: str = "RTSTRUCT", contours: str = "edges",
                   source: str | None = None, names_from: str | None = None):
    """A pydicom RTSTRUCT of a label map on ``reference``'s grid: one ROI per label.

    ROI Number = label value, named from ``names``, else the map's key/values
    (:mod:`.segment_keys`: also its colour), else ``label_N``; contours
    (``contours="edges"``) on voxel edges moved :data:`NUDGE` voxel inward
    (:func:`mask_outlines`), or (``"smooth"``) the zero level of each slice's
    sub-voxel distance field (:func:`smooth_outlines`), each referencing its
    slice's image (and its frame, ReferencedFrameNumber, when the reference is
    a multi-frame image); new SOP and Series UIDs made from the content. An
    outer ROI of the map's ``DICOM_ROI_nested`` is its voxels and those of the
    ROIs inside it (:func:`.segment_keys.nested_labels`), as it was read.
    ``names_from``: the file ``names`` came from (:func:`.dicom_seg.check_names`).
    """
    if contours not in CONTOUR_STYLES:
        raise VolwarpError(f"contours must be one of {', '.join(CONTOUR_STYLES)}, "
                           f"got {contours!r}")
    outlines = mask_outlines if contours == "edges" else smooth_outlines
    import pydicom
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence
    from pydicom.uid import ExplicitVRLittleEndian

    from .. import __version__
    from .dicom_seg import (
        _content_key,
        _stamp,
        check_names,
        check_on_reference_grid,
        new_uid,
        slice_labels,
    )

    check_on_reference_grid(vol, reference, where)
    if not reference.frame_of_reference_uid:  # (Type 1 in the structure set and each ROI)
        series = os.path.dirname(str(reference.files[0])) or "."
        raise VolwarpError(f"{where}: the reference series ({series}) has no "
                           "FrameOfReferenceUID, which an RTSTRUCT's contours must name (a SEG "
                           "is refused alike); give the series one, or write the labels as a "
                           "volume")
    values, in_slice = slice_labels(vol, where)
    names = dict(names or {})
    check_names(names, values, names_from or where)
    described = label_descriptions(vol.meta, values, source or where)
    key = _content_key(vol, reference, "rtstruct" if contours == "edges" else
                       f"rtstruct {contours}", names, described)
    date, time = _stamp(reference)
    src = pydicom.dcmread(reference.files[0], stop_before_pixels=True)
    g = reference.grid
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = RTSTRUCT_SOP
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = new_uid(key, "sop")
    ds.file_meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.SOPClassUID = RTSTRUCT_SOP
    for kw in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate",
               "StudyTime", "ReferringPhysicianName", "StudyID", "AccessionNumber",
               "StudyInstanceUID"):
        setattr(ds, kw, src.get(kw, ""))
    ds.Modality = "RTSTRUCT"
    ds.SeriesInstanceUID = new_uid(key, "series")
    ds.SeriesNumber = 902
    ds.InstanceNumber = 1
    ds.Manufacturer = "volwarp"
    ds.SoftwareVersions = str(__version__)
    ds.StructureSetLabel = "VOLWARP"
    ds.StructureSetDate, ds.StructureSetTime = date, time
    ds.InstanceCreationDate, ds.InstanceCreationTime = date, time
    sop_class = reference.sop_class_uid or str(src.SOPClassUID)

    def image_ref(k, frames=None):
        item = Dataset()
        item.ReferencedSOPClassUID = sop_class
        item.ReferencedSOPInstanceUID = reference.sop_uids[k]
        if reference.multi_frame:  # a frame of an enhanced image: which one
            item.ReferencedFrameNumber = frames or reference.frame_numbers[k]
        return item
    series = Dataset()
    series.SeriesInstanceUID = reference.series_uid
    series.ContourImageSequence = Sequence(_series_images(reference, image_ref))
    study = Dataset()
    study.ReferencedSOPClassUID = "1.2.840.10008.3.1.2.3.1"  # Study Component Management
    study.ReferencedSOPInstanceUID = reference.study_uid
    study.RTReferencedSeriesSequence = Sequence([series])
    frame = Dataset()
    frame.FrameOfReferenceUID = reference.frame_of_reference_uid
    frame.RTReferencedStudySequence = Sequence([study])
    ds.ReferencedFrameOfReferenceSequence = Sequence([frame])
    rois, contours, observations = [], [], []
    data = vol.data
    inside = nested_labels(vol.meta, values, source or where)  # (an outer ROI written whole)
    room = _Room(where, data.shape[1] * data.shape[2])
    for n, value in enumerate(values.tolist(), 1):
        roi = Dataset()
        roi.ROINumber = int(value)
        roi.ReferencedFrameOfReferenceUID = reference.frame_of_reference_uid
        d = described.get(int(value))
        roi.ROIName = (names.get(int(value)) or (d and (d.roi_name or d.seg_label))
                       or f"label_{int(value)}")[:64]
        roi.ROIGenerationAlgorithm = ""
        rois.append(roi)
        seq = []
        members = [value, *inside.get(value, ())]
        for k in (k for k, held in enumerate(in_slice) if not held.isdisjoint(members)):
            for loop in outlines(np.isin(data[k], members)):
                xyz = g.index_to_world(np.column_stack([loop, np.full(len(loop), float(k))]))
                item = _contour_item(xyz.ravel())
                item.ContourImageSequence = Sequence([image_ref(int(k))])
                item.ContourGeometricType = "CLOSED_PLANAR"
                item.NumberOfContourPoints = len(loop)
                seq.append(item)
                room.made(item.get_item(CONTOUR_DATA).length)  # (raw: [] would decode it)
            room.tick()  # (a plane done)
        c = Dataset()
        c.ReferencedROINumber = int(value)
        c.ROIDisplayColor = list(roi_colour(d) or (
            int((value * 67) % 256), int((value * 131 + 80) % 256), int((value * 29 + 160) % 256)))
        c.ContourSequence = Sequence(seq)
        contours.append(c)
        obs = Dataset()
        obs.ObservationNumber = n
        obs.ReferencedROINumber = int(value)
        obs.RTROIInterpretedType = ""
        obs.ROIInterpreter = ""
        observations.append(obs)
    ds.StructureSetROISequence = Sequence(rois)
    ds.ROIContourSequence = Sequence(contours)
    ds.RTROIObservationsSequence = Sequence(observations)
    room.check_write()
    return ds


#: What the memory checks of :class:`_Room` count, measured (peak less the process before,
#: 20-160 planes of 256^2-512^2, 1-40 labels, 4x4-voxel noise of 10 labels: 61,202
#: contours): a contour item about 3.7 KB of pydicom's objects beside its Contour Data's
#: bytes; a plane's masks and outlines up to 48 bytes a pixel; the file's encoding about its
#: size once more (pydicom encodes a sequence into a buffer before writing it), for which
#: half as much again and 16 MiB are kept.
CONTOUR_ITEM_BYTES = 4 << 10
PLANE_BYTES_PER_PIXEL = 48
ROOM_MARGIN = 16 << 20
#: bytes of a contour item beside its Contour Data in the file (its image reference's UIDs,
#: type, count and the items' and elements' headers: about 190)
CONTOUR_ITEM_FILE_BYTES = 256


class _Room:
    """The memory limit kept while contours are made (their number is known only then).

    An RTSTRUCT's size follows its contours, not its voxels (a speckled map
    makes a contour an island: 61,202 of them for 20 planes of 256^2 held 224
    MiB). So the budget is checked as they are made: every
    :data:`CHECK_EVERY` contours or planes, room for that many more and a
    plane's work must be left; and before the dataset is written, room for
    its encoding. A refusal stops the build (no file written).
    """

    CHECK_EVERY = 64

    def __init__(self, where: str, plane_pixels: int):
        self.where = where
        self.reserve = ROOM_MARGIN + PLANE_BYTES_PER_PIXEL * plane_pixels + \
            self.CHECK_EVERY * CONTOUR_ITEM_BYTES
        self.contours = self.data_bytes = self.since = 0

    def made(self, data_bytes: int) -> None:
        """A contour made, its Contour Data ``data_bytes`` long."""
        self.contours += 1
        self.data_bytes += data_bytes
        self.tick()

    def tick(self) -> None:
        """A contour or a plane done: the budget checked every :data:`CHECK_EVERY`."""
        self.since += 1
        if self.since < self.CHECK_EVERY:
            return
        from ..memory import ensure_fits_in_memory

        self.since = 0
        ensure_fits_in_memory(self.reserve, f"{self.where}: the RTSTRUCT's contours "
                                            f"({self.contours} made so far)")

    def check_write(self) -> None:
        from ..memory import ensure_fits_in_memory, human_bytes

        size = self.data_bytes + self.contours * CONTOUR_ITEM_FILE_BYTES
        ensure_fits_in_memory(size + size // 2 + ROOM_MARGIN,
                              f"{self.where}: encoding the RTSTRUCT's {self.contours} contours "
                              f"(about {human_bytes(size)})")


def _series_images(reference, image_ref) -> list:
    """The referenced series' ContourImageSequence: each image it has, once.

    One item per slice of single-frame images; one per multi-frame image, its
    ReferencedFrameNumber every frame of it that is a slice of the grid.
    """
    if not reference.multi_frame:
        return [image_ref(k) for k in range(len(reference.sop_uids))]
    first: dict[str, int] = {}
    frames: dict[str, list[int]] = {}
    for k, (uid, n) in enumerate(zip(reference.sop_uids, reference.frame_numbers, strict=True)):
        first.setdefault(uid, k)
        frames.setdefault(uid, []).append(n)
    return [image_ref(k, sorted(frames[uid]) if len(frames[uid]) > 1 else frames[uid][0])
            for uid, k in first.items()]


def write_rtstruct(vol: Volume, path: str | os.PathLike, reference, *,
                   names: dict[int, str] | None = None, contours: str = "edges",
                   source: str | None = None, names_from: str | None = None) -> None:
    """Write :func:`build_rtstruct`'s RTSTRUCT to ``path`` atomically."""
    from .atomic import atomic_output, check_output_path

    check_output_path(path)
    ds = build_rtstruct(vol, reference, names=names, where=str(path), contours=contours,
                        source=source, names_from=names_from)
    with atomic_output(path) as tmp:
        ds.save_as(tmp, enforce_file_format=True)
