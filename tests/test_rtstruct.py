"""DICOM RTSTRUCT input: contours rasterised on the reference series' grid by the stated rule.

The rule (even-odd; a voxel centre within 1e-3 voxel of a contour is inside) is
checked on hand-drawn contours with holes, islands, contours through voxel centres
(rt-utils' habit), 1- and 2-point contours, on an oblique series; and against a slow
point-in-polygon reference on random polygons.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")

from pydicom.data import get_testdata_file  # noqa: E402
from pydicom.dataset import Dataset, FileMetaDataset  # noqa: E402
from pydicom.sequence import Sequence  # noqa: E402
from pydicom.uid import ExplicitVRLittleEndian, generate_uid  # noqa: E402
from test_dicom_seg import write_ct  # noqa: E402

from volwarp_cli.errors import FormatError  # noqa: E402
from volwarp_cli.io import read_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402
from volwarp_cli.io.rtstruct import RTSTRUCT_SOP, rasterize  # noqa: E402

SHAPE = (5, 14, 16)  # z, y, x


def write_rtstruct(path, ct_paths, rois, *, series_uid=None, frame_uid=None):
    """An RTSTRUCT whose ``rois`` are {number: (name, [(type, points (n, 3) LPS mm), ...])}."""
    ref = pydicom.dcmread(ct_paths[0])
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = RTSTRUCT_SOP
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = RTSTRUCT_SOP
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "RTSTRUCT"
    ds.StudyInstanceUID = ref.StudyInstanceUID
    ds.SeriesInstanceUID = generate_uid()
    ds.StructureSetLabel = "test"
    frame = frame_uid or ref.FrameOfReferenceUID
    se = Dataset()
    se.SeriesInstanceUID = series_uid or ref.SeriesInstanceUID
    st = Dataset()
    st.ReferencedSOPInstanceUID = ref.StudyInstanceUID
    st.RTReferencedSeriesSequence = Sequence([se])
    fr = Dataset()
    fr.FrameOfReferenceUID = frame
    fr.RTReferencedStudySequence = Sequence([st])
    ds.ReferencedFrameOfReferenceSequence = Sequence([fr])
    ssroi, contours = [], []
    for number, (name, items) in rois.items():
        r = Dataset()
        r.ROINumber = number
        r.ROIName = name
        r.ReferencedFrameOfReferenceUID = frame
        ssroi.append(r)
        c = Dataset()
        c.ReferencedROINumber = number
        seq = []
        for kind, pts in items:
            item = Dataset()
            item.ContourGeometricType = kind
            item.NumberOfContourPoints = len(pts)
            item.ContourData = [f"{v:.6f}" for v in np.asarray(pts, float).ravel()]
            seq.append(item)
        c.ContourSequence = Sequence(seq)
        contours.append(c)
    ds.StructureSetROISequence = Sequence(ssroi)
    ds.ROIContourSequence = Sequence(contours)
    ds.save_as(path, enforce_file_format=True)
    return path


def world(vol, k, xy):
    """LPS points of in-plane (x, y) voxel indices on slice k."""
    xy = np.asarray(xy, float)
    return vol.index_to_world(np.column_stack([xy, np.full(len(xy), float(k))]))


def square(x0, y0, x1, y1):
    return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]


@pytest.fixture
def ct(tmp_path):
    folder = tmp_path / "ct"
    paths = write_ct(folder, SHAPE, spacing=(0.9, 0.6, 2.0))
    return folder, paths, read_dicom(folder)


def test_holes_islands_centres_and_short_contours(ct, tmp_path, run):
    folder, paths, vol = ct
    want = np.zeros(SHAPE, np.uint8)
    # ROI 4 on slice 1: a ring on voxel edges (x 2..9, y 2..9) with a hole (x 4..7, y 4..7)
    # and an island in the hole (x 5..6, y 5..6); the hole drawn the same way round
    ring = [("CLOSED_PLANAR", world(vol, 1, square(1.5, 1.5, 9.5, 9.5))),
            ("CLOSED_PLANAR", world(vol, 1, square(3.5, 3.5, 7.5, 7.5))),
            ("CLOSED_PLANAR", world(vol, 1, square(4.5, 4.5, 6.5, 6.5)))]
    want[1, 2:10, 2:10] = 4
    want[1, 4:8, 4:8] = 0
    want[1, 5:7, 5:7] = 4
    # ROI 7 on slice 2: through the boundary voxels' centres (x 3..8, y 1..5), and a hole
    # drawn through the centres of the voxels around it (x 5..6, y 3: those are inside)
    centres = [("CLOSED_PLANAR", world(vol, 2, square(3, 1, 8, 5))),
               ("CLOSED_PLANAR", world(vol, 2, square(4, 2, 7, 4)))]
    want[2, 1:6, 3:9] = 7
    want[2, 3, 5:7] = 0
    # ROI 9 on slice 3: a 1-point contour, a 2-point contour along x, a diagonal 2-point one
    short = [("POINT", world(vol, 3, [(12, 11)])),
             ("CLOSED_PLANAR", world(vol, 3, [(1, 12), (4, 12)])),
             ("OPEN_PLANAR", world(vol, 3, [(0, 0), (3, 3)]))]
    want[3, 11, 12] = 9
    want[3, 12, 1:5] = 9
    want[3, [0, 1, 2, 3], [0, 1, 2, 3]] = 9
    rs = write_rtstruct(tmp_path / "rs.dcm", paths,
                        {4: ("ring", ring), 7: ("centres", centres), 9: ("short", short)})
    out = tmp_path / "labels.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 0, res.stderr
    got = read_volume(out)
    np.testing.assert_array_equal(got.data, want)
    assert got.same_grid(vol)
    np.testing.assert_allclose(got.origin, vol.origin, atol=1e-9)
    np.testing.assert_allclose(got.direction, vol.direction, atol=1e-12)
    assert got.meta["DICOM_ROI_7"] == "centres"
    res = run("convert", rs, "--reference", folder, "--structure", "centres", "-o", out)
    assert res.code == 0, res.stderr
    np.testing.assert_array_equal(read_volume(out).data, (want == 7).astype(np.uint8))


def test_contours_off_a_voxel_centre_by_less_than_the_tolerance(ct, tmp_path):
    """A centre 0.5e-3 voxel off the contour (the file's decimals) is on it; 0.01 is not."""
    folder, paths, vol = ct
    near = [("CLOSED_PLANAR", world(vol, 0, square(3, 3 + 5e-4, 6, 6)))]
    far = [("CLOSED_PLANAR", world(vol, 4, square(3, 3 + 1e-2, 6, 6)))]
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {1: ("near", near), 2: ("far", far)})
    got = read_dicom(rs, reference=folder).data
    assert got[0, 3:7, 3:7].all() and got[0].sum() == 16 * 1
    assert not got[4, 3, 3:7].any() and (got[4, 4:7, 3:7] == 2).all()


