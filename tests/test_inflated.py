"""Compressed inputs larger than their share of memory: inflated once to scratch, read by box.

A ``.nii.gz``, a gzip NRRD or a compressed MetaImage whose samples exceed
``memory.READ_BY_BOX_SHARE`` of the budget is inflated into a scratch file
beside the run's first output and read from there box by box (the share is
set to 0 here to take that way on small files). The samples, the header and
the outputs are the ones read whole; the scratch folder is gone when the run
ends, after a failure too; a damaged file is the same error.
"""

from __future__ import annotations

import gzip
import os
import pickle
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from volwarp_cli import memory
from volwarp_cli.geometry import Geometry
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume


def _ball(shape=(23, 19, 17)) -> Volume:
    z, y, x = np.ogrid[:shape[0], :shape[1], :shape[2]]
    r2 = (x - 8.3) ** 2 + ((y - 9.1) * 1.2) ** 2 + ((z - 11.4) * 0.9) ** 2
    data = (1000 * np.exp(-r2 / 40.0)).astype(np.int16)
    return Volume(data, spacing=(0.9, 1.1, 1.3), origin=(-4.0, 7.5, 2.25))


def _write(kind: str, folder) -> str:
    vol = _ball()
    if kind == "nii.gz":
        path = folder / "in.nii.gz"
        write_volume(vol, path)
    elif kind == "nii.gz big-endian":  # another byte order, as nibabel writes it
        path = folder / "in_be.nii.gz"
        data = vol.data.astype(">i2")
        img = nib.Nifti1Image(np.asarray(data).transpose(2, 1, 0), np.diag([-0.9, -1.1, 1.3, 1]))
        img.header.set_data_dtype(">i2")
        nib.save(img, str(path))
    elif kind == "nrrd gzip":
        path = folder / "in.nrrd"
        write_volume(vol, path, compress=True)
    elif kind == "nhdr + raw.gz":
        path = folder / "in.nhdr"
        write_volume(vol, path, compress=True)
        assert any(p.name.endswith(".gz") for p in folder.iterdir())
    elif kind == "mha compressed":
        path = folder / "in.mha"
        write_volume(vol, path, compress=True)
    else:
        raise AssertionError(kind)
    return str(path)


#: a bundled warp spec in voxel units, as intensities
SPEC = Path(__file__).resolve().parent.parent / "specs" / "warp-ball-voxel.yaml"

KINDS = ["nii.gz", "nii.gz big-endian", "nrrd gzip", "nhdr + raw.gz", "mha compressed"]


@pytest.fixture
def by_box(monkeypatch):
    """Every input read by box: compressed ones through a scratch copy."""
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)


@pytest.fixture
def inflations(monkeypatch):
    """The inputs inflated to scratch in the test (their ``where``), as they are made."""
    from volwarp_cli.io import inflated

    made, real = [], inflated.inflated_array

    def spy(original, nbytes, file_dtype, shape_zyx, where, fill, part=0):
        made.append(where)
        return real(original, nbytes, file_dtype, shape_zyx, where, fill, part)

    monkeypatch.setattr(inflated, "inflated_array", spy)
    return made


def _scratch(folder) -> list[str]:
    return [n for n in os.listdir(folder) if n.endswith(".scratch")]


@pytest.mark.parametrize("kind", KINDS)
def test_compressed_input_read_by_box_equals_whole(kind, tmp_path, by_box):
    """The scratch copy's boxes are the samples read whole; the header is the same; it goes."""
    from volwarp_cli.io.inflated import InflatedArray
    from volwarp_cli.io.inputs import claim_output
    from volwarp_cli.io.lazy import LazySource, open_volume_header
    from volwarp_cli.runscope import run_scope

    src = tmp_path / "src"
    src.mkdir()
    path = _write(kind, src)
    whole = read_volume(path)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    with run_scope():
        claim_output(out_dir / "result.nrrd", "-o")
        header, array = open_volume_header(path)
        assert isinstance(array, InflatedArray)
        assert len(_scratch(out_dir)) == 1 and _scratch(src) == []  # (beside the output)
        assert Geometry.of(header) == Geometry.of(whole)
        assert (header.space, header.file_space, header.meta) == (whole.space, whole.file_space,
                                                                  whole.meta)
        assert header.shape == whole.data.shape and header.dtype == whole.data.dtype
        np.testing.assert_array_equal(np.asarray(array[...]), whole.data)
        box = (slice(3, 17), slice(2, 11), slice(5, 16))
        np.testing.assert_array_equal(array[box], whole.data[box])
        # a worker process gets the same scratch file, not a second inflation
        again = pickle.loads(pickle.dumps(LazySource(path, array=array)))
        assert isinstance(again._array, InflatedArray) and again._array.path == array.path
        np.testing.assert_array_equal(again[box], whole.data[box])
    assert _scratch(out_dir) == []  # the run ended: its scratch copy with it


