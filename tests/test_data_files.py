"""Detached data files: a header reads only beside itself, and an output's data file
never replaces an input or a file the user did not name (issue: hostile test run)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.errors import FormatError
from volwarp_cli.io import read_volume

DATA = (np.arange(4 * 5 * 6, dtype=np.int16).reshape(6, 5, 4) * 3 - 50)


def _nhdr(folder, name, data_file, extra=""):
    path = folder / name
    path.write_text("NRRD0004\ntype: short\ndimension: 3\nsizes: 4 5 6\nendian: little\n"
                    f"encoding: raw\n{extra}data file: {data_file}\n")
    return path


@pytest.fixture
def outside(tmp_path):
    """A secret file outside the header's folder, and the header's folder."""
    secret = tmp_path / "secret.raw"
    secret.write_bytes(DATA.astype("<i2").tobytes())
    (tmp_path / "hdr").mkdir()
    return secret, tmp_path / "hdr"


@pytest.mark.parametrize("how", ["absolute", "dotdot", "symlink", "list", "pattern"])
def test_a_header_cannot_read_outside_its_folder(run, outside, tmp_path, monkeypatch, how):
    monkeypatch.delenv("VOLWARP_ALLOW_OUTSIDE_DATA", raising=False)
    secret, folder = outside
    if how == "absolute":
        hdr = _nhdr(folder, "h.nhdr", str(secret))
    elif how == "dotdot":
        hdr = _nhdr(folder, "h.nhdr", "../secret.raw")
    elif how == "symlink":
        os.symlink(secret, folder / "link.raw")
        hdr = _nhdr(folder, "h.nhdr", "link.raw")
    elif how == "list":
        hdr = _nhdr(folder, "h.nhdr", "LIST")
        hdr.write_text(hdr.read_text() + "../secret.raw\n")
    else:
        (tmp_path / "s1.raw").write_bytes(DATA.astype("<i2").tobytes())
        hdr = _nhdr(folder, "h.nhdr", "../s%d.raw 1 1 1")
    out = tmp_path / "copy.nrrd"
    res = run("convert", hdr, "-o", out)
    assert res.code == 1, res
    assert "outside the header's folder" in res.stderr and "--allow-outside-data" in res.stderr
    assert not out.exists()
    # said so explicitly, it is read (the option for trusted batch set-ups)
    assert run("convert", hdr, "-o", out, "--allow-outside-data").code == 0
    np.testing.assert_array_equal(read_volume(out).data, DATA)


def test_the_environment_variable_allows_it_too(outside, monkeypatch):
    secret, folder = outside
    hdr = _nhdr(folder, "h.nhdr", "../secret.raw")
    monkeypatch.delenv("VOLWARP_ALLOW_OUTSIDE_DATA", raising=False)
    with pytest.raises(FormatError, match="outside the header's folder"):
        read_volume(hdr)
    monkeypatch.setenv("VOLWARP_ALLOW_OUTSIDE_DATA", "1")
    np.testing.assert_array_equal(read_volume(hdr).data, DATA)


def test_a_metaimage_header_cannot_read_outside_its_folder(outside, monkeypatch):
    monkeypatch.delenv("VOLWARP_ALLOW_OUTSIDE_DATA", raising=False)
    secret, folder = outside
    hdr = folder / "h.mhd"
    hdr.write_text("ObjectType = Image\nNDims = 3\nDimSize = 4 5 6\nElementType = MET_SHORT\n"
                   "ElementDataFile = ../secret.raw\n")
    with pytest.raises(FormatError, match=r"h\.mhd: data file .* outside the header's folder"):
        read_volume(hdr)


def test_data_files_inside_the_folder_still_read(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "d.raw").write_bytes(DATA.astype("<i2").tobytes())
    hdr = _nhdr(tmp_path, "h.nhdr", "sub/d.raw")
    np.testing.assert_array_equal(read_volume(hdr).data, DATA)


def test_a_detached_output_never_replaces_its_raw_input(run, tmp_path):
    # the defect: `convert scan.raw ... -o scan.nhdr` wrote scan.raw over the input
    scan = tmp_path / "scan.raw"
    scan.write_bytes(DATA.astype("<i2").tobytes())
    before = scan.read_bytes()
    out = tmp_path / "scan.nhdr"
    res = run("convert", scan, "--raw-shape", 4, 5, 6, "--raw-dtype", "int16", "--dtype",
              "uint8", "-o", out)
    assert res.code == 2, res  # a usage error, found before any work (test_output_is_input)
    assert "would overwrite the input" in res.stderr and "scan.raw" in res.stderr
    assert scan.read_bytes() == before and not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.raw"]


@pytest.mark.parametrize("name,data_name", [("o.nhdr", "o.raw"), ("o.mhd", "o.raw")])
def test_a_detached_output_replaces_only_its_own_earlier_data_file(run, data_dir, tmp_path,
                                                                    name, data_name):
    src = data_dir / "ball_30_uint8.nrrd"
    stranger = tmp_path / data_name
    stranger.write_bytes(b"someone else's file")
    out = tmp_path / name
    res = run("convert", src, "-o", out)
    assert res.code == 1 and "does not replace a file -o does not name" in res.stderr, res
    assert stranger.read_bytes() == b"someone else's file" and not out.exists()
    stranger.unlink()
    assert run("convert", src, "-o", out).code == 0
    first = (tmp_path / data_name).read_bytes()
    assert run("convert", src, "-o", out).code == 0  # a rerun replaces its own pair
    assert (tmp_path / data_name).read_bytes() == first
    np.testing.assert_array_equal(read_volume(out).data, read_volume(src).data)


@pytest.mark.parametrize("name,raw,packed", [("o.nhdr", "o.raw", "o.raw.gz"),
                                             ("o.mhd", "o.raw", "o.zraw")])
def test_a_detached_output_rewritten_compressed_takes_its_old_data_file_along(
        run, data_dir, tmp_path, name, raw, packed):
    """-o o.nhdr, then with --compress: o.raw.gz replaced o.raw in the header, and o.raw
    was left behind; the next uncompressed write of o.nhdr was then refused as if o.raw
    were a stranger's (a user-day review). The earlier output's data file goes with the
    commit; another header's, or an input, stays."""
    src = data_dir / "ball_30_uint8.nrrd"
    out = tmp_path / name
    assert run("convert", src, "-o", out).code == 0
    assert run("convert", src, "-o", out, "--compress").code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name, packed])
    assert run("convert", src, "-o", out).code == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([name, raw])
    np.testing.assert_array_equal(read_volume(out).data, read_volume(src).data)
    # o.raw named by another header (o.nhdr beside o.mhd): kept, and o.mhd refused
    other = tmp_path / ("o.mhd" if name == "o.nhdr" else "o.nhdr")
    res = run("convert", src, "-o", other)
    assert res.code == 1 and "not an earlier output's" in res.stderr
    assert (tmp_path / raw).exists() and read_volume(out).data.shape == (30, 30, 30)
    # o.raw named by a header written by hand beside it (one file, two tools): kept when
    # the volwarp header is rewritten compressed (a review: it was removed)
    other.write_text(("NRRD0004\ntype: uint8\ndimension: 3\nsizes: 30 30 30\n"
                      "encoding: raw\ndata file: o.raw\n\n") if other.suffix == ".nhdr" else
                     ("ObjectType = Image\nNDims = 3\nDimSize = 30 30 30\n"
                      "ElementType = MET_UCHAR\nElementDataFile = o.raw\n"))
    assert run("convert", src, "-o", out, "--compress").code == 0
    assert (tmp_path / raw).exists() and (tmp_path / packed).exists()
    np.testing.assert_array_equal(read_volume(other).data, read_volume(src).data)


