"""DICOM SEG and RTSTRUCT: volwarp's reading and writing vs highdicom's own, same run.

The case is the issue's: a 117-label map (TotalSegmentator's label count) on a
256x256x120 CT series, written by volwarp as a LABELMAP SEG, a BINARY SEG (one
frame per segment and slice it covers) and an RTSTRUCT. Reading a SEG is timed
against highdicom reading the same file into a volume (``segread(...)``
``.get_volume(...)``: the label map highdicom assembles); writing a LABELMAP SEG
(whole processes) against a script in which highdicom builds and saves it. An
RTSTRUCT has no highdicom reader: reading one is timed against rt-utils (when
installed: ``RTStructBuilder.create_from`` and every ROI's ``get_roi_mask_by_name``,
checked to give the same masks) on two RTSTRUCTs of 117 ROIs: the blocks above
(4-point contours) and 117 organ-like ellipsoids (:func:`organ_map`, contours of a
few dozen to a few hundred vertices, as a planning system's), both written by volwarp.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from common import median_time, paired_times, row, volwarp_argv  # noqa: E402

LABELS = 117


def label_map(shape_zyx, labels: int = LABELS) -> np.ndarray:
    """``labels`` organs, each a block 8 slices deep, in 8 layers of a 4x4 in-plane grid, uint8.

    Each label spans 8 slices, as a small organ does, so a BINARY SEG of it has
    8 frames per segment (936 for 117 labels) and a LABELMAP SEG 64 frames.
    """
    nz, ny, nx = shape_zyx
    lab = np.zeros(shape_zyx, np.uint8)
    cy, cx = ny // 4, nx // 4
    step = (nz - 8) // 8
    for n in range(labels):
        layer, cell = divmod(n, 16)
        z0 = 4 + step * layer
        y0, x0 = (cell // 4) * cy, (cell % 4) * cx
        lab[z0:z0 + 8, y0 + 2:y0 + cy - 2, x0 + 2:x0 + cx - 2] = n + 1
    return lab


def organ_map(shape_zyx, labels: int = LABELS, seed: int = 1) -> np.ndarray:
    """``labels`` ellipsoids (semi-axes 3-15 slices, 4-25 voxels in-plane), each taking the
    voxels no earlier one took, uint8: organ-like outlines, several contours per slice.

    On 256x256x120 all 117 keep voxels; on the quick run's 128x128x60, 114.
    """
    nz, ny, nx = shape_zyx
    rng = np.random.default_rng(seed)
    lab = np.zeros(shape_zyx, np.uint8)
    z, y, x = np.ogrid[:nz, :ny, :nx]
    for n in range(labels):
        c = rng.uniform([10, 20, 20], [nz - 10, ny - 20, nx - 20])
        r = rng.uniform([3, 4, 4], [15, 25, 25])
        inside = ((z - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + \
            ((x - c[2]) / r[2]) ** 2 <= 1
        lab[inside & (lab == 0)] = n + 1
    return lab


def write_series(folder: Path, nx: int, ny: int, nz: int) -> None:
    """A CT series of ``nz`` int16 slices, one study, with the patient module a SEG copies."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    pixels = np.random.default_rng(0).integers(0, 2000, size=(ny, nx), dtype=np.int16)
    study, series, frame = generate_uid(), generate_uid(), generate_uid()
    for k in range(nz):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.PatientName, ds.PatientID = "Bench^Case", "B-1"
        for kw in ("PatientBirthDate", "PatientSex", "StudyDate", "StudyTime",
                   "AccessionNumber", "ReferringPhysicianName"):
            setattr(ds, kw, "")
        ds.StudyID, ds.Manufacturer = "1", "bench"
        ds.StudyInstanceUID, ds.SeriesInstanceUID = study, series
        ds.SeriesNumber = 1
        ds.FrameOfReferenceUID = frame
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [-125.0, -125.0, -150.0 + 1.25 * k]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [0.9765625, 0.9765625]
        ds.SliceThickness = 1.25
        ds.Rows, ds.Columns = ny, nx
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 1
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.PixelData = (pixels + k).tobytes()
        ds.save_as(folder / f"IM{nz - k:05d}.dcm", enforce_file_format=True)