def test_small_compressed_input_is_read_whole(tmp_path):
    """Where the samples fit their share of the budget, nothing is written to disk."""
    from volwarp_cli.io.inputs import claim_output
    from volwarp_cli.io.lazy import open_volume_header
    from volwarp_cli.runscope import run_scope

    path = _write("nii.gz", tmp_path)
    with run_scope():
        claim_output(tmp_path / "o.nrrd", "-o")
        _, array = open_volume_header(path)
        assert isinstance(array, np.ndarray) and _scratch(tmp_path) == []


@pytest.mark.parametrize("command", [
    ["mesh", "--iso", "400"],
    ["distance", "--iso", "400", "--surface", "voxel"],
    ["warp", "--spec", "SPEC"],
])
def test_command_on_a_scratch_copy_writes_the_same_bytes(command, run, tmp_path, monkeypatch,
                                                         inflations):
    """A command by blocks on a compressed input through its scratch copy = read whole."""
    path = _write("nii.gz", tmp_path)
    args = [SPEC if a == "SPEC" else a for a in command]
    ext = ".ply" if command[0] == "mesh" else ".nrrd"
    first = run(args[0], path, "-o", tmp_path / f"whole{ext}", *args[1:])
    assert first.code == 0, first.stderr
    assert inflations == []
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    res = run(args[0], path, "-o", tmp_path / f"boxes{ext}", *args[1:], "--chunked")
    assert res.code == 0, res.stderr
    assert inflations == [path]
    assert (tmp_path / f"whole{ext}").read_bytes() == (tmp_path / f"boxes{ext}").read_bytes()
    assert _scratch(tmp_path) == []


def test_damaged_compressed_input_same_error_nothing_left(run, tmp_path, by_box):
    """A truncated .nii.gz inflated to scratch: the reader's error, no output, no scratch."""
    path = _write("nii.gz", tmp_path)
    whole = Path(path).read_bytes()
    cut = tmp_path / "cut.nii.gz"
    cut.write_bytes(whole[:len(whole) * 2 // 3])
    (tmp_path / "o.ply").write_bytes(b"earlier run")
    res = run("mesh", cut, "-o", tmp_path / "o.ply", "--iso", "400")
    assert res.code == 1
    assert "cut.nii.gz: cannot read NIfTI data (the gzip stream is truncated" in res.stderr
    assert (tmp_path / "o.ply").read_bytes() == b"earlier run"
    assert _scratch(tmp_path) == []


def test_gzip_nrrd_holding_more_than_its_sizes_refused(tmp_path, by_box):
    """A stream longer than the header's sizes is refused as when read whole."""
    from volwarp_cli.errors import FormatError
    from volwarp_cli.io.lazy import open_volume_header
    from volwarp_cli.runscope import run_scope

    vol = _ball()
    head = (b"NRRD0004\ntype: int16\ndimension: 3\nsizes: 17 19 23\nencoding: gzip\n"
            b"endian: little\n\n")
    extra = vol.data.astype("<i2").tobytes() + b"\0" * 4096
    path = tmp_path / "long.nrrd"
    path.write_bytes(head + gzip.compress(extra))
    with pytest.raises(FormatError, match="holds more than"):
        read_volume(path)
    with run_scope(), pytest.raises(FormatError, match="holds more than"):
        open_volume_header(path)
    assert _scratch(tmp_path) == [] and not any(
        n.endswith(".scratch") for n in os.listdir(os.path.dirname(os.path.abspath(path))))


def test_no_disk_room_reads_whole_and_says_both(run, tmp_path, monkeypatch, by_box):
    """No room on the disk for the copy: read whole where it fits; refused naming both sizes."""
    import shutil
    from collections import namedtuple

    from volwarp_cli.io import inflated

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10 << 30, 10 << 30, 100))
    path = _write("nii.gz", tmp_path)
    assert inflated.NoRoom  # (the reason the copy is not made)
    res = run("mesh", path, "-o", tmp_path / "a.ply", "--iso", "400")
    assert res.code == 0, res.stderr  # read whole: it fits the memory
    res = run("mesh", path, "-o", tmp_path / "b.ply", "--iso", "400", "--memory-limit", "1M")
    assert res.code == 1
    assert "needs" in res.stderr and "inflating it to read by blocks needs" in res.stderr
    assert "has 100 B free" in res.stderr
    assert not (tmp_path / "b.ply").exists() and _scratch(tmp_path) == []


