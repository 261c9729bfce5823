"""Writing a label map as an RTSTRUCT (`convert --dicom-type rtstruct`), read back exactly.

Holes, islands in holes and voxels touching only at a corner survive the round trip;
the outlines also give the mask to an independent polygon filler (scikit-image's
``polygon2mask``, XOR over a slice's loops); vertices lie within 0.05 voxel of voxel
corners; each contour references an image the series has.
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")

from test_dicom_seg import write_ct  # noqa: E402

from volwarp_cli.io import read_volume, write_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402
from volwarp_cli.io.rtstruct import NUDGE, mask_outlines  # noqa: E402

SHAPE = (4, 12, 13)


def tricky_labels() -> np.ndarray:
    lab = np.zeros(SHAPE, np.uint8)
    lab[0, 1:10, 1:10] = 5
    lab[0, 3:8, 3:8] = 0                 # a hole
    lab[0, 5, 5] = 5                     # an island in the hole
    lab[1, 2, 2] = lab[1, 3, 3] = 9      # corner-touching voxels
    lab[1, 4, 2] = lab[1, 3, 3]          # and a third at the other corner
    lab[1, 0, 0:13] = 9                  # a line along the whole edge of the grid
    lab[2, 5:8, 5:8] = 5
    lab[2, 6, 6] = 9                     # another label inside a label (not overlapping)
    lab[3, 11, 12] = 200                 # the last voxel of the grid
    return lab


def test_outlines_give_the_mask_to_an_independent_filler():
    from skimage.draw import polygon2mask

    rng = np.random.default_rng(2)
    for _ in range(25):
        mask = rng.random((9, 11)) < rng.uniform(0.2, 0.7)
        got = np.zeros(mask.shape, bool)
        for loop in mask_outlines(mask):
            # vertices within the nudge of a voxel corner (corners are at half indices)
            corner = np.rint(loop - 0.5) + 0.5
            assert np.abs(loop - corner).max() <= NUDGE + 1e-12 and NUDGE <= 0.05
            got ^= polygon2mask(mask.shape, loop[:, ::-1])  # (row, column) vertices
        np.testing.assert_array_equal(got, mask)


def test_rtstruct_round_trip_is_exact(tmp_path, run):
    folder = tmp_path / "ct"
    paths = write_ct(folder, SHAPE, spacing=(0.7, 0.9, 3.0))
    ref = read_dicom(folder)
    lab = tricky_labels()
    src = tmp_path / "labels.nrrd"
    write_volume(ref.with_data(lab), src)
    names = tmp_path / "names.csv"
    names.write_text("label,name\n5,ring\n")
    out = tmp_path / "rs.dcm"
    res = run("convert", src, "--reference", folder, "--dicom-type", "rtstruct", "--segments",
              names, "-o", out)
    assert res.code == 0, res.stderr
    back = tmp_path / "back.nrrd"
    assert run("convert", out, "--reference", folder, "-o", back).code == 0
    got = read_volume(back)
    np.testing.assert_array_equal(got.data, lab)
    assert got.same_grid(ref)
    ds = pydicom.dcmread(out)
    assert [(int(r.ROINumber), str(r.ROIName)) for r in ds.StructureSetROISequence] == \
        [(5, "ring"), (9, "label_9"), (200, "label_200")]
    ct = {str(pydicom.dcmread(p).SOPInstanceUID) for p in paths}
    listed = ds.ReferencedFrameOfReferenceSequence[0].RTReferencedStudySequence[0] \
        .RTReferencedSeriesSequence[0].ContourImageSequence
    assert {str(i.ReferencedSOPInstanceUID) for i in listed} == ct
    for roi in ds.ROIContourSequence:
        for c in roi.ContourSequence:
            (img,) = c.ContourImageSequence
            assert str(img.ReferencedSOPInstanceUID) in ct
            pts = np.array(c.ContourData, float).reshape(-1, 3)
            k = ref.world_to_index(pts)[:, 2]
            # the referenced image is the slice the contour lies on
            assert str(img.ReferencedSOPInstanceUID) == \
                str(pydicom.dcmread(_file_at(paths, ref, k[0])).SOPInstanceUID)
    assert str(ds.SeriesInstanceUID) != str(pydicom.dcmread(paths[0]).SeriesInstanceUID)
    again = tmp_path / "again.dcm"
    assert run("convert", src, "--reference", folder, "--dicom-type", "rtstruct", "--segments",
               names, "-o", again).code == 0
    assert again.read_bytes() == out.read_bytes()


def _file_at(paths, ref, k):
    for p in paths:
        pos = np.array(pydicom.dcmread(p).ImagePositionPatient, float)
        if abs(ref.world_to_index(pos)[2] - k) < 1e-3:
            return p
    raise AssertionError(k)


def _polygon_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_smooth_contours_read_back_and_their_volumes(tmp_path, run):
    """``--contours smooth``: the map back (Dice 1 >= 0.95, by volwarp and by an independent
    filler), outlines that cut the staircases, and polygon volumes within 1% of the voxels'."""
    from skimage.draw import polygon2mask

    shape = (12, 16, 17)
    folder = tmp_path / "ct"
    write_ct(folder, shape, spacing=(0.7, 0.9, 1.5))
    ref = read_dicom(folder)
    z, y, x = np.indices(shape)
    ball = (((x - 8) * 0.7) ** 2 + ((y - 7.5) * 0.9) ** 2 + ((z - 5.5) * 1.5) ** 2) <= 5.0 ** 2
    lab = np.where(ball, 4, 0).astype(np.uint8)
    lab[1, 2, 2] = lab[1, 3, 3] = 7  # corner-touching voxels: loops of their own
    src = tmp_path / "ball.nrrd"
    write_volume(ref.with_data(lab), src)
    out = tmp_path / "smooth.dcm"
    res = run("convert", src, "--reference", folder, "--dicom-type", "rtstruct", "--contours",
              "smooth", "-o", out)
    assert res.code == 0, res.stderr
    back = tmp_path / "back.nrrd"
    assert run("convert", out, "--reference", folder, "-o", back).code == 0
    got = read_volume(back).data
    dice = 2 * np.sum((got == 4) & ball) / (np.sum(got == 4) + ball.sum())
    assert dice >= 0.95
    np.testing.assert_array_equal(got, lab)  # (in fact exact)
    ds = pydicom.dcmread(out)
    filled = np.zeros(shape, bool)
    area = 0.0
    diagonal = False
    for c in ds.ROIContourSequence[0].ContourSequence:  # (ROI 4, the ball)
        pts = ref.world_to_index(np.array(c.ContourData, float).reshape(-1, 3))
        k = int(round(pts[0, 2]))
        filled[k] ^= polygon2mask(shape[1:], pts[:, 1::-1])
        area += _polygon_area(pts[:, :2])
        steps = np.diff(np.vstack([pts[:, :2], pts[:1, :2]]), axis=0)
        diagonal |= bool(np.any(np.all(np.abs(steps) > 1e-3, axis=1)))
    np.testing.assert_array_equal(filled, ball)
    assert diagonal  # not voxel edges: the staircases are cut
    assert abs(abs(area) / ball.sum() - 1) <= 0.01
    assert [int(c.NumberOfContourPoints) >= 3 for c in
            ds.ROIContourSequence[1].ContourSequence] == [True, True]
    again = tmp_path / "again.dcm"
    assert run("convert", src, "--reference", folder, "--dicom-type", "rtstruct", "--contours",
               "smooth", "-o", again).code == 0
    assert again.read_bytes() == out.read_bytes()
    res = run("convert", src, "--reference", folder, "--dicom-type", "seg", "--contours",
              "smooth", "-o", tmp_path / "seg.dcm")
    assert res.code == 2 and "--dicom-type rtstruct" in res.stderr


