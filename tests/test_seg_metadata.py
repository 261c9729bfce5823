"""Segment and ROI descriptions kept through a label map file and written back.

A SEG or RTSTRUCT read as a label map records each segment's label, colour,
property category and type, and algorithm (each ROI's name and colour) in the
volume's key/values; they travel through NRRD, NIfTI and ``warp``, and a SEG or
RTSTRUCT written from the map takes them back (``--segments`` names win).
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

from pydicom.sr.coding import Code  # noqa: E402
from test_dicom_seg import masks_of, sorted_sources, write_ct  # noqa: E402
from test_segmentation_inputs import WARP_SPEC, liver_and_ptv  # noqa: E402

from volwarp_cli.io import read_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402

SHAPE = (5, 14, 16)  # z, y, x
SPACING = (0.9, 0.6, 2.0)

CATEGORY = {1: Code("123037004", "SCT", "Anatomical Structure"),
            2: Code("49755003", "SCT", "Morphologically Altered Structure"),
            3: Code("123037004", "SCT", "Anatomical Structure")}
TYPE = {1: Code("10200004", "SCT", "Liver"),
        2: Code("108369006", "SCT", "Neoplasm"),
        3: Code("64033007", "SCT", "Kidney")}
LABEL = {1: "liver", 2: "tumour, left lobe", 3: "kidney"}
COLOUR = {1: (49107, 39048, 53188), 2: (30000, 50000, 20000)}  # (segment 3: none)


def lab_fixture() -> np.ndarray:
    """Three labels on SHAPE, far enough from the border to survive a small warp."""
    lab = np.zeros(SHAPE, np.uint8)
    lab[1:4, 3:8, 3:9] = 1
    lab[2, 4:6, 4:6] = 2
    lab[1:4, 8:12, 10:14] = 3
    return lab


def make_described_seg(paths, lab, kind: str, out):
    """highdicom's SEG of ``lab`` with distinct labels, codes, colours and algorithms."""
    algo = hd.AlgorithmIdentificationSequence(
        name="SegNet", family=Code("113289", "DCM", "Artificial Intelligence"), version="2.1")
    descs = []
    for n in (1, 2, 3):
        kw = {}
        if n in COLOUR:
            kw["display_color"] = hd.color.CIELabColor.from_dicom_value(COLOUR[n])
        if n == 2:
            kw["algorithm_identification"] = algo
        descs.append(hd.seg.SegmentDescription(
            segment_number=n, segment_label=LABEL[n], segmented_property_category=CATEGORY[n],
            segmented_property_type=TYPE[n],
            algorithm_type="AUTOMATIC" if n == 2 else "MANUAL", **kw))
    pixels = masks_of(lab) if kind == "BINARY" else lab
    seg = hd.seg.Segmentation(
        source_images=sorted_sources(paths), pixel_array=pixels, segmentation_type=kind,
        segment_descriptions=descs, series_instance_uid=hd.UID(), series_number=5,
        sop_instance_uid=hd.UID(), instance_number=1, manufacturer="test",
        manufacturer_model_name="test", software_versions="1", device_serial_number="1")
    seg.save_as(out)
    return out


def _code(seq) -> tuple:
    item = seq[0]
    return (str(item.CodingSchemeDesignator), str(item.CodeValue), str(item.CodeMeaning))


def described(ds) -> dict:
    """{segment number: (label, category, type, colour, algorithm type, name)} of a SEG.

    (A LABELMAP SEG's segment 0, highdicom's Background, is no label.)
    """
    out = {}
    for s in ds.SegmentSequence:
        if int(s.SegmentNumber) == 0:
            continue
        colour = s.get("RecommendedDisplayCIELabValue")
        out[int(s.SegmentNumber)] = (
            str(s.SegmentLabel), _code(s.SegmentedPropertyCategoryCodeSequence),
            _code(s.SegmentedPropertyTypeCodeSequence),
            tuple(int(v) for v in colour) if colour is not None else None,
            str(s.SegmentAlgorithmType), str(s.get("SegmentAlgorithmName", "")))
    return out


@pytest.fixture
def ct(tmp_path):
    folder = tmp_path / "ct"
    return folder, write_ct(folder, SHAPE, spacing=SPACING)