def _line_voxels(a, b) -> set:
    """The textbook nearest-centre line: each step t along the major axis, rint of its point."""
    (x0, y0), (x1, y1) = a, b
    steep = abs(y1 - y0) > abs(x1 - x0)
    if steep:
        x0, y0, x1, y1 = y0, x0, y1, x1
    out = set()
    for t in range(round(min(x0, x1)), round(max(x0, x1)) + 1):
        s = 0.0 if x1 == x0 else min(max((t - x0) / (x1 - x0), 0.0), 1.0)
        v = round(y0 + s * (y1 - y0))
        out.add((v, t) if steep else (t, v))
    return out


def _polyline_voxels(pts, ny, nx) -> np.ndarray:
    want = np.zeros((ny, nx), bool)
    for a, b in zip(pts[:-1], pts[1:], strict=True) if len(pts) > 1 else [(pts[0], pts[0])]:
        for i, j in _line_voxels(a, b):
            if 0 <= i < nx and 0 <= j < ny:
                want[j, i] = True
    return want


def test_markers_and_lines_off_the_voxel_centres_keep_their_voxels(ct, tmp_path, run):
    """A POINT anywhere in a voxel gives that voxel, a polyline off the centres the voxels it
    passes through (before, both gave nothing unless within 1e-3 voxel of a centre); an ROI
    still empty (a closed contour round no centre) is said, naming it."""
    folder, paths, vol = ct
    marks = {(3, 4): (0.01, 0.0), (10, 7): (0.49, -0.49), (0, 13): (-0.4, 0.3)}
    polyline = [(1.2, 12.6), (6.4, 10.2), (7.1, 13.4), (15.8, 11.3)]
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        1: ("markers", [("POINT", world(vol, 2, [(x + dx, y + dy)]))
                        for (x, y), (dx, dy) in marks.items()]),
        2: ("line", [("OPEN_PLANAR", world(vol, 1, [(2.2, 9.3), (13.7, 9.3)]))]),
        3: ("path", [("OPEN_PLANAR", world(vol, 3, polyline))]),
        4: ("tiny", [("CLOSED_PLANAR", world(vol, 4, square(7.1, 1.1, 7.6, 1.6)))])})
    want = np.zeros(SHAPE, np.uint8)
    for x, y in marks:
        want[2, y, x] = 1
    want[1, 9, 2:15] = 2
    want[3][_polyline_voxels(polyline, *SHAPE[1:])] = 3
    out = tmp_path / "o.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 0, res.stderr
    np.testing.assert_array_equal(read_volume(out).data, want)
    warned = [line for line in res.stderr.splitlines() if "warning" in line]
    assert len(warned) == 1 and str(rs) in warned[0] and "ROI 4 'tiny'" in warned[0]
    res = run("convert", rs, "--reference", folder, "--structure", "markers", "-o", out)
    assert res.code == 0 and "warning" not in res.stderr, res.stderr
    np.testing.assert_array_equal(read_volume(out).data, (want == 1).astype(np.uint8))


