"""DICOM inputs by blocks: a stack read slab by slab from its files, the in-memory results.

A shuffled single-slice series with a rescale (and a second series beside it, chosen
with --series), pydicom's multi-frame and compressed files; the lazy reader against
read_dicom for any box; the commands' outputs by blocks against their in-memory ones;
a worker process reading the stack without scanning the folder again.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydicom.data import get_testdata_file
from test_io_dicom import write_series

from volwarp_cli.io import read_volume
from volwarp_cli.io.dicom import read_dicom
from volwarp_cli.io.dicom._read import LazyDicom, open_dicom_lazy


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    """A 13-slice CT series (two blobs, rescaled to HU) and a second series in the folder."""
    folder = tmp_path_factory.mktemp("dicom") / "study"
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (13, 21, 17)], indexing="ij")
    stored = (1500 * np.exp(-((x - 0.2) ** 2 + y * y + z * z) / 0.2)
              + 900 * np.exp(-((x + 0.4) ** 2 + (y - 0.3) ** 2 + (z + 0.2) ** 2) / 0.06))
    write_series(folder, stored.astype(np.int16), slope=1, intercept=-1000,
                 orientation=(0, 1, 0, 0, 0, -1))  # a sagittal stack: not the identity
    write_series(folder / "other", np.zeros((3, 4, 5), np.int16),
                 series="1.2.826.0.1.3680043.8.498.2")
    return folder


def test_the_lazy_stack_is_read_dicoms_for_any_box(series):
    whole = read_dicom(series, series=0)
    template, lazy = open_dicom_lazy(series, series=0)
    assert lazy.shape == whole.data.shape and lazy.dtype == whole.dtype
    assert template.meta == whole.meta
    assert np.allclose(template.index_to_world_matrix, whole.index_to_world_matrix)
    for key in [np.s_[...], np.s_[3:9, 2:15, 5:6], np.s_[12, :, ::3], np.s_[0:13:4, -5:, 1]]:
        assert np.array_equal(lazy[key], whole.data[key])
    again = pickle.loads(pickle.dumps(lazy))  # (a worker: the frames travel, no scan)
    assert np.array_equal(again[4:7], whole.data[4:7])


@pytest.mark.parametrize("name", ["emri_small.dcm", "MR_small_RLE.dcm", "CT_small.dcm"])
def test_multiframe_and_compressed_files_lazily(name):
    path = get_testdata_file(name)
    whole = read_dicom(path)
    _, lazy = open_dicom_lazy(path)
    assert isinstance(lazy, LazyDicom)
    assert np.array_equal(np.asarray(lazy), whole.data)
    n = lazy.shape[0]
    assert np.array_equal(lazy[n // 2:], whole.data[n // 2:])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 12), st.integers(1, 13), st.integers(0, 20), st.integers(1, 21))
def test_any_slab_of_the_stack(series, z0, dz, y0, dy):
    whole = read_dicom(series, series=0).data
    _, lazy = open_dicom_lazy(series, series=0)
    key = np.s_[z0:z0 + dz, y0:y0 + dy]
    assert np.array_equal(lazy[key], whole[key])


@pytest.mark.parametrize("scheduler", [None, "processes"])
def test_commands_by_blocks_on_a_dicom_series(run, series, tmp_path, scheduler):
    extra = ["--chunked", "--block", "5,7,6"] + (["--scheduler", scheduler] if scheduler else [])
    sel = ["--series", "0"]
    for name, args in (("distance", ["--iso", "-400", "--surface", "voxel"]),
                       ("mesh", ["--iso", "-400"])):
        ext = ".ply" if name == "mesh" else ".nrrd"
        mem, blk = tmp_path / f"m_{name}{ext}", tmp_path / f"b_{name}{ext}"
        assert run(name, series, *sel, "-o", mem, *args).code == 0
        res = run(name, series, *sel, "-o", blk, *args, *extra)
        assert res.code == 0, res.stderr
        if name == "distance":
            a, b = read_volume(mem), read_volume(blk)
            assert np.array_equal(a.data, b.data)
            assert np.allclose(a.index_to_world_matrix, b.index_to_world_matrix)
            assert b.meta.get("DICOM_Modality") == "CT"  # the series' key/values kept
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 5}\nsteps:\n  - move:\n"
                    "      - {index: [2, 2, 2], by: [1.5, -1, 2]}\n")
    mem, blk = tmp_path / "m_warp.nrrd", tmp_path / "b_warp.nrrd"
    assert run("warp", series, *sel, "--spec", spec, "-o", mem).code == 0
    res = run("warp", series, *sel, "--spec", spec, "-o", blk, *extra)
    assert res.code == 0, res.stderr
    assert np.array_equal(read_volume(mem).data, read_volume(blk).data)


def test_dicom_options_for_another_format_are_refused_by_blocks(run, tmp_path):
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    src = tmp_path / "v.nrrd"
    write_volume(Volume(np.zeros((4, 5, 6), np.int16)), src)
    res = run("distance", src, "--iso", "1", "-o", tmp_path / "o.nrrd", "--series", "0",
              "--chunked")
    assert res.code == 2 and "DICOM" in res.stderr
