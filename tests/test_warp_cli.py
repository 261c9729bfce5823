"""`volwarp warp`: specs, geometry, dtypes, frames, errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

SPECS = Path(__file__).parent.parent / "specs"


def _spec(tmp_path, text, name="w.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _centroid_world(vol):
    w = vol.data.astype(np.float64)
    idx = np.argwhere(w >= 0.5 * w.max())[:, ::-1]  # (x, y, z)
    vals = w[w >= 0.5 * w.max()]
    c = (idx * vals[:, None]).sum(0) / vals.sum()
    return vol.index_to_world(c)


@pytest.mark.parametrize("spec", sorted(p.name for p in SPECS.glob("warp-*.yaml")))
def test_example_specs_run(run, data_dir, tmp_path, spec):
    sample = "mri_t1_head_coronal_2x2x3mm.nrrd" if "head" in spec else "ball_30_uint8.nrrd"
    out = tmp_path / "o.nrrd"
    res = run("warp", data_dir / sample, "--spec", SPECS / spec, "-o", out)
    assert res.code == 0, res.stderr
    vin, vout = read_volume(data_dir / sample), read_volume(out)
    assert vout.dtype == vin.dtype
    assert np.allclose(vout.spacing, vin.spacing) and np.allclose(vout.direction, vin.direction)
    assert not np.array_equal(vout.data.shape, vin.data.shape) or \
        not np.array_equal(vout.data, vin.data)


def test_world_move_shifts_the_model_by_the_world_amount(run, tmp_path):
    # whole lattice moved by one world vector on a rotated, anisotropic grid:
    # the model moves by exactly that vector, and unwarped output keeps world position
    nz, ny, nx = 20, 24, 28
    z, y, x = np.mgrid[:nz, :ny, :nx]
    data = (200 * ((x - 13.5) ** 2 / 64 + (y - 11.5) ** 2 / 36 + (z - 9.5) ** 2 / 25 <= 1)
            ).astype(np.uint8)
    ang = np.deg2rad(25)
    direction = np.array([[np.cos(ang), 0, -np.sin(ang)], [0, 1, 0], [np.sin(ang), 0, np.cos(ang)]])
    vol = Volume(data, spacing=(0.8, 1.2, 2.0), origin=(5, -3, 10), direction=direction,
                 meta={"patient": "x"})
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    shift = np.array([3.0, -2.4, 4.0])
    moves = "\n".join(f"      - {{index: [{i}, {j}, {k}], by: [{shift[0]}, {shift[1]}, {shift[2]}]}}"
                      for i in range(7) for j in range(7) for k in range(7))
    spec = _spec(tmp_path, f"version: 1\ncapture: {{lattice: 7}}\nsteps:\n  - move:\n{moves}\n")
    empty = _spec(tmp_path, "version: 1\ncapture: {lattice: 7}\nsteps: []\n", "e.yaml")
    out, ident = tmp_path / "o.nrrd", tmp_path / "i.nrrd"
    # (the ellipsoid is a 0/200 mask: warped as intensities here, on a grid grown to hold
    # the moved model)
    grow = ("--values", "intensity", "--grid", "grow")
    assert run("warp", src, "--spec", spec, "-o", out, *grow).code == 0
    assert run("warp", src, "--spec", empty, "-o", ident, *grow).code == 0
    vo, vi = read_volume(out), read_volume(ident)
    assert vo.meta.get("patient") == "x" and vo.dtype == np.uint8
    assert np.allclose(_centroid_world(vi), _centroid_world(vol), atol=0.05)
    assert np.allclose(_centroid_world(vo) - _centroid_world(vol), shift, atol=0.1)
    # --crop cuts back to the input grid
    crop = tmp_path / "c.nrrd"
    assert run("warp", src, "--spec", empty, "-o", crop, "--crop", *grow[:2]).code == 0
    vc = read_volume(crop)
    assert vc.same_grid(vol)
    diff = np.abs(vc.data.astype(int) - data)
    # box filtering blurs the binary edge a little, nothing more
    assert np.mean(diff > 100) < 0.01 and diff.mean() < 3.0


@pytest.mark.parametrize("dtype", ["uint8", "int8", "uint16", "int16", "uint32", "int32",
                                   "float32", "float64"])
def test_every_dtype_identity_is_exact_with_nearest(run, tmp_path, dtype):
    rng = np.random.default_rng(3)
    info = np.iinfo(dtype) if np.dtype(dtype).kind in "iu" else None
    lo, hi = (info.min, info.max) if info else (-1e6, 1e6)
    data = rng.uniform(lo, hi, size=(9, 11, 13))
    data = np.rint(data).astype(dtype) if info else data.astype(dtype)
    src = tmp_path / "in.nrrd"
    write_volume(Volume(data, spacing=(1, 2, 3)), src)
    spec = _spec(tmp_path, "version: 1\ncapture: {lattice: [5, 6, 4], oversample: 1, "
                 "sampling: nearest}\npushforward: nearest\nsteps: []\n")
    out = tmp_path / "o.nrrd"
    res = run("warp", src, "--spec", spec, "-o", out)
    assert res.code == 0, res.stderr
    got = read_volume(out)
    assert got.dtype == np.dtype(dtype)
    if np.dtype(dtype).kind == "f":
        # exact up to the fixed-point accumulators (2**-40 of the value range)
        assert np.max(np.abs(got.data - data)) <= 1e-11 * np.abs(data).max() + (
            np.finfo(dtype).eps * np.abs(data).max())
    else:
        assert np.array_equal(got.data, data)


def test_capture_file_then_warp_equals_direct_warp_and_frames(run, data_dir, tmp_path):
    src = data_dir / "ball_30_uint8.nrrd"
    scene = tmp_path / "s.vwc"
    spec = SPECS / "warp-ball.yaml"
    assert run("capture", src, "-o", scene, "--lattice", "9").code == 0
    a, b = tmp_path / "a.nrrd", tmp_path / "b.nrrd"
    res = run("warp", scene, "--spec", spec, "-o", a,
              "--frames-to", str(tmp_path / "f_{frame:02d}.nrrd"))
    assert res.code == 0, res.stderr
    assert run("warp", src, "--spec", spec, "-o", b).code == 0
    va, vb = read_volume(a), read_volume(b)
    assert np.array_equal(va.data, vb.data)
    frames = sorted(tmp_path.glob("f_*.nrrd"))
    assert [f.name for f in frames] == [f"f_{n:02d}.nrrd" for n in range(6)]  # 0 + 1 + 4
    assert np.array_equal(read_volume(frames[-1]).data, va.data)
    # provenance: the warp, its input's name and the spec's hash, in outputs and frames
    import hashlib
    sha = hashlib.sha256(spec.read_bytes()).hexdigest()
    for path, name in ((a, "s.vwc"), (b, src.name), (frames[2], "s.vwc")):
        meta = read_volume(path).meta
        assert meta["volwarp_command"] == "warp"
        assert meta["volwarp_input"] == name
        assert meta["volwarp_spec_sha256"] == sha
    # frame 0 is the unwarped model, frames change monotonically towards the end
    f0 = read_volume(frames[0]).data.astype(float)
    diffs = [np.abs(read_volume(f).data.astype(float) - f0).sum() for f in frames]
    assert diffs[0] == 0 and all(x < y for x, y in zip(diffs[1:], diffs[2:], strict=False))


def test_drag_reaches_its_target(run, tmp_path):
    # a smooth marker; drag its centre 4 voxels and find its peak there
    zz, yy, xx = np.mgrid[:24, :24, :24]
    data = (100 * np.exp(-((xx - 11) ** 2 + (yy - 11) ** 2 + (zz - 11) ** 2) / 4.0)
            ).astype(np.float32)
    src = tmp_path / "in.nrrd"
    write_volume(Volume(data), src)
    spec = _spec(tmp_path, "version: 1\nunits: voxel\ncapture: {lattice: 9, pad: 6}\n"
                 "steps:\n  - drag:\n      - {from: [11, 11, 11], to: [15, 11, 11]}\n")
    out = tmp_path / "o.nrrd"
    assert run("warp", src, "--spec", spec, "-o", out, "--crop").code == 0
    got = read_volume(out).data
    z, y, x = np.unravel_index(np.argmax(got), got.shape)
    assert (x, y, z) == (15, 11, 11)
    assert got.max() > 0.8 * data.max()


BAD = [
    ("version: 1\nsteps: []\nbogus: 1\n", "bogus", 3),
    ("version: 1\nsteps:\n  - move:\n      - {index: [9, 0, 0], by: [1, 0, 0]}\n",
     "steps[0].move[0].index", 4),
    ("version: 1\nsteps:\n  - move:\n      - {index: [1, 0], by: [1, 0, 0]}\n",
     "steps[0].move[0].index", 4),
    ("version: 1\nsteps:\n  - move:\n      - {index: [1, 0, 0], by: [1, 0, 'a']}\n",
     "steps[0].move[0].by", 4),
    ("version: 1\nsteps:\n  - move:\n      - {index: [1, 0, 0]}\n", "steps[0].move[0]", 4),
    ("version: 1\nunits: voxel\nsteps:\n  - drag:\n      - {from: [5, 5, 5], to: [6, 5, 5]}\n"
     "      - {from: [500, 5, 5], to: [6, 5, 5]}\n", "steps[0].drag[1].from", 6),
    ("version: 1\nsteps:\n  - frames: 0\n", "steps[0].frames", 3),
    ("version: 1\nsteps:\n  - radius: 3\n", "steps[0].radius", 3),
    ("version: 2\nsteps: []\n", "version", 1),
    ("version: 1\ncapture: {lattice: 3}\nsteps: []\n", "capture.lattice", 2),
    ("version: 1\nbackground: .nan\nsteps: []\n", "background", 2),
    ("version: 1\nbackground: far\nsteps: []\n", "background", 2),
]


@pytest.mark.parametrize("text, key, line", BAD)
def test_bad_specs_exit_2_with_key_and_line(run, data_dir, tmp_path, text, key, line):
    spec = _spec(tmp_path, text)
    out = tmp_path / "o.nrrd"
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", out,
              "--frames-to", str(tmp_path / "f{frame}.nrrd"))
    assert res.code == 2, res.stderr
    assert f"{spec}:{line}:" in res.stderr and key in res.stderr
    assert list(tmp_path.glob("*.nrrd")) == []


def test_spec_capture_conflicting_with_scene_is_exit_2(run, data_dir, tmp_path):
    scene = tmp_path / "s.vwc"
    assert run("capture", data_dir / "ball_30_uint8.nrrd", "-o", scene, "--lattice", "7").code == 0
    spec = _spec(tmp_path, "version: 1\ncapture: {lattice: 9}\nsteps: []\n")
    res = run("warp", scene, "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 2 and "capture.lattice" in res.stderr


@pytest.mark.parametrize("pattern", ["f.nrrd", "f_{nope}.nrrd", "f_{frame:q}.nrrd"])
def test_bad_frame_pattern_exit_2(run, data_dir, tmp_path, pattern):
    spec = _spec(tmp_path, "version: 1\nsteps: []\n")
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o",
              tmp_path / "o.nrrd", "--frames-to", str(tmp_path / pattern))
    assert res.code == 2
    assert list(tmp_path.glob("*.nrrd")) == []


TWO_STEPS = ("version: 1\nunits: voxel\ncapture: {lattice: 5}\nsteps:\n"
             "  - move: [{index: [2, 2, 2], by: [1, 0.5, -0.5]}]\n    frames: 3\n"
             "  - move: [{index: [2, 2, 2], by: [1, 0.5, -0.5]}]\n    frames: 2\n")


@pytest.mark.parametrize("values", ["intensity", "labels"])
def test_frames_a_pattern_gives_one_name_are_refused_before_any_is_written(run, data_dir,
                                                                           tmp_path, values):
    """{sub} restarts at each spec step: frames 1 and 4 would both be s1.nrrd (the second
    replacing the first, exit 0, before); -o or an export naming a frame's file
    likewise (only frame 1's name was checked)."""
    src = data_dir / "ball_30_uint8.nrrd"
    spec = _spec(tmp_path, TWO_STEPS)
    old = tmp_path / "s1.nrrd"
    old.write_bytes(b"an earlier frame")
    res = run("warp", src, "--spec", spec, "--frames-to", str(tmp_path / "s{sub}.nrrd"),
              "--values", values)
    assert res.code == 2, res.stderr
    assert "names frames 1 and 4 both" in res.stderr and "not {sub} alone" in res.stderr
    assert [p.name for p in tmp_path.glob("*.nrrd")] == ["s1.nrrd"]
    assert old.read_bytes() == b"an earlier frame"
    # a pattern that has {frame} and still names one file (its folders links to one) is
    # told to tell the frames apart, not to add {frame}
    (tmp_path / "one").mkdir()
    for n in range(10):
        (tmp_path / f"d{n}").symlink_to(tmp_path / "one")
    res = run("warp", src, "--spec", spec, "--frames-to", str(tmp_path / "d{frame}" / "f.nrrd"),
              "--values", values)
    assert res.code == 2 and "give {frame} a format that tells them apart" in res.stderr
    assert [p.name for p in tmp_path.glob("*.nrrd")] == ["s1.nrrd"]
    assert not any((tmp_path / "one").iterdir())
    for clash in (["-o", tmp_path / "f2.nrrd"], ["--jacobian-to", tmp_path / "f3.nrrd"]):
        res = run("warp", src, "--spec", spec, "--frames-to", str(tmp_path / "f{frame}.nrrd"),
                  *clash, "--values", values)
        assert res.code == 2 and "name the same file" in res.stderr, res.stderr
    # a detached header's data file: frame 2's f2.raw is the -o header's too
    res = run("warp", src, "--spec", spec, "--frames-to", str(tmp_path / "f{frame}.nhdr"),
              "-o", tmp_path / "f2.mhd", "--values", values)
    assert res.code == 2 and "f2.raw" in res.stderr, res.stderr
    assert not list(tmp_path.glob("f*"))
    res = run("warp", src, "--spec", spec, "--frames-to", str(tmp_path / "f{frame}.nrrd"),
              "--values", values)
    assert res.code == 0, res.stderr
    assert sorted(p.name for p in tmp_path.glob("f*.nrrd")) == [f"f{n}.nrrd" for n in range(6)]


def test_table_evaluator_gives_the_same_output(run, data_dir, tmp_path):
    a, b = tmp_path / "a.nrrd", tmp_path / "b.nrrd"
    spec = SPECS / "warp-ball-voxel.yaml"
    src = data_dir / "ball_30_uint8.nrrd"
    assert run("warp", src, "--spec", spec, "-o", a, "--pushforward", "box").code == 0
    assert run("warp", src, "--spec", spec, "-o", b, "--pushforward", "box",
               "--evaluator", "table").code == 0
    da, db = read_volume(a).data.astype(int), read_volume(b).data.astype(int)
    assert np.max(np.abs(da - db)) <= 1


def test_clay_block_example_specs(run, tmp_path):
    """examples/clay-block: the corner goes in with inward.yaml and out with outward.yaml."""
    import subprocess
    import sys

    folder = Path(__file__).parent.parent / "examples" / "clay-block"
    block = tmp_path / "block.nrrd"
    subprocess.run([sys.executable, str(folder / "make_block.py"), str(block)], check=True)
    scene = tmp_path / "block.vwc"
    assert run("capture", block, "-o", scene, "--lattice", "9").code == 0
    src = read_volume(block)
    corner = (slice(20, 24),) * 3  # inside the block, at its (+x, +y, +z) corner
    beyond = (slice(24, 28),) * 3  # outside it
    for name in ("inward", "outward"):
        out = tmp_path / f"{name}.nrrd"
        res = run("warp", scene, "--spec", folder / f"{name}.yaml", "-o", out, "--crop")
        assert res.code == 0, res.stderr
        got = read_volume(out).data.astype(float)
        if name == "inward":
            assert got[corner].mean() < 0.6 * src.data[corner].mean()
        else:
            assert got[beyond].mean() > src.data[beyond].astype(float).mean() + 40


def test_background_from_spec_and_command_line(run, data_dir, tmp_path):
    """The padding gets the background: the spec's, or --background over it."""
    src = data_dir / "ball_30_uint8.nrrd"
    spec = _spec(tmp_path, "version: 1\nunits: voxel\nbackground: 7\ncapture: {pad: 4}\n"
                           "steps:\n  - move:\n      - {index: [4, 4, 4], by: [1, 0, 0]}\n")
    outs = {}
    for name, extra in (("spec", []), ("cli", ["--background", "250"])):
        outs[name] = tmp_path / f"{name}.nrrd"
        res = run("warp", src, "--spec", spec, "-o", outs[name], "--values", "intensity",
                  *extra)
        assert res.code == 0, res.stderr
    a, b = read_volume(outs["spec"]).data, read_volume(outs["cli"]).data
    assert a[0, 0, 0] == 7 and b[0, 0, 0] == 250
    assert a[a.shape[0] // 2, a.shape[1] // 2, a.shape[2] // 2] == b[b.shape[0] // 2,
                                                                      b.shape[1] // 2,
                                                                      b.shape[2] // 2]


def test_capture_made_while_the_spec_is_checked_is_used_once(run, data_dir, tmp_path,
                                                            monkeypatch):
    """With frames, the volume is captured with the spec's settings before the schema
    check; the command uses that capture (made once) and writes the output of capturing,
    then warping. A one-shot warp gathers the domain box by box as its blocks stream it
    (a deferred capture of the input read lazily), the whole domain never."""
    from volwarp_cli.bspline import capture as capture_mod

    calls = []
    real = capture_mod.capture_volume
    monkeypatch.setattr(capture_mod, "capture_volume",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    spec = _spec(tmp_path, "version: 1\ncapture: {lattice: 6, oversample: 1}\nsteps:\n"
                 "  - move:\n      - {index: [2, 2, 2], by: [1.5, 0, 0]}\n")
    out = tmp_path / "o.nrrd"
    res = run("warp", "-vv", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", out,
              "--values", "intensity")
    assert res.code == 0, res.stderr
    assert calls == [] and "capture (pullback)" not in res.stderr
    framed = tmp_path / "framed.nrrd"
    res = run("warp", "-vv", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", framed,
              "--frames-to", str(tmp_path / "f{frame}.nrrd"), "--values", "intensity")
    assert res.code == 0, res.stderr
    assert calls == [1] and res.stderr.count("capture (pullback)") == 1
    from volwarp_cli.bspline.capture import capture_volume
    from volwarp_cli.bspline.plan import read_warp_spec
    from volwarp_cli.io import read_volume
    from volwarp_cli.spec.loader import load_spec
    from volwarp_cli.warp.prepare import output_volume, prepare
    from volwarp_cli.warp.prepare import run as run_warp

    doc = load_spec(spec, "warp")
    cap = capture_volume(read_volume(data_dir / "ball_30_uint8.nrrd"), lattice=6,
                         oversample=1)
    scene, frames = prepare(cap, doc, read_warp_spec(doc))
    expected = output_volume(cap, scene, run_warp(scene, frames, lambda *a: None)).data
    assert np.array_equal(read_volume(out).data, expected)
    assert np.array_equal(read_volume(framed).data, expected)


@pytest.mark.parametrize("text, input_name, code, words", [
    # capture settings that cannot be read early (tripled needs 6 points): the check reports
    ("version: 1\ncapture: {lattice: 5, placement: tripled}\nsteps: []\n", "ball_30_uint8.nrrd",
     2, ["capture.placement", "tripled"]),

    # a spec error comes before an input error
    ("version: 1\nsteps: []\nbogus: 1\n", "missing.nrrd", 2, ["bogus"]),
    # a good spec and a missing input: the input error
    ("version: 1\nsteps: []\n", "missing.nrrd", 1, ["missing.nrrd"]),
])
def test_errors_of_the_overlapped_read_and_capture_come_in_order(run, data_dir, tmp_path,
                                                                  text, input_name, code,
                                                                  words):
    spec = _spec(tmp_path, text)
    out = tmp_path / "o.nrrd"
    res = run("warp", data_dir / input_name, "--spec", spec, "-o", out)
    assert res.code == code, res.stderr
    assert all(w in res.stderr for w in words), res.stderr
    assert not out.exists()


def test_a_failed_early_capture_is_reported_after_the_spec_check(run, tmp_path):
    """The early capture of a volume with NaN fails; the capture after the check says why."""
    data = np.ones((12, 12, 12), np.float32)
    data[5, 5, 5] = np.nan
    src = tmp_path / "nan.nrrd"
    write_volume(Volume(data), src)
    out = tmp_path / "o.nrrd"
    res = run("warp", src, "--spec", _spec(tmp_path, "version: 1\nsteps: []\n"), "-o", out)
    assert res.code == 1 and "nan.nrrd" in res.stderr and "NaN" in res.stderr, res.stderr
    assert not out.exists()
    # with a bad spec too, the spec error comes first
    res = run("warp", src, "--spec", _spec(tmp_path, "version: 1\nsteps: []\nbogus: 1\n"),
              "-o", out)
    assert res.code == 2 and "bogus" in res.stderr, res.stderr


@pytest.mark.parametrize("extra", [[], ["--crop"], ["--dtype", "int16", "--byte-order", "big"],
                                   ["--crop", "--dtype", "float32"]])
def test_streamed_nrrd_output_is_the_whole_targets_file(run, data_dir, tmp_path, extra,
                                                        monkeypatch):
    """A one-shot warp (the final lattice's output, block by block, its planes written
    into the file as they are finished) writes the file that the incremental frames'
    last target gives, byte for byte (the --frames-to path: frame 0 in full, then local
    updates, written whole)."""
    from volwarp_cli import execute

    monkeypatch.setattr(execute, "STREAMED_FROM", 0)  # (this output is small)
    spec = SPECS / "warp-ball.yaml"
    src = data_dir / "ball_30_uint8.nrrd"
    streamed, whole = tmp_path / "streamed.nrrd", tmp_path / "whole.nrrd"
    extra = [*extra, "--values", "intensity"]  # (the ball is a 0/200 mask)
    assert run("warp", src, "--spec", spec, "-o", streamed, *extra).code == 0
    res = run("warp", src, "--spec", spec, "-o", whole, *extra,
              "--frames-to", str(tmp_path / "f{frame}.nrrd"))
    assert res.code == 0, res.stderr
    assert streamed.read_bytes() == whole.read_bytes()


def test_a_warp_failing_midway_leaves_the_existing_output(run, data_dir, tmp_path,
                                                          monkeypatch):
    from volwarp_cli.bspline import scene as scene_mod
    from volwarp_cli.warp import blocks as blocks_mod

    spec = SPECS / "warp-ball.yaml"
    out = tmp_path / "o.nrrd"
    out.write_bytes(b"an earlier result")
    calls = []
    real = scene_mod.Scene.contribute

    def failing(self, *a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise MemoryError("out of memory midway")
        return real(self, *a, **k)

    monkeypatch.setattr(scene_mod.Scene, "contribute", failing)
    monkeypatch.setattr(blocks_mod, "STREAM_PLANES", 1)  # many chunks: some planes done
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", out,
              "--values", "intensity")  # (the intensity warp's stream: a label map's is its own)
    assert len(calls) >= 3 and res.code == 1 and "memory" in res.stderr
    assert out.read_bytes() == b"an earlier result"
    assert [p.name for p in tmp_path.iterdir()] == ["o.nrrd"]


@pytest.mark.parametrize("capture, move", [
    ("{lattice: 5, oversample: 1, pad: 100000}", "[1.0, 0, 0]"),
    ("{lattice: 5, oversample: 1}", "[1.0e+11, 0, 0]"),  # (1e300: a spec error, below)
])
def test_a_target_too_big_to_make_is_refused_naming_the_input(run, data_dir, tmp_path, capture,
                                                              move):
    """A huge pad, or a displacement that asks for one, is refused before anything of the
    target's size is made (numpy could not even make its shape: that was an internal
    error), in one line naming the input and the size; the existing output is kept."""
    src = data_dir / "ball_30_uint8.nrrd"
    spec = _spec(tmp_path, f"version: 1\nunits: voxel\ncapture: {capture}\nsteps:\n"
                           f"  - move:\n      - {{index: [2, 2, 2], by: {move}}}\n")
    out = tmp_path / "o.nrrd"
    out.write_bytes(b"old")
    # (a displacement's own padding past 2x the input is refused first: --allow-growth)
    res = run("warp", src, "--spec", spec, "-o", out, "--allow-growth", "--grid", "grow")
    assert res.code == 1, res.stderr
    line = res.stderr.strip()
    assert "\n" not in line and len(line) < 400
    assert str(src) in line and "needs" in line  # (the target, or the labels' warp, by size)
    assert out.read_bytes() == b"old"


@pytest.mark.parametrize("move", ["[320.0, 0, 0]", "[0, 0, -100.0]"])  # 30^3: > 94 voxels
def test_a_move_that_would_grow_the_output_past_twice_needs_allow_growth(run, data_dir,
                                                                         tmp_path, move):
    """A mistyped 320 mm drag made a 181x217x1701 output: the padding a warp needs for its
    moves may grow the output up to 2x per axis; past that it stops (exit 2, the sizes)
    unless --allow-growth, and the existing output is kept (a small input may grow by 64
    voxels: moves of a few millimetres on a small volume need no option)."""
    src = data_dir / "ball_30_uint8.nrrd"
    spec = _spec(tmp_path, "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\n"
                           f"steps:\n  - move:\n      - {{index: [2, 2, 2], by: {move}}}\n")
    out = tmp_path / "o.nrrd"
    out.write_bytes(b"old")
    res = run("warp", src, "--spec", spec, "-o", out, "--grid", "grow")
    assert res.code == 2 and "--allow-growth" in res.stderr and "times the input" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and out.read_bytes() == b"old"
    res = run("warp", src, "--spec", spec, "-o", out, "--allow-growth", "--grid", "grow")
    assert res.code == 0, res
    assert max(read_volume(out).shape_xyz) > 94  # grown past 30 + 64 voxels


def test_the_growth_refusal_of_an_absurd_move_is_one_short_line(run, data_dir, tmp_path):
    """A move of 1e11 voxels: the sizes in the refusal are written short (2e+11), not as
    a long integer. (1e300, as before, is now refused earlier: beyond the exact sums.)"""
    src = data_dir / "ball_30_uint8.nrrd"
    spec = _spec(tmp_path, "version: 1\nunits: voxel\ncapture: {lattice: 5, oversample: 1}\n"
                           "steps:\n  - move:\n      - {index: [2, 2, 2], by: [1.0e+11, 0, 0]}\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--grid", "grow")
    line = res.stderr.strip()
    assert res.code == 2 and "\n" not in line and len(line) - len(str(spec)) < 250, line
    assert "would be 2e+11x30x30 voxels (" in line and "e+09 times the input's 30x30x30" in line


def test_a_failed_write_names_the_output_and_leaves_nothing(tmp_path):
    """An OSError while an output is written (a full disk, a quota) becomes an error
    naming the output; the temporary file goes, an existing output stays."""
    import errno

    from volwarp_cli.errors import VolwarpError
    from volwarp_cli.io.atomic import atomic_output

    out = tmp_path / "o.nrrd"
    out.write_bytes(b"old")
    with pytest.raises(VolwarpError, match=r"o\.nrrd: cannot write \(No space left on device\)"):
        with atomic_output(out) as tmp:
            tmp.write_bytes(b"part")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["o.nrrd"]


def _strict_json(text):
    """The one JSON document ``text`` holds (NaN / Infinity tokens refused)."""
    import json

    def no_constant(name):
        raise AssertionError(f"non-strict JSON token {name}")

    doc = json.loads(text, parse_constant=no_constant)  # extra data after it: an error
    assert isinstance(doc, dict) and text.strip().count("\n") == 0
    return doc


def test_json_reports_the_handles_in_world_mm(run, tmp_path):
    """`warp --json`: one JSON object on stdout (logs stay on stderr); per handle its
    spec step and index, from / to / reached in world mm and the miss |reached - to|."""
    zz, yy, xx = np.mgrid[:24, :24, :24]
    data = (100 * np.exp(-((xx - 11) ** 2 + (yy - 11) ** 2 + (zz - 11) ** 2) / 4.0)
            ).astype(np.float32)
    ang = np.deg2rad(30)
    direction = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0],
                          [0, 0, 1]])
    vol = Volume(data, spacing=(1.0, 1.2, 1.5), origin=(-4.0, 2.0, 7.0), direction=direction)
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    # step 0: one handle, free control points within 6 voxels: reachable;
    # step 1: two handles half a voxel apart pulled opposite ways: a compromise
    spec = _spec(tmp_path, "version: 1\nunits: voxel\ncapture: {lattice: 9, pad: 8}\nsteps:\n"
                 "  - radius: 6\n    drag:\n      - {from: [11, 11, 11], to: [13, 11, 11]}\n"
                 "  - drag:\n      - {from: [13, 11, 11], to: [16, 11, 11]}\n"
                 "      - {from: [13.5, 11, 11], to: [10, 11, 11]}\n")
    out = tmp_path / "o.nrrd"
    res = run("warp", src, "--spec", spec, "-o", out, "--json", "-v")
    assert res.code == 0, res.stderr
    doc = _strict_json(res.stdout)
    assert "missed its target" in res.stderr and "volwarp:" not in res.stdout
    assert doc["output"] == str(out)
    assert doc["shape"] == list(read_volume(out).shape_xyz)
    assert "frames" not in doc and "jacobian" not in doc and "displacement" not in doc
    hs = doc["handles"]
    assert [(h["step"], h["index"]) for h in hs] == [(0, 0), (1, 0), (1, 1)]
    spec_from = [[11, 11, 11], [13, 11, 11], [13.5, 11, 11]]
    spec_to = [[13, 11, 11], [16, 11, 11], [10, 11, 11]]
    for h, a, b in zip(hs, spec_from, spec_to, strict=True):
        assert np.allclose(h["from"], vol.index_to_world(a), atol=1e-9)
        assert np.allclose(h["to"], vol.index_to_world(b), atol=1e-9)
        miss = np.linalg.norm(np.subtract(h["reached"], h["to"]))
        assert h["miss_mm"] == pytest.approx(miss, abs=1e-9)
        assert isinstance(h["miss_mm"], float)
    assert hs[0]["miss_mm"] < 1e-3  # within its radius it is reached
    assert hs[1]["miss_mm"] > 0.3 and hs[2]["miss_mm"] > 0.3  # they conflict