def test_polylines_are_nearest_centre_lines_through_their_voxels():
    """Random polylines against the textbook loop, and two properties of their own: every
    voxel marked is one the polyline passes through (its square meets it), and every voxel
    centre within 1e-3 voxel of it (the rule before) is marked."""
    rng = np.random.default_rng(11)
    ny, nx = 26, 30
    jj, ii = np.mgrid[:ny, :nx]
    centres = np.column_stack([ii.ravel(), jj.ravel()]).astype(float)
    for _ in range(40):
        n = int(rng.integers(1, 5))
        pts = rng.uniform(-3, 32, (n, 2))
        if rng.random() < 0.3:
            pts = np.rint(pts)  # (through centres, as the old rule read them)
        got = rasterize([(0, pts, False)], (1, ny, nx))[0]
        np.testing.assert_array_equal(got, _polyline_voxels(pts, ny, nx))
        samples = np.concatenate([a + np.linspace(0, 1, 4000)[:, None] * (b - a)
                                  for a, b in zip(pts[:-1], pts[1:], strict=True)]) if n > 1 else pts
        for j, i in zip(*np.nonzero(got), strict=True):
            assert np.abs(samples - (i, j)).max(axis=1).min() <= 0.5 + 1e-2
        if n > 1:
            near = _distance_to_polyline(centres, pts) <= 1e-3
            assert got.ravel()[near].all()


def _distance_to_polyline(pts, poly):
    best = np.full(len(pts), np.inf)
    for a, b in zip(poly[:-1], poly[1:], strict=True):
        d = b - a
        t = np.clip(((pts - a) @ d) / (d @ d), 0, 1)
        best = np.minimum(best, np.linalg.norm(a + t[:, None] * d - pts, axis=1))
    return best


