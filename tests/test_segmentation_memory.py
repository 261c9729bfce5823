"""Writing a SEG or an RTSTRUCT under a memory limit: the limit is the process's peak.

The SEG's need is counted before highdicom builds it; an RTSTRUCT's, whose size follows
its contours, as they are made. Each case measures the command's unlimited peak, then
runs it under a limit a little below that peak: refused (exit 1, nothing written), its
peak under the limit (before, both ran through it). And the RTSTRUCT's Contour Data, kept
encoded while it is built, is the bytes pydicom writes for the numbers.
"""

from __future__ import annotations

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
pytest.importorskip("highdicom")

from peaks import volwarp_peak  # noqa: E402
from test_dicom_seg import write_ct  # noqa: E402

from volwarp_cli.io import write_volume  # noqa: E402
from volwarp_cli.io.dicom import read_dicom  # noqa: E402

MiB = 1 << 20


def _series_and_map(folder, shape, labels):
    """A CT series of ``shape`` in ``folder/ct`` and ``labels(shape)`` on it, as labels.nrrd."""
    write_ct(folder / "ct", shape)
    lab = labels(shape)
    src = folder / "labels.nrrd"
    write_volume(read_dicom(folder / "ct").with_data(lab), src)
    return src, lab


def _specks(shape, seed=5, keep=1.0):
    """4x4-voxel squares of labels 0..10 (``keep``: the share of squares kept)."""
    rng = np.random.default_rng(seed)
    coarse = (shape[0], shape[1] // 4, shape[2] // 4)
    ids = np.kron(rng.integers(0, 11, coarse, dtype=np.uint8), np.ones((1, 4, 4), np.uint8))
    kept = np.kron(rng.random(coarse) < keep, np.ones((1, 4, 4), bool))
    return np.where(kept, ids, 0).astype(np.uint8)


@pytest.fixture(scope="module")
def speckled(tmp_path_factory):
    """A CT series and a label map of 4x4-voxel squares of 10 labels: thousands of islands."""
    folder = tmp_path_factory.mktemp("speckled")
    src, lab = _series_and_map(folder, (8, 128, 128), _specks)
    return folder, src, lab


@pytest.mark.parametrize("kind", ["seg", "labelmap-seg", "rtstruct"])
def test_a_limit_below_the_peak_is_refused_and_never_crossed(speckled, tmp_path, kind):
    folder, src, _ = speckled
    out = tmp_path / "out.dcm"
    args = ["convert", src, "--reference", folder / "ct", "--dicom-type", kind, "-o", out]
    code, err, peak = volwarp_peak(*args)
    assert code == 0, err
    assert out.exists()
    out.unlink()
    limit = peak - 6 * MiB
    code, err, limited = volwarp_peak(*args, "--memory-limit", str(limit))
    assert code == 1, err
    assert "memory limit" in err and str(out) in err
    assert limited <= limit, (limited / MiB, limit / MiB)
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_rtstruct_contour_data_is_what_pydicom_writes_for_the_numbers(speckled, tmp_path):
    from volwarp_cli.io.dicom import read_reference
    from volwarp_cli.io.rtstruct import build_rtstruct

    folder, src, lab = speckled
    ref = read_reference(folder / "ct")
    vol = read_dicom(folder / "ct").with_data(lab)
    ds = build_rtstruct(vol, ref, where="t")
    ds.save_as(tmp_path / "raw.dcm", enforce_file_format=True)
    items = 0
    for roi in ds.ROIContourSequence:
        for item in roi.ContourSequence:
            values = item.ContourData  # (decoded from the kept bytes)
            item.ContourData = [str(v) for v in values]  # as numbers again: pydicom encodes
            items += 1
    assert items > 1000
    ds.save_as(tmp_path / "assigned.dcm", enforce_file_format=True)
    assert (tmp_path / "raw.dcm").read_bytes() == (tmp_path / "assigned.dcm").read_bytes()


@pytest.mark.parametrize("dtype", [np.int32, np.float32, np.uint16])
def test_binary_seg_of_any_id_type_has_the_same_frames(speckled, tmp_path, dtype):
    """8/16-bit ids index the segment table as they are; others are cast first."""
    from volwarp_cli.io.dicom import read_reference
    from volwarp_cli.io.dicom_seg import build_seg

    folder, src, lab = speckled
    ref = read_reference(folder / "ct")
    base = read_dicom(folder / "ct")
    pixels = [build_seg(base.with_data(lab.astype(t)), ref, where="t").PixelData
              for t in (np.uint8, dtype)]
    assert pixels[0] == pixels[1]


@pytest.fixture(scope="module")
def blocks(tmp_path_factory):
    """A CT series and a map of 64 labels in 8^3 blocks: a 14 MB map, its SEG or RTSTRUCT."""
    folder = tmp_path_factory.mktemp("blocks")

    def blocks_of(shape):
        z, y, x = np.indices(shape, dtype=np.int32)
        return (1 + (z * 4 // 96) * 16 + (y * 4 // 384) * 4 + (x * 4 // 384)).astype(np.uint8)
    src, _ = _series_and_map(folder, (96, 384, 384), blocks_of)
    return folder, src


@pytest.mark.parametrize("kind", ["labelmap-seg", "rtstruct"])
def test_reading_back_under_a_limit_below_its_peak_is_refused_and_never_crossed(
        blocks, tmp_path, kind):
    """The file, then the map, charged before each is held (the map was not: 14 MiB over)."""
    folder, src = blocks
    _read_back_below_its_peak(src, folder / "ct", kind, tmp_path, (2,))


def _read_back_below_its_peak(src, ct, kind, tmp_path, below_mib) -> None:
    """Write ``src`` as ``kind`` on ``ct``; its read back, under limits ``below_mib`` MiB below
    its own measured peak, is refused and stays under each limit, nothing written."""
    dcm = tmp_path / f"{kind}.dcm"
    code, err, _ = volwarp_peak("convert", src, "--reference", ct, "--dicom-type", kind,
                                "-o", dcm)
    assert code == 0, err
    out = tmp_path / "back.nrrd"
    args = ["convert", dcm, "--reference", ct, "-o", out]
    code, err, peak = volwarp_peak(*args)
    assert code == 0, err
    out.unlink()
    for below in below_mib:
        limit = peak - below * MiB
        code, err, limited = volwarp_peak(*args, "--memory-limit", str(limit))
        assert code == 1, err
        assert "memory limit" in err
        assert limited <= limit, (limited / MiB, limit / MiB)
        assert not out.exists()


def test_reading_back_a_speckled_rtstruct_charges_each_roi_s_mask(tmp_path):
    """Each ROI's mask is cut to its box, but a speckled ROI's box is the whole grid: ten
    of them held ten bytes a voxel beyond the map's charge (186 MiB under 180M)."""
    src, _ = _series_and_map(tmp_path, (24, 256, 256), lambda s: _specks(s, seed=1, keep=0.3))
    _read_back_below_its_peak(src, tmp_path / "ct", "rtstruct", tmp_path, (4, 12))
