"""Review of the day's notes and refusals: what they refused or said wrongly.

A sweep whose templates stay in one plane was refused per segment, on 257
samples of any direction: a staircase of lines (its in-plane legs add
nothing, as a polyline's do) and a direction that nods between two samples
were refused though they sweep a volume, exit 2 where they wrote it.

A DICOM folder's hidden link to one of its slices (no copy under way: rsync
writes files) was refused as one; a folder whose only DICOM file is a copy
under way was "a folder with no DICOM files".

An apply through a B-spline that moves every point out of the input (its
bound, the reach of its coefficients, still met the input) wrote the
background everywhere without the warning its docs promise.

The batch's hash cache trusted the ctime of FUSE mounts: sshfs and rclone
report the modification time as ctime, so a scan rewritten in place on the
server with its time kept (``rsync -a --inplace``) kept its old digest.
"""

from __future__ import annotations

import os
import struct

import numpy as np
import pytest
from test_io_dicom import write_series

from volwarp_cli.io import read_volume

STAIR_LINES = """\
version: 1
grid: {spacing: 0.5, margin: 2}
fields:
  opacity: 1
trajectory:
  - line: {from: [0, 0, 0], to: [0, 0, 10]}
  - line: {from: [0, 0, 10], to: [10, 0, 10]}
  - line: {from: [10, 0, 10], to: [10, 0, 20]}
direction: [0, 0, 1]
scale: [4, 4]
"""

STAIR_POLYLINE = """\
version: 1
grid: {spacing: 0.5, margin: 2}
fields:
  opacity: 1
trajectory:
  - polyline: {points: [[0, 0, 0], [0, 0, 10], [10, 0, 10], [10, 0, 20]]}
direction: [0, 0, 1]
scale: [4, 4]
"""


def _sweep(tmp_path, run, spec, name="s"):
    (tmp_path / f"{name}.yaml").write_text(spec)
    out = tmp_path / f"{name}.nrrd"
    res = run("sweep", tmp_path / f"{name}.yaml", "-o", out)
    return res, out


def test_a_staircase_of_lines_with_in_plane_legs_sweeps_as_its_polyline(tmp_path, run):
    """The flat middle leg adds nothing; the vertical legs sweep two prisms, as the polyline."""
    res, out = _sweep(tmp_path, run, STAIR_LINES, "lines")
    assert res.code == 0, res.stderr
    ref, ref_out = _sweep(tmp_path, run, STAIR_POLYLINE, "poly")
    assert ref.code == 0, ref.stderr
    a, b = read_volume(out), read_volume(ref_out)
    assert np.count_nonzero(a.data) > 1000
    # the same swept set: the lines' grid is the polyline's less its joint's reach
    lo = np.round((np.asarray(a.origin) - np.asarray(b.origin)) / 0.5).astype(int)
    nx, ny, nz = a.shape_xyz
    part = np.asarray(b.data)[lo[2]:lo[2] + nz, lo[1]:lo[1] + ny, lo[0]:lo[0] + nx]
    assert np.count_nonzero(np.asarray(b.data)) == np.count_nonzero(part)
    np.testing.assert_array_equal(np.asarray(a.data), part)


@pytest.mark.parametrize("direction", [
    # a nod narrower than 1/256 of the path, between two of the check's samples
    "{keyframes: [[0, [0, 0, 1]], [0.5005, [0, 0, 1]], [0.502, [1, 0, 1]],"
    " [0.5035, [0, 0, 1]], [1, [0, 0, 1]]]}",
    # a wobble whose every check sample is upright
    '{expr: ["0.5 * sin(2 * pi * 128 * u)", "0", "1"]}',
])
def test_a_direction_that_turns_between_samples_sweeps(tmp_path, run, direction):
    spec = STAIR_LINES.split("trajectory:")[0] + (
        "trajectory:\n  - line: {from: [0, 0, 0], to: [100, 0, 0]}\n"
        f"direction: {direction}\nscale: [10, 10]\n")
    res, out = _sweep(tmp_path, run, spec)
    assert res.code == 0, res.stderr
    assert np.count_nonzero(read_volume(out).data) > 1000 and "warning" not in res.stderr


def test_a_sweep_whose_every_segment_is_flat_is_still_refused(tmp_path, run):
    spec = STAIR_LINES.replace("to: [0, 0, 10]}", "to: [0, 10, 0]}").replace(
        "{from: [0, 0, 10], to: [10, 0, 10]}", "{from: [0, 10, 5], to: [10, 10, 5]}").replace(
        "{from: [10, 0, 10], to: [10, 0, 20]}", "{from: [10, 10, 5], to: [20, 10, 5]}")
    res, out = _sweep(tmp_path, run, spec)
    assert res.code == 2 and "sweeps no volume" in res.stderr and "s.yaml:9: direction" \
        in res.stderr, res.stderr
    assert not out.exists()


@pytest.fixture
def stack():
    return np.random.default_rng(43).integers(-1000, 2000, size=(5, 6, 7)).astype(np.int16)


def _apple_double(path):
    """A macOS AppleDouble companion (magic 0x00051607: Finder info, resource fork)."""
    head = struct.pack(">II16sH", 0x00051607, 0x00020000, b"Mac OS X        ", 2)
    head += struct.pack(">III", 9, 50, 3760) + struct.pack(">III", 2, 3810, 286)
    path.write_bytes(head.ljust(4096, b"\0"))