def test_json_counts_the_frames_written(run, tmp_path, data_dir):
    src = data_dir / "ball_30_uint8.nrrd"
    res = run("warp", src, "--spec", SPECS / "warp-ball.yaml", "-o", tmp_path / "o.nii.gz",
              "--frames-to", str(tmp_path / "f_{frame:02d}.nrrd"), "--json")
    assert res.code == 0, res.stderr
    doc = _strict_json(res.stdout)
    assert doc["frames"] == len(list(tmp_path.glob("f_*.nrrd"))) == 6
    assert doc["shape"] == list(read_volume(tmp_path / "o.nii.gz").shape_xyz)
    # without --json: nothing on stdout
    res = run("warp", src, "--spec", SPECS / "warp-ball.yaml", "-o", tmp_path / "p.nrrd")
    assert res.code == 0 and res.stdout == ""


def test_a_drag_outside_the_model_is_reported_in_the_specs_own_numbers(run, data_dir, tmp_path):
    """The spec says mm: the error quotes the point as written, in mm (not input voxels)."""
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 9, oversample: 1}\nsteps:\n  - drag:\n"
                    "      - {from: [127.0, 162.0, 270.0], to: [127.0, 162.0, 280.0]}\n")
    res = run("warp", data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd", "--spec", spec,
              "-o", tmp_path / "o.nrrd")
    assert res.code == 2
    assert "steps[0].drag[0].from" in res.stderr
    assert "[127.0, 162.0, 270.0] (LPS mm) is outside" in res.stderr
    assert not (tmp_path / "o.nrrd").exists()