@pytest.mark.parametrize("name", ["f.nii.gz", "f.nrrd", "f.mha"])
def test_a_compressed_field_without_disk_room_is_refused_naming_both(run, tmp_path, monkeypatch,
                                                                     by_box, name):
    """A compressed field (.nii.gz, gzip NRRD, compressed MetaImage), no room to copy it, no
    memory to hold it: refused as out of memory, with the disk's room too; nothing written."""
    import shutil
    from collections import namedtuple

    sitk = pytest.importorskip("SimpleITK")
    vec = np.zeros((40, 40, 40, 3), np.float32)
    sitk.WriteImage(sitk.GetImageFromArray(vec, isVector=True), str(tmp_path / name),
                    useCompression=True)
    write_volume(Volume(np.ones((8, 8, 8), np.float32)), tmp_path / "in.nrrd")
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10 << 30, 10 << 30, 100))
    res = run("apply", tmp_path / "in.nrrd", "-t", tmp_path / name, "-o", tmp_path / "o.nrrd",
              "--memory-limit", "1M")
    assert res.code == 1, res.stderr
    assert "needs" in res.stderr and "inflating it to read by blocks needs" in res.stderr
    assert "not a displacement field" not in res.stderr
    assert not (tmp_path / "o.nrrd").exists() and _scratch(tmp_path) == []


# -- displacement fields: a .nii.gz field by windows, points spread over it by cells -------
def _field(path, shape=(20, 22, 24), nan_at=None):
    """A smooth float32 displacement field (.nii.gz or .nii, as SimpleITK writes it)."""
    sitk = pytest.importorskip("SimpleITK")
    nz, ny, nx = shape
    z, y, x = np.mgrid[:nz, :ny, :nx].astype(float)
    vec = np.stack([1.5 * np.sin(z / 6), 1.5 * np.cos(x / 8), 0.9 * np.sin(y / 7)], -1)
    if nan_at is not None:
        vec[nan_at] = np.nan
    img = sitk.GetImageFromArray(vec.astype(np.float32), isVector=True)
    img.SetOrigin([-3.0, 2.0, 1.5])
    img.SetSpacing([1.1, 1.0, 1.3])
    sitk.WriteImage(img, str(path))
    return sitk.ReadImage(str(path), sitk.sitkVectorFloat64)


def _points(n=400):
    rng = np.random.default_rng(3)
    pts = rng.uniform([-6, -1, -2], [26, 25, 30], (n, 3))  # (some beyond the field's extent)
    return np.vstack([pts, [[np.nan, 1.0, 2.0]]])