def _big_nrrd(path, n=192):
    rng = np.random.default_rng(1)
    data = rng.random((n, n, n), dtype=np.float32)
    header = (f"NRRD0004\ntype: float\ndimension: 3\nsizes: {n} {n} {n}\nendian: little\n"
              "encoding: raw\n\n").encode()
    path.write_bytes(header + data.tobytes())
    return len(header)


@pytest.mark.slow
def test_an_input_truncated_while_a_warp_maps_it_fails_cleanly(tmp_path):
    """`cp new.nrrd in.nrrd` while a warp maps in.nrrd used to kill it with SIGBUS, no
    message, its 70 MB temporary left behind. Now: one line, exit 1, nothing left."""
    import subprocess
    import sys

    volwarp = Path(sys.executable).parent / "volwarp"
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 7, oversample: 1}\nsteps:\n"
                    "  - move:\n      - {index: [3, 3, 3], by: [5.0, 0.0, 0.0]}\n")
    src, out = tmp_path / "in.nrrd", tmp_path / "out.nrrd"
    header = _big_nrrd(src)
    start = time.perf_counter()
    done = subprocess.run([str(volwarp), "warp", str(src), "--spec", str(spec), "-o", str(out)],
                          capture_output=True, text=True)
    length = time.perf_counter() - start
    assert done.returncode == 0, done.stderr
    outcomes = set()
    for delay in np.linspace(0.15, length * 0.9, 6):
        header = _big_nrrd(src)
        out.write_bytes(b"old output")
        proc = subprocess.Popen([str(volwarp), "warp", str(src), "--spec", str(spec), "-o",
                                 str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        time.sleep(float(delay))
        os.truncate(src, header + 1000)  # what `cp` does first
        _, err = proc.communicate(timeout=120)
        if proc.returncode == 0:  # it had finished before the truncation
            outcomes.add("finished")
            continue
        lines = err.strip().splitlines()
        assert proc.returncode == 1 and len(lines) == 1, (delay, proc.returncode, err)
        assert "in.nrrd" in lines[0] and ("truncated" in lines[0] or "changed" in lines[0])
        assert out.read_bytes() == b"old output"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["in.nrrd", "out.nrrd", "w.yaml"]
        outcomes.add(lines[0].split(": ", 2)[-1][:30])
    print(outcomes)
    assert len(outcomes - {"finished"}) >= 1, outcomes


@pytest.mark.parametrize("time_put_back", [False, True])
def test_an_input_rewritten_in_place_while_mapped_is_not_used(tmp_path, time_put_back):
    """The same size rewritten in place (no fault, but a mix of two files): refused at the
    output's rename; also with its modification time put back (`cp -p`), which went
    unseen."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.runscope import run_scope

    src = tmp_path / "in.nrrd"
    _big_nrrd(src, n=16)
    with run_scope():  # (this process goes on with other tests: the mapped file is this run's)
        vol = read_volume(src, mmap=True)
        first = os.stat(src)
        time.sleep(0.02)  # (past the kernel clock's tick: the change time is a later one)
        with open(src, "r+b") as fh:  # rewrite a sample in place, as `cp` onto it would
            fh.seek(-4, os.SEEK_END)
            fh.write(b"\0\0\0\0")
        shift = 0 if time_put_back else 1_000_000
        os.utime(src, ns=(first.st_atime_ns, first.st_mtime_ns + shift))
        out = tmp_path / "out.nrrd"
        with pytest.raises(FormatError,
                           match=r"in\.nrrd: the file changed while it was being read"):
            write_volume(vol, out)
        assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["in.nrrd"]


def test_a_truncation_between_the_size_check_and_the_map_is_a_file_error(tmp_path):
    """The sweep above once caught this window: numpy's "mmap length is greater than file
    size" came out as an internal error."""
    from unittest import mock

    from volwarp_cli.runscope import run_scope

    src = tmp_path / "in.nrrd"
    _big_nrrd(src, n=8)
    real = np.memmap

    def shrink_then_map(fh, **kwargs):
        os.truncate(src, 100)
        return real(fh, **kwargs)

    with run_scope(), mock.patch("volwarp_cli.io.nrrd.np.memmap", side_effect=shrink_then_map), \
            pytest.raises(FormatError, match=r"in\.nrrd: the file was truncated while"):
        read_volume(src, mmap=True)  # (the mapped file is this scope's: other tests go on)


@pytest.mark.parametrize("chunked", [True, False])
def test_an_input_rewritten_in_place_while_read_by_pread_is_not_used(run, tmp_path, monkeypatch,
                                                                     chunked):
    """An input read box by box as the work goes (by pread: apply by blocks, the streamed
    warp) and rewritten in place meanwhile, at the same size (`dd conv=notrunc`, a program
    saving over it): apply by blocks wrote a mix of the old and the new scan, exit 0.
    Refused at the output's rename, the old output kept, also when the rewrite puts the
    modification time back (`cp -p`, `touch -r`: the change time moves, and the sampled
    bytes tell), with or without a chmod. A chmod (even to the mode the file has), a hard
    link made or removed, an xattr, `touch -a` meanwhile (metadata only: each moves the
    change time) refuse nothing."""
    from volwarp_cli.io import filearray, write_volume
    from volwarp_cli.volume import Volume

    src = tmp_path / "in.nrrd"
    z, y, x = np.mgrid[:24, :24, :24]
    write_volume(Volume((x + 2 * y + 3 * z).astype(np.float32)), src)
    (tmp_path / "t.tfm").write_text(
        "#Insight Transform File V1.0\n#Transform 0\nTransform: AffineTransform_double_3_3\n"
        "Parameters: 1 0 0 0 1 0 0 0 1 0.5 0.25 0\nFixedParameters: 0 0 0\n")
    out = tmp_path / "out.nrrd"
    real = filearray.FileArray.__getitem__
    reads = []

    def touch_after_first(self, key, change):
        reads.append(key)
        if len(reads) == 1:  # (after the first box: the rest is read from the new bytes)
            change()
        return real(self, key)

    def rewrite(value=999.0):
        with open(src, "r+b") as fh:
            fh.seek(-24 * 24 * 4, os.SEEK_END)
            fh.write(np.full(24 * 24, value, np.float32).tobytes())

    def later(step):
        def change():
            time.sleep(0.02)  # (past a coarse kernel clock's tick: the change time is a later one)
            step()
        return change

    def put_time_back(step):
        def change():
            st = os.stat(src)
            later(step)()
            os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns))
            assert os.stat(src).st_mtime_ns == st.st_mtime_ns
        return change

    def link_and_unlink():
        os.link(src, tmp_path / "backup.nrrd")
        os.unlink(tmp_path / "backup.nrrd")

    def xattr():
        try:
            os.setxattr(src, "user.backup", b"done")
        except OSError:  # (a file system without user xattrs: the change time moves anyway)
            os.chmod(src, os.stat(src).st_mode)

    def rewrite_then_chmod():
        rewrite(555.0)
        os.chmod(src, 0o600)

    extra = ["--chunked", "--block", "8"] if chunked else []
    changes = [  # (each moves the change time; only those that change bytes are refused)
        (later(lambda: os.chmod(src, 0o640)), False),
        (later(lambda: os.chmod(src, os.stat(src).st_mode)), False),  # (the mode it has)
        (later(lambda: os.link(src, tmp_path / "backup.nrrd")), False),
        (later(link_and_unlink), False),
        (later(xattr), False),
        (put_time_back(lambda: os.utime(src, ns=(os.stat(src).st_atime_ns + 5,
                                                  os.stat(src).st_mtime_ns))), False),
        (rewrite, True),
        (put_time_back(lambda: rewrite(777.0)), True),
        (put_time_back(rewrite_then_chmod), True),
    ]
    for change, refused in changes:
        (tmp_path / "backup.nrrd").unlink(missing_ok=True)
        before = os.stat(src).st_ctime_ns
        reads.clear()
        monkeypatch.setattr(filearray.FileArray, "__getitem__",
                            lambda self, key, change=change: touch_after_first(self, key, change))
        out.write_bytes(b"old output")
        r = run("apply", src, "-o", out, "-t", tmp_path / "t.tfm", *extra)
        assert len(reads) > 1, "the input was not read box by box"
        assert os.stat(src).st_ctime_ns != before  # (each change moved the change time)
        if not refused:
            assert r.code == 0, (change, r.stderr)
            continue
        assert r.code == 1, (change, r.stderr)
        assert "in.nrrd: the file changed while it was being read" in r.stderr, r.stderr
        assert out.read_bytes() == b"old output"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["in.nrrd", "out.nrrd", "t.tfm"]
