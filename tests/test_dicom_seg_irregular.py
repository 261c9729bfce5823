"""A SEG whose frames lie on some slices only, with no SpacingBetweenSlices, read on its series.

SpacingBetweenSlices is Type 3 (optional). Without it, frames on slices 0, 2 and 5
of a series have no regular grid of their own (gaps of 2 and 3 slices), and the
reader refused the SEG even with ``--reference SERIES``, whose grid places every
frame (found by a review): each frame is now placed on the reference slice at
its own ImagePositionPatient. Without a reference the SEG is still refused, with
a message that names ``--reference SERIES`` (none where the frames lie on a
gantry-tilted stack, which no reference gives them). SEGs that read before give the same
bytes (compared with the earlier route: the SEG's own grid, then the reference).
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
hd = pytest.importorskip("highdicom")

from test_dicom_seg import SHAPE, make_seg, masks_of, write_ct  # noqa: E402

from volwarp_cli.io import dicom_seg, read_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402
from volwarp_cli.io.dicom._read import read_reference  # noqa: E402
from volwarp_cli.io.dicom_seg import open_seg, read_seg  # noqa: E402

SLICES = (0, 2, 5)  # gaps of 2 and 3 slices: no regular grid without a spacing


def sparse_labels(shape=SHAPE) -> np.ndarray:
    lab = np.zeros(shape, np.uint8)
    lab[0, 3, 4] = 1
    lab[2, 1:4, 2:5] = 2
    lab[2, 8, 10] = 1
    lab[5, 6:9, 7:11] = 3
    return lab


def compression(kind, compressed: bool) -> dict:
    """make_seg's keywords: uncompressed, or the lossless syntax highdicom takes for ``kind``."""
    from pydicom.uid import JPEG2000Lossless, RLELossless

    if not compressed:
        return {}
    return {"transfer_syntax_uid": JPEG2000Lossless if kind == "BINARY" else RLELossless}


def pixels_of(lab, kind):
    if kind == "LABELMAP":
        return lab
    if kind == "FRACTIONAL":
        return masks_of(lab).astype(np.float32) * 0.75
    return masks_of(lab)


def drop_spacing(path, out=None):
    """The SEG at ``path`` without SpacingBetweenSlices (saved to ``out``, else in place)."""
    ds = pydicom.dcmread(path)
    measures = ds.SharedFunctionalGroupsSequence[0].PixelMeasuresSequence[0]
    del measures.SpacingBetweenSlices
    ds.save_as(out or path)
    return out or path


@pytest.fixture
def ct(tmp_path):
    paths = write_ct(tmp_path / "ct")
    return tmp_path / "ct", paths


def series_for(tmp_path, kind, compressed):
    """``(folder, paths, shape)`` of a CT series: 32x32 pixels for JPEG 2000 (openjpeg's least)."""
    shape = (SHAPE[0], 32, 32) if compressed and kind == "BINARY" else SHAPE
    return tmp_path / "ct", write_ct(tmp_path / "ct", shape), shape


def slice_worlds(paths) -> dict[int, np.ndarray]:
    """World point (LPS) of pixel (column 0, row 0) of each CT slice, by slice index."""
    ref = read_dicom(paths[0].parent)
    out = {}
    for p in paths:
        ds = pydicom.dcmread(p)
        ipp = np.array(ds.ImagePositionPatient, float)
        k = int(np.rint(ref.world_to_index(ipp)[2]))
        out[k] = ipp
    return out


def world_of_voxels(paths, zyx) -> np.ndarray:
    """The LPS points of voxels (z, y, x) computed from their slice file's own header."""
    first = slice_worlds(paths)
    ds = pydicom.dcmread(paths[0])
    iop = np.array(ds.ImageOrientationPatient, float)
    dy, dx = (float(v) for v in ds.PixelSpacing)
    return np.array([first[z] + iop[:3] * dx * x + iop[3:] * dy * y for z, y, x in zyx])


@pytest.mark.parametrize("compressed", [False, True])
@pytest.mark.parametrize("kind", ["BINARY", "FRACTIONAL", "LABELMAP"])
def test_sparse_frames_without_spacing_land_on_their_reference_slices(tmp_path, run, kind,
                                                                      compressed):
    folder, paths, shape = series_for(tmp_path, kind, compressed)
    lab = sparse_labels(shape)
    seg = make_seg(paths, pixels_of(lab, kind), kind, tmp_path / "seg.dcm",
                   **compression(kind, compressed))
    ds = pydicom.dcmread(seg)
    assert ds.NumberOfFrames == (3 if kind == "LABELMAP" else 4)  # frames on slices 0, 2, 5
    drop_spacing(seg)
    out = tmp_path / "out.nrrd"
    res = run("convert", seg, "--reference", folder, "-o", out)
    assert res.code == 0, res.stderr
    vol = read_volume(out)
    ref = read_dicom(folder)
    assert vol.same_grid(ref)
    np.testing.assert_array_equal(vol.data, lab)
    for label in (1, 2, 3):
        zyx = np.argwhere(vol.data == label)
        assert set(zyx[:, 0]) <= set(SLICES)
        got = vol.index_to_world(zyx[:, ::-1].astype(float))
        np.testing.assert_allclose(got, world_of_voxels(paths, zyx), atol=1e-5)
    one = read_dicom(seg, reference=folder, segment=2)
    np.testing.assert_array_equal(one.data, (lab == 2).astype(np.uint8))


