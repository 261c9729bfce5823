"""An OME-Zarr read whole holds the memory ceiling: zarr's decoding charged, its chunks given back.

A hunt measured reads over ``--memory-limit`` (256^3 float32 of 64^3 chunks): a whole
read charged only its samples, and the chunks zarr's threads decoded and freed stayed in
their malloc arenas (25 MiB, to the end of the process: ``convert`` at 120M held 140
MiB before its write was refused). Now the whole read charges a row of chunks in flight
too, and maps its large allocations so that freed chunks go back at once. Read by box
(``distance`` at 112M peaked at 121-125 MiB), a store's reads now share fewer malloc
arenas (:func:`volwarp_cli.memory.bound_arenas`).
"""

from __future__ import annotations

import numpy as np
import pytest
from peaks import volwarp_peak

from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

MiB = 1 << 20


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ozread")
    rng = np.random.default_rng(3)
    z, y, x = np.indices((192, 192, 192), dtype=np.float32)
    data = (np.sin(x / 9) * np.cos(y / 7) * 100 + z / 3 + rng.normal(0, 1, x.shape)).astype(
        np.float32)
    path = folder / "in.ome.zarr"
    write_volume(Volume(data), path)
    return path


def test_a_whole_read_under_a_limit_below_its_peak_is_refused_before_it_reads(store, tmp_path):
    out = tmp_path / "back.nrrd"
    code, err, peak = volwarp_peak("convert", store, "-o", out)
    assert code == 0, err
    out.unlink()
    limit = peak - 3 * MiB
    code, err, limited = volwarp_peak("convert", store, "-o", out, "--memory-limit", str(limit))
    assert code == 1, err
    assert "memory limit" in err and str(store) in err  # (the read's refusal, not the write's)
    assert limited <= limit, (limited / MiB, limit / MiB)
    assert not out.exists()


@pytest.mark.parametrize("limit_mib", [96, 112])
def test_a_distance_by_blocks_of_a_store_stays_under_its_limit(store, tmp_path, limit_mib):
    """Read by box, the chunks zarr's threads freed stayed in their malloc arenas (a 256^3
    store: 125 MiB under 112M); fewer arenas, shared, reuse them."""
    out = tmp_path / "d.nrrd"
    code, err, peak = volwarp_peak("distance", store, "--iso", "50", "--surface", "voxel",
                                   "-o", out, "--memory-limit", f"{limit_mib}M")
    assert code in (0, 1), err
    assert peak <= limit_mib * MiB, (peak / MiB, limit_mib)
    assert out.exists() == (code == 0)


def test_a_store_that_fits_is_read_whole_in_a_run_and_by_box_when_it_does_not(store,
                                                                             monkeypatch):
    """Read by box, each block decoded its chunks again: a 256^3 warp of a store took
    2.35 s against 0.5 s for the same volume as NRRD (1.0 s whole now)."""
    from volwarp_cli import memory
    from volwarp_cli.io.lazy import open_volume_header
    from volwarp_cli.io.omezarr import LazyOmeZarr
    from volwarp_cli.runscope import run_scope

    with run_scope():
        _, whole = open_volume_header(store)
        assert isinstance(whole, np.ndarray)
        monkeypatch.setattr(memory, "_limit", lambda: (3 * whole.nbytes, "a test's limit"))
        _, lazy = open_volume_header(store)
        assert isinstance(lazy, LazyOmeZarr)
        assert np.array_equal(lazy[:, :, :], whole)
    _, outside = open_volume_header(store)  # (a library's call: by box, as before)
    assert isinstance(outside, LazyOmeZarr)
