"""Paths that are legal but read back as something else: odd output names, inputs that are pipes.

A detached header (``.nhdr``, ``.mhd``) writes its data file's name on one
header line, where readers strip the spaces around it and read ``LIST``, a
``%`` pattern or a line break as something else: ``-o ' x.nhdr'`` exited 0
and its header named an unrelated ``x.raw``. And an input that is a named
pipe was opened twice: the first open drained it, the second waited forever
(a cron job that never ended). Both are refused before any work; a spec,
read once, may still be a pipe.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import ball

from volwarp_cli.errors import BadUsage
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.metaimage import write_metaimage
from volwarp_cli.io.nrrd import write_nrrd
from volwarp_cli.volume import Volume

#: output names whose data file a header cannot name, and why (in the message)
BAD_NAMES = {
    " x.nhdr": "strip the spaces",
    "LIST x.nhdr": "list of files",
    "x%d 0 0 1 2.nhdr": "numbered pattern",
    "n\nl.nhdr": "line break",
    " x.mhd": "strip the spaces",
    "LIST.mhd": "list of files",
    "n\rl.mhd": "line break",
}

WARP_SPEC = ("version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\nsteps:\n"
             "  - move:\n      - {index: [2, 2, 2], by: [1.0, 0.0, 0.0]}\n")
SWEEP_SPEC = ("version: 1\ngrid: {spacing: 0.5}\nfields:\n  opacity: {value: 0.8}\n"
              "trajectory:\n  - line: {from: [0, 0, 0], to: [6, 0, 0]}\nup: [0, 0, 1]\n"
              "scale: [2, 2]\n")


def _damaged_input(folder: Path) -> Path:
    """A NRRD whose samples are cut short: a command that read them would fail (exit 1)."""
    path = folder / "in.nrrd"
    write_volume(Volume(ball(12)), path)
    path.write_bytes(path.read_bytes()[:-100])
    return path


def _one_line(res, code: int, *needles: str) -> str:
    assert res.code == code, (res.code, res.stderr)
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("volwarp: error: "), res.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.mark.parametrize("name", list(BAD_NAMES))
def test_a_header_that_cannot_name_its_data_file_is_refused_before_any_work(run, tmp_path,
                                                                             name):
    src = _damaged_input(tmp_path)
    out = tmp_path / name
    out.write_bytes(b"an earlier output")  # (left as it is)
    data = out.with_suffix(".raw")
    res = run("convert", src, "-o", out)
    line = _one_line(res, 2, f"-o {str(out)!r}", f"cannot be named {data.name!r}",
                     BAD_NAMES[name], "choose another name")
    clean = name.replace("\n", "_").replace("\r", "_").replace("%", "_").strip()
    clean = "_" + clean if clean.startswith("LIST") else clean
    assert repr(clean) in line  # (a name that works)
    assert out.read_bytes() == b"an earlier output"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["in.nrrd", name])


def test_the_writers_refuse_such_a_name_too_and_keep_every_other(tmp_path):
    """The library's writers check as the commands do; a space inside a name is a name."""
    vol = Volume(ball(8))
    for write, name in ((write_nrrd, " x.nhdr"), (write_metaimage, "a%d.mhd")):
        with pytest.raises(BadUsage, match="cannot be named"):
            write(vol, tmp_path / name)
    assert list(tmp_path.iterdir()) == []
    for name in ("a b.nhdr", "x LIST.nhdr", "c d.mhd"):
        write_volume(vol, tmp_path / name)
        assert np.array_equal(read_volume(tmp_path / name).data, vol.data)


@pytest.mark.parametrize("command", ["warp", "warp-frames", "distance", "morph", "sweep",
                                     "batch"])
def test_every_command_writing_a_header_refuses_such_a_name(run, tmp_path, command):
    """Each output a command names (-o, patterns of frames and fields, a batch step's) is
    checked before any work (the input's samples are damaged: read, they would fail)."""
    src = _damaged_input(tmp_path)
    (tmp_path / "w.yaml").write_text(WARP_SPEC)
    (tmp_path / "s.yaml").write_text(SWEEP_SPEC)
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {list: [in.nrrd]}\noutput_dir: out\nsteps:\n"
        "  - {name: c, run: convert, output: ' {stem}.nhdr'}\n")
    args = {"warp": ["warp", src, "--spec", tmp_path / "w.yaml", "-o", tmp_path / " o.nhdr"],
            "warp-frames": ["warp", src, "--spec", tmp_path / "w.yaml", "--frames-to",
                            tmp_path / "f%{frame}.nhdr"],
            "distance": ["distance", src, "-o", tmp_path / "LIST.nhdr"],
            "morph": ["morph", src, src, "--frames", "2", "--iso", "0.5", "-o",
                      tmp_path / " m_{i}.nhdr"],
            "sweep": ["sweep", tmp_path / "s.yaml", "-o", tmp_path / " s_{field}.nhdr"],
            "batch": ["batch", tmp_path / "m.yaml"]}[command]
    before = sorted(p.name for p in tmp_path.iterdir())
    _one_line(run(*args), 2, "its data file cannot be named")
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_a_batch_refuses_a_scan_whose_name_its_header_cannot_hold_before_any_scan(run,
                                                                                  tmp_path):
    """Only the first scan is dry-run: the others' names are checked with the outputs."""
    (tmp_path / "scans").mkdir()
    for name in ("a.nrrd", "b%.nrrd"):
        write_volume(Volume(ball(8)), tmp_path / "scans" / name)
    (tmp_path / "m.yaml").write_text(
        "version: 1\ninputs: {glob: 'scans/*.nrrd'}\noutput_dir: out\nsteps:\n"
        "  - {name: c, run: convert, output: '{stem}_c.nhdr'}\n")
    _one_line(run("batch", tmp_path / "m.yaml"), 2, "scan b%:", "'b%_c.raw'", "numbered pattern")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*_c.*"))


