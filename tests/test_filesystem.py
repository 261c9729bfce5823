"""Outputs on a full disk: every write fails naming the output, exit 1, and leaves the
earlier output byte-identical and no temporary file behind.

OpenImageIO's writers report a short write only through ``has_error``/``geterror()``
(``write_image`` and ``close`` still return success), so a PNG cut at a few KiB, with
no IEND chunk, used to be renamed over a complete render with exit 0.

The full disk is a 64 KiB tmpfs mounted by the test (CI runs the tests as root); the
tests skip when mounting is not permitted.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import ball

from volwarp_cli.io import write_volume
from volwarp_cli.io.images import write_image
from volwarp_cli.volume import Volume

PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


@pytest.fixture
def small_fs(tmp_path):
    """A 64 KiB tmpfs at ``tmp_path / "full"`` (unmounted afterwards)."""
    if shutil.which("mount") is None:
        pytest.skip("no mount command")
    where = tmp_path / "full"
    where.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(where)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({proc.stderr.strip()})")
    try:
        yield where
    finally:
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def fill(folder: Path, leave: int) -> None:
    """Fill ``folder``'s file system but ``leave`` bytes (with a file named ``filler``)."""
    st = os.statvfs(folder)
    free = st.f_bavail * st.f_frsize
    if free > leave:
        (folder / "filler").write_bytes(b"\0" * (free - leave))


def old_png(folder: Path, name: str = "out.png") -> tuple[Path, bytes]:
    """A complete small PNG already in place; returns its path and bytes."""
    path = folder / name
    write_image(path, np.full((16, 16, 3), 200, np.uint8))
    data = path.read_bytes()
    assert data.endswith(PNG_END)
    return path, data


def only(folder: Path, *names: str) -> None:
    """``folder`` holds exactly ``names`` (and the filler): no temporary file remains."""
    assert sorted(p.name for p in folder.iterdir() if p.name != "filler") == sorted(names)


def assert_failed(res, output: Path) -> None:
    assert res.code == 1, res
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("volwarp: error: ")
    assert str(output) in lines[0]
    assert "internal error" not in lines[0]


@pytest.fixture
def ball_file(tmp_path):
    path = tmp_path / "ball.nrrd"
    write_volume(Volume(ball(30) * 100), path)
    return path


def test_mesh_render_on_a_full_disk_keeps_the_old_png(run, small_fs, ball_file):
    out, before = old_png(small_fs)
    res = run("mesh", ball_file, "--iso", 50, "--render", out, "--size", "800x600", "-q")
    assert_failed(res, out)
    assert out.read_bytes() == before
    only(small_fs, "out.png")


def test_mesh_render_that_fits_is_written_whole(run, small_fs, ball_file):
    out, _ = old_png(small_fs)
    res = run("mesh", ball_file, "--iso", 50, "--render", out, "--size", "60x40", "-q")
    assert res.code == 0, res
    assert out.read_bytes().endswith(PNG_END)
    only(small_fs, "out.png")


def test_sweep_render_on_a_full_disk_keeps_the_old_png(run, small_fs, tmp_path):
    spec = tmp_path / "sweep.yaml"
    spec.write_text("version: 1\ngrid: {shape: [16, 16, 16]}\nfields:\n  opacity: 1\n"
                    "trajectory:\n  - arc: {center: [0, 0, 0], radius: 6, axis: [0, 0, 1]}\n"
                    "up: [0, 0, 1]\nscale: [3, 3]\n")
    out, before = old_png(small_fs)
    fill(small_fs, 8192)
    res = run("sweep", spec, "-o", tmp_path / "sw.nrrd", "--render", out,
              "--render-size", "300x300", "-q")
    assert_failed(res, out)
    assert out.read_bytes() == before
    only(small_fs, "out.png")
    # the volume, elsewhere, was complete, but a command's outputs are one set: not put in place
    assert not (tmp_path / "sw.nrrd").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_morph_sheet_on_a_full_disk_keeps_the_old_png(run, small_fs, tmp_path, ball_file):
    out, before = old_png(small_fs, "sheet.png")
    fill(small_fs, 8192)
    res = run("morph", ball_file, ball_file, "--frames", 2, "--iso", 50,
              "-o", tmp_path / "m{i}.nrrd", "--render-to", tmp_path / "m{i}.png",
              "--size", "200x150", "--sheet", out, "-q")
    assert_failed(res, out)
    assert out.read_bytes() == before
    only(small_fs, "sheet.png")