def make_case(folder: Path, quick: bool = False) -> dict[str, Path]:
    """The CT series, the label map (NRRD) and volwarp's three files of it, under ``folder``."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.io.dicom import read_dicom, read_reference
    from volwarp_cli.io.dicom_seg import write_seg
    from volwarp_cli.io.rtstruct import write_rtstruct

    nx = ny = 128 if quick else 256
    nz = 60 if quick else 120
    ct = folder / "ct"
    ct.mkdir()
    write_series(ct, nx, ny, nz)
    grid = read_dicom(ct)
    lab = grid.with_data(label_map((nz, ny, nx)))
    paths = {"ct": ct, "labels": folder / "labels.nrrd", "labelmap": folder / "labelmap.dcm",
             "binary": folder / "binary.dcm", "rtstruct": folder / "rtstruct.dcm",
             "organs": folder / "organs.nrrd", "organs_rtstruct": folder / "organs_rs.dcm"}
    write_volume(lab, paths["labels"])
    ref = read_reference(ct)
    write_seg(lab, paths["labelmap"], ref, labelmap=True)
    write_seg(lab, paths["binary"], ref)
    write_rtstruct(lab, paths["rtstruct"], ref)
    organs = grid.with_data(organ_map((nz, ny, nx)))
    write_volume(organs, paths["organs"])
    write_rtstruct(organs, paths["organs_rtstruct"], ref)
    return paths


def rtutils_masks(ct: Path, rtstruct: Path) -> dict[str, np.ndarray]:
    """Every ROI's mask [z, y, x] as rt-utils reads it (its masks are [row, column, slice])."""
    import warnings

    import rt_utils

    with warnings.catch_warnings():  # (its pydicom 3 deprecations)
        warnings.simplefilter("ignore", DeprecationWarning)
        rt = rt_utils.RTStructBuilder.create_from(str(ct), str(rtstruct))
        return {name: rt.get_roi_mask_by_name(name).transpose(2, 0, 1)
                for name in rt.get_roi_names()}


#: highdicom building and saving a LABELMAP SEG of a label map on a series, as a script would
HIGHDICOM_WRITE = """
import sys, glob
import numpy as np, pydicom, highdicom as hd, nrrd
from pydicom.sr.codedict import codes
lab, _ = nrrd.read(sys.argv[2], index_order="C")
ds = sorted((pydicom.dcmread(p) for p in glob.glob(sys.argv[1] + "/*.dcm")),
            key=lambda d: float(d.ImagePositionPatient[2]))
values = [int(v) for v in np.unique(lab) if v]
descs = [hd.seg.SegmentDescription(
    segment_number=v, segment_label=f"label {v}", segmented_property_category=codes.SCT.Tissue,
    segmented_property_type=codes.SCT.Tissue,
    algorithm_type=hd.seg.SegmentAlgorithmTypeValues.MANUAL) for v in values]
seg = hd.seg.Segmentation(
    source_images=ds, pixel_array=lab, segmentation_type="LABELMAP",
    segment_descriptions=descs, series_instance_uid=hd.UID(), series_number=1,
    sop_instance_uid=hd.UID(), instance_number=1, manufacturer="x",
    manufacturer_model_name="x", software_versions="1", device_serial_number="1")
seg.save_as(sys.argv[3])
"""


