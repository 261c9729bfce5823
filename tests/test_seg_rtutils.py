"""RTSTRUCTs exchanged with rt-utils, the field's most used RTSTRUCT library, both ways.

rt-utils writes a mask's contours through its boundary voxels' centres (OpenCV's
``findContours``) and reads a contour by rounding its vertices to voxel centres and
filling the polygon with its boundary (``fillPoly``). So:

- an RTSTRUCT rt-utils wrote from masks reads back in volwarp as those masks,
  exactly: the on-contour rule (a centre within 1e-3 voxel of a contour is
  inside) takes the boundary voxels the contours pass through, even-odd the rest,
  holes (rt-utils' inner contours run through the centres of the voxels around
  a hole), islands in holes, voxels touching only at a corner and one-voxel
  structures included; without the on-contour rule the same contours lose voxels
  (the check can fail);
- an RTSTRUCT ``volwarp convert --dicom-type rtstruct`` wrote reads in rt-utils
  as the label map: one ROI per label, named ``label_N``, each mask exactly the
  label's voxels (the issue asks Dice >= 0.95): volwarp's voxel-edge contours are
  nudged 0.01 voxel inward, so rt-utils' rounding puts every vertex on a
  boundary voxel's centre.

The series is oblique with square images and equal pixel spacings: rt-utils
assumes both (it swaps the two PixelSpacing values otherwise).
"""

from __future__ import annotations

import contextlib
import io
import warnings

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
# (ImportError too: rt-utils' OpenCV fails to import where the system lacks libGL/glib)
rt_utils = pytest.importorskip("rt_utils", exc_type=ImportError)

from scipy import ndimage  # noqa: E402
from test_dicom_seg import OBLIQUE, write_ct  # noqa: E402
from test_rtstruct_write import tricky_labels  # noqa: E402

from volwarp_cli.io import read_volume, write_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402
from volwarp_cli.io.rtstruct import ON_CONTOUR, open_rtstruct, rasterize  # noqa: E402

N = 24  # rows = columns
SPACING = (0.8, 0.8, 2.0)  # x, y, z: equal in-plane spacings


@contextlib.contextmanager
def quiet_rtutils():
    """rt-utils on pydicom 3: its ``is_little_endian`` set warns (removed in pydicom 4), and it prints."""
    with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
        warnings.filterwarnings("ignore", category=DeprecationWarning,
                                message=".*is_(little_endian|implicit_VR).*")
        yield


def label_maps(nz: int) -> list[np.ndarray]:
    """The write test's tricky map (holes, an island in a hole, corner-touching voxels, a line
    along the grid's edge, one voxel in the grid's last corner) and random maps of three labels
    (speckle and opened blobs: many holes and diagonal contacts)."""
    tricky = np.zeros((nz, N, N), np.uint8)
    t = tricky_labels()
    tricky[:t.shape[0], N - t.shape[1]:, N - t.shape[2]:] = t
    maps = [tricky]
    rng = np.random.default_rng(7)
    for opened in (False, True):
        lab = np.zeros((nz, N, N), np.uint8)
        for v in (1, 2, 3):
            m = rng.random(lab.shape) < 0.35
            if opened:
                m = ndimage.binary_opening(m, np.ones((1, 2, 2)))
            lab[m & (lab == 0)] = v
        maps.append(lab)
    return maps


@pytest.fixture
def ct(tmp_path):
    folder = tmp_path / "ct"
    write_ct(folder, (4, N, N), spacing=SPACING, orientation=OBLIQUE)
    return folder


def values(lab) -> list[int]:
    return [int(v) for v in np.unique(lab) if v]


@pytest.mark.parametrize("which", ["tricky", "speckle", "blobs"])
def test_an_rtutils_rtstruct_reads_back_as_its_masks(ct, tmp_path, run, which):
    lab = label_maps(4)[["tricky", "speckle", "blobs"].index(which)]
    rs = tmp_path / "rtutils.dcm"
    with quiet_rtutils():
        rt = rt_utils.RTStructBuilder.create_new(str(ct))
        for v in values(lab):
            rt.add_roi(mask=(lab == v).transpose(1, 2, 0), name=f"organ {v}")  # [row, col, slice]
        rt.save(str(rs))
    # rt-utils numbers its ROIs 1.. in the order they were added
    numbers = {v: n for n, v in enumerate(values(lab), 1)}
    whole = np.zeros_like(lab)
    for v, n in numbers.items():
        whole[lab == v] = n
    out = tmp_path / "labels.nrrd"
    res = run("convert", rs, "--reference", ct, "-o", out)
    assert res.code == 0, res.stderr
    np.testing.assert_array_equal(read_volume(out).data, whole)
    for v in values(lab):
        res = run("convert", rs, "--reference", ct, "--structure", f"organ {v}", "-o", out)
        assert res.code == 0, res.stderr
        np.testing.assert_array_equal(read_volume(out).data, (lab == v).astype(np.uint8))

    # rt-utils' vertices are voxel centres, so the on-contour rule is what takes its
    # boundary voxels: even-odd alone (a negative tolerance) loses them from its rings
    grid = read_dicom(ct)
    ds = open_rtstruct(rs)
    for roi in ds.ROIContourSequence:
        contours = []
        for c in roi.ContourSequence:
            ijk = grid.world_to_index(np.asarray(c.ContourData, float).reshape(-1, 3))
            assert np.abs(ijk - np.rint(ijk)).max() < 1e-4  # on voxel centres
            contours.append((int(np.rint(ijk[0, 2])), ijk[:, :2], True))
        v = values(lab)[int(roi.ReferencedROINumber) - 1]
        np.testing.assert_array_equal(rasterize(contours, lab.shape, tol=ON_CONTOUR), lab == v)
        even_odd = rasterize(contours, lab.shape, tol=-1.0)  # (a 1-point contour: its voxel)
        assert not (even_odd & (lab != v)).any()
        if any(len(p) >= 3 for _, p, _ in contours):
            assert even_odd.sum() < (lab == v).sum()


@pytest.mark.parametrize("which", ["tricky", "speckle", "blobs"])
def test_a_volwarp_rtstruct_reads_in_rtutils_as_the_label_map(ct, tmp_path, run, which):
    lab = label_maps(4)[["tricky", "speckle", "blobs"].index(which)]
    src = tmp_path / "labels.nrrd"
    write_volume(read_dicom(ct).with_data(lab), src)
    rs = tmp_path / "volwarp.dcm"
    res = run("convert", src, "--reference", ct, "--dicom-type", "rtstruct", "-o", rs)
    assert res.code == 0, res.stderr
    with quiet_rtutils():
        rt = rt_utils.RTStructBuilder.create_from(str(ct), str(rs))
        names = rt.get_roi_names()
        masks = {name: rt.get_roi_mask_by_name(name).transpose(2, 0, 1).astype(bool)
                 for name in names}
    assert names == [f"label_{v}" for v in values(lab)]  # one ROI per label
    for v in values(lab):
        got, want = masks[f"label_{v}"], lab == v
        dice = 2 * np.count_nonzero(got & want) / (np.count_nonzero(got) + np.count_nonzero(want))
        assert dice >= 0.95
        np.testing.assert_array_equal(got, want)  # and in fact exactly
