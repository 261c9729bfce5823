"""`volwarp info`, `volwarp convert`, the command group, and bad input handling."""

from __future__ import annotations

import gzip
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import volwarp_cli
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

VOLWARP = [sys.executable, "-m", "volwarp_cli"]


def test_help_lists_every_subcommand(run):
    """`volwarp --help` lists every subcommand of main.COMMANDS, and each one's module
    imports and gives its own --help (the group loads them lazily: listing them imports
    none). tests/test_cli_help.py checks each help's examples."""
    import importlib

    from volwarp_cli.cli.main import COMMANDS

    res = run("--help")
    assert res.code == 0
    for name in ("capture", "warp", "morph", "sweep", "distance", "mesh", "info", "convert"):
        assert f"\n  {name} " in res.stdout
    for name in COMMANDS:
        assert f"\n  {name} " in res.stdout
        command = importlib.import_module(f"volwarp_cli.cli.{name}").command
        assert command.name == name
        sub = run(name, "--help")
        assert sub.code == 0, (name, sub.stderr)
        assert "Examples:" in sub.stdout and f"volwarp {name} " in sub.stdout.rsplit(
            "Examples:", 1)[1], name


def test_version(run):
    res = run("--version")
    assert res.code == 0
    assert volwarp_cli.__version__ in res.stdout


def test_python_dash_m_entry_point():
    out = subprocess.run(VOLWARP + ["--version"], capture_output=True, text=True, check=True)
    assert volwarp_cli.__version__ in out.stdout