def test_gz_field_by_windows_maps_as_whole(tmp_path, monkeypatch):
    """A .nii.gz field over its share: a scratch copy read by windows, mapping as held whole.

    Points spread wider than one window (here any) are mapped a cell of
    them at a time: the same images as the whole field's, NaN where a
    point or the vectors it reaches are NaN, and ITK's TransformPoint.
    """
    sitk = pytest.importorskip("SimpleITK")
    from volwarp_cli.io.inputs import claim_output
    from volwarp_cli.runscope import run_scope
    from volwarp_cli.transforms import model, read_chain

    img = _field(tmp_path / "f.nii.gz", nan_at=(5, 6, 7))
    pts = _points()
    with run_scope():
        whole = read_chain([str(tmp_path / "f.nii.gz")]).steps[0]
        assert whole.vectors is not None
        expect = whole.map(pts)
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    monkeypatch.setattr(model, "WINDOW_BYTES", 0)
    with run_scope():
        claim_output(tmp_path / "o.nrrd", "-o")
        lazy = read_chain([str(tmp_path / "f.nii.gz")]).steps[0]
        assert lazy.vectors is None and ".scratch" in lazy.source.path
        got = lazy.map(pts)
        np.testing.assert_array_equal(got, expect)
    assert _scratch(tmp_path) == []
    theirs = sitk.DisplacementFieldTransform(img)
    finite = np.isfinite(expect).all(axis=1)
    assert 0 < (~finite).sum() < 10  # (the NaN point and those reaching the NaN vector)
    ref = np.array([theirs.TransformPoint(p.tolist()) for p in pts[finite]])
    assert np.abs(expect[finite] - ref).max() < 1e-5


@pytest.mark.parametrize("ext", [".nii.gz", ".nrrd"])
def test_worker_that_cannot_see_a_fields_scratch_copy_reads_the_field_whole(ext, tmp_path,
                                                                            by_box, inflations,
                                                                            monkeypatch):
    """A compressed field read by windows goes to workers with its scratch copy; a worker on
    another machine (the copy not there) reads the field whole from its own file instead
    (once, whatever the threads asking; no second scratch copy), and maps points as the
    command's copy does."""
    import threading
    import time

    from volwarp_cli.io.inflated import InflatedArray
    from volwarp_cli.runscope import run_scope
    from volwarp_cli.transforms import fields, read_chain

    sitk = pytest.importorskip("SimpleITK")
    path = tmp_path / f"f{ext}"
    img = _field(tmp_path / "f.nii.gz")
    if ext == ".nrrd":  # (a gzip NRRD of the same vectors, as SimpleITK writes it)
        sitk.WriteImage(sitk.Cast(img, sitk.sitkVectorFloat32), str(path), True)
    pts = _points()
    with run_scope():  # (no output claimed: the copy goes to the temporary folder)
        field = read_chain([str(path)]).steps[0]
        copy = field.source.samples
        assert field.vectors is None and isinstance(copy, InflatedArray)
        expect = field.map(pts)
        shipped = pickle.dumps(field)
        assert pickle.loads(shipped).source.samples is not None  # (here: the same copy)
        hidden = copy.path + ".elsewhere"
        os.rename(copy.path, hidden)  # (a worker on another machine)
        reads, real = [], fields.read_whole

        def slow_read(*args):
            reads.append(args)
            time.sleep(0.2)  # (the other threads ask meanwhile)
            return real(*args)

        monkeypatch.setattr(fields, "read_whole", slow_read)
        try:
            remote = pickle.loads(shipped)
            assert remote.source.samples is None
            threads = [threading.Thread(target=remote.source.read, args=((0, 0, 0), (2, 2, 2)))
                       for _ in range(4)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            got = remote.map(pts)
        finally:
            os.rename(hidden, copy.path)
        assert len(reads) == 1 and isinstance(remote.source._whole, np.ndarray)
        assert len(inflations) == 1  # (the command's copy only: read whole, not copied again)
        np.testing.assert_array_equal(got, expect)
        assert np.isfinite(got).sum() > 0.9 * got.size


def test_points_spread_over_a_lazy_field_read_by_cells(tmp_path, monkeypatch):
    """Mapping a lattice over a field read by windows never holds the field's window whole."""
    import tracemalloc

    from volwarp_cli.transforms import model, read_chain

    _field(tmp_path / "f.nii", shape=(64, 64, 64))  # 3 MiB of vectors
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    field = read_chain([str(tmp_path / "f.nii")]).steps[0]
    assert field.vectors is None
    axes = [np.linspace(lo, hi, 9) for lo, hi in ((-3, 66), (2, 65), (1.5, 83))]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    field.map(lattice[:2])  # (the kernel compiled outside the measure)
    for limit, most in ((64 << 20, None), (1 << 20, 1 << 20)):
        monkeypatch.setattr(model, "WINDOW_BYTES", limit)
        tracemalloc.start()
        got = field.map(lattice)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        if most is None:
            assert peak > 3 << 20  # one window: the whole field's vectors
            whole = got
        else:
            assert peak < most  # a cell's windows at a time
            np.testing.assert_array_equal(got, whole)


def test_points_inverted_through_a_lazy_field_as_through_the_whole(tmp_path, monkeypatch):
    """Newton's inverse through a field read by windows: the whole field's answers, few reads.

    The points (mesh vertices, landmarks) go the other way than images: each
    iteration maps them several times. With their common window too large,
    the points are solved a half at a time, each half through one window read
    once. A folding field sends some iterates out of their window: those are
    mapped through the field itself, so every point, residual and unsolved
    point is the field in memory's, bit for bit.
    """
    import SimpleITK as sitk

    from volwarp_cli.transforms import model, read_chain

    n = 48
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32)
    vec = np.stack([4 * np.sin(z / 3 + 1), 4 * np.cos(x / 4), 4 * np.sin(y / 2.5)], -1)
    sitk.WriteImage(sitk.GetImageFromArray(vec, isVector=True), str(tmp_path / "f.nii"))
    pts = np.vstack([np.random.default_rng(0).uniform(-3, n + 2, (900, 3)), [[np.nan, 1, 2]]])
    whole = read_chain([str(tmp_path / "f.nii")])
    want = whole.invert_points(pts)
    assert 50 < len(want.unsolved) < 600  # (the field folds: some points have no preimage)
    assert np.isnan(want.points[want.unsolved]).all()  # (unsolved: NaN, not a last guess)
    want_solved = model._solve(whole.steps[0], pts)  # (Newton's own answers, unsolved too)
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    monkeypatch.setattr(model, "WINDOW_BYTES", 1 << 20)  # (the whole field: 1.3 MB x 2)
    chain = read_chain([str(tmp_path / "f.nii")])
    field = chain.steps[0]
    assert field.vectors is None
    field._tiles()  # (the field's reach: read once, slab by slab, before the count)
    reads = []
    real = field.source.read
    monkeypatch.setattr(field.source, "read", lambda lo, hi: reads.append(1) or real(lo, hi))
    got = model._solve(field, pts)
    windows = len(reads)
    np.testing.assert_array_equal(got, want_solved)
    assert 1 < windows < 400  # (a few halves' windows and the strays' cells, not per iteration)
    lazy = chain.invert_points(pts)
    assert lazy.unsolved.tolist() == want.unsolved.tolist()
    np.testing.assert_array_equal(lazy.residual, want.residual)
    np.testing.assert_array_equal(lazy.points, want.points)
    assert model._solve(field, pts[:0]).shape == (0, 3)  # (no points: none read)
    off = np.array([[-50.0, -50, -50], [300, 300, 300]])  # (none on the field: not moved)
    np.testing.assert_array_equal(model._solve(field, off), off)