def test_a_hidden_link_to_a_slice_is_skipped_as_other_hidden_files(tmp_path, stack, run):
    paths = write_series(tmp_path / "s", stack, shuffle=False)
    (tmp_path / "s" / ".current").symlink_to(paths[0].name)
    for p in paths:
        _apple_double(p.parent / f"._{p.name}")
    res = run("convert", tmp_path / "s", "-o", tmp_path / "o.nrrd")
    assert res.code == 0 and "warning" not in res.stderr, res.stderr
    np.testing.assert_array_equal(read_volume(tmp_path / "o.nrrd").data, stack)


def test_a_folder_whose_only_slice_is_being_copied_says_so(tmp_path, stack, run):
    first = write_series(tmp_path / "s", stack[:1])[0]
    first.rename(first.parent / f".{first.name}.Gx81kQ")
    res = run("convert", tmp_path / "s", "-o", tmp_path / "o.nrrd")
    assert res.code == 1 and "a copy under way" in res.stderr, res.stderr
    assert not (tmp_path / "o.nrrd").exists()


def test_an_sshfs_mount_is_found_and_its_cache_not_trusted(tmp_path, monkeypatch):
    """Its mount point escaped (``\\040``), optional fields before ``-``: found by
    ``major:minor``; a file rewritten in place with its size and times kept (sshfs's
    ctime is its mtime) is hashed again, as on FAT."""
    from volwarp_cli.batch import content

    dev = os.stat(tmp_path).st_dev
    table = tmp_path / "mountinfo"
    table.write_text(
        "25 1 8:1 / / rw,relatime shared:1 - ext4 /dev/sda1 rw\n"
        f"52 25 {os.major(dev)}:{os.minor(dev)} / /mnt/pacs\\040share rw,nosuid,nodev "
        "shared:30 master:2 - fuse.sshfs user@pacs:/export\\040data rw,user_id=0\n")
    assert content.filesystem_type(dev, str(table)) == "fuse.sshfs"

    def sshfs_key(st):  # (what sshfs reports: ctime is the mtime)
        return [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_mtime_ns]

    monkeypatch.setattr(content, "stat_key", sshfs_key)
    path = tmp_path / "scan.nrrd"
    path.write_bytes(b"the scan, first export")
    old = os.stat(path)
    saved = [*sshfs_key(old), content.file_sha256(path)]
    with open(path, "r+b") as fh:
        fh.write(b"THE SCAN")
    os.utime(path, ns=(old.st_atime_ns, old.st_mtime_ns))
    assert sshfs_key(os.stat(path)) == saved[:-1]
    monkeypatch.setattr(content, "_change_time_kept", {})
    monkeypatch.setattr(content, "filesystem_type", lambda dev: "fuse.sshfs")
    assert content.FileHashes({str(path): saved}).sha256(path) == content.file_sha256(path)


def _bspline_away(path, image, moved_nodes):
    """A B-spline over ``image`` moving the points of the mesh nodes ``moved_nodes`` 5 m in x.

    All of them but the middle one: whose support's points move by its neighbours' too.
    """
    import SimpleITK as sitk

    bs = sitk.BSplineTransformInitializer(image, [4, 4, 4], 3)
    n = len(bs.GetParameters()) // 3
    cx = np.zeros((7, 7, 7))
    cx[moved_nodes] = 5000.0
    cx[3, 3, 3] = 0.0  # (one node unmoved: the coefficients' range, the bound, reaches in)
    bs.SetParameters(np.concatenate([cx.ravel(), np.zeros(2 * n)]).tolist())
    sitk.WriteTransform(bs, str(path))
    return bs


@pytest.mark.parametrize("blocks", [[], ["--chunked", "--block", "4", "--scheduler", "processes"]])
@pytest.mark.parametrize("moved, said", [((slice(None),) * 3, True),
                                         ((slice(None), slice(None), slice(3, None)), False)])
def test_a_bspline_moving_every_point_out_is_said(tmp_path, run, blocks, moved, said):
    import SimpleITK as sitk

    image = sitk.GetImageFromArray((np.arange(20 ** 3).reshape(20, 20, 20) % 97 + 1)
                                   .astype(np.float32))
    image.SetSpacing((2, 2, 2))
    image.SetOrigin((-20, -20, -20))
    sitk.WriteImage(image, str(tmp_path / "in.nrrd"))
    bs = _bspline_away(tmp_path / "bs.tfm", image, moved)
    ref = sitk.GetArrayFromImage(sitk.Resample(image, image, bs, sitk.sitkLinear, 0.0))
    assert ref.any() != said  # (SimpleITK: every voxel the background, or not)
    out = tmp_path / "o.nrrd"
    res = run("apply", tmp_path / "in.nrrd", "-t", tmp_path / "bs.tfm", "-o", out,
              "--background-value", "0", *blocks)
    assert res.code == 0, res.stderr
    assert np.count_nonzero(read_volume(out).data) == np.count_nonzero(ref)
    assert res.stderr.count("no output point maps inside") == int(said), res.stderr