def test_without_a_reference_the_error_names_the_option(ct, tmp_path, run):
    _, paths = ct
    seg = drop_spacing(make_seg(paths, masks_of(sparse_labels()), "BINARY", tmp_path / "seg.dcm"))
    out = tmp_path / "o.nrrd"
    res = run("convert", seg, "-o", out)
    assert res.code == 1 and not out.exists()
    assert len(res.stderr.strip().splitlines()) == 1
    assert str(seg) in res.stderr and "--reference SERIES" in res.stderr, res.stderr


@pytest.mark.parametrize("slices", [SLICES, range(SHAPE[0])])
def test_frames_of_a_tilted_series_name_no_option_that_fails(tmp_path, run, slices):
    """A SEG drawn on a gantry-tilted series has no grid, and --reference cannot give one.

    The error suggested ``--reference SERIES``, which then failed too: a tilted
    reference is resampled, and a segmentation's frames must lie on stored slices.
    """
    paths = write_ct(tmp_path / "ct", tilt_deg=15.0)
    shift = 2.5 * np.tan(np.radians(15.0))  # in-plane, from one slice to the next
    lab = np.zeros(SHAPE, np.uint8)
    for k in slices:
        lab[k, 2 + k % 3, 4] = 1
    seg = make_seg(paths, masks_of(lab, 1), "BINARY", tmp_path / "seg.dcm")
    out = tmp_path / "o.nrrd"
    res = run("convert", seg, "-o", out)
    assert res.code == 1 and not out.exists(), res
    line, = res.stderr.strip().splitlines()
    assert line.startswith(f"volwarp: error: {seg}: its frames lie on a gantry-tilted stack "
                           f"(their positions move {(max(slices) - min(slices)) * shift:.3g} mm "
                           "within the slice plane)"), line
    assert "--reference SERIES" not in line and "cannot place these frames" in line, line
    res = run("convert", seg, "--reference", tmp_path / "ct", "-o", out)  # (what it said)
    assert res.code == 1 and "must be read as it is stored" in res.stderr and not out.exists()


def test_a_frame_between_reference_slices_is_an_error(ct, tmp_path, run):
    folder, paths = ct
    seg = drop_spacing(make_seg(paths, masks_of(sparse_labels()), "BINARY", tmp_path / "seg.dcm"))
    ds = pydicom.dcmread(seg)
    item = ds.PerFrameFunctionalGroupsSequence[-1].PlanePositionSequence[0]
    iop = np.array(ds.SharedFunctionalGroupsSequence[0].PlaneOrientationSequence[0]
                   .ImageOrientationPatient, float)
    normal = np.cross(iop[:3], iop[3:])
    item.ImagePositionPatient = [f"{v:.6f}" for v in
                                 np.array(item.ImagePositionPatient, float) + 1.25 * normal]
    ds.save_as(seg)
    out = tmp_path / "o.nrrd"
    res = run("convert", seg, "--reference", folder, "-o", out)
    assert res.code == 1 and not out.exists()
    assert len(res.stderr.strip().splitlines()) == 1
    assert str(seg) in res.stderr and "is not a slice of the reference series" in res.stderr
    # another series (another frame of reference) is refused as before
    other = tmp_path / "other"
    write_ct(other)
    res = run("convert", seg, "--reference", other, "-o", out)
    assert res.code == 1 and "frame of reference" in res.stderr and not out.exists()


def _before(path, ref, **kw):
    """The earlier route: the SEG on its own grid, then its slices placed on the reference."""
    own = read_seg(path, **kw)
    return dicom_seg._onto_reference(own.data, own.spacing, own.origin, own.direction,
                                     open_seg(path), ref, str(path))