def test_apply_through_a_gz_field_by_scratch_equals_whole(run, tmp_path, monkeypatch,
                                                          inflations):
    """`volwarp apply` through a .nii.gz field copied to scratch and read by windows: same bytes."""
    vol = _ball((20, 22, 24))
    write_volume(Volume(vol.data, spacing=(1.1, 1.0, 1.3), origin=(-3.0, 2.0, 1.5)),
                 tmp_path / "in.nrrd")
    _field(tmp_path / "f.nii.gz")
    args = ["apply", tmp_path / "in.nrrd", "-t", tmp_path / "f.nii.gz"]
    assert run(*args, "-o", tmp_path / "whole.nrrd").code == 0
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    res = run(*args, "-o", tmp_path / "boxes.nrrd", "--chunked", "--block", "7,8,9")
    assert res.code == 0, res.stderr
    assert inflations == [str(tmp_path / "f.nii.gz")]
    assert (tmp_path / "whole.nrrd").read_bytes() == (tmp_path / "boxes.nrrd").read_bytes()
    assert _scratch(tmp_path) == []


def test_morph_by_blocks_inflates_each_compressed_input_once(run, tmp_path, monkeypatch,
                                                              inflations):
    """A morph of two large .nii.gz shapes: each inflated once (its plan's copy reused), same frames."""
    a, b = _ball(), _ball()
    b = Volume(np.roll(b.data, 3, axis=2), spacing=b.spacing, origin=b.origin)
    write_volume(a, tmp_path / "a.nii.gz")
    write_volume(b, tmp_path / "b.nii.gz")
    args = ["morph", tmp_path / "a.nii.gz", tmp_path / "b.nii.gz", "--iso", "400",
            "--frames", "3", "--max-distance", "4"]
    assert run(*args, "-o", tmp_path / "m_{i}.nrrd").code == 0
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    res = run(*args, "-o", tmp_path / "k_{i}.nrrd", "--chunked")
    assert res.code == 0, res.stderr
    assert sorted(inflations) == [str(tmp_path / "a.nii.gz"), str(tmp_path / "b.nii.gz")]
    for i in range(3):
        assert (read_volume(tmp_path / f"m_{i}.nrrd").data.tobytes()
                == read_volume(tmp_path / f"k_{i}.nrrd").data.tobytes())
    assert _scratch(tmp_path) == []