def test_rasterize_matches_a_slow_point_in_polygon_reference():
    rng = np.random.default_rng(5)
    ny, nx = 30, 34
    jj, ii = np.mgrid[:ny, :nx]
    centres = np.column_stack([ii.ravel(), jj.ravel()]).astype(float)
    for _ in range(20):
        polys = []
        for _ in range(rng.integers(1, 4)):
            n = int(rng.integers(3, 12))
            angles = np.sort(rng.uniform(0, 2 * np.pi, n))
            radii = rng.uniform(2, 12, n)
            c = rng.uniform(5, 28, 2)
            polys.append(c + np.column_stack([np.cos(angles), np.sin(angles)]) * radii[:, None])
        got = rasterize([(0, p, True) for p in polys], (1, ny, nx))[0].ravel()
        inside = np.zeros(len(centres), bool)
        near = np.zeros(len(centres), bool)
        for p in polys:
            inside ^= _crossing_parity(centres, p)
            near |= _distance_to_polygon(centres, p) <= 1e-3
        np.testing.assert_array_equal(got, inside | near)


def _crossing_parity(pts, poly):
    """Ray casting towards +x, one edge at a time (the textbook loop)."""
    out = np.zeros(len(pts), bool)
    n = len(poly)
    for m in range(n):
        (x0, y0), (x1, y1) = poly[m], poly[(m + 1) % n]
        for q, (px, py) in enumerate(pts):
            if (y0 > py) != (y1 > py):
                x = x0 + (py - y0) * (x1 - x0) / (y1 - y0)
                if px < x:
                    out[q] = not out[q]
    return out


def _distance_to_polygon(pts, poly):
    best = np.full(len(pts), np.inf)
    for m in range(len(poly)):
        a, b = poly[m], poly[(m + 1) % len(poly)]
        d = b - a
        t = np.clip(((pts - a) @ d) / (d @ d), 0, 1)
        best = np.minimum(best, np.linalg.norm(a + t[:, None] * d - pts, axis=1))
    return best


def test_nested_structures_share_one_map(ct, tmp_path, run):
    """A BODY holding organs, a GTV in a CTV in a PTV: each voxel takes the smallest ROI
    holding it, whatever the ROIs' order in the file; each ROI alone is still its mask."""
    folder, paths, vol = ct

    def on(k, *box):
        return ("CLOSED_PLANAR", world(vol, k, square(*box)))
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        5: ("GTV", [on(2, 3.5, 3.5, 4.5, 4.5)]),
        1: ("BODY", [on(k, 0.5, 0.5, 14.5, 12.5) for k in (1, 2, 3)]),
        4: ("PTV", [on(2, 1.5, 1.5, 7.5, 7.5), on(3, 1.5, 1.5, 7.5, 7.5)]),
        3: ("CTV", [on(2, 2.5, 2.5, 5.5, 5.5)]),
        2: ("Liver", [on(1, 9.5, 8.5, 12.5, 11.5)])})
    out = tmp_path / "o.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 0, res.stderr
    got = read_volume(out)
    want = np.zeros(SHAPE, np.uint8)
    want[1:4, 1:13, 1:15] = 1
    want[2:4, 2:8, 2:8] = 4
    want[2, 3:6, 3:6] = 3
    want[2, 4:5, 4:5] = 5
    want[1, 9:12, 10:13] = 2
    np.testing.assert_array_equal(got.data, want)
    assert got.meta["DICOM_ROI_nested"] == "2 in 1; 3 in 1; 3 in 4; 4 in 1; 5 in 1; 5 in 3; 5 in 4"
    res = run("convert", rs, "--reference", folder, "--structure", "BODY", "-o", out)
    assert res.code == 0, res.stderr
    assert read_volume(out).data.sum() == 3 * 12 * 14