@pytest.mark.parametrize("in_memory", [True, False])
def test_write_image_refuses_a_cut_file_even_when_the_writer_says_nothing(tmp_path,
                                                                         monkeypatch,
                                                                         in_memory):
    # a writer that "succeeds" but leaves a PNG without its IEND chunk: made in a memory
    # file (where the system has them) or in the temporary itself
    import OpenImageIO as oiio

    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.io import images

    out, before = old_png(tmp_path)
    made = []
    memory_file = images._memory_file
    monkeypatch.setattr(images, "_memory_file",
                        lambda: made.append(memory_file()) or made[-1] if in_memory else None)

    def cut_then_verify(oiio_mod, path, tmp, shape):
        raise AssertionError("not reached: the IEND check comes first")

    original_close = oiio.ImageOutput.close

    def close_and_cut(self):
        ok = original_close(self)
        for fd in made:
            os.ftruncate(fd, os.fstat(fd).st_size - 12)
        for p in tmp_path.glob(".out.png.*"):
            p.write_bytes(p.read_bytes()[:-12])
        return ok

    monkeypatch.setattr(oiio.ImageOutput, "close", close_and_cut)
    monkeypatch.setattr(images, "_verify_readback", cut_then_verify)
    with pytest.raises(VolwarpError, match="cut short"):
        write_image(out, np.zeros((40, 50, 3), np.uint8))
    assert out.read_bytes() == before
    only(tmp_path, "out.png")


@pytest.mark.parametrize("ext", ["nrrd", "nii.gz", "mha", "tif"])
def test_volume_output_on_a_full_disk_keeps_the_old_one(run, small_fs, tmp_path, ext):
    # already atomic before the image fix: this documents it for the volume writers
    src = tmp_path / "noise.nrrd"
    write_volume(Volume(np.random.default_rng(0).random((40, 40, 40), np.float32)), src)
    out = small_fs / f"old.{ext}"
    write_volume(Volume(np.zeros((4, 4, 4), np.uint8)), out)
    before = out.read_bytes()
    res = run("convert", src, "-o", out, "-q")
    assert_failed(res, out)
    assert out.read_bytes() == before
    only(small_fs, out.name)


def test_a_jpeg_over_the_file_size_limit_is_said_not_the_end_of_the_process(tmp_path, ball_file):
    """The JPEG library ends the process on a short write ("Output file write error ---
    out of disk space?", exit 1, the temporaries left): the image is made through a pipe
    (no file size limit there), and the output written by Python, whose error is said;
    a JPEG that fits under the limit is written."""
    import resource
    import sys

    out = tmp_path / "out.jpg"
    write_image(out, np.full((16, 16, 3), 90, np.uint8))
    before = out.read_bytes()

    def limit(soft, hard):
        return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))

    for soft, hard, why in ((100 * 1024, resource.RLIM_INFINITY, "File too large"),
                            (100 * 1024, 100 * 1024, "File too large")):
        res = subprocess.run([sys.executable, "-m", "volwarp_cli", "mesh", str(ball_file),
                              "--iso", "50", "-o", str(tmp_path / "m.ply"), "--render",
                              str(out), "--render-size", "1500x1500", "-q"],
                             capture_output=True, text=True, preexec_fn=limit(soft, hard))
        assert res.returncode == 1, res.stderr
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("volwarp: error: "), res.stderr
        assert str(out) in lines[0] and why in lines[0]
        assert out.read_bytes() == before
        only(tmp_path, "ball.nrrd", "out.jpg")
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "mesh", str(ball_file), "--iso",
                          "50", "--render", str(out), "--render-size", "400x300", "-q"],
                         capture_output=True, text=True, preexec_fn=limit(300 * 1024, 300 * 1024))
    assert res.returncode == 0, res.stderr
    assert out.read_bytes() != before and out.read_bytes()[:2] == b"\xff\xd8"