# -- where copies are not made, and made once -------------------------------------------------
def test_worker_reopening_an_input_reads_it_whole_never_copies(tmp_path, by_box):
    """A LazySource pickled without its samples (read whole by the command) reopens them whole.

    A worker process's tasks have a smaller budget than the command: a copy
    made there was removed by the reopening's own scope at once (the review's
    FileNotFoundError), and would be one copy per block.
    """
    from volwarp_cli.io.lazy import LazySource
    from volwarp_cli.runscope import run_scope

    path = _write("nii.gz", tmp_path)
    whole = read_volume(path)
    with run_scope():
        shipped = pickle.loads(pickle.dumps(LazySource(path, array=whole.data)))
        box = (slice(0, 5), slice(2, 9), slice(3, 4))
        np.testing.assert_array_equal(shipped[box], whole.data[box])
        assert isinstance(shipped._array, np.ndarray)
    assert _scratch(tmp_path) == [] and not [
        n for n in os.listdir(tempfile_dir()) if n.startswith(".in.nii.gz.vw-")]


def tempfile_dir():
    import tempfile

    return tempfile.gettempdir()


@pytest.mark.parametrize("ext", ["nii.gz", "scaled nii.gz"])
def test_worker_that_cannot_see_the_scratch_copy_reads_the_input_whole(ext, tmp_path, by_box):
    """A command without an output file makes its copy in the temporary folder, which a
    remote cluster's worker does not see: unpickled where the copy is not, the source
    reopens the input by path (read whole) and reads the same samples."""
    from volwarp_cli.io.inflated import InflatedArray
    from volwarp_cli.io.lazy import LazySource, ScaledSamples, open_volume_header
    from volwarp_cli.runscope import run_scope

    if ext == "nii.gz":
        path = _write("nii.gz", tmp_path)
    else:  # scl_slope/scl_inter: the copy inside ScaledSamples
        path = str(tmp_path / "scaled.nii.gz")
        img = nib.Nifti1Image(_ball().data.transpose(2, 1, 0), np.eye(4))
        img.header.set_slope_inter(0.5, -3.0)
        nib.save(img, path)
    whole = read_volume(path)
    box = (slice(3, 17), slice(2, 11), slice(5, 16))
    with run_scope():  # (no output claimed: the copy goes to the temporary folder)
        _, array = open_volume_header(path)
        copy = array.base if isinstance(array, ScaledSamples) else array
        assert isinstance(copy, InflatedArray)
        assert os.path.dirname(os.path.dirname(copy.path)) == tempfile_dir()
        shipped = pickle.dumps(LazySource(path, array=array))
        here = pickle.loads(shipped)  # (a worker on this machine: the same copy)
        assert here._array is not None and here._array.reachable()
        hidden = copy.path + ".elsewhere"
        os.rename(copy.path, hidden)  # (a worker on another machine)
        try:
            remote = pickle.loads(shipped)
            assert remote._array is None
            got = remote[box]
            assert isinstance(remote._array, np.ndarray)  # (reopened whole, not copied)
        finally:
            os.rename(hidden, copy.path)
        np.testing.assert_array_equal(got, whole.data[box])
        assert got.dtype == whole.data.dtype


