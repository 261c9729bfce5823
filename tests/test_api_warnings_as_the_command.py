"""What the command line warns, a caller of :mod:`volwarp_cli.api` learns too.

The API's warnings are the ``volwarp`` logger's records (as its module notes
say), the command's words without the ``volwarp: `` prefix. Some of a
command's warnings are gathered over its blocks and said when its run ends
(:mod:`volwarp_cli.samples`); outside a run they were said at every block
(a warp cast to uint8 said its clipping once a plane group, and a 0..255
ramp's every narrow block was "rounded away") or not at all (a sweep beside
its grid and a morph's empty frame returned zeros without a word). An API
call now says them as a command's run does: once, when it returns.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from volwarp_cli import api
from volwarp_cli.io import write_volume
from volwarp_cli.volume import Volume

DATA = Path(__file__).parent / "data"
SCAN = DATA / "mri_t1_head_coronal_2x2x3mm.nrrd"

BESIDE = {"version": 1, "grid": {"shape": [10, 10, 10], "origin": [100, 100, 100], "spacing": 1},
          "fields": {"opacity": 1}, "trajectory": [{"line": {"from": [0, 0, 0], "to": [10, 0, 0]}}],
          "scale": [4, 4]}
GOOD = {"version": 1, "grid": {"spacing": 0.5, "margin": 3}, "fields": {"opacity": 1},
        "trajectory": [{"line": {"from": [0, 0, 0], "to": [6, 0, 0]}}], "scale": [3, 3]}
NUDGE = {"version": 1, "units": "voxel", "values": "intensity",
         "steps": [{"move": [{"index": [4, 6, 4], "by": [0, -1, 0]}]}]}
Z, Y, X = np.mgrid[:30, :30, :30]


@pytest.fixture
def said(caplog):
    """The ``volwarp`` logger's warnings, as a list of messages (called after the work).

    caplog's handler on the logger itself: the command line's set-up stops its
    records from reaching the root's. Each message begins ``warning: `` as the
    command line's formatter makes it begin.
    """
    logger = logging.getLogger("volwarp")
    level, propagate = logger.level, logger.propagate
    logger.addHandler(caplog.handler)
    logger.setLevel(logging.WARNING)
    logger.propagate = False
    try:
        yield lambda: [as_said(r.getMessage()) for r in caplog.records
                       if r.levelno == logging.WARNING]
    finally:
        logger.removeHandler(caplog.handler)
        logger.setLevel(level)
        logger.propagate = propagate


def as_said(message: str) -> str:
    """A record's message as the command line's formatter says it (``warning: `` first)."""
    return message if message.startswith("warning") else "warning: " + message


def cli_warnings(stderr: str) -> list[str]:
    """The command's warning lines, as the API's records say them (no ``volwarp: ``)."""
    return [line[len("volwarp: "):] for line in stderr.splitlines()
            if line.startswith("volwarp: warning")]


def test_a_sweep_beside_its_grid_is_said(said, run, tmp_path):
    fields = api.sweep(BESIDE)
    assert not fields["opacity"].data.any()
    words = said()
    assert len(words) == 1 and "does not meet the sweep" in words[0], words
    import yaml

    (tmp_path / "s.yaml").write_text(yaml.safe_dump(BESIDE))
    res = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o.nrrd")
    assert res.code == 0 and cli_warnings(res.stderr) == words


def test_a_sweep_that_reaches_its_grid_says_nothing(said):
    assert api.sweep(GOOD)["opacity"].data.any()
    assert said() == []


def test_a_call_that_raises_says_its_error_not_its_notes(said, monkeypatch):
    """As a command that fails says nothing of the outputs it did not write.

    A sweep whose blocks fail after its plan was made has noted that it
    expects to reach its grid, and no block noted reaching it: said on the
    way out, that would be a false "every field of the sweep is 0".
    """
    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.sweep.run import SweepOperation

    def fails(op, box, *, threads):
        op.prepare()
        raise VolwarpError("a block failed")

    monkeypatch.setattr(SweepOperation, "compute", fails)
    with pytest.raises(VolwarpError, match="a block failed"):
        api.sweep(GOOD)
    assert said() == []


def balls(tmp_path: Path, centres_x) -> list[str]:
    """0/1 balls of radius 5 voxels on 30^3 grids, one per centre (voxel x)."""
    paths = []
    for n, cx in enumerate(centres_x):
        data = ((X - cx) ** 2 + (Y - 15) ** 2 + (Z - 15) ** 2 < 25).astype(np.uint8)
        paths.append(str(tmp_path / f"ball{n}.nrrd"))
        write_volume(Volume(data), paths[-1])
    return paths


def test_an_empty_morph_frame_is_said(said, run, tmp_path):
    """Balls 15 voxels apart: the middle frame's blend is positive everywhere."""
    a, b = balls(tmp_path, (7, 22))
    frames = api.morph({"version": 1, "source": {"volume": a}, "target": {"volume": b},
                        "frames": 3})
    assert frames[1].volume.data.min() > 0
    words = said()
    assert len(words) == 1 and "frame 1 (t = 0.5) is empty" in words[0], words
    res = run("morph", a, b, "--frames", "3", "-o", tmp_path / "f_{i}.nrrd")
    assert res.code == 0 and cli_warnings(res.stderr) == words


