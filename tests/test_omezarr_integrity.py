"""OME-Zarr integrity: every chunk volwarp writes is checksummed, and pyramids of label maps
never invent labels, whatever their number of labels.

References: numcodecs/zarr decode the chunks (a zstd frame checksum that fails is their error);
ngff-zarr and ome-zarr-py read the stores; ``label_map_hint`` (labelmap.py) is the rule
``--pyramid-method auto`` keeps up to 256 labels.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.errors import FormatError
from volwarp_cli.io import omezarr, read_volume, write_volume
from volwarp_cli.io.blockwrite import grid_boxes
from volwarp_cli.labelmap import label_map_hint, looks_like_labels, looks_like_labels_by_blocks
from volwarp_cli.volume import Volume

NB = Path(os.path.dirname(__import__("nibabel").__file__)) / "tests" / "data"
RNG = np.random.default_rng(343)


def chunk_files(store: Path, level: int = 0) -> list[Path]:
    return sorted(p for p in (store / str(level)).rglob("*") if p.is_file()
                  and not p.name.startswith((".z", "zarr.json")))


def flip(path: Path, at: int) -> None:
    b = bytearray(path.read_bytes())
    b[at] ^= 0x10
    path.write_bytes(bytes(b))


def blocks_label_map(n: int = 40, per_axis: int = 7, step: int = 10, seed: int = 1):
    """A [z, y, x] map of per_axis**3 random-sized blocks, labels step, 2*step, ... (int16)."""
    rng = np.random.default_rng(seed)
    cuts = [np.sort(rng.choice(np.arange(1, n), per_axis - 1, replace=False)) for _ in range(3)]
    idx = [np.searchsorted(c, np.arange(n), side="right") for c in cuts]
    block = (idx[0][:, None, None] * per_axis ** 2 + idx[1][None, :, None] * per_axis
             + idx[2][None, None, :])
    perm = rng.permutation(per_axis ** 3)
    return ((perm[block] + 1) * step).astype(np.int16)


# -- chunk checksums ---------------------------------------------------------------------

def test_both_versions_write_zstd_with_its_checksum(tmp_path):
    """0.5: the codec says checksum; 0.4: every chunk's zstd frame has the checksum flag
    (the .zarray names plain zstd, which every reader accepts)."""
    import zarr

    vol = Volume(RNG.integers(0, 1000, (5, 70, 7)).astype(np.int16))
    for version in ("0.4", "0.5"):
        path = tmp_path / f"v{version}.ome.zarr"
        write_volume(vol, path, ome_zarr_version=version, pyramid=1)
        for level in ("0", "1"):
            arr = zarr.open_array(str(path / level), mode="r")
            if version == "0.5":
                assert omezarr.chunks_are_checksummed(arr)
                continue
            zarray = json.loads((path / level / ".zarray").read_text())
            assert zarray["compressor"] == {"id": "zstd", "level": 3}
            files = chunk_files(path, int(level))
            assert len(files) == (2 if level == "0" else 1)
            for f in files:
                head = f.read_bytes()[:5]
                assert head[:4] == b"\x28\xb5\x2f\xfd" and head[4] & 0x04, f


@pytest.mark.parametrize("version", ["0.4", "0.5"])
def test_one_altered_byte_of_a_chunk_is_a_one_line_error(run, tmp_path, version):
    """The tester's case: anatomical.nii to 0.4, one byte flipped, converted back: was exit 0
    with one wrong voxel (0.4 chunks had no checksum)."""
    store = tmp_path / "oz.ome.zarr"
    res = run("convert", "-q", NB / "anatomical.nii", "--ome-zarr-version", version, "-o", store)
    assert res.code == 0, res.stderr
    (victim,) = chunk_files(store)
    flip(victim, victim.stat().st_size // 2)
    back = tmp_path / "back.nrrd"
    res = run("convert", store, "-o", back)
    assert res.code == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(f"volwarp: error: {store}: chunk data is damaged")
    assert "checksum" in lines[0]
    assert not back.exists()


@pytest.mark.parametrize("version", ["0.4", "0.5"])
def test_every_altered_byte_of_a_chunk_is_detected(tmp_path, version):
    data = RNG.integers(0, 60000, (3, 4, 5)).astype(np.uint16)
    path = tmp_path / "s.ome.zarr"
    write_volume(Volume(data), path, ome_zarr_version=version)
    (victim,) = chunk_files(path)
    good = victim.read_bytes()
    for at in range(len(good)):
        flip(victim, at)
        try:
            got = read_volume(path).data
        except FormatError as exc:
            assert "chunk data is damaged" in str(exc)
        else:  # pragma: no cover - the defect: wrong samples read without an error
            assert np.array_equal(got, data), f"byte {at} altered, samples wrong, no error"
        victim.write_bytes(good)
    assert np.array_equal(read_volume(path).data, data)


def test_other_readers_read_checksummed_04_stores(tmp_path):
    import ngff_zarr
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    data = RNG.integers(0, 255, (6, 7, 8)).astype(np.uint8)
    path = tmp_path / "r.ome.zarr"
    write_volume(Volume(data, spacing=(0.5, 0.75, 2.0)), path, ome_zarr_version="0.4",
                 pyramid=1)
    ms = ngff_zarr.from_ngff_zarr(str(path))
    assert np.array_equal(np.asarray(ms.images[0].data), data)
    node = list(Reader(parse_url(str(path)))())[0]
    assert np.array_equal(np.asarray(node.data[0]), data)
    assert np.asarray(node.data[1]).shape == (3, 4, 4)


def test_a_volwarp_store_without_checksums_is_read_with_a_warning(tmp_path, caplog):
    """A 0.4 store of an older volwarp (zstd frames without checksum) cannot be verified:
    read, with one warning; stores of other writers are read without one."""
    import ngff_zarr
    from numcodecs import Zstd

    data = RNG.integers(0, 255, (6, 70, 8)).astype(np.uint8)
    old = tmp_path / "old.ome.zarr"
    write_volume(Volume(data), old, ome_zarr_version="0.4")
    for f in chunk_files(old):  # as the older volwarp wrote them
        f.write_bytes(Zstd(level=3).encode(Zstd().decode(f.read_bytes())))
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        assert np.array_equal(read_volume(old).data, data)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 1 and "carry no checksum" in warned[0] and str(old) in warned[0]
    caplog.clear()
    other = tmp_path / "other.ome.zarr"
    image = ngff_zarr.to_ngff_image(data, dims=["z", "y", "x"])
    ngff_zarr.to_ngff_zarr(str(other), ngff_zarr.to_multiscales(image), version="0.4")
    with caplog.at_level(logging.WARNING, logger="volwarp"):
        assert np.array_equal(read_volume(other).data, data)
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_chunks_are_checksummed_knows_the_codecs(tmp_path):
    import zarr
    from numcodecs import GZip, Zstd
    from zarr.codecs import ZstdCodec

    def v2(compressor):
        g = zarr.open_group(str(tmp_path / f"g{len(os.listdir(tmp_path))}"), mode="w",
                            zarr_format=2)
        return g.create_array("a", shape=(2, 2), dtype="u1", compressors=compressor)

    assert not omezarr.chunks_are_checksummed(v2(Zstd(level=3)))
    assert omezarr.chunks_are_checksummed(v2(Zstd(level=3, checksum=True)))
    assert omezarr.chunks_are_checksummed(v2(GZip()))
    g3 = zarr.open_group(str(tmp_path / "v3"), mode="w", zarr_format=3)
    assert not omezarr.chunks_are_checksummed(
        g3.create_array("a", shape=(2, 2), dtype="u1", compressors=[ZstdCodec()]))
    assert not omezarr.chunks_are_checksummed(
        g3.create_array("b", shape=(4, 4), chunks=(2, 2), shards=(4, 4), dtype="u1",
                        compressors=[ZstdCodec()]))
    assert omezarr.chunks_are_checksummed(
        g3.create_array("c", shape=(4, 4), chunks=(2, 2), shards=(4, 4), dtype="u1",
                        compressors=[ZstdCodec(checksum=True)]))


# -- pyramids of label maps --------------------------------------------------------------

def test_a_343_label_map_pyramid_invents_no_label(run, tmp_path):
    """The tester's case: 343 labels (10 ... 3430): the 256-label hint took it for an image
    and averaged it (265 invented values at level 1); auto now takes the mode, and info's
    hint, no longer capped at 256 labels, says it is a label map."""
    import nibabel as nib
    import zarr

    labels = blocks_label_map()
    assert len(np.unique(labels)) == 343 and label_map_hint(labels)["labels"] == 343
    src = tmp_path / "parc343.nii.gz"
    nib.save(nib.Nifti1Image(labels.transpose(2, 1, 0), np.eye(4)), str(src))
    given = set(np.unique(labels).tolist())
    for method, expect in (("auto", "mode"), ("mode", "mode"), ("mean", "mean")):
        out = tmp_path / f"{method}.ome.zarr"
        res = run("convert", "-q", src, "--pyramid", 2, "--pyramid-method", method, "-o", out)
        assert res.code == 0 and res.stderr == "", res.stderr
        group = zarr.open_group(str(out), mode="r")
        assert group.attrs["volwarp"]["downsampling"] == expect
        assert group.attrs["ome"]["multiscales"][0]["type"] == expect
        invented = set(np.unique(np.asarray(group["1"][...])).tolist()) - given
        if expect == "mode":
            assert not invented
            assert not set(np.unique(np.asarray(group["2"][...])).tolist()) - given
        else:
            assert invented  # what the mean does to labels: why auto must not pick it
    res = run("convert", "-q", src, "--pyramid", 1, "-o", tmp_path / "default.ome.zarr")
    assert res.code == 0
    default = zarr.open_group(str(tmp_path / "default.ome.zarr"), mode="r")
    assert default.attrs["volwarp"]["downsampling"] == "mode"


def test_pyramid_method_chooses_for_intensities_too(run, tmp_path):
    import zarr

    out = tmp_path / "a.ome.zarr"
    res = run("convert", "-q", NB / "anatomical.nii", "--pyramid", 1, "-o", out)
    assert res.code == 0
    assert zarr.open_group(str(out), mode="r").attrs["volwarp"]["downsampling"] == "mean"
    res = run("convert", "-q", NB / "anatomical.nii", "--pyramid", 1, "--pyramid-method",
              "mode", "-o", out)
    assert res.code == 0
    group = zarr.open_group(str(out), mode="r")
    assert group.attrs["volwarp"]["downsampling"] == "mode"
    level0 = np.asarray(group["0"][...])
    assert np.array_equal(np.asarray(group["1"][...]), omezarr.downsample(level0, labels=True))


def test_pyramid_method_without_pyramid_is_a_usage_error(run, tmp_path):
    for out in ("x.ome.zarr", "x.nrrd"):
        res = run("convert", "-q", NB / "anatomical.nii", "--pyramid-method", "mode",
                  "-o", tmp_path / out)
        assert res.code == 2 and "--pyramid-method mode" in res.stderr
        assert not (tmp_path / out).exists()
    res = run("convert", "-q", NB / "anatomical.nii", "--pyramid-method", "median",
              "-o", tmp_path / "y.ome.zarr")
    assert res.code == 2


def test_auto_up_to_256_values_is_the_hint():
    """auto keeps label_map_hint's answer wherever it has one (up to 256 values)."""
    rng = np.random.default_rng(7)
    cases = [
        np.kron(rng.integers(0, 9, (4, 5, 6)), np.ones((3, 3, 3), int)).astype(np.uint8),
        rng.integers(0, 200, (10, 11, 12)).astype(np.int16),  # noisy: not labels
        np.zeros((4, 4, 4), np.uint8),  # one value
        np.kron(rng.integers(-100, 100, (5, 5, 5)), np.ones((2, 2, 2), int)).astype(np.int8),
        np.kron(rng.integers(0, 256, (6, 6, 6)), np.ones((2, 2, 2), int)).astype(np.uint16),
        (rng.random((8, 9, 10)) > 0.5).astype(np.uint32),
        rng.integers(0, 3, (6, 7, 1)).astype(np.int32),  # x of size 1: no pairs
        rng.normal(0, 1, (4, 4, 4)).astype(np.float32),
    ]
    for data in cases:
        assert looks_like_labels(data) == (label_map_hint(data) is not None), data.dtype


