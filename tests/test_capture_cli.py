"""`volwarp capture` and the .vwc capture file."""

from __future__ import annotations

import json

import numpy as np
import pytest

from volwarp_cli.bspline.capture import capture_volume
from volwarp_cli.io import read_volume
from volwarp_cli.warp.capture_file import read_capture


def test_capture_writes_checked_file_and_info_lists_lattice(run, data_dir, tmp_path):
    src = data_dir / "block_int16_aniso.nrrd"
    out = tmp_path / "s.vwc"
    res = run("capture", src, "-o", out, "--lattice", "5", "6", "7", "--oversample", "1.5",
              "--pad", "3")
    assert res.code == 0, res.stderr
    vol = read_volume(src)
    cap = read_capture(out)
    ref = capture_volume(vol, lattice=(5, 6, 7), oversample=1.5)
    assert np.array_equal(cap.domain, ref.domain)
    assert cap.grid.lattice == (5, 6, 7) and cap.pad == (3, 3, 3)
    assert cap.grid.domain_shape == tuple(g * (c - 3) for g, c in
                                          zip(cap.grid.granularity, (5, 6, 7), strict=False))
    res = run("info", out, "--json")
    assert res.code == 0, res.stderr
    d = json.loads(res.stdout)
    assert d["format"] == "vwc" and d["shape"] == [24, 16, 10] and d["dtype"] == "int16"
    assert d["lattice"] == [5, 6, 7]
    assert np.allclose(d["spacing"], vol.spacing) and np.allclose(d["origin"], vol.origin)
    assert np.allclose(d["direction"], vol.direction)
    assert d["min"] == vol.data.min() and d["max"] == vol.data.max()
    assert d["meta"] == {k: str(v) for k, v in vol.meta.items()}
    pts = np.array(d["lattice_points"])  # [i][j][k] -> world x y z
    assert pts.shape == (5, 6, 7, 3)
    # uniform lattice: point (i, j, k) sits at input index -0.5 + (I/R) * (i - 1, ...)
    for ijk in [(0, 0, 0), (2, 3, 4), (4, 5, 6)]:
        idx = [-0.5 + n / (c - 3) * (i - 1) for n, c, i in zip((24, 16, 10), (5, 6, 7), ijk, strict=False)]
        assert np.allclose(pts[ijk], vol.index_to_world(idx))
    text = run("info", out)
    assert text.code == 0 and "lattice" in text.stdout


def test_capture_is_deterministic(run, data_dir, tmp_path):
    a, b = tmp_path / "a.vwc", tmp_path / "b.vwc"
    for p in (a, b):
        assert run("capture", data_dir / "ball_30_uint8.nrrd", "-o", p).code == 0
    assert a.read_bytes() == b.read_bytes()


def test_truncated_and_foreign_capture_files(run, data_dir, tmp_path):
    good = tmp_path / "g.vwc"
    assert run("capture", data_dir / "ball_30_uint8.nrrd", "-o", good,
               "--oversample", "1").code == 0
    raw = good.read_bytes()
    trunc = tmp_path / "t.vwc"
    trunc.write_bytes(raw[:-100])
    foreign = tmp_path / "f.vwc"
    foreign.write_bytes((data_dir / "ball_30_uint8.nrrd").read_bytes())
    corrupt = tmp_path / "c.vwc"
    corrupt.write_bytes(raw[:-1] + bytes([raw[-1] ^ 0xFF]))
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nsteps: []\n")
    for path, msg in [(trunc, "truncated"), (foreign, "not a volwarp capture"),
                      (corrupt, "corrupt")]:
        res = run("warp", path, "--spec", spec, "-o", tmp_path / "o.nrrd")
        assert res.code == 1 and msg in res.stderr and str(path) in res.stderr
        res = run("info", path, "--json")  # (info checks the payload's checksum too)
        assert res.code == 1 and msg in res.stderr and not res.stdout
    assert not (tmp_path / "o.nrrd").exists()


def _rewritten(raw: bytes, edit) -> bytes:
    """A capture file with its JSON header edited by ``edit(dict)`` (the prefix's length kept
    right): what a hand edit or a damaged header gives."""
    import struct

    magic, version, n = struct.unpack("<16sII", raw[:24])
    head = json.loads(raw[24:24 + n])
    edit(head)
    text = json.dumps(head, sort_keys=True).encode()
    return struct.pack("<16sII", magic, version, len(text)) + text + raw[24 + n:]