@pytest.mark.parametrize("radius, warned", [(3, True), (8, False), (None, False)])
def test_a_radius_that_makes_a_drag_stronger_is_warned_about(run, data_dir, tmp_path, radius,
                                                             warned):
    """On the 30 mm ball (control points 5 mm apart) a 4 mm drag with radius 3 frees one
    point, which must move 13.7 mm: a warning says a smaller radius is stronger, not gentler;
    radius 8 (19 points, 9.4 mm) and no radius do not warn. The output is written either way."""
    spec = tmp_path / "s.yaml"
    text = ("version: 1\ncapture: {lattice: 9}\nsteps:\n  - drag:\n"
            "      - {from: [14.5, 14.5, 24.0], to: [14.5, 14.5, 28.0]}\n")
    spec.write_text(text + (f"    radius: {radius}\n" if radius else ""))
    res = run("warp", data_dir / "ball_30_uint8.nrrd", "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 0, res.stderr
    assert ("stronger, not gentler" in res.stderr) == warned, res.stderr
    if warned:
        assert "13.7 mm, 3.4 times the largest drag (4 mm)" in res.stderr
    assert (tmp_path / "o.nrrd").exists()


def test_integers_written_with_a_point_are_integers(run, tmp_path):
    """The schema takes 7.0 for an integer (as jsonschema does); the spec reader then
    crashed on it (internal error, exit 1) for capture.lattice, capture.pad and a move's
    index (found by a review). The same warp as with 7, 2 and [3, 3, 3]."""
    z, y, x = np.indices((14, 16, 18))
    write_volume(Volume(np.exp(-((x - 9.0) ** 2 + (y - 8) ** 2 + (z - 7) ** 2) / 20)
                        .astype(np.float32)), tmp_path / "in.nrrd")
    outs = []
    for name, (lattice, pad, index) in {"point": ("7.0", "2.0", "[3.0, 3, 3]"),
                                        "plain": ("7", "2", "[3, 3, 3]")}.items():
        spec = tmp_path / f"{name}.yaml"
        spec.write_text(f"version: 1\ncapture: {{lattice: {lattice}, pad: {pad}}}\nsteps:\n"
                        f"  - move: [{{index: {index}, by: [1, 0.5, 0.2]}}]\n")
        res = run("warp", tmp_path / "in.nrrd", "--spec", spec, "-o", tmp_path / f"{name}.nrrd")
        assert res.code == 0, res.stderr
        outs.append(read_volume(tmp_path / f"{name}.nrrd"))
    assert outs[0].shape == outs[1].shape and np.array_equal(outs[0].data, outs[1].data)


@pytest.mark.parametrize("step", ["move: [{index: [3, 3, 3], by: [1e50, 1, 1]}]",
                                  "drag: [{from: [5, 5, 5], to: [1e300, 1, 1]}]"])
def test_a_move_beyond_the_exact_sums_is_a_spec_error(run, tmp_path, step):
    """A control point moved 1e50 voxels wrapped the pushforward's 64-bit sums: values far
    outside the input's range (-8e9 from 0..983), exit 0 (found by a review)."""
    z, y, x = np.indices((12, 12, 12))
    write_volume(Volume((x + y + z).astype(np.float32)), tmp_path / "in.nrrd")
    (tmp_path / "s.yaml").write_text(f"version: 1\nsteps:\n  - {step}\n")
    out = tmp_path / "o.nrrd"
    res = run("warp", tmp_path / "in.nrrd", "--spec", tmp_path / "s.yaml", "-o", out)
    key = "move[0].by" if step.startswith("move") else "drag[0].to"  # (the value's own key)
    assert res.code == 2 and f"s.yaml:3: steps[0].{key}: moves a control point" in res.stderr
    assert not out.exists()
    (tmp_path / "s.yaml").write_text("version: 1\nsteps:\n  - move: [{index: [3, 3, 3], "
                                     "by: [1e9, 1, 1]}]\n")  # (far, and placed exactly)
    assert run("warp", tmp_path / "in.nrrd", "--spec", tmp_path / "s.yaml", "-o", out).code == 0
    assert 0 <= read_volume(out).data.min() and read_volume(out).data.max() <= 33


def test_a_handle_miss_is_said_in_the_spec_s_units(run, tmp_path):
    """Two drags of one point 10 mm apart along z, on 2.5 mm slices: each misses by 5 mm (it
    was said as "2 voxel", the input's z voxels, while the spec speaks millimetres)."""
    z, y, x = np.mgrid[:20, :40, :40]
    src = tmp_path / "aniso.nrrd"
    write_volume(Volume(((x - 20) ** 2 + (y - 20) ** 2 + ((z - 10) * 2.5) ** 2 < 150)
                        .astype(np.float32) * 100, spacing=(1, 1, 2.5)), src)
    spec = tmp_path / "conflict.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 7}\nsteps:\n  - drag:\n"
                    "      - {from: [20, 20, 25], to: [20, 20, 30]}\n"
                    "      - {from: [20, 20, 25], to: [20, 20, 20]}\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 0, res.stderr
    assert "the handles cannot all be reached (largest miss 5 mm)" in res.stderr, res.stderr
    voxel = tmp_path / "voxel.yaml"  # (the same drags in input voxels: 2 voxels along z)
    voxel.write_text("version: 1\nunits: voxel\ncapture: {lattice: 7}\nsteps:\n  - drag:\n"
                     "      - {from: [20, 20, 10], to: [20, 20, 12]}\n"
                     "      - {from: [20, 20, 10], to: [20, 20, 8]}\n")
    res = run("warp", src, "--spec", voxel, "-o", tmp_path / "v.nrrd")
    assert res.code == 0 and "(largest miss 2 voxel)" in res.stderr, res.stderr


def test_a_step_that_moves_nothing_and_a_point_moved_twice_are_said(run, tmp_path):
    """Both are the spec's right and more often a slip: said, and the warp goes on."""
    z, y, x = np.mgrid[:20, :20, :20]
    src = tmp_path / "ball.nrrd"
    write_volume(Volume(((x - 10) ** 2 + (y - 10) ** 2 + (z - 10) ** 2 < 30)
                        .astype(np.float32)), src)
    spec = tmp_path / "s.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 5}\nsteps:\n  - frames: 3\n  - move:\n"
                    "      - {index: [2, 2, 2], by: [1, 0, 0]}\n"
                    "      - {index: [2, 2, 2], by: [1, 0, 0]}\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd")
    assert res.code == 0, res.stderr
    assert "steps[0] moves nothing: its 3 frames are the same lattice" in res.stderr
    assert "steps[1].move[1]: control point [2, 2, 2] is moved again" in res.stderr
    once = tmp_path / "once.yaml"  # (the two 'by's add up: the same as one of 2)
    once.write_text("version: 1\ncapture: {lattice: 5}\nsteps:\n  - move:\n"
                    "      - {index: [2, 2, 2], by: [2, 0, 0]}\n")
    res = run("warp", src, "--spec", once, "-o", tmp_path / "once.nrrd")
    assert res.code == 0 and res.stderr == "", res.stderr
    assert np.array_equal(read_volume(tmp_path / "o.nrrd").data,
                          read_volume(tmp_path / "once.nrrd").data)