def test_auto_above_256_values_tells_segmentations_from_scans():
    rng = np.random.default_rng(11)
    # instance segmentation: 4000 ids (uint32, a wide range: the sort path)
    ids = rng.choice(np.arange(1, 2 ** 31, 997), 4000, replace=False).astype(np.uint32)
    seg = ids[np.kron(rng.integers(0, 4000, (12, 12, 12)), np.ones((4, 4, 4), int))]
    seg[:, :8] = 0
    assert looks_like_labels(seg)
    # a CT: air clipped at -1024 HU around a noisy body (more than 256 values): the air
    # alone would pass the neighbour test; the body decides
    z, y, x = np.mgrid[:32, :96, :96]
    body = ((x - 48) ** 2 / 40 ** 2 + (y - 48) ** 2 / 25 ** 2) < 1
    ct = np.full(body.shape, -1024, np.int16)
    ct[body] = np.clip(rng.normal(40, 60, body.sum()), -1024, 3071).astype(np.int16)
    assert len(np.unique(ct)) > 256 and not looks_like_labels(ct)
    # a scan with thousands of grey levels, and one with a zero background
    assert not looks_like_labels(rng.integers(0, 4000, (20, 20, 20)).astype(np.int16))
    mr = np.where(body, rng.integers(100, 3000, body.shape), 0).astype(np.uint16)
    assert not looks_like_labels(mr)
    # write_volume's default ("auto") on the segmentation: the mode
    assert omezarr.resolve_labels("auto", seg) and not omezarr.resolve_labels("auto", ct)