@pytest.mark.parametrize("what", ["origin", "input shape", "oversample", "dtype",
                                  "origin, checksum deleted"])
def test_an_edited_capture_header_is_refused(run, data_dir, tmp_path, what):
    """Only the payload was checksummed: an origin 1 mm off, an input shape halved, an
    oversample or type changed were read and warped wrong (exit 0). A version 3 file needs
    its checksum: an edit that deleted it too was read as a file from before it."""
    good = tmp_path / "g.vwc"
    assert run("capture", data_dir / "ball_30_uint8.nrrd", "-o", good,
               "--oversample", "1").code == 0

    def edit(head):
        inp, cap = head["input"], head["capture"]
        if what.startswith("origin"):
            inp["origin"][1] += 1.0
            if what.endswith("deleted"):
                head.pop("header_crc32")
        elif what == "input shape":
            inp["shape"][0] //= 2
        elif what == "oversample":
            cap["oversample"] = 2.0
        else:
            inp["dtype"] = "int16"

    bad = tmp_path / "b.vwc"
    bad.write_bytes(_rewritten(good.read_bytes(), edit))
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nsteps: []\n")
    said = "header checksum is missing" if what.endswith("deleted") else \
        "header checksum mismatch"
    res = run("warp", bad, "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 1 and said in res.stderr, res.stderr
    res = run("info", bad, "--json")
    assert res.code == 1 and said in res.stderr
    assert not (tmp_path / "o.nrrd").exists()


def test_a_capture_file_from_before_the_header_checksum_is_read_as_before(run, data_dir,
                                                                          tmp_path):
    good = tmp_path / "g.vwc"
    assert run("capture", data_dir / "ball_30_uint8.nrrd", "-o", good,
               "--oversample", "1").code == 0
    import struct

    def version_2(head):  # (a version 2 file from before the checksum and the border)
        head.pop("header_crc32")
        head["input"].pop("border")
        head["version"] = 2

    raw = _rewritten(good.read_bytes(), version_2)
    old = tmp_path / "old.vwc"
    old.write_bytes(raw[:16] + struct.pack("<I", 2) + raw[20:])
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nsteps: []\n")
    for src, out in ((good, "a.nrrd"), (old, "b.nrrd")):
        res = run("warp", src, "--spec", spec, "-o", tmp_path / out)
        assert res.code == 0, res.stderr
    assert np.array_equal(read_volume(tmp_path / "a.nrrd").data,
                          read_volume(tmp_path / "b.nrrd").data)


@pytest.mark.parametrize("placement, oversample", [("tripled", "2"), ("uniform", "1.7"),
                                                    ("uniform", "2")])
def test_a_capture_file_warps_with_the_inputs_own_background(run, data_dir, tmp_path,
                                                               placement, oversample):
    """On a spanning grid (tripled, or a non-integer oversample) the capture file's default
    background was the median of the domain's interpolated faces, not the input's: a CT's
    warp through its capture file differed from the direct warp in 295 of 3840 voxels
    (background -1790 against -2027). The file now records the input's border value; a
    file without it (before 0.1.8) takes it from the domain as before."""
    src = data_dir / "block_int16_aniso.nrrd"
    cap = tmp_path / "c.vwc"
    assert run("capture", src, "-o", cap, "--lattice", "6", "--placement", placement,
               "--oversample", oversample, "--sampling", "nearest").code == 0
    spec = tmp_path / "w.yaml"
    spec.write_text(f"version: 1\nunits: voxel\ncapture: {{lattice: 6, placement: {placement}, "
                    f"oversample: {oversample}, sampling: nearest}}\nsteps:\n  - move:\n"
                    "      - {index: [3, 3, 3], by: [1.5, -2.0, 0.7]}\n")
    direct = run("warp", src, "--spec", spec, "-o", tmp_path / "direct.nrrd", "-v")
    through = run("warp", cap, "--spec", spec, "-o", tmp_path / "through.nrrd", "-v")
    assert direct.code == through.code == 0, (direct.stderr, through.stderr)
    said = [line for line in direct.stderr.splitlines() if "background:" in line]
    assert said and said[0] in through.stderr, (said, through.stderr)
    a, b = read_volume(tmp_path / "direct.nrrd"), read_volume(tmp_path / "through.nrrd")
    assert a.data.dtype == b.data.dtype and np.array_equal(a.data, b.data)  # (the provenance
    for key in ("spacing", "origin", "direction"):                        # names differ)
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    from volwarp_cli.border import border_value
    from volwarp_cli.warp.capture_file import HEADER_CRC, _header_crc

    recorded = {}
    _rewritten(cap.read_bytes(), lambda head: recorded.update(head["input"]))
    assert recorded["border"] == border_value(read_volume(src).data) == -2027

    def before_0_1_8(head):  # (no border recorded; its checksum as that volwarp wrote it)
        head["input"].pop("border")
        head[HEADER_CRC] = _header_crc(head)

    old = tmp_path / "old.vwc"
    old.write_bytes(_rewritten(cap.read_bytes(), before_0_1_8))
    res = run("warp", old, "--spec", spec, "-o", tmp_path / "old.nrrd", "-v")
    assert res.code == 0, res.stderr
    if placement == "tripled":  # (from the domain's faces, as then: what the key mends)
        assert "background: -1790" in res.stderr, res.stderr


@pytest.mark.parametrize("args, msg", [
    (["--lattice", "3"], "at least 4"),
    (["--lattice", "5", "5"], "one size or three"),
    (["--placement", "tripled", "--lattice", "5"], "at least 6"),
    (["--oversample", "0"], "oversample"),
])
def test_bad_capture_options_exit_2(run, data_dir, tmp_path, args, msg):
    out = tmp_path / "s.vwc"
    res = run("capture", data_dir / "ball_30_uint8.nrrd", "-o", out, *args)
    assert res.code == 2 and msg in res.stderr
    assert not out.exists()


def test_capture_missing_input_exit_1(run, tmp_path):
    res = run("capture", tmp_path / "nope.nrrd", "-o", tmp_path / "s.vwc")
    assert res.code == 1 and "nope.nrrd" in res.stderr


def test_capture_refuses_non_finite_samples(run, tmp_path):
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    data = np.ones((6, 7, 8), np.float32)
    data[2, 3, 4] = np.nan
    src = tmp_path / "nan.nrrd"
    write_volume(Volume(data), src)
    res = run("capture", src, "-o", tmp_path / "s.vwc")
    assert res.code == 1 and "NaN" in res.stderr and str(src) in res.stderr
    assert not (tmp_path / "s.vwc").exists()


@pytest.mark.parametrize("field, value, what", [
    (("input", "shape"), [30, -1, 30], "input shape"),
    (("input", "dtype"), "complex64", "input dtype"),
    (("input", "min"), float("nan"), "input range"),
    (("capture", "placement"), "weird", "placement"),
    (("capture", "domain_shape"), [31, 30, 30], "domain shape does not match"),
    (("capture", "granularity"), [1.5, 2, 2], "granularity"),
    (("capture", "subdivision"), 7, "subdivision"),  # 7 x 30 voxels do not fit in 30
    (("capture", "subdivision"), None, "subdivision"),
])
def test_damaged_header_fields_are_the_capture_files_fault(run, data_dir, tmp_path, field,
                                                           value, what):
    """The JSON header carries no checksum: each field is checked on load, so a damaged
    one is reported as the capture file's (exit 1, naming it) by warp and info alike,
    not blamed on the spec or the output, nor used."""
    import struct

    good = tmp_path / "g.vwc"
    assert run("capture", data_dir / "ball_30_uint8.nrrd", "-o", good,
               "--oversample", "1").code == 0
    raw = good.read_bytes()
    magic, version, n = struct.unpack("<16sII", raw[:24])
    head = json.loads(raw[24:24 + n])
    head[field[0]][field[1]] = value
    text = json.dumps(head, sort_keys=True).encode()
    bad = tmp_path / "b.vwc"
    bad.write_bytes(struct.pack("<16sII", magic, version, len(text)) + text + raw[24 + n:])
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nsteps: []\n")
    for args in (("warp", bad, "--spec", spec, "-o", tmp_path / "o.nrrd"),
                 ("info", bad, "--json")):
        res = run(*args)
        assert res.code == 1, res.stderr
        assert "header is malformed" in res.stderr and what in res.stderr
        assert str(bad) in res.stderr
    assert not (tmp_path / "o.nrrd").exists()


def test_version_1_capture_files_keep_their_spanning_grid(run, data_dir, tmp_path):
    """Version 2 files record the grid's subdivision (an integer oversample's exact
    subdivision of the input voxels); a version 1 file, from before, has none: it is
    read with the spanning grid it was captured on and warps as before."""
    import struct

    from volwarp_cli.warp.capture_file import VERSION

    src = data_dir / "ball_30_uint8.nrrd"
    new = tmp_path / "new.vwc"
    assert run("capture", src, "-o", new, "--lattice", "7", "--oversample", "1.5",
               "--values", "intensity").code == 0
    raw = new.read_bytes()
    magic, version, n = struct.unpack("<16sII", raw[:24])
    assert version == VERSION == 3
    head = json.loads(raw[24:24 + n])
    assert head["capture"]["subdivision"] == 0  # a non-integer oversample: spanning
    del head["capture"]["subdivision"]
    del head["header_crc32"]  # (version 1 files had neither)
    head["version"] = 1
    text = json.dumps(head, sort_keys=True).encode()
    old = tmp_path / "old.vwc"
    old.write_bytes(struct.pack("<16sII", magic, 1, len(text)) + text + raw[24 + n:])
    a, b = read_capture(new), read_capture(old)
    assert a.grid == b.grid and b.grid.subdivision == 0
    assert np.array_equal(a.domain, b.domain)
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\nsteps:\n  - move:\n"
                    "      - {index: [3, 3, 3], by: [1.5, 0, -1]}\n")
    outs = []
    for path in (new, old):
        out = tmp_path / f"{path.stem}.nrrd"
        assert run("warp", path, "--spec", spec, "-o", out).code == 0
        outs.append(read_volume(out).data)
    assert np.array_equal(outs[0], outs[1])
    d = json.loads(run("info", old, "--json").stdout)
    assert d["version"] == 1 and d["domain_shape"] == list(b.grid.domain_shape)
    bad = tmp_path / "future.vwc"
    bad.write_bytes(struct.pack("<16sII", magic, 4, n) + raw[24:])
    res = run("info", bad, "--json")
    assert res.code == 1 and "version 4 is not supported" in res.stderr


