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
from volwarp_cli.parallel import use_threads
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
@pytest.mark.parametrize("beside", [False, True])  # the pieces placed on a thread of their own
def test_gzip_field_vectors_as_nibabel_reads_them(tmp_path, monkeypatch, dtype, slope, piece,
                                                  beside):
    monkeypatch.setattr(deflate, "INFLATE_INPUT", piece)
    monkeypatch.setattr(deflate, "BESIDE_BATCH", 64 if beside else 1 << 40)
    placing = []
    real = deflate.sink_beside

    def watched(sink, total):
        placing.append(total >= 4 * deflate.BESIDE_BATCH)
        return real(sink, total)

    monkeypatch.setattr(deflate, "sink_beside", watched)
    rng = np.random.default_rng(3)
    shape = (9, 7, 5, 3)  # x, y, z, component
    if np.dtype(dtype).kind == "f":
        planes = rng.normal(size=shape)
    else:
        planes = rng.integers(0, 200 if dtype.endswith("u1") else 3000, size=shape)
    path = tmp_path / "f.nii.gz"
    write_nifti_field(path, planes, dtype, slope=slope, inter=0.25 if slope else 0.0)
    expected = np.asarray(nib.load(str(path)).dataobj, dtype=np.float64)[:, :, :, 0, :]
    with use_threads(2):
        field = read_field(str(path), "nifti")
    assert placing == [beside]
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


def _vector_field(path, kind: str) -> np.ndarray:
    """A smooth float32 field written as ``kind`` says; its LPS vectors (z, y, x, 3)."""
    import SimpleITK as sitk

    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    nz, ny, nx = 11, 13, 17
    z, y, x = np.mgrid[:nz, :ny, :nx].astype(float)
    lps = np.stack([1.5 * np.sin(z / 4), np.cos(x / 5) - 0.2, 0.8 * np.sin(y / 3)],
                   -1).astype(np.float32)
    if kind.startswith("itk"):  # SimpleITK's writers: interleaved vectors, LPS
        img = sitk.GetImageFromArray(lps, isVector=True)
        img.SetOrigin([-3.0, 2.0, 1.5])
        img.SetSpacing([1.1, 1.0, 1.3])
        sitk.WriteImage(img, str(path), useCompression=kind.endswith("gz"))
    elif kind == "ras":  # pynrrd, a RAS frame: the file's x and y components are LPS's negated
        import nrrd

        ras = lps * np.float32([-1, -1, 1])
        nrrd.write(str(path), ras, index_order="C", header={
            "space": "right-anterior-superior", "kinds": ["vector", "domain", "domain", "domain"],
            "space directions": np.array([[np.nan] * 3, [-1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]]),
            "space origin": np.array([3.0, -2.0, 1.5])})
    else:  # components as the last (slowest) axis: three volumes one after the other
        write_volume(Volume(lps[..., 0]), path.with_suffix(".tmp.nrrd"))
        head = path.with_suffix(".tmp.nrrd").read_bytes().split(b"\n\n", 1)[0].decode()
        lines = [ln for ln in head.splitlines() if not ln.startswith(("data file", "encoding"))]
        lines = [("dimension: 4" if ln.startswith("dimension:") else
                  f"sizes: {nx} {ny} {nz} 3" if ln.startswith("sizes:") else
                  ln.replace(")\n", ")") + " none" if ln.startswith("space directions:") else
                  "kinds: domain domain domain vector" if ln.startswith("kinds:") else ln)
                 for ln in lines]
        path.write_text("\n".join([*lines, "encoding: raw", "data file: planes.raw", ""]))
        (path.parent / "planes.raw").write_bytes(np.moveaxis(lps, -1, 0).astype("<f4").tobytes())
    return lps


@pytest.mark.parametrize("kind,name", [("itk", "f.nrrd"), ("itk", "f.mha"), ("itk-gz", "f.nrrd"),
                                       ("itk-gz", "f.mha"), ("ras", "f.nrrd"),
                                       ("planar", "f.nhdr")])