def test_no_copy_outside_a_run_nor_for_a_header(tmp_path, by_box, inflations):
    """A library call outside any run reads whole (nothing left behind); a header alone inflates nothing."""
    from volwarp_cli.io.lazy import open_volume_header
    from volwarp_cli.runscope import run_scope

    path = _write("nii.gz", tmp_path)
    _, array = open_volume_header(path)
    assert isinstance(array, np.ndarray)
    with run_scope():
        header, array = open_volume_header(path, samples=False)
        assert array is None and header.shape == read_volume(path).data.shape
    assert inflations == []


def test_the_same_file_twice_in_a_run_is_copied_once(tmp_path, by_box, inflations):
    from volwarp_cli.io import inflated
    from volwarp_cli.io.lazy import open_volume_header
    from volwarp_cli.runscope import run_scope

    path = _write("nii.gz", tmp_path)
    made = []
    real = inflated._scratch_for
    with run_scope(), pytest.MonkeyPatch.context() as mp:
        mp.setattr(inflated, "_scratch_for", lambda *a: made.append(a) or real(*a))
        first = open_volume_header(path)[1]
        second = open_volume_header(path)[1]
        assert first.path == second.path and len(made) == 1


def test_cells_of_an_oblique_field_read_small_windows(tmp_path, monkeypatch):
    """Points far outside a rotated field are not windowed: each read stays a cell's size.

    (A cell's window was the world box of its points, strays clamped into it
    included: on an oblique field that box's index range was the whole grid.)
    """
    sitk = pytest.importorskip("SimpleITK")
    from volwarp_cli.transforms import model, read_chain

    n = 48
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float32)
    vec = np.stack([np.sin(z / 5), np.cos(x / 7), 0.5 * np.sin(y / 6)], -1).astype(np.float32)
    img = sitk.GetImageFromArray(vec, isVector=True)
    rot = sitk.Euler3DTransform((0, 0, 0), 0.3, -0.25, 0.2)
    img.SetDirection(rot.GetMatrix())
    img.SetOrigin((3.0, -2.0, 5.0))
    sitk.WriteImage(img, str(tmp_path / "f.nii"))
    rng = np.random.default_rng(7)
    inside = np.asarray([img.TransformContinuousIndexToPhysicalPoint(v.tolist())
                         for v in rng.uniform(0, n - 1, (3000, 3))])
    strays = rng.uniform(-3000, 3000, (40, 3))
    pts = np.vstack([inside, strays, [[np.inf, 0.0, 1.0]]])
    whole = read_chain([str(tmp_path / "f.nii")]).steps[0].map(pts)
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    monkeypatch.setattr(model, "WINDOW_BYTES", 0)
    field = read_chain([str(tmp_path / "f.nii")]).steps[0]
    sizes = []
    real = field.source.read
    monkeypatch.setattr(field.source, "read", lambda lo, hi: sizes.append(
        np.prod(np.subtract(hi, lo))) or real(lo, hi))
    np.testing.assert_array_equal(field.map(pts), whole)
    theirs = sitk.DisplacementFieldTransform(sitk.Cast(img, sitk.sitkVectorFloat64))
    ref = np.array([theirs.TransformPoint(p.tolist()) for p in pts[:3040]])
    assert np.abs(whole[:3040] - ref).max() < 1e-5
    cell = model.TILE + 3  # (a cell's points, one voxel either side and the upper neighbour)
    assert sizes and max(sizes) <= cell ** 3


def test_nan_count_computed_once_per_process_across_pickled_copies(tmp_path, monkeypatch):
    """Block tasks in a worker process each get a pickled field: its NaN scan runs once there."""
    from volwarp_cli.transforms import model, read_chain

    _field(tmp_path / "f.nii", nan_at=(3, 4, 5))
    field = read_chain([str(tmp_path / "f.nii")]).steps[0]
    calls = []
    real = model.DisplacementField._nonfinite
    monkeypatch.setattr(model.DisplacementField, "_nonfinite",
                        lambda self: calls.append(1) or real(self))
    copies = [pickle.loads(pickle.dumps(field)) for _ in range(3)]
    counts = {c.nonfinite() for c in copies} | {field.nonfinite()}
    assert counts == {(1, (5, 4, 3), (5, 4, 3))} and len(calls) == 1


