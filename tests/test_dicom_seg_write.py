"""Writing a label map as a DICOM SEG (`convert --dicom-type seg|labelmap-seg`).

Read back by highdicom (pixels equal) and by volwarp (exactly); new, reproducible
UIDs; the reference series and frame of reference referenced; off-grid maps refused.
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

from test_dicom_seg import write_ct  # noqa: E402

from volwarp_cli.io import write_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402

SHAPE = (6, 9, 11)


@pytest.fixture
def case(tmp_path):
    folder = tmp_path / "ct"
    paths = write_ct(folder, SHAPE)
    ref = read_dicom(folder)
    lab = np.zeros(SHAPE, np.uint16)
    lab[1:4, 2:7, 2:8] = 7
    lab[2, 3:5, 3:6] = 0          # a hole
    lab[2, 4, 4] = 300            # an island in it
    lab[4, 0, 0] = 2              # a slice with one voxel; slice 3 has 7 only
    lab[4, 1, 1] = 2              # touching the first at a corner
    src = tmp_path / "labels.nrrd"
    write_volume(ref.with_data(lab), src)
    return folder, paths, ref, lab, src


def test_labelmap_seg_round_trip_and_highdicom_reads_it(case, tmp_path, run):
    folder, paths, ref, lab, src = case
    out = tmp_path / "seg.dcm"
    res = run("convert", src, "--reference", folder, "--dicom-type", "labelmap-seg", "-o", out)
    assert res.code == 0, res.stderr
    seg = hd.seg.segread(out)
    assert seg.segmentation_type.value == "LABELMAP"
    assert sorted(seg.segment_numbers) == [2, 7, 300]
    theirs = seg.get_volume(combine_segments=True)
    assert theirs.spatial_shape[0] == 4  # slices 1..4: the empty ones are left out
    back = read_dicom(out, reference=folder)
    np.testing.assert_array_equal(back.data, lab)
    assert back.same_grid(ref)
    # highdicom's pixels, placed by its own affine, are volwarp's
    k, j, i = np.indices(theirs.spatial_shape).reshape(3, -1)
    world = (theirs.affine @ np.stack([k, j, i, np.ones_like(k)]))[:3].T
    x, y, z = np.rint(ref.world_to_index(world)).astype(int).T
    np.testing.assert_array_equal(lab[z, y, x], np.asarray(theirs.array)[k, j, i])


def test_binary_seg_numbers_segments_and_names_them(case, tmp_path, run):
    folder, paths, ref, lab, src = case
    names = tmp_path / "names.csv"
    names.write_text("label,name\n7,kidney\n300,cyst\n")
    out = tmp_path / "seg.dcm"
    res = run("convert", src, "--reference", folder, "--dicom-type", "seg", "--segments", names,
              "-o", out)
    assert res.code == 0, res.stderr
    seg = hd.seg.segread(out)
    assert seg.segmentation_type.value == "BINARY"
    labels = {int(s.SegmentNumber): str(s.SegmentLabel) for s in seg.SegmentSequence}
    assert labels == {1: "label 2", 2: "kidney", 3: "cyst"}
    assert all(s.SegmentedPropertyCategoryCodeSequence[0].CodingSchemeDesignator == "SCT"
               for s in seg.SegmentSequence)
    back = read_dicom(out, reference=folder)
    renumbered = np.select([lab == 2, lab == 7, lab == 300], [1, 2, 3], 0)
    np.testing.assert_array_equal(back.data, renumbered)
    # references the series and its frame of reference; its own UIDs are new
    ct = [pydicom.dcmread(p) for p in paths]
    ds = pydicom.dcmread(out)
    assert ds.ReferencedSeriesSequence[0].SeriesInstanceUID == ct[0].SeriesInstanceUID
    assert ds.FrameOfReferenceUID == ct[0].FrameOfReferenceUID
    assert ds.StudyInstanceUID == ct[0].StudyInstanceUID
    old = {str(d.SOPInstanceUID) for d in ct} | {str(ct[0].SeriesInstanceUID)}
    assert str(ds.SOPInstanceUID) not in old and str(ds.SeriesInstanceUID) not in old
    # the same inputs write the same bytes (no clock, UIDs made from the content)
    again = tmp_path / "again.dcm"
    assert run("convert", src, "--reference", folder, "--dicom-type", "seg", "--segments",
               names, "-o", again).code == 0
    assert again.read_bytes() == out.read_bytes()


def test_a_map_off_the_reference_grid_is_refused(case, tmp_path, run):
    folder, paths, ref, lab, src = case
    shifted = tmp_path / "half.nrrd"
    write_volume(ref.with_data(lab, origin=ref.index_to_world([0.5, 0, 0])), shifted)
    out = tmp_path / "seg.dcm"
    out.write_bytes(b"keep")
    res = run("convert", shifted, "--reference", folder, "--dicom-type", "seg", "-o", out)
    assert res.code == 1 and len(res.stderr.strip().splitlines()) == 1
    assert "the label map's grid" in res.stderr and "the reference series" in res.stderr
    assert res.stderr.count("origin") == 2
    assert out.read_bytes() == b"keep"
    for args, words in [((), "--dicom-type"), (("--dicom-type", "seg"), "--reference")]:
        res = run("convert", src, *args, "-o", tmp_path / "x.dcm")
        assert res.code == 2 and words in res.stderr
    res = run("convert", src, "--dicom-type", "seg", "--reference", folder, "-o",
              tmp_path / "x.nrrd")
    assert res.code == 2 and "-o NAME.dcm" in res.stderr
    bad = tmp_path / "bad.csv"
    bad.write_text("label,name\nseven,kidney\n")
    res = run("convert", src, "--reference", folder, "--dicom-type", "seg", "--segments", bad,
              "-o", tmp_path / "x.dcm")
    assert res.code == 2 and "bad.csv:2" in res.stderr
    assert not (tmp_path / "x.dcm").exists()