def test_nrrd_and_metaimage_fields_by_windows_are_the_whole(tmp_path, monkeypatch, kind, name):
    """A NRRD or MetaImage field over its share of the budget is read by windows (issue 30).

    Interleaved (ITK's writers, compressed ones through a scratch copy),
    RAS (vectors turned to LPS window by window) and planar: the vectors
    and the points' images are those read whole, and a window reads only its box.
    """
    from volwarp_cli import memory
    from volwarp_cli.io.inputs import claim_output
    from volwarp_cli.runscope import run_scope

    lps = _vector_field(tmp_path / name, kind)
    whole = read_field(str(tmp_path / name), "metaimage" if name.endswith("mha") else "nrrd")
    assert whole.vectors is not None and np.array_equal(whole.vectors, lps)
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    with run_scope():
        claim_output(tmp_path / "o.nrrd", "-o")  # (a compressed file's copy goes beside it)
        lazy = read_field(str(tmp_path / name), "metaimage" if name.endswith("mha") else "nrrd")
        assert lazy.vectors is None
        nz, ny, nx = lps.shape[:3]
        assert np.array_equal(lazy.source.read((0, 0, 0), (nz, ny, nx)), lps)
        assert np.array_equal(lazy.source.read((2, 3, 4), (5, 9, 16)), lps[2:5, 3:9, 4:16])
        pts = np.random.default_rng(1).uniform([-5, 0, 0], [22, 16, 16], (300, 3))
        np.testing.assert_array_equal(lazy.map(pts), whole.map(pts))
        for a, b in zip(vars(lazy.frame).values(), vars(whole.frame).values(), strict=True):
            assert np.array_equal(a, b)


@pytest.mark.parametrize("name", ["f.nrrd", "f.mha"])
def test_apply_through_a_nrrd_field_by_windows_writes_the_same_bytes(run, tmp_path, monkeypatch,
                                                                      name):
    """`volwarp apply` by blocks through a NRRD/MetaImage field read by windows: the same file."""
    from volwarp_cli import memory
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    _vector_field(tmp_path / name, "itk-gz")
    z, y, x = np.mgrid[:10, :10, :14].astype(np.float32)  # (inside the field's extent)
    write_volume(Volume(np.sin(x / 3) * np.cos(y / 4) + z / 7, origin=(-2.0, 3.0, 2.5)),
                 tmp_path / "in.nrrd")
    args = ["apply", tmp_path / "in.nrrd", "-t", tmp_path / name]
    assert run(*args, "-o", tmp_path / "whole.nrrd").code == 0
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    opened = []
    from volwarp_cli.transforms import fields

    real = fields.LazyField.__init__
    monkeypatch.setattr(fields.LazyField, "__init__",
                        lambda self, *a, **k: opened.append(1) or real(self, *a, **k))
    res = run(*args, "-o", tmp_path / "windows.nrrd", "--chunked", "--block", "5,6,7")
    assert res.code == 0, res.stderr
    assert opened  # (read by windows, not whole)
    assert (tmp_path / "windows.nrrd").read_bytes() == (tmp_path / "whole.nrrd").read_bytes()
    assert not list(tmp_path.glob("*.scratch*"))  # (the compressed field's copy: removed)


def test_an_integer_compressed_nrrd_field_is_read_whole_without_a_scratch_copy(tmp_path,
                                                                               monkeypatch):
    """Only float vectors are read by windows: an int16 gzip NRRD field is not inflated to disk
    first (then read whole again); its vectors are the file's, as float32."""
    import SimpleITK as sitk

    from volwarp_cli import memory
    from volwarp_cli.io import inflated
    from volwarp_cli.io.inputs import claim_output
    from volwarp_cli.runscope import run_scope

    vec = (np.random.default_rng(0).normal(size=(12, 13, 14, 3)) * 10).astype(np.int16)
    sitk.WriteImage(sitk.GetImageFromArray(vec, isVector=True), str(tmp_path / "i.nrrd"),
                    useCompression=True)
    copies = []
    real = inflated.inflated_array
    monkeypatch.setattr(inflated, "inflated_array", lambda *a, **k: copies.append(a) or real(*a, **k))
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    with run_scope():
        claim_output(tmp_path / "o.nrrd", "-o")
        field = read_field(str(tmp_path / "i.nrrd"), "nrrd")
    assert copies == [] and field.vectors.dtype == np.float32
    assert np.array_equal(field.vectors, vec.astype(np.float32))