def test_a_render_named_in_no_utf8_is_written(tmp_path, ball_file):
    """OpenImageIO takes only str names: a render named ``r\xff.png`` was an internal
    error. It now makes the image in memory and never sees the name."""
    import sys

    name = os.fsdecode(b"r\xff.png")
    runs = {}
    for out in (tmp_path / name, tmp_path / "plain.png"):
        res = subprocess.run([sys.executable, "-m", "volwarp_cli", "mesh", str(ball_file),
                              "--iso", "50", "-o", str(tmp_path / "m.ply"), "--render",
                              str(out), "-q"], capture_output=True, text=True)
        assert res.returncode == 0, res.stderr
        runs[out.name] = out.read_bytes()
    assert runs[name] == runs["plain.png"]
    assert runs[name].endswith(PNG_END)


def test_long_output_names_are_written_or_refused_before_the_work(run, tmp_path, ball_file):
    """A legal name of 220-255 bytes failed after the work (its temporary's name, 40 bytes
    longer, too long to make; the error named the temporary); a name over 255 bytes too."""
    from volwarp_cli.io import atomic

    for n in (222, 250):
        out = tmp_path / ("d" * (n - 5) + ".nrrd")
        res = run("distance", ball_file, "--iso", "50", "-o", out)
        assert res.code == 0, res.stderr
        assert out.exists()
        store = tmp_path / ("z" * (n - 9) + ".ome.zarr")
        assert run("convert", ball_file, "-o", store).code == 0
        assert store.is_dir()
    names = sorted(p.name for p in tmp_path.iterdir())
    assert not [m for m in names if ".vw-" in m]
    # a dead process's temporary of a long name is cleaned by the next write, as a short one's
    out = tmp_path / ("d" * 245 + ".nrrd")
    stale = tmp_path / f".{atomic._temporary_stem(out.name)}.vw-4194303@{atomic._host()}.abcdefgh.part.nrrd"
    stale.write_bytes(b"left by a killed run")
    assert run("distance", ball_file, "--iso", "50", "-o", out).code == 0
    assert not stale.exists()
    too_long = tmp_path / ("e" * 251 + ".nrrd")
    res = run("distance", ball_file, "--iso", "50", "-o", too_long)
    assert res.code == 2 and "the name is 256 bytes, more than the 255" in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == names


def test_an_output_name_ending_in_a_slash_is_refused_but_a_stores(run, tmp_path, ball_file):
    """``-o out.nrrd/`` wrote the file ``out.nrrd`` without a word (a slash names a folder:
    ``-o scans/`` made a file named ``scans``); a store is a folder and may end in one."""
    for args in (["convert", ball_file, "-o", f"{tmp_path / 'new.nrrd'}/"],
                 ["mesh", ball_file, "--iso", "50", "-o", f"{tmp_path / 'm.ply'}/"],
                 ["capture", ball_file, "-o", f"{tmp_path / 'c.vwc'}/"],
                 ["distance", ball_file, "--iso", "50", "-o", f"{tmp_path / 'scans'}/"],
                 # (an image or a frame pattern wrote its file too: `--render x.png/`)
                 ["mesh", ball_file, "--iso", "50", "-o", tmp_path / "m.ply", "--render",
                  f"{tmp_path / 'r.png'}/"],
                 ["morph", ball_file, ball_file, "--frames", "2", "-o", tmp_path / "f{i}.nrrd",
                  "--render-to", f"{tmp_path / 'f{i}.png'}/"],
                 ["morph", ball_file, ball_file, "--frames", "2", "-o", tmp_path / "f{i}.nrrd",
                  "--mesh-to", f"{tmp_path / 'f{i}.ply'}/"],
                 ["morph", ball_file, ball_file, "--frames", "2", "-o", tmp_path / "f{i}.nrrd",
                  "--render-to", tmp_path / "f{i}.png", "--sheet", f"{tmp_path / 's.png'}/"]):
        res = run(*args)
        assert res.code == 2, (args, res.stderr)
        assert "ends in a slash, which names a folder" in res.stderr
    res = run("convert", ball_file, "-o", f"{tmp_path / 'st.ome.zarr'}/")
    assert res.code == 0, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ball.nrrd", "st.ome.zarr"]