def main(quick: bool = False) -> None:
    import highdicom as hd

    from volwarp_cli.io import read_volume
    from volwarp_cli.io.dicom import read_dicom

    pairs = 3 if quick else 5
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        p = make_case(tmp, quick)
        want = read_volume(p["labels"]).data
        size = "x".join(str(n) for n in want.shape[::-1])
        for kind in ("labelmap", "binary"):
            path = p[kind]

            def ours(path=path):
                return read_volume(path)

            if kind == "labelmap":
                def peer(path=path):
                    return hd.seg.segread(str(path)).get_volume(combine_segments=True)
            else:
                def peer(path=path):
                    return hd.seg.segread(str(path)).get_volume(combine_segments=True,
                                                                dtype=np.uint8)
            # (on the series' whole grid, the map written; labels 1..117 all present, so the
            # BINARY SEG's segment numbers 1..K are the labels too)
            if not np.array_equal(read_dicom(path, reference=p["ct"]).data, want):
                raise AssertionError(f"volwarp reads the {kind} SEG wrongly")
            ours()
            peer()
            t_ours, t_peer, ratio = paired_times(ours, peer, pairs=pairs)
            frames = int(hd.seg.segread(str(path)).NumberOfFrames)
            row(f"read {LABELS}-label {kind.upper()} SEG {size} ({frames} frames)", t_ours,
                t_peer, "highdicom get_volume", ratio=ratio)

        try:
            import rt_utils  # noqa: F401
        except ImportError:  # (not installed, or its OpenCV lacks libGL: volwarp alone)
            rt_utils = None
        for kind, labels_key, what in (("rtstruct", "labels", "blocks, 4-point contours"),
                                       ("organs_rtstruct", "organs", "organ shapes")):
            def rs_read(kind=kind):
                return read_dicom(p[kind], reference=p["ct"])

            truth = read_volume(p[labels_key]).data
            if not np.array_equal(rs_read().data, truth):
                raise AssertionError(f"volwarp reads its RTSTRUCT ({what}) wrongly")
            rois = len(np.unique(truth)) - 1
            name = f"read {rois}-ROI RTSTRUCT ({what}) on {size}"
            if rt_utils is None:
                row(name, median_time(rs_read, pairs))
                continue

            def peer(kind=kind):
                return rtutils_masks(p["ct"], p[kind])

            masks = peer()
            if len(masks) != rois or any(
                    not np.array_equal(m, truth == int(n.removeprefix("label_")))
                    for n, m in masks.items()):
                raise AssertionError(f"rt-utils reads volwarp's RTSTRUCT ({what}) otherwise")
            t_ours, t_peer, ratio = paired_times(rs_read, peer, pairs=min(pairs, 3))
            row(name, t_ours, t_peer, "rt-utils every ROI", ratio=ratio)

        out = tmp / "out"
        out.mkdir()

        def ours_cmd():
            subprocess.run(volwarp_argv("convert", str(p["labels"]), "--reference", str(p["ct"]),
                                        "--dicom-type", "labelmap-seg", "-o",
                                        str(out / "v.dcm")),
                           check=True, stdout=subprocess.DEVNULL)

        def peer_cmd():
            subprocess.run([sys.executable, "-c", HIGHDICOM_WRITE, str(p["ct"]),
                            str(p["labels"]), str(out / "h.dcm")],
                           check=True, stdout=subprocess.DEVNULL)

        ours_cmd()
        peer_cmd()
        t_ours, t_peer, ratio = paired_times(ours_cmd, peer_cmd, pairs=pairs)
        row(f"write {LABELS}-label LABELMAP SEG {size} (whole command)", t_ours, t_peer,
            "highdicom script", ratio=ratio)

        def rs_cmd():
            subprocess.run(volwarp_argv("convert", str(p["labels"]), "--reference", str(p["ct"]),
                                        "--dicom-type", "rtstruct", "-o", str(out / "r.dcm")),
                           check=True, stdout=subprocess.DEVNULL)

        row(f"write {LABELS}-ROI RTSTRUCT {size} (whole command)", median_time(rs_cmd, pairs))


if __name__ == "__main__":
    main(quick="--quick" in sys.argv)