@pytest.mark.parametrize("space,refused", [("right-anterior-superior", True), ("LAS", True),
                                           ("left-posterior-superior", False),
                                           ("scanner-xyz", False), (None, False)])
def test_version_1_capture_files_from_a_ras_input_are_refused(run, data_dir, tmp_path, space,
                                                              refused):
    """Before the LPS world frame a capture of a RAS NRRD kept the RAS numbers (and its
    measurement frame): `info` printed them unconverted while `warp` converted the
    geometry only. Such files are refused, by both, naming the remedy."""
    import struct

    src = data_dir / "ball_30_uint8.nrrd"
    new = tmp_path / "new.vwc"
    assert run("capture", src, "-o", new, "--lattice", "7", "--oversample", "1.5",
               "--values", "intensity").code == 0
    raw = new.read_bytes()
    magic, _, n = struct.unpack("<16sII", raw[:24])
    head = json.loads(raw[24:24 + n])
    del head["capture"]["subdivision"]
    del head["header_crc32"]  # (version 1 files had neither)
    head["version"] = 1
    head["input"]["space"] = space
    text = json.dumps(head, sort_keys=True).encode()
    old = tmp_path / "old.vwc"
    old.write_bytes(struct.pack("<16sII", magic, 1, len(text)) + text + raw[24 + n:])
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\nsteps: []\n")
    for args in (["info", old, "--json"], ["warp", old, "--spec", spec, "-o", tmp_path / "o.nrrd"]):
        res = run(*args)
        if refused:
            assert res.code == 1 and "capture the input again" in res.stderr, res
        else:
            assert res.code == 0, res
    if not refused:
        d = json.loads(run("info", old, "--json").stdout)
        assert d["space"] == (None if space is None else "left-posterior-superior")