# -- NIfTI: scaled samples and a volume of a 4-D (or a component of a 5-D) file, by box ------
def _nifti_cases(folder, ext):
    """A scaled 4-D int16 file and a 5-D vector file (x, y, z, 1, 3), both written by nibabel."""
    rng = np.random.default_rng(1)
    four = (rng.normal(size=(17, 19, 23, 4)) * 100).astype(np.int16)
    img = nib.Nifti1Image(four, np.diag([1.1, 0.9, 1.3, 1]))
    img.header.set_slope_inter(0.37, -12.5)
    nib.save(img, str(folder / f"s4.{ext}"))
    five = rng.normal(size=(13, 11, 9, 1, 3)).astype(np.float32)
    vec = nib.Nifti1Image(five, np.diag([-1.0, -1.0, 2.0, 1]))
    vec.header.set_intent("vector")
    nib.save(vec, str(folder / f"v5.{ext}"))
    return [(str(folder / f"s4.{ext}"), i) for i in (0, 3)] + [
        (str(folder / f"v5.{ext}"), i) for i in (1, 2)]


@pytest.mark.parametrize("ext", ["nii", "nii.gz"])
def test_scaled_and_4d_nifti_read_by_box_equal_read_volume(ext, tmp_path, by_box):
    """scl_slope/scl_inter applied box by box, a 4-D file's volume and a 5-D file's component
    are their own samples: values, type and key/values are read_volume's; a pickled
    source (a worker's) reads the same."""
    from volwarp_cli.io.inputs import claim_output
    from volwarp_cli.io.lazy import LazySource, ScaledSamples, open_volume_header
    from volwarp_cli.runscope import run_scope

    for path, index in _nifti_cases(tmp_path, ext):
        whole = read_volume(path, volume_index=index)
        with run_scope():
            claim_output(tmp_path / "o.nrrd", "-o")
            header, array = open_volume_header(path, volume_index=index)
            assert not isinstance(array, np.ndarray)
            assert isinstance(array, ScaledSamples) == path.endswith(f"s4.{ext}")
            got = np.asarray(array[...])
            assert got.dtype == whole.data.dtype and header.dtype == whole.data.dtype
            np.testing.assert_array_equal(got, whole.data)
            assert header.meta == whole.meta and Geometry.of(header) == Geometry.of(whole)
            box = (slice(2, 7), slice(1, 8), slice(3, 6))
            src = pickle.loads(pickle.dumps(LazySource(path, volume_index=index, array=array)))
            np.testing.assert_array_equal(src[box], whole.data[box])
        assert _scratch(tmp_path) == []


def test_command_by_blocks_on_a_scaled_4d_nifti_writes_the_same_bytes(run, tmp_path,
                                                                       monkeypatch, inflations):
    """`distance --volume-index 3` of a scaled 4-D .nii.gz by blocks, its volume copied to
    scratch and scaled box by box, writes the in-memory bytes."""
    path, index = _nifti_cases(tmp_path, "nii.gz")[1]
    args = ["distance", path, "--volume-index", str(index), "--iso", "0", "--surface", "voxel"]
    assert run(*args, "-o", tmp_path / "whole.nrrd").code == 0
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    res = run(*args, "-o", tmp_path / "blocks.nrrd", "--chunked", "--block", "5,6,7")
    assert res.code == 0, res.stderr
    assert inflations == [path]
    assert (tmp_path / "whole.nrrd").read_bytes() == (tmp_path / "blocks.nrrd").read_bytes()


def test_two_volumes_of_one_gz_file_in_a_run_are_their_own(tmp_path, by_box):
    """A 4-D .nii.gz's volumes opened in one run: each its own copy (the cache's key holds
    which block; volume 3 came back as volume 0's samples)."""
    from volwarp_cli.io.lazy import open_volume_header
    from volwarp_cli.runscope import run_scope

    path, _ = _nifti_cases(tmp_path, "nii.gz")[0]
    with run_scope():
        for index in (0, 3, 0):
            _, array = open_volume_header(path, volume_index=index)
            np.testing.assert_array_equal(np.asarray(array[...]),
                                          read_volume(path, volume_index=index).data)
