"""``read_dicom``: choose a candidate, plan its grid, read its pixels, build the Volume."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ...errors import BadUsage, FormatError, VolwarpError
from ...geometry import check_placement
from ...progress import log
from ...volume import Header, Volume
from ..common import ensure_fits_in_memory, make_volume
from ..lazy import make_header
from ._geometry import plan_stack, resample
from ._pixels import output_dtype, read_frames
from ._scan import (
    META_TAGS,
    NO_PIXEL_SPACING,
    PHI_TAGS,
    Candidate,
    DicomSeriesChoiceError,
    scan_dicom,
)

_LPS = "left-posterior-superior"


def choose(candidates: list[Candidate], series, where: str) -> Candidate:
    """The candidate ``series`` names (SeriesInstanceUID or index), or the only one."""
    def listing(cands):
        return "; ".join(c.one_line() for c in cands)

    if series is None:
        if len(candidates) == 1:
            return candidates[0]
        raise DicomSeriesChoiceError(f"{where}: {len(candidates)} candidate volumes, choose one "
                                     f"with --series UID|INDEX: {listing(candidates)}")
    if isinstance(series, int) or (isinstance(series, str) and series.strip().isdigit()
                                   and not any(c.series_uid == series for c in candidates)):
        i = int(series)
        if not 0 <= i < len(candidates):
            raise DicomSeriesChoiceError(f"{where}: --series {i} is outside 0..{len(candidates) - 1}"
                                         f": {listing(candidates)}")
        return candidates[i]
    hits = [c for c in candidates if c.series_uid == str(series).strip()]
    if not hits:
        raise DicomSeriesChoiceError(f"{where}: no series {series}: {listing(candidates)}")
    if len(hits) > 1:
        raise DicomSeriesChoiceError(f"{where}: series {series} has {len(hits)} candidate "
                                     f"volumes, choose one by index: {listing(hits)}")
    return hits[0]


def read_dicom(path: str | os.PathLike, *, series: str | int | None = None,
               irregular: str = "error", duplicates: str = "error", keep_shear: bool = False,
               keep_phi: bool = False, candidates: list[Candidate] | None = None,
               reference: str | os.PathLike | None = None, segment: int | None = None,
               structure: str | None = None) -> Volume:
    """Read one volume from a DICOM folder, DICOMDIR or file (rules: the package docstring).

    ``series``: a SeriesInstanceUID or a 0-based candidate index (required when
    the path holds several candidates). ``irregular``: ``"error"`` or
    ``"resample"``; ``duplicates``: ``"error"``, ``"first"`` or ``"last"``.
    ``candidates``: :func:`scan_dicom` of ``path``, when the caller has it already.

    A SEG or RTSTRUCT file is read as a label map (:func:`read_segmentation`):
    ``reference`` is the image series it lies on (required for an RTSTRUCT;
    ``series``, ``irregular`` and ``duplicates`` then choose how that is read),
    ``segment`` one SEG segment and ``structure`` one RTSTRUCT ROI as 0/1 masks.
    """
    where = str(path)
    kind = segmentation_kind(path)
    if kind is not None:
        return read_segmentation(path, kind, reference=reference, segment=segment,
                                 structure=structure, series=series, irregular=irregular,
                                 duplicates=duplicates, keep_shear=keep_shear,
                                 keep_phi=keep_phi)
    for name, value in (("--reference", reference), ("--segment", segment),
                        ("--structure", structure)):
        if value is not None:
            raise BadUsage(f"{name} applies to DICOM SEG and RTSTRUCT inputs; {where} is an "
                           "image series")
    plan, dtype, meta = _plan(path, series=series, irregular=irregular, duplicates=duplicates,
                              keep_shear=keep_shear, keep_phi=keep_phi, candidates=candidates)
    rows, cols = plan.frames[0].file.rows, plan.frames[0].file.columns
    n_in = len(plan.frames)
    nbytes = n_in * rows * cols * dtype.itemsize
    if plan.resampled:
        nbytes += 2 * plan.n_out * rows * cols * 4
    ensure_fits_in_memory(nbytes, f"{where} ({cols}x{rows}x{plan.n_out} {dtype.name})")
    data = np.empty((n_in, rows, cols), dtype=dtype)
    read_frames(plan.frames, dtype, data)
    if plan.resampled:
        from ...labelmap import looks_like_labels

        labels = looks_like_labels(data)
        if labels:  # (a label map stored as an image series: its ids must not blend)
            log.warning("warning: %s: a label map (by volwarp's rule): its slices are "
                        "resampled by nearest neighbour, its ids kept", where)
        data = resample(plan, data, labels=labels)
    return make_volume(where, data, spacing=plan.spacing, origin=plan.origin,
                       direction=plan.direction, space=_LPS, file_space=_LPS, meta=meta)


def segmentation_kind(path) -> str | None:
    """``"seg"`` or ``"rtstruct"`` for a file holding that SOP class, else None."""
    if os.path.isdir(path) or not os.path.isfile(path):
        return None
    import pydicom

    from ..dicom_seg import SEG_SOPS
    from ..rtstruct import RTSTRUCT_SOP

    try:
        ds = pydicom.dcmread(path, stop_before_pixels=True, specific_tags=["SOPClassUID"],
                             force=path_has_dcm_suffix(path))
    except Exception:  # not DICOM, or damaged: the image reader says what is wrong
        return None
    uid = ds.get("SOPClassUID") or getattr(ds, "file_meta", {}).get("MediaStorageSOPClassUID")
    uid = str(uid or "")
    if uid in SEG_SOPS:
        return "seg"
    if uid == RTSTRUCT_SOP:
        return "rtstruct"
    return None


def path_has_dcm_suffix(path) -> bool:
    return str(path).lower().endswith(".dcm")


def read_segmentation(path, kind: str, *, reference=None, segment=None, structure=None,
                      series=None, irregular="error", duplicates="error", keep_shear=False,
                      keep_phi=False) -> Volume:
    """A SEG or RTSTRUCT file as a label map (see :mod:`..dicom_seg`, :mod:`..rtstruct`)."""
    where = str(path)
    if keep_shear:
        raise BadUsage(f"--keep-shear: the series a segmentation ({where}) lies on is read "
                       "as stored (no tilt resampling to keep)")
    if reference is None:
        given = [n for n, v in (("--series", series is not None), ("--irregular", irregular != "error"),
                                ("--duplicates", duplicates != "error")) if v]
        if given:
            raise BadUsage(f"{' '.join(given)} choose how the --reference series of {where} is "
                           "read: give --reference")
    if kind == "seg":
        if structure is not None:
            raise BadUsage(f"--structure names an RTSTRUCT ROI; {where} is a SEG (--segment N)")
        from ..dicom_seg import open_seg, read_seg, referenced_series

        seg = open_seg(path)
        ref = None
        if reference is not None:
            ref = read_reference(reference, series=series, irregular=irregular,
                                 duplicates=duplicates, want_series=referenced_series(seg))
        return read_seg(path, segment=segment, reference=ref, keep_phi=keep_phi, seg=seg)
    if segment is not None:
        raise BadUsage(f"--segment numbers a SEG segment; {where} is an RTSTRUCT "
                       "(--structure NAME)")
    from ..rtstruct import read_rtstruct

    return read_rtstruct(path, reference, structure=structure, series=series,
                         irregular=irregular, duplicates=duplicates, keep_phi=keep_phi)


def _plan(path, *, series, irregular, duplicates, keep_shear, keep_phi, candidates=None):
    """``(plan, sample type, key/values)`` of the volume ``path`` holds (checked options)."""
    if irregular not in ("error", "resample"):
        raise VolwarpError(f"irregular must be error or resample, got {irregular!r}")
    if duplicates not in ("error", "first", "last"):
        raise VolwarpError(f"duplicates must be error, first or last, got {duplicates!r}")
    where = str(path)
    cand = choose(candidates if candidates is not None else scan_dicom(path), series, where)
    f0 = cand.frames[0]
    if cand.problem:  # (a file of its series cut before its pixels)
        raise FormatError(cand.problem)
    bad = next((f for f in cand.frames if f.problem), None)  # any file's, not the first's
    if bad is not None:
        raise FormatError(f"{bad.file.path}: {bad.problem}")
    plan = plan_stack(list(cand.frames), where, irregular=irregular, duplicates=duplicates,
                      keep_shear=keep_shear)
    if f0.assumed and plan.n_out > 1 and f0.synthetic:  # (not silently: a guessed axis)
        log.warning("warning: %s: %d frames without positions of their own, stacked with %s",
                    f0.file.path, plan.n_out, f0.assumed)
    elif NO_PIXEL_SPACING in f0.assumed:  # (a guessed scale: distances, volumes off)
        log.warning("warning: %s: no PixelSpacing (nor ImagerPixelSpacing): 1 mm pixels "
                    "assumed, as ITK does (recorded in DICOM_geometry)", where)
    _check_plan(plan)
    return plan, output_dtype(plan.frames), _meta(cand, plan, keep_phi)


def _check_plan(plan) -> None:
    """The grid's placement by the one rule (:func:`~volwarp_cli.geometry.check_placement`).

    A refusal names the first slice's file and the tag the number came from:
    the slice spacing is the positions' (one slice: SpacingBetweenSlices; RT
    Dose: GridFrameOffsetVector).
    """
    f0 = plan.frames[0]
    if plan.n_out == 1 or f0.synthetic:
        z_name = "SpacingBetweenSlices"
    elif f0.file.dose_scaling is not None and f0.file.n_frames > 1:
        z_name = "GridFrameOffsetVector"
    else:
        z_name = "ImagePositionPatient"
    shape = (f0.file.columns, f0.file.rows, plan.n_out)
    plan.spacing, plan.origin, plan.direction = check_placement(
        plan.spacing, plan.origin, plan.direction, shape, where=f0.file.path,
        fields={"spacing": ("PixelSpacing", "PixelSpacing", z_name),
                "origin": "ImagePositionPatient", "direction": "ImageOrientationPatient"})


class LazyDicom:
    """A DICOM stack's samples, read slab by slab from its frames' files on demand.

    Sliceable ``[z, y, x]`` as the array :func:`read_dicom` returns, and
    picklable: a worker process reads the same files, without scanning the
    folder again. Only for stacks that need no resampling (the tilt and the
    irregular-spacing resampling read the whole stack).
    """

    portable = True  # (its pickled state is all it needs: no path to reopen)

    def __init__(self, frames, dtype, rows: int, cols: int):
        self.frames = list(frames)
        self.dtype = np.dtype(dtype)
        self.shape = (len(self.frames), int(rows), int(cols))
        self.ndim = 3

    def __getitem__(self, key) -> np.ndarray:
        from ..filearray import box_of_key

        ((z0, z1), (y0, y1), (x0, x1)), pick = box_of_key(key, self.shape)
        out = np.empty((z1 - z0,) + self.shape[1:], self.dtype)
        if z1 > z0:
            read_frames(self.frames[z0:z1], self.dtype, out)
        return np.ascontiguousarray(out[:, y0:y1, x0:x1])[pick]

    def __array__(self, dtype=None, copy=None):
        data = self[...]
        return data if dtype is None else data.astype(dtype)


def open_dicom_lazy(path: str | os.PathLike, *, series=None, irregular: str = "error",
                    duplicates: str = "error", keep_shear: bool = False, keep_phi: bool = False,
                    reference=None, segment=None, structure=None):
    """``(header, LazyDicom)``: :func:`read_dicom`'s Volume's Header, and its samples.

    None when the stack must be resampled (a gantry tilt, irregular spacing
    with ``irregular="resample"``): that is read whole. A SEG or RTSTRUCT (a
    label map made from its frames or contours) is read whole too
    (:class:`~volwarp_cli.io.lazy.NotLazy` says so), and so is an image series
    given ``reference``, ``segment`` or ``structure`` (:func:`read_dicom` refuses them).
    """
    from ..lazy import NotLazy

    where = str(path)
    if segmentation_kind(path) is not None:
        raise NotLazy("a DICOM SEG or RTSTRUCT is read whole (a label map made from its "
                      "frames or contours)")
    if reference is not None or segment is not None or structure is not None:
        raise NotLazy("--reference, --segment and --structure read segmentations")
    plan, dtype, meta = _plan(path, series=series, irregular=irregular, duplicates=duplicates,
                              keep_shear=keep_shear, keep_phi=keep_phi)
    if plan.resampled:
        return None
    rows, cols = plan.frames[0].file.rows, plan.frames[0].file.columns
    lazy = LazyDicom(plan.frames, dtype, rows, cols)
    return make_header(where, lazy.shape, dtype, spacing=plan.spacing, origin=plan.origin,
                       direction=plan.direction, space=_LPS, file_space=_LPS, meta=meta), lazy


def _meta(cand: Candidate, plan, keep_phi: bool) -> dict[str, str]:
    src = plan.frames[0].file.meta
    keep = META_TAGS + (PHI_TAGS if keep_phi else ())
    meta = {f"DICOM_{k}": str(src[k]) for k in keep if k in src}
    if plan.frames[0].assumed:
        meta["DICOM_geometry"] = f"assumed: {plan.frames[0].assumed}"
    if cand.why:
        meta["DICOM_candidate"] = cand.why
    return meta




@dataclass(frozen=True)
class ReferenceSeries:
    """The image series a segmentation was drawn on: its grid and its images' identities.

    ``grid`` is :func:`read_dicom`'s Volume's :class:`~volwarp_cli.volume.Header`
    (no pixels are read); ``files[k]`` and ``sop_uids[k]`` are the image of slice
    ``k`` (z order); ``frame_numbers[k]`` its frame number (1 ...) in that file
    when the file is a multi-frame image (an enhanced CT or MR: one file, one
    SOP Instance UID for every slice), else None. ``image_uids``: the SOP
    Instance UIDs of every image of the series read, those of duplicates
    ``duplicates`` left off the grid included (a file skipped as unreadable is
    not one).
    """

    path: str
    grid: Header
    series_uid: str
    frame_of_reference_uid: str
    study_uid: str
    sop_class_uid: str
    sop_uids: tuple
    files: tuple
    frame_numbers: tuple = ()
    image_uids: frozenset = frozenset()

    @property
    def multi_frame(self) -> bool:
        """Whether the slices are frames of multi-frame images (referenced by frame number)."""
        return any(n is not None for n in self.frame_numbers)


def read_reference(path: str | os.PathLike, *, series=None, want_series: tuple = (),
                   irregular: str = "error", duplicates: str = "error") -> ReferenceSeries:
    """The series of ``path`` a SEG or RTSTRUCT lies on (geometry only, no pixels).

    ``want_series``: SeriesInstanceUIDs the segmentation references; when the
    path holds several candidates and ``series`` chose none, the referenced one
    is taken. A stack that must be resampled (gantry tilt, irregular gaps) is
    refused: its slices are not the grid the contours or frames refer to.
    """
    where = str(path)
    cands = scan_dicom(path)
    if series is None and len(cands) > 1:
        hits = [c for c in cands if c.series_uid in want_series]
        if len(hits) == 1:
            series = hits[0].index
    cand = choose(cands, series, where)
    if cand.frames[0].synthetic:  # (before _plan, which warns of what it assumes)
        raise FormatError(f"{where}: the reference series gives no position per image "
                          "(ImagePositionPatient / ImageOrientationPatient of each slice): "
                          "nothing to place a segmentation on")
    plan, dtype, meta = _plan(path, series=None, irregular=irregular, duplicates=duplicates,
                              keep_shear=False, keep_phi=False, candidates=[cand])
    if plan.resampled:
        raise FormatError(f"{where}: the reference series must be read as it is stored (its "
                          "slices are resampled: gantry tilt or irregular gaps), so a "
                          "segmentation's frames or contours cannot be placed on it")
    f0 = plan.frames[0]
    rows, cols = f0.file.rows, f0.file.columns
    grid = make_header(where, (plan.n_out, rows, cols), np.uint8,
                       spacing=plan.spacing, origin=plan.origin, direction=plan.direction,
                       space=_LPS, file_space=_LPS, meta=meta)
    return ReferenceSeries(
        path=where, grid=grid, series_uid=f0.file.meta.get("SeriesInstanceUID", ""),
        frame_of_reference_uid=f0.file.meta.get("FrameOfReferenceUID", ""),
        study_uid=f0.file.meta.get("StudyInstanceUID", ""),
        sop_class_uid=f0.file.meta.get("SOPClassUID", ""),
        sop_uids=tuple(f.file.sop_uid for f in plan.frames),
        files=tuple(f.file.path for f in plan.frames),
        frame_numbers=tuple(f.frame + 1 if f.file.n_frames > 1 else None
                            for f in plan.frames),
        image_uids=frozenset(f.file.sop_uid for f in cand.frames))