def test_info_says_where_the_control_points_lie(run, tmp_path):
    """info SCENE.vwc: the index convention, the corners, each index step as a world
    vector (the coronal head's j runs up the head, world +z) and which indices lie inside
    the volume; the figures agree with --json's lattice_points."""
    from pathlib import Path

    src = Path(__file__).parent / "data" / "mri_t1_head_coronal_2x2x3mm.nrrd"
    vwc = tmp_path / "h.vwc"
    assert run("capture", src, "-o", vwc, "--lattice", 9, "--oversample", 1).code == 0
    text = run("info", vwc).stdout
    pts = np.array(json.loads(run("info", vwc, "--json").stdout)["lattice_points"])
    assert "along the input's voxel axes x y z" in text
    step_j = pts[0, 1, 0] - pts[0, 0, 0]
    assert np.allclose(step_j, [0, 0, 44])  # j +1 is 44 mm up the head
    assert "j +1 = world 0 0 44 mm" in text
    assert f"[8, 8, 8]: world {' '.join(f'{v:g}' for v in pts[8, 8, 8])} mm" in text
    assert "lattice inside: [2..6, 2..6, 2..6]" in text


def test_a_captures_values_choice_travels_in_the_file(run, tmp_path):
    """capture --values labels was accepted and dropped: the file was the one captured
    without it, and the warp's rule took a mask with three one-voxel ids for intensities
    and blended them (0 1 2 3 4 6 out of 0 1 5 7 9; a review). The choice is now recorded
    (key volwarp_values) and the warp takes it; its own --values still overrides."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    z, y, x = np.mgrid[:24, :24, :24]
    mask = ((x - 12) ** 2 + (y - 12) ** 2 + (z - 12) ** 2 < 40).astype(np.uint8)
    mask[3, 3, 3], mask[20, 4, 5], mask[5, 19, 18] = 5, 7, 9
    src = tmp_path / "m.nrrd"
    write_volume(Volume(mask), src)
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 7}\nsteps:\n  - move:\n"
                    "      - {index: [3, 3, 3], by: [1.3, 0.7, 0.0]}\n")
    vwc = tmp_path / "m.vwc"
    assert run("capture", src, "-o", vwc, "--lattice", "7", "--values", "labels").code == 0
    res = run("warp", vwc, "--spec", spec, "-o", tmp_path / "o.nrrd", "--json")
    assert res.code == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["values"] == "labels" and "recorded" in summary["values_why"]
    assert set(np.unique(read_volume(tmp_path / "o.nrrd").data)) == {0, 1, 5, 7, 9}
    res = run("warp", vwc, "--spec", spec, "-o", tmp_path / "i.nrrd", "--values", "intensity",
              "--json")
    assert res.code == 0 and json.loads(res.stdout)["values"] == "intensity"
    plain = tmp_path / "p.vwc"
    assert run("capture", src, "-o", plain, "--lattice", "7").code == 0
    res = run("warp", plain, "--spec", spec, "-o", tmp_path / "q.nrrd", "--json")
    assert res.code == 0 and json.loads(res.stdout)["values"] == "intensity"
    assert "taken for intensities" in res.stderr  # (the ids beside the mask: said)



def test_the_payload_checksum_pass_holds_no_large_read(tmp_path):
    """The checksum pass read the payload 64 MiB at a time, which no budget charged: a warp
    of a 256^3 capture peaked at 98 MiB under --memory-limit 64M (a hunt). ``info`` of a
    32 MiB payload now peaks as that of a tiny one does (it was 31 MiB higher)."""
    import subprocess
    import sys

    from peaks import volwarp_peak

    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    rng = np.random.default_rng(0)
    peaks = []
    for n in (16, 200):
        write_volume(Volume(rng.random((n, n, n), dtype=np.float32)), tmp_path / f"v{n}.nrrd")
        cap = tmp_path / f"c{n}.vwc"
        done = subprocess.run([sys.executable, "-m", "volwarp_cli", "capture",
                               str(tmp_path / f"v{n}.nrrd"), "--oversample", "1", "-o",
                               str(cap)], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        code, err, peak = volwarp_peak("info", cap)
        assert code == 0, err
        peaks.append(peak)
    assert cap.stat().st_size > 32 << 20
    assert peaks[1] - peaks[0] < 8 << 20, peaks