def test_partly_overlapping_structures_need_the_option(ct, tmp_path, run):
    folder, paths, vol = ct
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        1: ("body", [("CLOSED_PLANAR", world(vol, 2, square(0.5, 0.5, 12.5, 12.5)))]),
        2: ("PTV", [("CLOSED_PLANAR", world(vol, 2, square(3.5, 3.5, 5.5, 5.5)))]),
        3: ("rectum", [("CLOSED_PLANAR", world(vol, 2, square(4.5, 4.5, 7.5, 7.5)))]),
        4: ("copy", [("CLOSED_PLANAR", world(vol, 2, square(4.5, 4.5, 7.5, 7.5)))])})
    out = tmp_path / "o.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 1 and "--structure NAME" in res.stderr
    assert "2 'PTV' and 3 'rectum' share 1 voxels" in res.stderr
    assert "2 'PTV' and 4 'copy' share 1 voxels" in res.stderr
    assert "3 'rectum' and 4 'copy' share 9 voxels (the same voxels)" in res.stderr
    assert "'body' and" not in res.stderr  # (nested: not a clash)
    assert len(res.stderr.strip().splitlines()) == 1 and not out.exists()
    res = run("convert", rs, "--reference", folder, "--structure", "PTV", "-o", out)
    assert res.code == 0, res.stderr
    assert read_volume(out).data.sum() == 4


def test_bad_requests_are_one_line_and_write_nothing(ct, tmp_path, run):
    folder, paths, vol = ct
    rois = {1: ("a", [("CLOSED_PLANAR", world(vol, 1, square(1, 1, 3, 3)))])}
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, rois)
    out = tmp_path / "o.nrrd"
    out.write_bytes(b"keep")
    cases = [
        ((), 2, "--reference"),                                  # no reference
        (("--structure", "nope"), 2, "no structure named 'nope'"),
        (("--segment", 1), 2, "--structure NAME"),
    ]
    for args, code, words in cases:
        ref = () if not args else ("--reference", folder)
        res = run("convert", rs, *ref, *args, "-o", out)
        assert res.code == code, (args, res.stderr)
        assert len(res.stderr.strip().splitlines()) == 1 and words in res.stderr, res.stderr
        assert out.read_bytes() == b"keep"
    # the wrong series: another series of the same frame of reference, and another frame
    other = tmp_path / "other"
    f0 = pydicom.dcmread(paths[0])
    write_ct(other, SHAPE, spacing=(0.9, 0.6, 2.0), frame_uid=f0.FrameOfReferenceUID)
    res = run("convert", rs, "--reference", other, "-o", out)
    assert res.code == 1 and "drawn on series" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and out.read_bytes() == b"keep"
    off = write_rtstruct(tmp_path / "off.dcm", paths, rois, frame_uid=generate_uid())
    res = run("convert", off, "--reference", folder, "-o", out)
    assert res.code == 1 and "frame of reference" in res.stderr
    # a contour between two slices
    pts = world(vol, 1, square(1, 1, 3, 3))
    pts = pts + 0.5 * vol.spacing[2] * vol.direction[:, 2]
    between = write_rtstruct(tmp_path / "between.dcm", paths,
                             {1: ("a", [("CLOSED_PLANAR", pts)])})
    res = run("convert", between, "--reference", folder, "-o", out)
    assert res.code == 1 and "slice plane" in res.stderr and "'a'" in res.stderr
    assert out.read_bytes() == b"keep"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".o.nrrd")) == []


@pytest.mark.parametrize("listed", [False, True])
def test_an_roi_in_another_frame_of_reference_is_refused(ct, tmp_path, run, listed):
    """An ROI whose ReferencedFrameOfReferenceUID is not the reference's has its contours in
    another coordinate system: the map of every ROI is refused naming it (before, it was
    painted on the CT's grid, exit 0), whether or not the structure set lists that frame
    too; ``--structure`` of an ROI in the reference's frame still reads."""
    folder, paths, vol = ct
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        1: ("ct roi", [("CLOSED_PLANAR", world(vol, 2, square(1.5, 1.5, 4.5, 4.5)))]),
        2: ("mr roi", [("CLOSED_PLANAR", world(vol, 2, square(8.5, 8.5, 11.5, 11.5)))])})
    ds = pydicom.dcmread(rs)
    other = generate_uid()
    ds.StructureSetROISequence[1].ReferencedFrameOfReferenceUID = other
    if listed:
        item = Dataset()
        item.FrameOfReferenceUID = other
        ds.ReferencedFrameOfReferenceSequence.append(item)
    ds.save_as(rs)
    out = tmp_path / "o.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 1 and not out.exists(), res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and str(rs) in res.stderr
    assert "ROI 2 'mr roi'" in res.stderr and other in res.stderr
    assert "frame of reference" in res.stderr and "--structure NAME" in res.stderr
    res = run("convert", rs, "--reference", folder, "--structure", "mr roi", "-o", out)
    assert res.code == 1 and "ROI 2 'mr roi'" in res.stderr and not out.exists()
    res = run("convert", rs, "--reference", folder, "--structure", "ct roi", "-o", out)
    assert res.code == 0, res.stderr
    want = np.zeros(SHAPE, np.uint8)
    want[2, 2:5, 2:5] = 1
    np.testing.assert_array_equal(read_volume(out).data, want)