def test_a_spec_read_from_a_pipe_is_hashed_as_it_was_read(tmp_path):
    """``--spec /dev/stdin``: the provenance hash is of the spec's bytes (it was the empty
    input's: the pipe was read again, drained, when the output was stamped); a sweep's too."""
    import hashlib
    import subprocess
    import sys

    src = tmp_path / "in.nrrd"
    write_volume(Volume(np.random.default_rng(0).random((12, 12, 12), dtype=np.float32)), src)
    text = ("version: 1\r\ncapture: {lattice: 5, oversample: 1}\r\nsteps:\r\n  - move:\r\n"
            "      - {index: [2, 2, 2], by: [1.0, 0.5, 0.0]}\r\n")
    sha = hashlib.sha256(text.encode()).hexdigest()
    piped, filed = tmp_path / "piped.nrrd", tmp_path / "filed.nrrd"
    (tmp_path / "w.yaml").write_bytes(text.encode())
    for spec, out, stdin in (("/dev/stdin", piped, text.encode()),
                             (str(tmp_path / "w.yaml"), filed, b"")):
        res = subprocess.run([sys.executable, "-m", "volwarp_cli", "warp", str(src), "--spec",
                              spec, "-o", str(out), "-q"], input=stdin, capture_output=True)
        assert res.returncode == 0, res.stderr
        assert read_volume(out).meta["volwarp_spec_sha256"] == sha
    assert np.array_equal(read_volume(piped).data, read_volume(filed).data)
    sweep = ("version: 1\ngrid: {spacing: 0.5}\nfields:\n  opacity: {value: 0.8}\n"
             "trajectory:\n  - line: {from: [0, 0, 0], to: [6, 0, 0]}\nup: [0, 0, 1]\n"
             "scale: [2, 2]\n")
    res = subprocess.run([sys.executable, "-m", "volwarp_cli", "sweep", "/dev/stdin", "-o",
                          str(tmp_path / "s_{field}.nrrd"), "-q"], input=sweep.encode(),
                         capture_output=True)
    assert res.returncode == 0, res.stderr
    assert read_volume(tmp_path / "s_opacity.nrrd").meta["volwarp_spec_sha256"] == \
        hashlib.sha256(sweep.encode()).hexdigest()
