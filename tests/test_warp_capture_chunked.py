"""`volwarp warp SCENE.vwc --chunked`: a capture file warped by blocks, its domain left in the file.

The domain voxmap is read box by box from the file (``StoredDomain``), in this process
or in worker processes (which reopen the file by its path); the output equals the
in-memory warp of the same capture file byte for byte, and the in-memory warp of the
volume it was captured from. A corrupted or truncated capture file is refused before
any output exists.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from volwarp_cli.box import Box
from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

SPEC = """version: 1
capture: {lattice: 6, oversample: 2}
steps:
  - move:
      - {index: [2, 3, 2], by: [3, -2, 4]}
      - {index: [3, 2, 3], by: [-2, 1.5, -3]}
"""

ROTATED = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture
def scene(tmp_path, run):
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (23, 27, 19)], indexing="ij")
    rng = np.random.default_rng(5)
    data = 1000 * np.exp(-(x * x + y * y + z * z) / 0.3) + rng.integers(0, 40, x.shape)
    vol = Volume(data.astype(np.int16), spacing=np.array([0.8, 0.9, 1.1]),
                 origin=np.array([10.0, -5.0, 3.0]), direction=ROTATED)
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    spec = tmp_path / "warp.yaml"
    spec.write_text(SPEC)
    vwc = tmp_path / "scene.vwc"
    res = run("capture", src, "-o", vwc, "--lattice", "6", "--oversample", "2")
    assert res.code == 0, res.stderr
    return src, spec, vwc


def test_stored_domain_boxes_equal_the_read_capture(scene):
    """Any box of the file's domain is the held domain's box (hypothesis-free: every
    block of an odd tiling, which covers the domain)."""
    from volwarp_cli.warp.capture_file import open_capture_lazy, read_capture

    _, _, vwc = scene
    held = read_capture(vwc)
    lazy = open_capture_lazy(vwc)
    assert lazy.domain is None and lazy.sampler.shape == held.domain.shape
    assert lazy.stats == held.stats and lazy.grid == held.grid
    for box in Box.from_shape(held.domain.shape).blocks((7, 5, 11)):
        got = lazy.sampler.box(box)
        assert got.dtype == held.domain.dtype
        assert np.array_equal(got, held.domain[box.slices])


def test_a_capture_file_replaced_while_its_blocks_run_refuses_the_output(run, scene, tmp_path,
                                                                        monkeypatch):
    """The blocks' tasks reopen the file by its path: a capture written over it meanwhile
    (`volwarp capture -o` renames a new file into place) gave a mix of the two files, exit
    0 (a review, with the processes scheduler). The file is watched from its opening, as
    a mapped volume is: the output is refused and nothing is left."""
    from volwarp_cli.warp import capture_file

    src, spec, vwc = scene
    other = tmp_path / "other.vwc"
    assert run("capture", src, "-o", other, "--lattice", "6", "--oversample", "2").code == 0
    real = capture_file.open_capture_lazy

    def replaced_after_opening(path):
        cap = real(path)
        os.replace(other, vwc)  # (a new file of the same name, as capture -o makes it)
        return cap

    monkeypatch.setattr(capture_file, "open_capture_lazy", replaced_after_opening)
    out = tmp_path / "o.nrrd"
    res = run("warp", vwc, "--spec", spec, "-o", out, "--chunked", "--block", "8")
    assert res.code == 1 and "the file changed while it was being read" in res.stderr, res
    assert not out.exists()


@pytest.mark.parametrize("scheduler", ["threads", "processes"])
def test_a_capture_file_by_blocks_equals_in_memory(run, scene, tmp_path, scheduler):
    src, spec, vwc = scene
    mem, blk, vol_mem = tmp_path / "mem.nrrd", tmp_path / "blk.nrrd", tmp_path / "vol.nrrd"
    assert run("warp", vwc, "--spec", spec, "-o", mem).code == 0
    res = run("warp", vwc, "--spec", spec, "-o", blk, "--chunked", "--block", "9,7,11",
              "--scheduler", scheduler, "--json")
    assert res.code == 0, res.stderr
    assert '"blocks"' in res.stdout
    assert blk.read_bytes() == mem.read_bytes()
    # and the volume it was captured from, warped in memory, gives the same samples
    assert run("warp", src, "--spec", spec, "-o", vol_mem).code == 0
    from volwarp_cli.io import read_volume

    assert np.array_equal(read_volume(vol_mem).data, read_volume(blk).data)


def test_a_corrupted_capture_file_is_refused_by_blocks(run, scene, tmp_path):
    _, spec, vwc = scene
    raw = bytearray(vwc.read_bytes())
    raw[-5] ^= 0xFF
    bad = tmp_path / "bad.vwc"
    bad.write_bytes(bytes(raw))
    out = tmp_path / "o.nrrd"
    res = run("warp", bad, "--spec", spec, "-o", out, "--chunked")
    assert res.code == 1 and "checksum" in res.stderr and not out.exists()
    short = tmp_path / "short.vwc"
    short.write_bytes(vwc.read_bytes()[:-100])
    res = run("warp", short, "--spec", spec, "-o", out, "--chunked")
    assert res.code == 1 and "truncated" in res.stderr and not out.exists()


def test_a_capture_whose_settings_differ_from_the_spec_is_a_spec_error(run, scene, tmp_path):
    _, _, vwc = scene
    spec = tmp_path / "other.yaml"
    spec.write_text(SPEC.replace("lattice: 6", "lattice: 7"))
    out = tmp_path / "o.nrrd"
    res = run("warp", vwc, "--spec", spec, "-o", out, "--chunked")
    assert res.code == 2 and not out.exists()


def test_a_capture_file_too_big_for_the_budget_runs_by_blocks(run, scene, tmp_path,
                                                              monkeypatch):
    """No --chunked: reading the domain would not fit, so the warp runs by blocks."""
    from volwarp_cli import memory

    _, spec, vwc = scene
    mem, blk = tmp_path / "mem.nrrd", tmp_path / "blk.nrrd"
    assert run("warp", vwc, "--spec", spec, "-o", mem).code == 0
    monkeypatch.setattr(memory, "process_rss", lambda: 0)
    monkeypatch.setattr("volwarp_cli.execute.MIN_BLOCK_BUDGET", 64 << 10)
    res = run("warp", vwc, "--spec", spec, "-o", blk, "--memory-limit", "200K")
    assert res.code == 0, res.stderr
    assert "running by blocks" in res.stderr
    assert blk.read_bytes() == mem.read_bytes()


def test_a_cut_capture_file_and_a_capture_given_as_a_volume_say_what_they_are(run, scene,
                                                                               tmp_path):
    """A .vwc cut within its first bytes was 'not a volwarp capture file (file starts with
    b'VOLWARP-CAPTURE\\n')', the right magic; a .vwc given to a command that reads volumes
    was an 'unknown volume extension', exit 1 (a review)."""
    src, spec, vwc = scene
    cut = tmp_path / "cut.vwc"
    cut.write_bytes(vwc.read_bytes()[:20])
    res = run("warp", cut, "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 1 and "truncated capture file (20 bytes" in res.stderr, res.stderr
    (tmp_path / "empty.vwc").write_bytes(b"")
    res = run("info", tmp_path / "empty.vwc")
    assert res.code == 1 and "empty file" in res.stderr
    for args in (["convert", vwc, "-o", tmp_path / "c.nrrd"],
                 ["distance", vwc, "-o", tmp_path / "d.nrrd", "--iso", "1"],
                 ["warp", src, "--spec", spec, "-o", tmp_path / "w.vwc"]):
        res = run(*args)
        assert res.code == 2 and "a capture file (.vwc) is" in res.stderr, (args, res.stderr)
    assert not [p for p in tmp_path.iterdir() if p.suffix == ".nrrd" and p.name != "in.nrrd"]