@pytest.mark.parametrize("kind", ["BINARY", "LABELMAP"])
@pytest.mark.parametrize("ext", [".nrrd", ".nii.gz"])
def test_seg_descriptions_kept_through_a_label_map_file(ct, tmp_path, run, kind, ext):
    folder, paths = ct
    lab = lab_fixture()
    seg = make_described_seg(paths, lab, kind, tmp_path / "seg.dcm")
    original = described(pydicom.dcmread(seg))
    mid = tmp_path / f"lab{ext}"
    res = run("convert", seg, "--reference", folder, "-o", mid)
    assert res.code == 0, res.stderr
    meta = read_volume(mid).meta
    assert meta["DICOM_Segment_2_Label"] == "tumour, left lobe"
    assert meta["DICOM_Segment_2_Category"] == "SCT^49755003^Morphologically Altered Structure"
    assert meta["DICOM_Segment_1_Type"] == "SCT^10200004^Liver"
    assert meta["DICOM_Segment_1_CIELab"] == "49107 39048 53188"
    assert "DICOM_Segment_3_CIELab" not in meta
    assert meta["DICOM_Segment_2_Algorithm"] == "AUTOMATIC"
    assert meta["DICOM_Segment_2_AlgorithmName"] == "SegNet"
    for dicom_type in ("seg", "labelmap-seg"):
        out = tmp_path / f"{dicom_type}.dcm"
        res = run("convert", mid, "--reference", folder, "--dicom-type", dicom_type, "-o", out)
        assert res.code == 0, res.stderr
        ds = hd.seg.segread(out)
        assert described(ds) == original  # (labels 1..3: the segment numbers are the same)
        algo = {int(s.SegmentNumber): s for s in ds.SegmentSequence}[2]
        ident = algo.SegmentationAlgorithmIdentificationSequence[0]
        assert (ident.AlgorithmName, ident.AlgorithmVersion,
                _code(ident.AlgorithmFamilyCodeSequence)) == (
            "SegNet", "2.1", ("DCM", "113289", "Artificial Intelligence"))
        np.testing.assert_array_equal(read_dicom(out, reference=folder).data, lab)


def test_seg_descriptions_kept_through_warp(ct, tmp_path, run):
    folder, paths = ct
    lab = lab_fixture()
    seg = make_described_seg(paths, lab, "BINARY", tmp_path / "seg.dcm")
    original = described(pydicom.dcmread(seg))
    mid = tmp_path / "lab.nrrd"
    assert run("convert", seg, "--reference", folder, "-o", mid).code == 0
    spec = tmp_path / "w.yaml"
    spec.write_text(WARP_SPEC)
    warped = tmp_path / "warped.nrrd"
    res = run("warp", mid, "--spec", spec, "--preserve-labels", "-o", warped)
    assert res.code == 0, res.stderr
    moved = read_volume(warped)
    assert not np.array_equal(moved.data, lab) and set(np.unique(moved.data)) == {0, 1, 2, 3}
    before = read_volume(mid).meta
    assert {k: v for k, v in moved.meta.items() if k.startswith("DICOM_Segment_")} == \
        {k: v for k, v in before.items() if k.startswith("DICOM_Segment_")}
    out = tmp_path / "out.dcm"
    res = run("convert", warped, "--reference", folder, "--dicom-type", "seg", "-o", out)
    assert res.code == 0, res.stderr
    assert described(pydicom.dcmread(out)) == original


def test_segments_csv_wins_and_unkeyed_labels_keep_the_defaults(ct, tmp_path, run):
    folder, paths = ct
    lab = lab_fixture()
    seg = make_described_seg(paths, lab, "LABELMAP", tmp_path / "seg.dcm")
    original = described(pydicom.dcmread(seg))
    mid = tmp_path / "lab.nrrd"
    assert run("convert", seg, "--reference", folder, "-o", mid).code == 0
    vol = read_volume(mid)
    more = vol.data.copy()
    more[0, 0, 0] = 9  # a label the SEG did not have: no keys
    from volwarp_cli.io import write_volume

    mid = tmp_path / "more.nrrd"
    write_volume(vol.with_data(more), mid)
    names = tmp_path / "names.csv"
    names.write_text("label,name\n1,hepar\n")
    out = tmp_path / "out.dcm"
    res = run("convert", mid, "--reference", folder, "--dicom-type", "labelmap-seg",
              "--segments", names, "-o", out)
    assert res.code == 0, res.stderr
    got = described(pydicom.dcmread(out))
    assert got[1] == ("hepar",) + original[1][1:]  # the name from --segments, the rest kept
    assert got[2] == original[2] and got[3] == original[3]
    assert got[9] == ("label 9", ("SCT", "85756007", "Tissue"), ("SCT", "85756007", "Tissue"),
                      None, "MANUAL", "")