@pytest.mark.parametrize("block", [(5, 7, 9), (40, 40, 40), (1, 40, 40)])
def test_auto_by_blocks_is_the_whole_arrays(block):
    rng = np.random.default_rng(5)
    z, y, x = np.mgrid[:40, :40, :40]
    body = ((x - 20) ** 2 + (y - 20) ** 2) < 300
    ct = np.full(body.shape, -1024, np.int16)
    ct[body] = rng.normal(40, 60, body.sum()).astype(np.int16)
    cases = [blocks_label_map(), ct, blocks_label_map(per_axis=5).astype(np.uint8),
             rng.integers(0, 9, (40, 40, 40)).astype(np.int32)]
    for data in cases:
        boxes = list(grid_boxes(data.shape, block))
        assert looks_like_labels_by_blocks(data, boxes) == \
            looks_like_labels(data)


def test_a_store_named_by_a_link_is_replaced_and_nothing_left_beside_it(run, tmp_path):
    """The link swapped aside was left as a hidden ``.NAME.vw-...partdir`` (exit 0): the
    removal of a tree refused a link, its error ignored. The link's target is untouched,
    and the name holds the new store, as an output file named by a link is replaced."""
    src = tmp_path / "in.nrrd"
    first = Volume(np.arange(60, dtype=np.float32).reshape(3, 4, 5))
    write_volume(first, src)
    target = tmp_path / "store.ome.zarr"
    assert run("convert", src, "-o", target).code == 0
    link = tmp_path / "cur.ome.zarr"
    link.symlink_to(target.name)
    second = tmp_path / "second.nrrd"
    write_volume(first.with_data(first.data * 2), second)
    res = run("convert", second, "-o", link)
    assert res.code == 0, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "cur.ome.zarr", "in.nrrd", "second.nrrd", "store.ome.zarr"]
    assert not link.is_symlink()
    np.testing.assert_array_equal(read_volume(link).data, first.data * 2)
    np.testing.assert_array_equal(read_volume(target).data, first.data)