def test_nested_rois_written_back_keep_the_outer_roi_whole(tmp_path, run):
    """A map read from nested ROIs holds each voxel in the smallest ROI (BODY's label only where
    no organ is); written back as an RTSTRUCT or a BINARY SEG, BODY is its whole mask again,
    the organs inside it (before, it had their holes: 1520 -> 1445 voxels, silently). A
    LABELMAP SEG cannot overlap: it keeps the holes and says so."""
    from test_rtstruct import square, world, write_rtstruct

    shape = (5, 20, 24)
    folder = tmp_path / "ct"
    paths = write_ct(folder, shape, spacing=(0.8, 0.8, 2.0))
    ct = read_dicom(folder)

    def on(k, *box):
        return ("CLOSED_PLANAR", world(ct, k, square(*box)))
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        1: ("BODY", [on(k, 1.5, 1.5, 20.5, 17.5) for k in range(5)]),
        2: ("liver", [on(k, 4.5, 4.5, 9.5, 9.5) for k in (1, 2, 3)]),
        3: ("tumour", [on(2, 6.5, 6.5, 8.5, 8.5)])})
    masks = {n: np.zeros(shape, np.uint8) for n in (1, 2, 3)}
    masks[1][:, 2:18, 2:21] = 1
    masks[2][1:4, 5:10, 5:10] = 1
    masks[3][2, 7:9, 7:9] = 1
    names = {1: "BODY", 2: "liver", 3: "tumour"}
    whole = tmp_path / "map.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", whole)
    assert res.code == 0, res.stderr
    lab = read_volume(whole)
    assert lab.meta["DICOM_ROI_nested"] == "2 in 1; 3 in 1; 3 in 2"
    assert np.count_nonzero(lab.data == 1) == masks[1].sum() - masks[2].sum() == 1520 - 75

    back = tmp_path / "back.dcm"
    res = run("convert", whole, "--reference", folder, "--dicom-type", "rtstruct", "-o", back)
    assert res.code == 0 and "warning" not in res.stderr, res.stderr
    for n, name in names.items():
        got = tmp_path / f"roi{n}.nrrd"
        res = run("convert", back, "--reference", folder, "--structure", name, "-o", got)
        assert res.code == 0, res.stderr
        np.testing.assert_array_equal(read_volume(got).data, masks[n])
    res = run("convert", back, "--reference", folder, "-o", tmp_path / "again.nrrd")
    assert res.code == 0, res.stderr
    np.testing.assert_array_equal(read_volume(tmp_path / "again.nrrd").data, lab.data)

    seg = tmp_path / "seg.dcm"
    res = run("convert", whole, "--reference", folder, "--dicom-type", "seg", "-o", seg)
    assert res.code == 0 and "warning" not in res.stderr, res.stderr
    ds = pydicom.dcmread(seg)
    assert [str(s.SegmentLabel) for s in ds.SegmentSequence] == ["BODY", "liver", "tumour"]
    for n in names:  # (segment numbers 1..K in label order: here the labels)
        got = tmp_path / f"seg{n}.nrrd"
        res = run("convert", seg, "--reference", folder, "--segment", n, "-o", got)
        assert res.code == 0, res.stderr
        np.testing.assert_array_equal(read_volume(got).data, masks[n])

    flat = tmp_path / "labelmap.dcm"
    res = run("convert", whole, "--reference", folder, "--dicom-type", "labelmap-seg", "-o", flat)
    assert res.code == 0, res.stderr
    warned = [line for line in res.stderr.splitlines() if "warning" in line]
    assert len(warned) == 1 and str(flat) in warned[0] and "1 holds 2 3; 2 holds 3" in warned[0]
    assert "--dicom-type seg or rtstruct" in warned[0]
    res = run("convert", flat, "--reference", folder, "-o", tmp_path / "flat.nrrd")
    assert res.code == 0, res.stderr
    np.testing.assert_array_equal(read_volume(tmp_path / "flat.nrrd").data, lab.data)