@pytest.mark.parametrize("kind", ["seg", "labelmap-seg", "rtstruct"])
def test_segments_csv_rows_naming_no_label_are_warned(ct, tmp_path, run, kind):
    """Rows of --segments for 0 or a label the map lacks name nothing: one warning naming the
    CSV and those ids (before: silent); the rows that match still name their labels."""
    from volwarp_cli.io import write_volume

    folder, paths = ct
    ref = read_dicom(folder)
    lab = tmp_path / "lab.nrrd"
    write_volume(ref.with_data(lab_fixture()), lab)
    names = tmp_path / "names.csv"
    names.write_text("label,name\n0,air\n2,tumour\n7,spleen\n12,bladder\n")
    out = tmp_path / "out.dcm"
    res = run("convert", lab, "--reference", folder, "--dicom-type", kind, "--segments", names,
              "-o", out)
    assert res.code == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "warning" in lines[0] and str(names) in lines[0], res.stderr
    assert "labels 0 7 12 name nothing" in lines[0]
    ds = pydicom.dcmread(out)
    got = roi_table(ds) if kind == "rtstruct" else {
        int(s.SegmentNumber): (str(s.SegmentLabel),) for s in ds.SegmentSequence}
    assert {n: v[0] for n, v in got.items() if n} == (  # (a LABELMAP SEG's 0: highdicom's)
        {1: "label_1", 2: "tumour", 3: "label_3"} if kind == "rtstruct" else
        {1: "label 1", 2: "tumour", 3: "label 3"})
    names.write_text("2,tumour\n3,kidney\n")
    res = run("convert", lab, "--reference", folder, "--dicom-type", kind, "--segments", names,
              "-o", out)
    assert res.code == 0 and not res.stderr.strip(), res.stderr


def test_one_segment_mask_keeps_its_description(ct, tmp_path, run):
    folder, paths = ct
    seg = make_described_seg(paths, lab_fixture(), "BINARY", tmp_path / "seg.dcm")
    original = described(pydicom.dcmread(seg))
    mid = tmp_path / "two.nrrd"
    assert run("convert", seg, "--segment", 2, "--reference", folder, "-o", mid).code == 0
    out = tmp_path / "out.dcm"
    res = run("convert", mid, "--reference", folder, "--dicom-type", "seg", "-o", out)
    assert res.code == 0, res.stderr
    assert described(pydicom.dcmread(out)) == {1: original[2]}


def roi_table(ds) -> dict:
    """{ROI Number: (name, colour)} of an RTSTRUCT."""
    colours = {int(c.ReferencedROINumber): tuple(int(v) for v in c.ROIDisplayColor)
               for c in ds.ROIContourSequence if "ROIDisplayColor" in c}
    return {int(r.ROINumber): (str(r.ROIName), colours.get(int(r.ROINumber)))
            for r in ds.StructureSetROISequence}


@pytest.fixture
def rs_case(tmp_path, ct):
    folder, paths = ct
    rs = liver_and_ptv(tmp_path / "rs.dcm", folder, paths)
    ds = pydicom.dcmread(rs)
    ds.ROIContourSequence[0].ROIDisplayColor = [220, 40, 7]
    ds.ROIContourSequence[1].ROIDisplayColor = [0, 128, 255]
    ds.save_as(rs, enforce_file_format=True)
    return folder, rs