def test_overlapping_shapes_morph_without_a_word(said, tmp_path):
    a, b = balls(tmp_path, (12, 17))
    api.morph({"version": 1, "source": {"volume": a}, "target": {"volume": b}, "frames": 3})
    assert said() == []


@pytest.mark.parametrize("data", [
    (X * 30.0 - 200).astype(np.float32),  # clipped: one line, the whole's reach
    (X / 10.0).astype(np.float32),  # a 0..3 field rounded to 4 levels: one line
    (Z * 255.0 / 29 + 0.3).astype(np.float32),  # a 0..255 ramp: no line for narrow blocks
], ids=["clipped", "rounded", "wide"])
def test_a_warp_cast_is_said_as_the_command_says_it(said, run, tmp_path, data):
    """The output's cast is judged whole, once: the command's lines, no more, no fewer."""
    out = api.warp(Volume(data), NUDGE, dtype="uint8")
    words = said()
    import yaml

    write_volume(Volume(data), tmp_path / "in.nrrd")
    (tmp_path / "w.yaml").write_text(yaml.safe_dump(NUDGE))
    res = run("warp", tmp_path / "in.nrrd", "--spec", tmp_path / "w.yaml", "-o",
              tmp_path / "o.nrrd", "--dtype", "uint8")
    assert res.code == 0, res.stderr
    assert words == cli_warnings(res.stderr), (words, res.stderr)
    assert len(words) == (0 if data.max() > 100 and data.min() > 0 else 1)
    from volwarp_cli.io import read_volume

    np.testing.assert_array_equal(out.data, read_volume(tmp_path / "o.nrrd").data)


def test_a_warp_off_the_grid_is_said(said):
    moves = [{"index": [i, j, k], "by": [0, 0, 5000]}
             for i in range(4) for j in range(4) for k in range(4)]
    out = api.warp(SCAN, {"version": 1, "capture": {"lattice": 4, "oversample": 1},
                          "steps": [{"move": moves}]})
    assert not out.data.any()
    words = said()
    assert len(words) == 1 and "off the output's grid" in words[0], words


@pytest.mark.parametrize("data, words", [
    ((X / 10.0).astype(np.float32), "fractions were rounded away"),
    ((X * 100).astype(np.int16), "as high as 2900 lie outside uint8's range"),
], ids=["rounded", "clipped"])
def test_a_write_cast_is_said_once(said, tmp_path, data, words):
    api.write(Volume(data), tmp_path / "o.nrrd", dtype="uint8", labels=False)
    assert [words in w for w in said()] == [True]


def test_a_script_outside_the_api_still_hears_each_cast(said):
    """cast_samples called directly (no API call, no run) says each cast at once, as before."""
    from volwarp_cli.samples import cast_samples

    cast_samples(np.array([0.0, 300.0]), "uint8", what="a")
    cast_samples(np.array([0.0, 400.0]), "uint8", what="b")
    assert [w[:12] for w in said()] == ["warning: a: ", "warning: b: "]


def test_a_warning_said_once_a_run_is_said_once_a_call(said, run, tmp_path):
    """The NaN samples of a distance's shape: the scan and the passes both check it.

    The command says it once a run (``first_said``); the API said it twice.
    """
    data = ((X - 15) ** 2 + (Y - 15) ** 2 + (Z - 15) ** 2 < 64).astype(np.float32) * 100
    data[0, 0, :5] = np.nan
    api.distance(Volume(data), iso=50)
    words = said()
    write_volume(Volume(data), tmp_path / "nan.nrrd")
    res = run("distance", tmp_path / "nan.nrrd", "--iso", "50", "-o", tmp_path / "d.nrrd")
    assert res.code == 0 and cli_warnings(res.stderr) == words
    assert len(words) == 1 and "NaN samples" in words[0]


def test_a_sweep_s_fields_are_written_all_or_none(tmp_path):
    """api.write of a dict of fields wrote them one by one: a later field's failure (a NaN
    cast to an integer type) left the earlier files written, against "no partial output"."""
    import numpy as np

    from volwarp_cli import api
    from volwarp_cli.volume import Volume

    good = Volume(np.full((3, 4, 5), 0.5, np.float32))
    bad = Volume(np.full((3, 4, 5), np.nan, np.float32))
    (tmp_path / "o_a.nrrd").write_bytes(b"an earlier output")
    with pytest.raises(Exception):  # noqa: B017 - the cast's own error, whichever it is
        api.write({"a": good, "b": bad}, tmp_path / "o_{field}.nrrd", dtype="uint8")
    assert (tmp_path / "o_a.nrrd").read_bytes() == b"an earlier output"
    assert not (tmp_path / "o_b.nrrd").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # (no temporary)