def _ome_v3(store: Path, version="0.5", path="0", shards=None, data=None):
    import zarr

    g = zarr.open_group(str(store), mode="w", zarr_format=3)
    data = np.full((8, 8, 8), 3, np.uint8) if data is None else data
    kw = {"shards": shards} if shards else {}
    a = g.create_array("0", shape=data.shape, dtype=data.dtype, chunks=(4, 4, 4),
                       fill_value=5, **kw)
    a[...] = data
    axes = [{"name": n, "type": "space", "unit": "millimeter"} for n in "zyx"]
    g.attrs["ome"] = {"version": version, "multiscales": [{"axes": axes, "datasets": [
        {"path": path, "coordinateTransformations": [{"type": "scale", "scale": [1, 1, 1]}]}]}]}
    return store


def test_an_empty_shard_file_is_refused_not_read_as_its_fill_value(run, tmp_path):
    """zarr reads an empty shard as missing: volwarp's own store read as zeros, another
    program's as its fill value, exit 0."""
    src = tmp_path / "in.nrrd"
    write_volume(Volume(np.full((20, 20, 20), 7, np.uint8)), src)
    own = tmp_path / "own.ome.zarr"
    assert run("convert", src, "-o", own).code == 0
    (own / "0" / "c" / "0" / "0" / "0").write_bytes(b"")
    other = _ome_v3(tmp_path / "other.ome.zarr", shards=(8, 8, 8))
    shard = next(p for p in (other / "0").rglob("*") if p.is_file() and p.name != "zarr.json")
    shard.write_bytes(b"")
    for store in (own, other):
        res = run("info", store)
        assert res.code == 1 and "is an empty file" in res.stderr, res.stderr
        with pytest.raises(FormatError, match="is an empty file"):
            read_volume(store)


def test_an_unknown_ngff_version_and_a_path_out_of_the_store_are_refused(run, tmp_path):
    """(a later version's coordinate transformations read as 0.4's; a dataset path of
    ``../other/0`` read another store's array)"""
    res = run("info", _ome_v3(tmp_path / "v9.ome.zarr", version="0.9"))
    assert res.code == 1 and "OME-NGFF version '0.9'" in res.stderr
    _ome_v3(tmp_path / "elsewhere.ome.zarr")
    for path in ("../elsewhere.ome.zarr/0", str(tmp_path / "elsewhere.ome.zarr" / "0")):
        store = _ome_v3(tmp_path / "esc.ome.zarr", path=path)
        res = run("info", store)
        assert res.code == 1 and "leads out of the store" in res.stderr, res.stderr
    np.testing.assert_array_equal(read_volume(_ome_v3(tmp_path / "ok.ome.zarr")).data, 3)