def test_nested_labels_are_followed_to_every_depth():
    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.io.segment_keys import nested_labels

    meta = {"DICOM_ROI_nested": "3 in 2; 2 in 1; 7 in 9"}
    assert nested_labels(meta, [1, 2, 3, 9], "m") == {1: [2, 3], 2: [3]}
    assert nested_labels(meta, [1, 3], "m") == {1: [3]}  # (label 2 warped away: 3 still in 1)
    assert nested_labels({}, [1, 2], "m") == {}
    with pytest.raises(VolwarpError, match="m: key/value DICOM_ROI_nested.*INNER in OUTER"):
        nested_labels({"DICOM_ROI_nested": "2 inside 1"}, [1, 2], "m")


def test_a_series_without_a_frame_of_reference_is_refused(tmp_path, run):
    """An RTSTRUCT names its frame of reference (Type 1, in the structure set and each ROI):
    over a series that has none it was written with empty UIDs, exit 0, as no other tool
    would read it; it is refused as the SEG is, nothing written."""
    folder = tmp_path / "ct"
    for p in write_ct(folder, (6, 10, 12)):
        ds = pydicom.dcmread(p)
        del ds.FrameOfReferenceUID
        ds.save_as(p)
    ref = read_dicom(folder)
    lab = np.zeros(ref.shape, np.uint8)
    lab[2:4, 3:7, 4:8] = 3
    write_volume(ref.with_data(lab), tmp_path / "lab.nrrd")
    for kind in ("rtstruct", "seg"):
        out = tmp_path / f"{kind}.dcm"
        res = run("convert", tmp_path / "lab.nrrd", "--reference", folder, "--dicom-type", kind,
                  "-o", out)
        assert res.code == 1 and "Frame Of Reference UID" in res.stderr.replace(
            "FrameOfReferenceUID", "Frame Of Reference UID"), res
        assert not out.exists()
        if kind == "rtstruct":  # (the series at fault named)
            assert f"the reference series ({folder}) has no" in res.stderr
