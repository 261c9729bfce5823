"""The block-wise TIFF reader refuses and accepts what the whole reader does.

``open_volume_lazy`` (apply, distance, mesh, ...) and ``read_volume`` (info,
convert) make the same checks of a TIFF: an ImageJ hyperstack's channels or
frames, an OME-TIFF's channels or time points, pages fewer than declared. It
once skipped them: a 2-channel hyperstack was an internal error, a stack of
12 "channels" read as 12 z slices.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import tifffile

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.lazy import open_volume_lazy
from volwarp_cli.volume import Volume

RNG = np.random.default_rng(3)
STACK = RNG.integers(0, 255, (12, 17, 23)).astype(np.uint8)


def _refused(folder):
    """TIFFs the whole reader refuses, each with the words of its refusal."""
    hs = RNG.integers(0, 255, (6, 2, 17, 23)).astype(np.uint8)
    files = {
        "zc.tif": ("2 channels", lambda p: tifffile.imwrite(
            p, hs, imagej=True, metadata={"axes": "ZCYX"})),
        "tz.tif": ("3 frames", lambda p: tifffile.imwrite(
            p, hs.reshape(3, 4, 17, 23), imagej=True, metadata={"axes": "TZYX"})),
        "c.ome.tif": ("2 channels", lambda p: tifffile.imwrite(
            p, hs.transpose(1, 0, 2, 3), ome=True, metadata={"axes": "CZYX"})),
        "t.ome.tif": ("3 time points", lambda p: tifffile.imwrite(
            p, hs.reshape(3, 4, 17, 23), ome=True, metadata={"axes": "TZYX"})),
        # tifffile's shaped 4-D series without axes: 3 volumes of 4 planes, not 12 slices
        "qq.tif": ("3 entries along an unnamed axis", lambda p: tifffile.imwrite(
            p, hs.reshape(3, 4, 17, 23), photometric="minisblack")),
        # ImageJ's default axes for a 3-D array: its planes are channels, not slices
        "cyx.tif": ("12 channels", lambda p: tifffile.imwrite(p, STACK, imagej=True)),
    }
    out = {}
    for name, (what, write) in files.items():
        write(folder / name)
        out[name] = what
    # a tile of page 3 that does not decompress: refused on reading its samples
    # (its voxel size given, so that the error is the only line: a plain TIFF's is said)
    tifffile.imwrite(folder / "bad.tif", STACK, compression="zlib", tile=(16, 16),
                     metadata={"spacing": [1.0, 1.0, 1.0]})
    raw = bytearray((folder / "bad.tif").read_bytes())
    with tifffile.TiffFile(folder / "bad.tif") as tif:
        at = tif.pages[3].dataoffsets[1]
    raw[at:at + 20] = b"\xff" * 20
    (folder / "bad.tif").write_bytes(bytes(raw))
    out["bad.tif"] = "cannot read TIFF data"
    return out


@pytest.fixture(scope="module")
def refused(tmp_path_factory):
    folder = tmp_path_factory.mktemp("refused")
    return folder, _refused(folder)


def test_the_lazy_reader_refuses_what_the_whole_reader_refuses(refused):
    folder, files = refused
    for name, what in files.items():
        with pytest.raises(FormatError) as whole:
            read_volume(folder / name)
        assert str(whole.value).startswith(f"{folder / name}: ") and what in str(whole.value)
        for require_lazy in (False, True):
            with pytest.raises(FormatError) as lazy:
                np.asarray(open_volume_lazy(folder / name, require_lazy=require_lazy)[1][...])
            assert str(lazy.value) == str(whole.value), name


def test_every_command_path_says_the_whole_readers_line(refused, run):
    """info (whole), apply, distance and mesh (by blocks): one line, the same one."""
    folder, files = refused
    sitk.WriteTransform(sitk.Transform(3, sitk.sitkIdentity), str(folder / "id.tfm"))
    for name in files:
        src = folder / name
        res = run("info", src)
        assert res.code == 1, res
        line = res.stderr.strip()
        assert line.startswith(f"volwarp: error: {src}: ") and "\n" not in line, res
        for cmd in (["apply", src, "-t", folder / "id.tfm", "-o", folder / "a.nrrd"],
                    ["distance", src, "--iso", 100, "-o", folder / "d.nrrd"],
                    ["mesh", src, "--iso", 100, "-o", folder / "m.ply"]):
            res = run(*cmd)
            assert (res.code, res.stderr.strip()) == (1, line), (cmd[0], name, res)
            assert not list(folder.glob("[adm].*")), (cmd[0], name)


def _accepted(folder):
    """TIFFs the whole reader reads, of several layouts."""
    paths = []
    tifffile.imwrite(folder / "ij.tif", STACK, imagej=True, metadata={"axes": "ZYX"})
    tifffile.imwrite(folder / "plain.tif", STACK, resolution=(2.0, 4.0))
    tifffile.imwrite(folder / "z.ome.tif", STACK, ome=True, metadata={"axes": "ZYX"})
    # tifffile's shaped series of a 4-D array whose time axis has size 1: dropped
    tifffile.imwrite(folder / "shaped.tif", STACK[None], photometric="minisblack",
                     metadata={"axes": "TZYX"})
    tifffile.imwrite(folder / "tiled.tif", STACK, tile=(16, 16), compression="zlib")
    tifffile.imwrite(folder / "be.tif", STACK.astype(np.uint16) * 257, byteorder=">")
    write_volume(Volume(STACK.astype(np.float64)), folder / "f64.tif")
    paths += [folder / n for n in ("ij.tif", "plain.tif", "z.ome.tif", "shaped.tif",
                                   "tiled.tif", "be.tif", "f64.tif")]
    # ImageJ's layout of stacks over 4 GiB: one IFD, the planes back to back
    write_volume(Volume(STACK.astype(np.uint16)), folder / "s.tif")
    raw = bytearray((folder / "s.tif").read_bytes())
    first_ifd = struct.unpack_from("<I", raw, 4)[0]
    ntags = struct.unpack_from("<H", raw, first_ifd)[0]
    struct.pack_into("<I", raw, first_ifd + 2 + 12 * ntags, 0)
    (folder / "one_ifd.tif").write_bytes(bytes(raw))
    paths.append(folder / "one_ifd.tif")
    return paths


SLICES = [np.s_[:, :, :], np.s_[1:4, 2:7, 0:5], np.s_[5, :, 3:], np.s_[::2, 1, ::-3],
          np.s_[11:, 16:, 22:], np.s_[::-5]]


def test_the_lazy_reader_reads_the_samples_the_whole_reader_reads(tmp_path):
    for path in _accepted(tmp_path):
        ref = read_volume(path)
        assert ref.data.shape == STACK.shape, path.name
        _, arr = open_volume_lazy(path)
        assert tuple(arr.shape) == ref.data.shape, path.name
        # by box where the stack allows it
        kind = {"one_ifd.tif": "FileArray"}.get(path.name, "_ZarrView")
        assert type(arr).__name__ == kind, path.name
        for s in SLICES:
            np.testing.assert_array_equal(np.asarray(arr[s]), ref.data[s],
                                          err_msg=f"{path.name} {s}")


def test_a_truncated_tiff_says_one_line_on_every_command_path(tmp_path):
    """tifffile's own log lines ("<tifffile.TiffPages @8> invalid page offset ...") stay
    off stderr when the block-wise reader opens a damaged file first (a fresh process:
    in this one the tifffile logger may have been quietened by an earlier test)."""
    tifffile.imwrite(tmp_path / "z.tif", STACK, imagej=True, metadata={"axes": "ZYX"})
    raw = (tmp_path / "z.tif").read_bytes()
    sitk.WriteTransform(sitk.Transform(3, sitk.sitkIdentity), str(tmp_path / "id.tfm"))
    tree = str(Path(__file__).resolve().parents[1])  # (the package under test, not another)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [tree, *filter(None, [os.environ.get("PYTHONPATH")])])}
    for n in (len(raw) // 2, len(raw) - 300):
        (tmp_path / "cut.tif").write_bytes(raw[:n])
        lines = set()
        for args in (["info", "cut.tif"], ["apply", "cut.tif", "-t", "id.tfm", "-o", "a.nrrd"],
                     ["distance", "cut.tif", "--iso", "100", "-o", "d.nrrd"]):
            proc = subprocess.run([sys.executable, "-m", "volwarp_cli", *args], cwd=tmp_path,
                                  env=env, capture_output=True, text=True, timeout=120)
            assert proc.returncode == 1, (args, proc.stderr)
            assert len(proc.stderr.strip().splitlines()) == 1, (args, proc.stderr)
            assert proc.stderr.startswith("volwarp: error: cut.tif: TIFF is truncated")
            lines.add(proc.stderr)
        assert len(lines) == 1, lines


def test_a_damaged_tiff_read_by_box_leaves_no_file_open(refused):
    """A failed read through tifffile's zarr store left the files it had opened open,
    held by the failure's traceback until a garbage collection (whose ResourceWarning
    then failed whatever test ran next); they are closed as the failure is raised."""
    import os

    folder, _ = refused
    path = folder / "bad.tif"

    def open_on_it():
        fds = os.listdir("/proc/self/fd")
        return [fd for fd in fds if os.path.realpath(f"/proc/self/fd/{fd}") == str(path)]

    before = set(open_on_it())  # (the module's other tests share the file)
    header, samples = open_volume_lazy(path, require_lazy=True)
    with pytest.raises(FormatError, match="cannot read TIFF data"):
        np.asarray(samples[...])
    assert set(open_on_it()) <= before


def test_commands_that_fail_reading_a_damaged_tiff_by_box_leave_no_file_open(refused, run):
    """The reads of a box's other chunks go on after one failed, and one starting after the
    store was closed opened the file again: left open by apply and mesh (a ResourceWarning
    at a later collection, which failed the test that ran next in a full run)."""
    import os

    folder, _ = refused
    path = folder / "bad.tif"
    sitk.WriteTransform(sitk.Transform(3, sitk.sitkIdentity), str(folder / "id2.tfm"))

    def open_on_it():
        fds = os.listdir("/proc/self/fd")
        return {fd for fd in fds if os.path.realpath(f"/proc/self/fd/{fd}") == str(path)}

    before = open_on_it()
    for cmd in (["apply", path, "-t", folder / "id2.tfm", "-o", folder / "x.nrrd"],
                ["mesh", path, "--iso", 100, "-o", folder / "x.ply"],
                ["distance", path, "--iso", 100, "-o", folder / "x2.nrrd"]):
        for _ in range(3):  # (a race: a few times each)
            res = run(*cmd)
            assert res.code == 1 and "cannot read TIFF data" in res.stderr, res
            assert open_on_it() <= before, cmd[0]
