"""A compressed NIfTI displacement field read piece by piece into its vectors.

The decompressed planes go straight into the interleaved (z, y, x, 3) vectors
(no copy of the file's planes): every byte order, sample type and scaling must
give the vectors nibabel reads, whatever the pieces' sizes (a sample split
between two pieces).
"""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest

from volwarp_cli.io import deflate
from volwarp_cli.transforms.fields import read_field


def write_nifti_field(path, planes_xyz: np.ndarray, dtype, slope=None, inter=0.0):
    """A 5-D (x, y, z, 1, 3) NIfTI of intent 1007 holding ``planes_xyz`` (x, y, z, 3)."""
    data = planes_xyz[:, :, :, None, :].astype(dtype)
    img = nib.Nifti1Image(data, np.diag([-1.0, -1.0, 1.0, 1.0]))
    img.header.set_intent(1007)
    if slope is not None:
        img.header.set_slope_inter(slope, inter)
    img.header.set_data_dtype(np.dtype(dtype))
    nib.save(img, str(path))


@pytest.mark.parametrize("dtype,slope", [("<f4", None), (">f4", None), ("<f8", None),
                                         (">i2", 0.01), ("<u1", 0.5)])
@pytest.mark.parametrize("piece", [1 << 17, 7])
def test_gzip_field_vectors_as_nibabel_reads_them(tmp_path, monkeypatch, dtype, slope, piece):
    monkeypatch.setattr(deflate, "INFLATE_INPUT", piece)
    rng = np.random.default_rng(3)
    shape = (9, 7, 5, 3)  # x, y, z, component
    if np.dtype(dtype).kind == "f":
        planes = rng.normal(size=shape)
    else:
        planes = rng.integers(0, 200 if dtype.endswith("u1") else 3000, size=shape)
    path = tmp_path / "f.nii.gz"
    write_nifti_field(path, planes, dtype, slope=slope, inter=0.25 if slope else 0.0)
    expected = np.asarray(nib.load(str(path)).dataobj, dtype=np.float64)[:, :, :, 0, :]
    field = read_field(str(path), "nifti")
    got = field.vectors.transpose(2, 1, 0, 3)  # (z, y, x, 3) -> (x, y, z, 3)
    assert field.vectors.dtype == (np.float64 if dtype == "<f8" else np.float32)
    assert field.vectors.dtype.isnative
    tol = 0 if field.vectors.dtype == np.float64 else 1e-6 * np.abs(expected).max()
    assert np.abs(got - expected).max() <= tol
    assert not np.array_equal(got[..., 0], got[..., 1])  # (components not confused)


def test_an_integer_field_is_budgeted_as_the_float32_vectors_it_becomes(tmp_path):
    from volwarp_cli.errors import OutOfMemoryError
    from volwarp_cli.memory import process_rss, use_memory_limit

    planes = np.random.default_rng(0).integers(0, 200, size=(160, 160, 160, 3))
    path = tmp_path / "u8.nii.gz"
    write_nifti_field(path, planes, "<u1", slope=0.1)
    file_bytes = planes.size  # 12 MB of uint8 samples; 49 MB as float32 vectors
    with use_memory_limit(process_rss() + 2 * file_bytes), \
            pytest.raises(OutOfMemoryError, match="needs 46.9 MiB"):
        read_field(str(path), "nifti")
    with use_memory_limit(process_rss() + 8 * file_bytes):
        assert read_field(str(path), "nifti").vectors.dtype == np.float32
