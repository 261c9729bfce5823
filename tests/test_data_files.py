"""Detached data files: a header reads only beside itself, and an output's data file
never replaces an input or a file the user did not name (issue: hostile test run)."""

from __future__ import annotations

import os

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
    assert res.code == 1, res
    assert "is an input of this command" in res.stderr
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