@pytest.mark.parametrize("compressed", [False, True])
@pytest.mark.parametrize("kind", ["BINARY", "FRACTIONAL", "LABELMAP"])
def test_seg_that_read_before_gives_the_same_bytes(tmp_path, run, kind, compressed):
    folder, paths, shape = series_for(tmp_path, kind, compressed)
    lab = np.zeros(shape, np.uint8)  # slices 1, 2 and 4: regular with one missing
    lab[1:3, 2:5, 2:6] = 1
    lab[4, 6:9, 7:11] = 2
    lab[1, 0:2, 0:2] = 3
    seg = make_seg(paths, pixels_of(lab, kind), kind, tmp_path / "seg.dcm",
                   **compression(kind, compressed))
    ref = read_reference(folder)
    for kw in ({}, {"segment": 2}):
        new = read_seg(seg, reference=ref, **kw)
        old = _before(seg, ref, **kw)
        assert new.data.dtype == old.dtype and new.data.shape == old.shape
        assert new.data.tobytes() == old.tobytes()
        g = ref.grid
        assert np.array_equal(new.spacing, g.spacing) and np.array_equal(new.origin, g.origin)
        assert np.array_equal(new.direction, g.direction)
    # the whole command too: NRRD files of the same bytes by either route
    out = tmp_path / "new.nrrd"
    assert run("convert", seg, "--reference", folder, "-o", out).code == 0
    saved = dicom_seg._fast_frames
    dicom_seg._fast_frames = lambda *a, **k: None  # (highdicom's volume, then the reference)
    try:
        assert run("convert", seg, "--reference", folder, "-o", tmp_path / "hd.nrrd").code == 0
    finally:
        dicom_seg._fast_frames = saved
    assert out.read_bytes() == (tmp_path / "hd.nrrd").read_bytes()
    np.testing.assert_array_equal(read_volume(out).data, lab)


def test_one_segment_named_in_the_shared_groups(ct, tmp_path, run):
    """highdicom names a lone segment once, in the shared functional groups (the
    review's case: one voxel on slices 0, 2 and 5); such a SEG read the same way."""
    folder, paths = ct
    lab = np.zeros(SHAPE, bool)
    lab[list(SLICES), 3, 4] = True
    regular = make_seg(paths, lab[..., None], "BINARY", tmp_path / "regular.dcm")
    shared = pydicom.dcmread(regular).SharedFunctionalGroupsSequence[0]
    assert "SegmentIdentificationSequence" in shared
    seg = drop_spacing(regular, tmp_path / "seg.dcm")
    out = tmp_path / "out.nrrd"
    res = run("convert", seg, "--reference", folder, "-o", out)
    assert res.code == 0, res.stderr
    vol = read_volume(out)
    assert vol.same_grid(read_dicom(folder))
    zyx = np.argwhere(vol.data)
    assert zyx.tolist() == [[k, 3, 4] for k in SLICES]
    np.testing.assert_allclose(vol.index_to_world(zyx[:, ::-1].astype(float)),
                               world_of_voxels(paths, zyx), atol=1e-5)
    # the SEG with its spacing reads on its own grid as before, and on the reference the same
    ref = read_reference(folder)
    assert read_seg(regular, reference=ref).data.tobytes() == _before(regular, ref).tobytes()
    res = run("convert", regular, "--reference", folder, "-o", tmp_path / "regular.nrrd")
    assert res.code == 0 and (tmp_path / "regular.nrrd").read_bytes() == out.read_bytes()


@pytest.mark.parametrize("compressed", [False, True])
@pytest.mark.parametrize("kind", ["BINARY", "LABELMAP"])
def test_frames_at_twice_the_slice_thickness_without_spacing_are_warned(tmp_path, run, kind,
                                                                        compressed):
    """Frames on slices 1, 3 and 5 of a 2.5 mm series (its empty frames left out) without
    SpacingBetweenSlices read as 3 slices 5 mm apart: a gapped acquisition would too, so this
    is read, but said, naming both spacings and ``--reference SERIES`` (before: silent).
    With the reference, or on consecutive slices, nothing is said."""
    folder, paths, shape = series_for(tmp_path, kind, compressed)
    lab = np.zeros(shape, np.uint8)
    lab[1, 2:5, 2:6] = 1
    lab[3, 4:7, 3:5] = 2
    lab[5, 6, 7] = 1
    seg = drop_spacing(make_seg(paths, pixels_of(lab, kind), kind, tmp_path / "seg.dcm",
                                **compression(kind, compressed)))
    out = tmp_path / "o.nrrd"
    res = run("convert", seg, "-o", out)
    assert res.code == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "warning" in lines[0] and str(seg) in lines[0], res.stderr
    assert "5 mm apart" in lines[0] and "2.5 mm" in lines[0] and "--reference SERIES" in lines[0]
    vol = read_volume(out)
    assert vol.data.shape[0] == 3 and vol.spacing[2] == pytest.approx(5.0)
    np.testing.assert_array_equal(vol.data, lab[[1, 3, 5]])
    res = run("convert", seg, "--reference", folder, "-o", out)
    assert res.code == 0 and not res.stderr.strip(), res.stderr
    np.testing.assert_array_equal(read_volume(out).data, lab)
    solid = np.zeros_like(lab)
    solid[2:5] = lab[1]  # (frames on slices 2, 3 and 4: no gap)
    seg = drop_spacing(make_seg(paths, pixels_of(solid, kind), kind, tmp_path / "next.dcm",
                                **compression(kind, compressed)))
    res = run("convert", seg, "-o", out)
    assert res.code == 0 and not res.stderr.strip(), res.stderr
    np.testing.assert_array_equal(read_volume(out).data, solid[2:5])