def test_rtstruct_names_and_colours_kept_through_a_label_map_file(rs_case, tmp_path, run):
    folder, rs = rs_case
    original = roi_table(pydicom.dcmread(rs))
    mid = tmp_path / "lab.nrrd"
    assert run("convert", rs, "--reference", folder, "-o", mid).code == 0
    meta = read_volume(mid).meta
    assert meta["DICOM_ROI_3"] == "liver" and meta["DICOM_ROI_3_Color"] == "220 40 7"
    spec = tmp_path / "w.yaml"
    spec.write_text(WARP_SPEC)
    warped = tmp_path / "warped.nrrd"
    assert run("warp", mid, "--spec", spec, "--preserve-labels", "-o", warped).code == 0
    out = tmp_path / "out.dcm"
    res = run("convert", warped, "--reference", folder, "--dicom-type", "rtstruct", "-o", out)
    assert res.code == 0, res.stderr
    assert roi_table(pydicom.dcmread(out)) == original
    # --segments wins over the keys
    names = tmp_path / "names.csv"
    names.write_text("7,planning target\n")
    res = run("convert", warped, "--reference", folder, "--dicom-type", "rtstruct",
              "--segments", names, "-o", out)
    assert res.code == 0, res.stderr
    assert roi_table(pydicom.dcmread(out)) == {3: original[3],
                                               7: ("planning target", original[7][1])}


def test_descriptions_cross_between_seg_and_rtstruct(ct, rs_case, tmp_path, run):
    folder, paths = ct
    seg = make_described_seg(paths, lab_fixture(), "BINARY", tmp_path / "seg.dcm")
    mid = tmp_path / "seg_lab.nrrd"
    assert run("convert", seg, "--reference", folder, "-o", mid).code == 0
    out = tmp_path / "rs_out.dcm"
    res = run("convert", mid, "--reference", folder, "--dicom-type", "rtstruct", "-o", out)
    assert res.code == 0, res.stderr
    rois = roi_table(pydicom.dcmread(out))
    assert {n: name for n, (name, _) in rois.items()} == LABEL
    assert rois[1][1] == hd.color.CIELabColor.from_dicom_value(COLOUR[1]).to_rgb()
    # an RTSTRUCT's names and colours name and colour a SEG's segments
    _, rs = rs_case
    mid = tmp_path / "rs_lab.nrrd"
    assert run("convert", rs, "--reference", folder, "-o", mid).code == 0
    out = tmp_path / "seg_out.dcm"
    res = run("convert", mid, "--reference", folder, "--dicom-type", "labelmap-seg", "-o", out)
    assert res.code == 0, res.stderr
    got = described(pydicom.dcmread(out))
    assert {n: d[0] for n, d in got.items()} == {3: "liver", 7: "PTV"}
    assert got[3][3] == hd.color.CIELabColor.from_rgb(220, 40, 7).value


def test_a_key_that_does_not_parse_is_one_line_naming_it(ct, tmp_path, run):
    folder, paths = ct
    ref = read_dicom(folder)
    from volwarp_cli.io import write_volume

    src = tmp_path / "lab.nrrd"
    write_volume(ref.with_data(lab_fixture(), meta={"DICOM_Segment_2_CIELab": "red"}), src)
    out = tmp_path / "out.dcm"
    res = run("convert", src, "--reference", folder, "--dicom-type", "seg", "-o", out)
    assert res.code == 1 and len(res.stderr.strip().splitlines()) == 1
    assert "lab.nrrd" in res.stderr and "DICOM_Segment_2_CIELab='red'" in res.stderr
    assert not out.exists()


def test_a_code_a_seg_read_beyond_the_standard_still_writes_back():
    """A SEG with an 81-character meaning (or an empty one) reads, and its keys then
    refused the write back (exit 1; a review). The meaning is cut at DICOM's 64
    characters, an empty part gives the default code; a code without three parts is
    still an error naming the key."""
    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.io.segment_keys import label_descriptions

    long = "M" * 81
    meta = {"DICOM_Segment_1_Type": f"SCT^10200004^{long}",
            "DICOM_Segment_2_Type": "SCT^10200004^", "DICOM_Segment_2_Label": "two"}
    d = label_descriptions(meta, [1, 2], "x.nrrd")
    assert d[1].type == ("SCT", "10200004", "M" * 64)
    assert d[2].type is None and d[2].seg_label == "two"
    with pytest.raises(VolwarpError, match="DICOM_Segment_1_Type"):
        label_descriptions({"DICOM_Segment_1_Type": "SCT-Liver"}, [1], "x.nrrd")