def test_pydicoms_rtstruct_file(run):
    path = get_testdata_file("rtstruct.dcm")
    with pytest.raises(FormatError, match="no PixelData.*--reference"):
        read_dicom(path)
    res = run("info", path, "--json")
    assert res.code == 0, res.stderr
    desc = json.loads(res.stdout)
    assert [s["name"] for s in desc["structures"]] == ["patient", "Isocenter 1", "Isocenter 2"]
    assert [s["contours"] for s in desc["structures"]] == [3, 1, 1]
    assert desc["referenced_series"] == ["1.2.826.0.1.3680043.8.498.2010020400001.2.1.1"]


@pytest.mark.parametrize("number", [0, -3])
def test_an_roi_numbered_0_or_less_is_never_lost(ct, tmp_path, run, number):
    """ROI Number 0 is a label map's background, and no label is negative: the map of every
    ROI is refused naming the ROI and ``--structure``, which gives its voxels."""
    folder, paths, vol = ct
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        number: ("left corner", [("CLOSED_PLANAR", world(vol, 2, square(0.5, 0.5, 2.5, 2.5)))]),
        300: ("liver", [("CLOSED_PLANAR", world(vol, 1, square(5.5, 5.5, 8.5, 8.5)))])})
    out = tmp_path / "o.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 1 and not out.exists()
    assert len(res.stderr.strip().splitlines()) == 1 and str(rs) in res.stderr
    assert f"ROI {number} 'left corner'" in res.stderr
    assert "--structure 'left corner'" in res.stderr
    res = run("convert", rs, "--reference", folder, "--structure", "left corner", "-o", out)
    assert res.code == 0, res.stderr
    want = np.zeros(SHAPE, np.uint8)
    want[2, 1:3, 1:3] = 1
    np.testing.assert_array_equal(read_volume(out).data, want)


@pytest.mark.parametrize("orphan", [7, 300])
def test_contours_of_an_roi_the_structure_set_does_not_list(ct, tmp_path, run, orphan):
    """Contours whose ReferencedROINumber StructureSetROISequence does not list have no ROI:
    the map of every ROI is refused naming the number (300 crashed sizing a uint8 map);
    the listed ROIs still read one at a time."""
    folder, paths, vol = ct
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        2: ("a", [("CLOSED_PLANAR", world(vol, 1, square(1.5, 1.5, 3.5, 3.5)))]),
        orphan: ("gone", [("CLOSED_PLANAR", world(vol, 3, square(5.5, 5.5, 8.5, 8.5)))])})
    ds = pydicom.dcmread(rs)
    ds.StructureSetROISequence = Sequence([r for r in ds.StructureSetROISequence
                                           if r.ROINumber == 2])
    ds.save_as(rs)
    out = tmp_path / "o.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 1 and not out.exists()
    assert len(res.stderr.strip().splitlines()) == 1 and str(rs) in res.stderr
    assert f"ROI Number {orphan}" in res.stderr and "StructureSetROISequence" in res.stderr
    res = run("convert", rs, "--reference", folder, "--structure", "a", "-o", out)
    assert res.code == 0, res.stderr
    want = np.zeros(SHAPE, np.uint8)
    want[1, 2:4, 2:4] = 1
    np.testing.assert_array_equal(read_volume(out).data, want)