def test_command_line_runs_exit_quietly(data_dir, tmp_path):
    """A whole process (the path that freezes objects before exit) prints nothing
    at shutdown: no library's leak report after a render, nothing after a distance."""
    ball = data_dir / "ball_30_uint8.nrrd"
    for args in (["mesh", ball, "-o", tmp_path / "b.ply", "--render", tmp_path / "b.png",
                  "--render-size", "64x64"],
                 ["distance", ball, "-o", tmp_path / "d.nrrd", "--iso", "127"]):
        out = subprocess.run(VOLWARP + [str(a) for a in args], capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        assert out.stderr == "", out.stderr[:500]


def _closing(*fds):
    """A ``preexec_fn`` that starts the child without the standard descriptors ``fds``."""
    def close():
        for fd in fds:
            os.close(fd)
    return close


@pytest.mark.parametrize("quiet", [False, True])
def test_a_closed_stderr_loses_nothing_and_fails_nothing(data_dir, tmp_path, quiet):
    """``volwarp ... 2>&-`` (a launcher that closes descriptor 2): the command runs, exits 0
    and writes the same file as with a stderr. Python leaves ``sys.stderr`` None then: the
    command failed before it began (without -q) or after its output was renamed into
    place (with -q), exit 1 either way; and the output's temporary could have taken
    descriptor 2 (/dev/null holds it now)."""
    ball = data_dir / "ball_30_uint8.nrrd"
    args = VOLWARP + ["distance", str(ball), "--iso", "127"] + (["-q"] if quiet else []) + ["-o"]
    ref = subprocess.run(args + [str(tmp_path / "ref.nrrd")], capture_output=True)
    assert ref.returncode == 0, ref.stderr
    got = subprocess.run(args + [str(tmp_path / "got.nrrd")], stdout=subprocess.PIPE,
                         preexec_fn=_closing(2))
    assert got.returncode == 0
    assert (tmp_path / "got.nrrd").read_bytes() == (tmp_path / "ref.nrrd").read_bytes()


def test_standard_descriptors_missing_at_start_are_held_by_dev_null(tmp_path):
    """0 and 2 get /dev/null to read and write, 1 to read only: a command's product on a
    closed stdout (``info >&-``) fails as it would on the closed descriptor, with exit 1
    and its one line, instead of vanishing with exit 0."""
    probe = ("import os, sys; from volwarp_cli.entry import occupy_standard_fds; "
             "occupy_standard_fds(); sys.stderr.write('discarded'); sys.stderr.flush(); "
             "f = open(os.environ['OUT'], 'w'); "
             "print(os.readlink('/proc/self/fd/0'), os.readlink('/proc/self/fd/2'), f.fileno(), "
             "file=f)")
    out = tmp_path / "fds.txt"
    res = subprocess.run([sys.executable, "-c", probe], env={**os.environ, "OUT": str(out)},
                         preexec_fn=_closing(0, 2), stdout=subprocess.DEVNULL)
    assert res.returncode == 0
    fd0, fd2, first_free = out.read_text().split()
    assert fd0 == fd2 == os.devnull and int(first_free) > 2
    res = subprocess.run(VOLWARP + ["--version"], preexec_fn=_closing(1),
                         stderr=subprocess.PIPE, text=True)
    assert res.returncode == 1
    assert res.stderr.startswith("volwarp: error: ") and res.stderr.count("\n") == 1


def test_info_json_is_stable(run, data_dir):
    res = run("info", data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd", "--json")
    assert res.code == 0, res.stderr
    d = json.loads(res.stdout)
    assert list(d) == ["format", "shape", "dtype", "spacing", "origin", "direction", "space",
                       "file_space", "min", "max", "mean", "meta"]
    assert d["format"] == "nrrd"
    assert d["shape"] == [128, 128, 62]
    assert d["dtype"] == "int16"
    assert d["spacing"] == [2.0, 2.0, 3.0]
    assert d["origin"] == [0.0, 254.0, 0.0]
    # rows of ITK's direction matrix (columns are the axes), per the data README
    assert d["direction"] == [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    assert d["space"] == "left-posterior-superior"
    assert (d["min"], d["max"]) == (0, 255)
    assert round(d["mean"], 4) == 19.2298


def test_info_text(run, data_dir):
    res = run("info", data_dir / "block_int16_aniso.nrrd")
    assert res.code == 0
    assert "24 16 10 (x y z)" in res.stdout
    assert "description = volwarp test block" in res.stdout


def test_info_raw_with_layout(run, tmp_path):
    data = np.arange(60, dtype=np.float32).reshape(3, 4, 5)
    (tmp_path / "v.raw").write_bytes(data.astype(">f4").tobytes())
    res = run("info", tmp_path / "v.raw", "--raw-shape", 5, 4, 3, "--raw-dtype", "float32",
              "--raw-endian", "big", "--raw-spacing", 1, 2, 3, "--json")
    assert res.code == 0, res.stderr
    d = json.loads(res.stdout)
    assert d["shape"] == [5, 4, 3] and d["spacing"] == [1, 2, 3]
    assert d["max"] == 59.0


@pytest.mark.parametrize("out_name", ["o.tif", "o.nii.gz", "o.nhdr", "o.nrrd"])
def test_convert_keeps_geometry_and_samples(run, data_dir, tmp_path, out_name):
    src = data_dir / "block_int16_aniso.nrrd"
    res = run("convert", src, "-o", tmp_path / out_name)
    assert res.code == 0, res.stderr
    a, b = read_volume(src), read_volume(tmp_path / out_name)
    np.testing.assert_array_equal(a.data, b.data)
    tol = 1e-5 if "nii" in out_name else 1e-12
    np.testing.assert_allclose(b.spacing, a.spacing, atol=tol)
    np.testing.assert_allclose(b.origin, a.origin, atol=tol)
    np.testing.assert_allclose(b.direction, a.direction, atol=tol)


def test_convert_dtype_rounds_and_clips(run, tmp_path):
    data = np.array([-3.7, -0.4, 0.5, 1.5, 254.6, 300.0, 1e9, 2.49], np.float32).reshape(2, 2, 2)
    write_volume(Volume(data), tmp_path / "f.nrrd")
    res = run("convert", tmp_path / "f.nrrd", "-o", tmp_path / "u.nrrd", "--dtype", "uint8")
    assert res.code == 0, res.stderr
    out = read_volume(tmp_path / "u.nrrd").data.ravel().tolist()
    assert out == [0, 0, 0, 2, 255, 255, 255, 2]  # numpy rounds half to even


def test_convert_nan_to_integer_is_refused(run, tmp_path):
    data = np.zeros((2, 2, 2), np.float32)
    data[0, 0, 0] = np.nan
    write_volume(Volume(data), tmp_path / "n.nrrd")
    res = run("convert", tmp_path / "n.nrrd", "-o", tmp_path / "n8.nrrd", "--dtype", "uint8")
    assert res.code == 1
    assert "NaN" in res.stderr
    assert not (tmp_path / "n8.nrrd").exists()


# -- bad input: exit code, one-line message, nothing written -------------------

def _assert_clean_failure(res, code, *needles, out: Path | None = None, before: bytes | None = None):
    assert res.code == code, (res.code, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("volwarp: error: ")
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    assert "Traceback" not in res.stderr
    if out is not None:
        if before is None:
            assert not out.exists()
        else:
            assert out.read_bytes() == before
        leftovers = [p.name for p in out.parent.iterdir() if ".part" in p.name]
        assert leftovers == []


@pytest.fixture
def existing_output(tmp_path):
    out = tmp_path / "existing.nrrd"
    out.write_bytes(b"precious previous output")
    return out


def test_truncated_raw(run, tmp_path, existing_output):
    (tmp_path / "t.raw").write_bytes(b"\0" * 999)
    res = run("convert", tmp_path / "t.raw", "--raw-shape", 10, 10, 10, "--raw-dtype", "uint8",
              "-o", existing_output)
    _assert_clean_failure(res, 1, "t.raw", "999 bytes", "1000 bytes", out=existing_output,
                          before=b"precious previous output")


def test_truncated_gzip_nrrd(run, data_dir, tmp_path, existing_output):
    good = (data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd").read_bytes()
    (tmp_path / "cut.nrrd").write_bytes(good[: len(good) // 2])
    res = run("convert", tmp_path / "cut.nrrd", "-o", existing_output)
    _assert_clean_failure(res, 1, "cut.nrrd", "truncated", out=existing_output,
                          before=b"precious previous output")


def test_header_with_wrong_sizes(run, tmp_path):
    data = np.zeros((4, 4, 4), np.uint8)
    (tmp_path / "w.nrrd").write_bytes(b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 5\n"
                                      b"encoding: raw\n\n" + data.tobytes())
    res = run("convert", tmp_path / "w.nrrd", "-o", tmp_path / "o.nrrd")
    _assert_clean_failure(res, 1, "w.nrrd", "truncated", out=tmp_path / "o.nrrd")
    (tmp_path / "w2.nrrd").write_bytes(b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 3\n"
                                       b"encoding: raw\n\n" + data.tobytes())
    res = run("convert", tmp_path / "w2.nrrd", "-o", tmp_path / "o.nrrd")
    _assert_clean_failure(res, 1, "w2.nrrd", "expected 48", out=tmp_path / "o.nrrd")


def test_gzip_nrrd_with_too_much_data(run, tmp_path):
    payload = gzip.compress(np.zeros(80, np.uint8).tobytes())
    (tmp_path / "g.nrrd").write_bytes(b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 4 4 4\n"
                                      b"encoding: gzip\n\n" + payload)
    res = run("info", tmp_path / "g.nrrd")
    _assert_clean_failure(res, 1, "g.nrrd", "more than 64 bytes")


def test_unknown_encoding(run, tmp_path):
    (tmp_path / "e.nrrd").write_bytes(b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 2 2\n"
                                      b"encoding: zstd\n\n" + b"\0" * 8)
    res = run("convert", tmp_path / "e.nrrd", "-o", tmp_path / "o.nrrd")
    _assert_clean_failure(res, 1, "e.nrrd", "unknown encoding 'zstd'", out=tmp_path / "o.nrrd")


def test_huge_claimed_size_is_refused_before_allocating(run, tmp_path):
    (tmp_path / "huge.nrrd").write_bytes(b"NRRD0004\ntype: float\ndimension: 3\n"
                                         b"sizes: 100000 100000 100000\nencoding: gzip\n"
                                         b"endian: little\n\n")
    res = run("convert", tmp_path / "huge.nrrd", "-o", tmp_path / "o.nrrd")
    _assert_clean_failure(res, 1, "huge.nrrd", "needs", "memory", out=tmp_path / "o.nrrd")


def test_huge_raw_is_refused(run, tmp_path):
    (tmp_path / "h.raw").write_bytes(b"")
    res = run("info", tmp_path / "h.raw", "--raw-shape", 100000, 100000, 100000,
              "--raw-dtype", "float64")
    _assert_clean_failure(res, 1, "h.raw", "bytes")


def test_tiff_with_pages_of_different_shapes(run, tmp_path):
    import tifffile

    # plain pages (no tifffile description: with one, each page is an image of its own)
    with tifffile.TiffWriter(tmp_path / "mixed.tif") as tw:
        tw.write(np.zeros((8, 8), np.uint8), metadata=None)
        tw.write(np.zeros((8, 9), np.uint8), metadata=None)
    res = run("convert", tmp_path / "mixed.tif", "-o", tmp_path / "o.nrrd")
    _assert_clean_failure(res, 1, "mixed.tif", "page 1", out=tmp_path / "o.nrrd")


def test_missing_input(run, tmp_path):
    res = run("convert", tmp_path / "nope.nrrd", "-o", tmp_path / "o.nrrd")
    _assert_clean_failure(res, 1, "nope.nrrd", "no such file", out=tmp_path / "o.nrrd")


def test_missing_output_folder(run, data_dir, tmp_path):
    res = run("convert", data_dir / "ball_30_uint8.nrrd", "-o", tmp_path / "no" / "o.nrrd")
    _assert_clean_failure(res, 1, "does not exist")


@pytest.mark.parametrize("output", ["o.nrrd", "o.ply", "o.png"])
def test_an_output_named_by_a_fifo_is_refused_before_any_work(run, data_dir, tmp_path, output):
    """A named pipe (a user's sink) where an output goes: refused, not replaced by a file
    (the finished output is renamed onto its name), and no other output written."""
    os.mkfifo(tmp_path / output)
    ball = data_dir / "ball_30_uint8.nrrd"
    args = {"o.nrrd": ["convert", ball, "-o", tmp_path / output],
            "o.ply": ["mesh", ball, "--iso", "127", "-o", tmp_path / output],
            "o.png": ["mesh", ball, "--iso", "127", "-o", tmp_path / "m.ply", "--render",
                      tmp_path / output, "--render-size", "32x32"]}[output]
    res = run(*args)
    _assert_clean_failure(res, 1, "is a named pipe (FIFO), not a regular file")
    assert (tmp_path / output).is_fifo() and sorted(p.name for p in tmp_path.iterdir()) == [output]


def test_content_not_matching_extension(run, tmp_path):
    (tmp_path / "fake.nrrd").write_bytes(b"GIF89a......")
    res = run("info", tmp_path / "fake.nrrd")
    _assert_clean_failure(res, 1, "fake.nrrd", "not NRRD")


def test_unknown_extension_and_usage_errors(run, data_dir, tmp_path):
    res = run("convert", data_dir / "ball_30_uint8.nrrd", "-o", tmp_path / "o.xyz")
    _assert_clean_failure(res, 2, "unknown volume extension")  # usage: before any work
    res = run("convert", data_dir / "ball_30_uint8.nrrd")  # no -o
    _assert_clean_failure(res, 2, "-o")
    res = run("info", tmp_path / "x.raw", "--raw-shape", 2, 2, 2)  # no --raw-dtype
    _assert_clean_failure(res, 2, "--raw-dtype")


def test_debug_shows_traceback(tmp_path):
    out = subprocess.run(VOLWARP + ["info", str(tmp_path / "nope.nrrd"), "--debug"],
                         capture_output=True, text=True)
    assert out.returncode == 1
    assert "Traceback" in out.stderr


def test_sigterm_while_writing_leaves_nothing(tmp_path):
    """Kill `volwarp convert` mid-write: no partial output, no temporary file, old output kept."""
    rng = np.random.default_rng(0)
    big = Volume(rng.random((160, 256, 256), dtype=np.float32))  # 40 MiB of incompressible data
    write_volume(big, tmp_path / "big.nrrd")
    out = tmp_path / "out.nrrd"
    out.write_bytes(b"old output")
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(VOLWARP + ["convert", str(tmp_path / "big.nrrd"), "-o", str(out),
                                       "--compress", "--dtype", "float64"],
                            stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.time() + 60
    while time.time() < deadline:  # wait until the temporary output exists and grows
        parts = [p for p in tmp_path.iterdir() if ".part" in p.name]
        if parts and parts[0].stat().st_size > 0:
            break
        if proc.poll() is not None:
            pytest.fail("convert finished before it could be interrupted")
        time.sleep(0.01)
    else:
        pytest.fail("no temporary output appeared")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert "interrupted by SIGTERM" in err
    assert out.read_bytes() == b"old output"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.nrrd", "out.nrrd"]


def test_verbose_log_reaches_each_invocations_stderr(run, tmp_path, data_dir):
    """The log handler follows sys.stderr: a second in-process run still shows its steps."""
    path = tmp_path / "b.nrrd"
    run("convert", data_dir / "ball_30_uint8.nrrd", "-o", path)
    for _ in range(2):
        res = run("info", path, "-v")
        assert res.code == 0
        assert f"volwarp: read {path}" in res.stderr


def test_info_json_stays_strict_with_nan_and_inf_samples(run, tmp_path):
    """min/max/mean describe the finite samples; `nonfinite` counts the rest; no NaN or
    Infinity tokens (strict JSON parsers reject them)."""
    data = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    data[0, 0, 0] = np.nan
    data[1, 2, 3] = -np.inf
    path = tmp_path / "n.nrrd"
    write_volume(Volume(data), path)
    res = run("info", path, "--json")
    assert res.code == 0, res.stderr

    def strict(token):
        raise AssertionError(f"non-standard JSON token {token}")

    d = json.loads(res.stdout, parse_constant=strict)
    assert (d["min"], d["max"], d["nonfinite"]) == (1.0, 22.0, 2)
    assert d["mean"] == pytest.approx(np.arange(1, 23).mean())
    text = run("info", path)
    assert text.code == 0 and "nonfinite: 2 samples" in text.stdout


def test_bad_inputs_and_options_get_the_designed_exit_codes(run, data_dir, tmp_path):
    """A folder given as the input is a file error (1), not click's usage wording; a
    non-finite or non-positive number, a --frames-to pattern that cannot format, an
    unknown output extension, --raw-* options for a file with a header are usage
    errors (2), found before any work."""
    ball = data_dir / "ball_30_uint8.nrrd"
    spec = tmp_path / "w.yaml"
    spec.write_text("version: 1\nsteps: []\n")
    out = tmp_path / "o.nrrd"
    _assert_clean_failure(run("warp", data_dir, "--spec", spec, "-o", out), 1, "is a folder",
                          str(data_dir), out=out)
    _assert_clean_failure(run("info", tmp_path), 1, "is a folder")
    _assert_clean_failure(run("capture", ball, "-o", tmp_path / "c.vwc", "--oversample", "nan"),
                          2, "--oversample", "finite", out=tmp_path / "c.vwc")
    raw = tmp_path / "x.raw"
    raw.write_bytes(bytes(8))
    for flag, values, what in (("--raw-spacing", ("0", "1", "1"), "positive"),
                               ("--raw-spacing", ("nan", "1", "1"), "finite"),
                               ("--raw-origin", ("0", "inf", "0"), "finite")):
        res = run("info", raw, "--raw-shape", 2, 2, 2, "--raw-dtype", "uint8", flag, *values)
        _assert_clean_failure(res, 2, flag, what)
    for pattern in ("f_{frame[0]}.nrrd", "f_{frame}.xyz"):
        res = run("warp", ball, "--spec", spec, "-o", out, "--frames-to", pattern)
        _assert_clean_failure(res, 2, "--frames-to", out=out)
    res = run("warp", ball, "--spec", spec, "-o", tmp_path / "o.xyz")
    _assert_clean_failure(res, 2, "unknown volume extension", out=tmp_path / "o.xyz")
    # a file with a header describes itself: --raw-* would be parsed and ignored
    res = run("info", ball, "--raw-shape", 2, 2, 2, "--raw-dtype", "uint8")
    _assert_clean_failure(res, 2, "--raw-*", str(ball))