# -- inputs that are pipes -----------------------------------------------------------

def _feed(fifo: Path, data: bytes) -> threading.Thread:
    """A writer of ``data`` into the named pipe ``fifo``, as ``cat scan > fifo &`` is."""
    def write():
        try:
            with open(fifo, "wb") as fh:
                fh.write(data)
        except OSError:  # (the reader went away: a broken pipe)
            pass

    thread = threading.Thread(target=write, daemon=True)
    thread.start()
    return thread


def _release(fifo: Path, writer: threading.Thread) -> None:
    """End a writer still waiting for a reader (volwarp never opened the pipe)."""
    if writer.is_alive():
        fd = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)
        writer.join(5)
        os.close(fd)
    writer.join(5)
    assert not writer.is_alive()


def _volwarp(*args, stdin: bytes = b"") -> subprocess.CompletedProcess:
    """The command line in a process of its own, which may not hang (killed after 20 s)."""
    return subprocess.run([sys.executable, "-m", "volwarp_cli", *map(str, args)],
                          input=stdin, capture_output=True, timeout=20)


@pytest.mark.parametrize("case", ["info", "convert", "nifti", "transform"])
def test_an_input_that_is_a_named_pipe_is_refused_at_once(tmp_path, case):
    src = tmp_path / "ball.nrrd"
    write_volume(Volume(ball(12)), src)
    tfm = (b"#Insight Transform File V1.0\n#Transform 0\nTransform: "
           b"AffineTransform_double_3_3\nParameters: 1 0 0 0 1 0 0 0 1 1 2 3\n"
           b"FixedParameters: 0 0 0\n")
    name, data = {"info": ("p.nrrd", src.read_bytes()), "convert": ("p.nrrd", src.read_bytes()),
                  "nifti": ("p.nii.gz", src.read_bytes()), "transform": ("p.tfm", tfm)}[case]
    fifo = tmp_path / name
    os.mkfifo(fifo)
    out = tmp_path / "o.nrrd"
    args = {"info": ["info", fifo], "convert": ["convert", fifo, "-o", out],
            "nifti": ["convert", fifo, "-o", out],
            "transform": ["apply", src, "-t", fifo, "-o", out]}[case]
    writer = _feed(fifo, data)
    try:
        start = time.monotonic()
        res = _volwarp(*args)
        took = time.monotonic() - start
    finally:
        _release(fifo, writer)
    assert res.returncode == 1, res.stderr
    lines = res.stderr.decode().strip().splitlines()
    assert lines == [lines[0]] and lines[0].startswith(f"volwarp: error: {fifo}: is a named "
                                                       "pipe (FIFO), not a regular file")
    assert "write the stream to a file first" in lines[0]
    assert took < 10 and not out.exists()


def test_a_character_device_input_is_refused(run, tmp_path):
    (tmp_path / "z.nrrd").symlink_to("/dev/zero")
    _one_line(run("info", tmp_path / "z.nrrd"), 1, "is a character device, not a regular file")


@pytest.mark.parametrize("how", ["fifo", "stdin"])
def test_a_spec_from_a_pipe_is_still_read(tmp_path, how):
    """A spec is read once: ``--spec /dev/stdin``, ``<(...)`` or a named pipe still work,
    and give what the spec's file gives."""
    src = tmp_path / "in.nrrd"
    write_volume(Volume(np.random.default_rng(0).random((12, 12, 12), dtype=np.float32)), src)
    (tmp_path / "w.yaml").write_text(WARP_SPEC)
    assert _volwarp("warp", src, "--spec", tmp_path / "w.yaml", "-o", tmp_path / "f.nrrd",
                    "-q").returncode == 0
    if how == "fifo":
        fifo = tmp_path / "spec.yaml"
        os.mkfifo(fifo)
        writer = _feed(fifo, WARP_SPEC.encode())
        try:
            res = _volwarp("warp", src, "--spec", fifo, "-o", tmp_path / "p.nrrd", "-q")
        finally:
            _release(fifo, writer)
    else:
        res = _volwarp("warp", src, "--spec", "/dev/stdin", "-o", tmp_path / "p.nrrd", "-q",
                       stdin=WARP_SPEC.encode())
    assert res.returncode == 0, res.stderr
    assert np.array_equal(read_volume(tmp_path / "p.nrrd").data,
                          read_volume(tmp_path / "f.nrrd").data)