def slice_file(paths, vol, k):
    """The file of the series' slice k (z order)."""
    at = vol.index_to_world([0, 0, k])
    return next(p for p in paths if np.allclose(
        np.array(pydicom.dcmread(p).ImagePositionPatient, float), at, atol=1e-4))


def on_image(rs, uid) -> None:
    """Make every contour of the RTSTRUCT ``rs`` reference the image ``uid``."""
    ds = pydicom.dcmread(rs)
    for roi in ds.ROIContourSequence:
        for c in roi.ContourSequence:
            item = Dataset()
            item.ReferencedSOPClassUID = "1.2.840.10008.5.1.4.1.1.2"
            item.ReferencedSOPInstanceUID = uid
            c.ContourImageSequence = Sequence([item])
    ds.save_as(rs)


def test_a_contour_whose_image_the_reference_lacks_is_an_error(ct, tmp_path, run):
    """A contour outside the reference's slices (its image not in the reference's folder) or
    on an image the reference does not hold is an error naming the ROI, never dropped."""
    folder, paths, vol = ct
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        1: ("low", [("CLOSED_PLANAR", world(vol, 1, square(1.5, 1.5, 3.5, 3.5)))]),
        2: ("top", [("CLOSED_PLANAR", world(vol, 4, square(5.5, 5.5, 8.5, 8.5)))])})
    os.remove(slice_file(paths, vol, 4))  # the reference's grid is 4 slices
    out = tmp_path / "o.nrrd"
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 1 and not out.exists(), res.stderr
    assert str(rs) in res.stderr and "ROI 2 'top'" in res.stderr
    assert "outside" in res.stderr and "slices 0..3" in res.stderr
    res = run("convert", rs, "--reference", folder, "--structure", "top", "-o", out)
    assert res.code == 1 and "ROI 2 'top'" in res.stderr and not out.exists()
    # within the grid, but on an image the reference does not hold
    rs = write_rtstruct(tmp_path / "rs2.dcm", paths, {
        1: ("low", [("CLOSED_PLANAR", world(vol, 1, square(1.5, 1.5, 3.5, 3.5)))])})
    on_image(rs, "1.2.3.4.5")
    res = run("convert", rs, "--reference", folder, "-o", out)
    assert res.code == 1 and not out.exists(), res.stderr
    assert str(rs) in res.stderr and "ROI 1 'low'" in res.stderr and "1.2.3.4.5" in res.stderr
    assert [line for line in res.stderr.splitlines() if "error:" in line] == \
        [res.stderr.strip().splitlines()[-1]]  # (after the header-only file's warning)


@pytest.mark.parametrize("keep", ["first", "last"])
def test_a_contour_on_a_duplicate_image_dropped_from_the_grid(ct, tmp_path, run, keep):
    """A duplicate image ``--duplicates`` leaves out is still the reference's: a contour on it
    lies on its slice of the grid."""
    folder, paths, vol = ct
    copy = pydicom.dcmread(slice_file(paths, vol, 2))
    copy.SOPInstanceUID = copy.file_meta.MediaStorageSOPInstanceUID = generate_uid()
    copy.save_as(folder / "copy.dcm")
    rs = write_rtstruct(tmp_path / "rs.dcm", paths, {
        1: ("a", [("CLOSED_PLANAR", world(vol, 2, square(1.5, 1.5, 3.5, 3.5)))])})
    on_image(rs, copy.SOPInstanceUID)
    out = tmp_path / "o.nrrd"
    res = run("convert", rs, "--reference", folder, "--duplicates", keep, "-o", out)
    assert res.code == 0, res.stderr
    want = np.zeros(SHAPE, np.uint8)
    want[2, 2:4, 2:4] = 1
    np.testing.assert_array_equal(read_volume(out).data, want)
