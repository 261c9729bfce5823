"""The warp pipeline's core (volwarp_cli.warp.run, .export_outputs), without click.

Each path is checked against the steps it strings together, called one by one
(capture, prepare, run, output_volume): the pipeline must add nothing but the
overlap and the plumbing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from volwarp_cli.bspline.capture import capture_volume
from volwarp_cli.bspline.plan import read_warp_spec
from volwarp_cli.errors import SpecError, VolwarpError
from volwarp_cli.io import read_volume
from volwarp_cli.spec.loader import load_spec
from volwarp_cli.volume import Volume
from volwarp_cli.warp.export_outputs import ExportRequests, write_exports
from volwarp_cli.warp.prepare import output_volume, prepare
from volwarp_cli.warp.prepare import run as run_warp
from volwarp_cli.warp.run import (
    IntensityWarp,
    LabelMapWarp,
    WarpInput,
    WarpOptions,
    frame_fields,
    handle_report,
)

DATA = Path(__file__).parent / "data"
BALL = DATA / "ball_30_uint8.nrrd"

MOVE = ("version: 1\nunits: voxel\ncapture: {lattice: 6, oversample: 1}\nsteps:\n"
        "  - move:\n      - {index: [2, 2, 2], by: [1.5, 0, 0]}\n    frames: 2\n")


def _spec(tmp_path, text=MOVE) -> Path:
    path = tmp_path / "w.yaml"
    path.write_text(text)
    return path


def _opened(spec_path, read=lambda: read_volume(BALL), **kw):
    if not kw.get("labels"):  # (the ball is a 0/200 mask: the label rule takes it for labels)
        kw.setdefault("values", "intensity")
    with WarpInput(str(BALL), read_volume=read, **kw) as w:
        doc, spec = w.load_spec(spec_path)
        return doc, spec, w.source(doc, spec)


def _reference(spec_path, **prepare_kw):
    doc = load_spec(spec_path, "warp")
    spec = read_warp_spec(doc)
    s = spec.capture
    cap = capture_volume(read_volume(BALL), lattice=s.lattice, placement=s.placement,
                         oversample=s.oversample, sampling=s.sampling)
    scene, frames = prepare(cap, doc, spec, **prepare_kw)
    return cap, scene, frames


def _last(scene, frames):
    """The incremental frames' last target (frame 0 in full, then local updates)."""
    return run_warp(scene, frames, lambda *a: None)


@pytest.mark.parametrize("defer", [False, True])
def test_render_is_capture_prepare_run(tmp_path, defer):
    """The one-shot render (the operation's whole output, block by block) is the last
    frame of the incremental warp, of a captured domain or of a deferred capture."""
    spec_path = _spec(tmp_path)
    doc, spec, cap = _opened(spec_path)
    if defer:
        s = spec.capture
        cap = capture_volume(read_volume(BALL), lattice=s.lattice, oversample=s.oversample,
                             defer=True)
        assert cap.domain is None
    out = IntensityWarp(cap, doc, spec).compute()
    rcap, scene, frames = _reference(spec_path)
    expected = output_volume(rcap, scene, _last(scene, frames))
    assert np.array_equal(out.data, expected.data)
    assert out.data.dtype == np.uint8
    np.testing.assert_allclose(out.origin, expected.origin)


def test_options_override_the_spec(tmp_path):
    spec_path = _spec(tmp_path)
    doc, spec, cap = _opened(spec_path)
    opts = WarpOptions(pushforward="nearest", background=9.0, crop=True, dtype="float32")
    out = IntensityWarp(cap, doc, spec, opts).compute()
    rcap, scene, frames = _reference(spec_path, method="nearest", background=9.0)
    expected = output_volume(rcap, scene, _last(scene, frames), crop=True, dtype="float32")
    assert out.data.dtype == np.float32 and out.shape_xyz == (30, 30, 30)
    assert np.array_equal(out.data, expected.data)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_operations_blocks_are_the_whole_outputs_parts(tmp_path, threads):
    """Any block of the operation, computed alone, is that part of the whole output, and
    the whole computed over any thread count is the same bytes."""
    from volwarp_cli.box import Box

    spec_path = _spec(tmp_path)
    doc, spec, cap = _opened(spec_path)
    whole = IntensityWarp(cap, doc, spec, WarpOptions(crop=True)).compute()
    op = IntensityWarp(cap, doc, spec, WarpOptions(crop=True)).operation()
    assert op.grid.shape == whole.data.shape
    got = op.compute(op.grid.box, threads=threads)[op.KEY]
    assert got.dtype == whole.data.dtype and np.array_equal(got, whole.data)
    for box in (Box((0, 0, 0), (30, 30, 30)), Box((3, 0, 7), (29, 11, 30)),
                Box((13, 14, 15), (14, 15, 16))):
        assert np.array_equal(op.compute(box, threads=1)[op.KEY], whole.data[box.slices])


def test_render_frames_hands_over_every_frame_and_returns_the_last(tmp_path):
    spec_path = _spec(tmp_path)
    doc, spec, cap = _opened(spec_path)
    got = []
    warp = IntensityWarp(cap, doc, spec)
    last = warp.compute_frames(lambda fields, vol: got.append((fields, vol.data.copy())))
    assert [f for f, _ in got] == [frame_fields(n, fr) for n, fr in
                                   enumerate([None, *warp.frames])]
    assert [f["spec_step"] for f, _ in got] == [0, 1, 1] and len(got) == 3
    assert np.array_equal(got[-1][1], last.data)
    doc, spec, cap = _opened(spec_path)
    assert np.array_equal(IntensityWarp(cap, doc, spec).compute().data, last.data)
    # frame 0 is the unmoved lattice: at oversample 1 the input, exactly, inside the pad
    pad = warp.scene.pad
    inner = got[0][1][pad[2]:pad[2] + 30, pad[1]:pad[1] + 30, pad[0]:pad[0] + 30]
    assert np.array_equal(inner, read_volume(BALL).data)


def test_a_spec_error_comes_before_the_inputs_error(tmp_path):
    def unreadable():
        raise VolwarpError("ball.nrrd: damaged")

    bad = _spec(tmp_path, "version: 1\nsteps: []\nbogus: 1\n")
    with pytest.raises(SpecError, match="bogus"):
        _opened(bad, read=unreadable)
    with pytest.raises(VolwarpError, match="damaged"):
        _opened(_spec(tmp_path, "version: 1\nsteps: []\n"), read=unreadable)


def test_the_early_capture_is_used_when_it_matches(tmp_path, monkeypatch):
    from volwarp_cli.bspline import capture as capture_module

    calls = []
    real = capture_module.capture_volume
    monkeypatch.setattr(capture_module, "capture_volume",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    _opened(_spec(tmp_path))
    assert calls == [1]
    _opened(_spec(tmp_path), labels=True)  # a label map: no intensity capture at all
    assert calls == [1]


def test_warp_input_needs_one_reader():
    with pytest.raises(ValueError):
        WarpInput("x")
    with pytest.raises(ValueError):
        WarpInput("x", read_volume=lambda: None, read_capture=lambda: None)


def test_capture_file_settings_are_checked_against_the_spec(tmp_path):
    cap = capture_volume(read_volume(BALL), lattice=7, oversample=1)
    with WarpInput("ball.vwc", read_capture=lambda: cap) as w:
        doc, spec = w.load_spec(_spec(tmp_path))
        with pytest.raises(SpecError, match="capture.lattice"):
            w.source(doc, spec)


def test_label_map_warp_of_an_unmoved_lattice_is_the_map(tmp_path):
    lab = np.zeros((20, 20, 20), np.int16)
    lab[4:10, 5:15, 3:12] = 3
    lab[11:17, 2:9, 8:18] = -7
    spec_path = _spec(tmp_path, "version: 1\nunits: voxel\ncapture: {lattice: 6, oversample: 1}"
                                "\nsteps:\n  - move:\n      - {index: [2, 2, 2], by: [0, 0, 0]}\n")
    with WarpInput("lab", read_volume=lambda: Volume(lab), labels=True) as w:
        doc, spec = w.load_spec(spec_path)
        vol = w.source(doc, spec)
        assert w.choice.values == "labels" and w.choice.why == "given"
    warp = LabelMapWarp(vol, doc, spec, WarpOptions(crop=True))
    frames = []
    out, report = warp.compute_frames(lambda f, v: frames.append(v.data.copy()))
    assert out.data.dtype == np.int16 and np.array_equal(out.data, lab)
    assert len(frames) == 2 and all(np.array_equal(f, lab) for f in frames)
    assert report["labels"][3]["output_voxels"] == int((lab == 3).sum())
    with pytest.raises(VolwarpError):
        LabelMapWarp(vol, doc, spec, WarpOptions(dtype="float32"))


def test_handle_report_is_in_world_mm(tmp_path):
    zz, yy, xx = np.mgrid[:24, :24, :24]
    ball = ((xx - 11.5) ** 2 + (yy - 11.5) ** 2 + (zz - 11.5) ** 2 < 36).astype(np.float32)
    vol = Volume(ball, spacing=(2.0, 2.0, 2.0), origin=(10.0, 0.0, 0.0))
    spec_path = _spec(tmp_path, "version: 1\ncapture: {lattice: 7, oversample: 1}\nsteps:\n"
                                "  - drag:\n      - {from: [33, 23, 23], to: [37, 23, 23]}\n"
                                "    radius: 20\n")
    with WarpInput("ball", read_volume=lambda: vol, values="intensity") as w:
        doc, spec = w.load_spec(spec_path)
        cap = w.source(doc, spec)
    warp = IntensityWarp(cap, doc, spec)
    (h,) = warp.handles()
    assert h["step"] == 0 and h["index"] == 0
    np.testing.assert_allclose(h["from"], [33, 23, 23], atol=1e-9)
    np.testing.assert_allclose(h["to"], [37, 23, 23], atol=1e-9)
    assert h["miss_mm"] == pytest.approx(np.linalg.norm(np.subtract(h["reached"], h["to"])))
    assert h["miss_mm"] < 1.0
    assert handle_report(cap, warp.frames) == [h]


def test_exports_of_an_unmoved_warp(tmp_path):
    spec_path = _spec(tmp_path, "version: 1\nunits: voxel\ncapture: {lattice: 6, oversample: 1}"
                                "\nsteps:\n  - move:\n      - {index: [2, 2, 2], by: [0, 0, 0]}\n")
    doc, spec, cap = _opened(spec_path)
    warp = IntensityWarp(cap, doc, spec, WarpOptions(crop=True))
    assert not ExportRequests()
    req = ExportRequests(jacobian=str(tmp_path / "j.nrrd"),
                         displacement=str(tmp_path / "d.nrrd"))
    assert req
    stats = write_exports(req, warp, meta={"volwarp_command": "warp"}, mesh_meta={})
    assert stats["jacobian"]["min"] == pytest.approx(1.0, abs=1e-5)
    assert stats["jacobian"]["max"] == pytest.approx(1.0, abs=1e-5)
    assert stats["displacement"]["folded"] == 0 and stats["displacement"]["voxels"] == 30 ** 3
    det = read_volume(tmp_path / "j.nrrd")
    assert det.meta["volwarp_field"] == "jacobian" and det.shape_xyz == (30, 30, 30)
    for axis in range(3):
        field = read_volume(tmp_path / "d.nrrd", volume_index=axis)
        assert np.nanmax(np.abs(field.data)) < 1e-4


def _block_writer(path):
    """``open_output(header, block)`` writing a NRRD by blocks (what the command passes)."""
    from volwarp_cli.io.blockwrite import committed, open_block_output

    seen = []

    def open_output(header, block):
        seen.append(tuple(block))
        return committed(open_block_output(path, header, chunks_zyx=block))

    return open_output, seen


@pytest.mark.parametrize("block", [None, (5, 7, 6)])
def test_the_operation_by_blocks_writes_the_rendered_volume(tmp_path, block):
    """The warp's operation run by the executor without the command line, the input read
    lazily: by blocks on an engine's tasks (in the block asked, else the operation's
    choice), and whole, the file is render()'s samples."""
    from volwarp_cli import execute
    from volwarp_cli.bspline.capture import capture_source
    from volwarp_cli.engine import open_engine
    from volwarp_cli.io.lazy import LazySource, open_volume_header

    spec_path = _spec(tmp_path)
    doc = load_spec(spec_path, "warp")
    spec = read_warp_spec(doc)
    whole = IntensityWarp(*_opened(spec_path)[2:], doc, spec).compute()
    header, array = open_volume_header(BALL)
    source = LazySource(BALL, array=array)
    s = spec.capture
    cap = capture_source(header, source, lattice=s.lattice, placement=s.placement,
                         oversample=s.oversample, sampling=s.sampling)
    warp = IntensityWarp(cap, doc, spec)
    ran = {}
    for chunked, name in ((True, "b.nrrd"), (False, "m.nrrd")):
        out = tmp_path / name
        target = execute.Target(out, warp.output_header(), whole.data.dtype)
        how = execute.How(chunked=chunked, block=block,
                          open_engine=lambda: open_engine("threads", workers=2))
        ran[chunked] = execute.run(warp.operation(target, source=source), how)
        got = read_volume(out)
        assert np.array_equal(got.data, whole.data) and got.data.dtype == whole.data.dtype
        assert ran[chunked].by_blocks == chunked
    assert ran[False].results is not None and ran[True].results is None  # (small: whole)
    assert ran[True].blocks >= (2 if block else 1)
    if block:
        assert ran[True].block == block


def test_label_map_blocks_equal_the_label_warp(tmp_path):
    """OneShotLabelWarp, without the command line: the same map and per-label report
    as LabelMapWarp, by slabs of the asked depth."""
    from volwarp_cli.engine import open_engine
    from volwarp_cli.io import write_volume
    from volwarp_cli.io.lazy import LazySource, open_volume_header
    from volwarp_cli.warp.label_blocks import OneShotLabelWarp

    lab = np.zeros((20, 21, 22), np.int16)
    lab[4:10, 5:15, 3:12] = 3
    lab[11:17, 2:9, 8:18] = -7
    src = tmp_path / "lab.nrrd"
    write_volume(Volume(lab), src)
    spec_path = _spec(tmp_path, "version: 1\nunits: voxel\ncapture: {lattice: 6, oversample: 1}"
                                "\nsteps:\n  - move:\n      - {index: [2, 2, 2], by: [2, 1, 0]}\n")
    doc = load_spec(spec_path, "warp")
    spec = read_warp_spec(doc)
    want, want_report = LabelMapWarp(Volume(lab), doc, spec).compute()
    header, array = open_volume_header(src)
    warp = OneShotLabelWarp(header, LazySource(src, array=array), doc, spec)
    assert warp.header.shape == want.data.shape
    out = tmp_path / "o.nrrd"
    open_output, seen = _block_writer(out)
    with open_engine("threads", workers=2) as engine:
        report = warp.compute_by_slabs(engine, open_output, 64 << 20, slab=3)
    assert np.array_equal(read_volume(out).data, want.data)
    assert report == want_report
    assert seen == [(3, 21, 22)]
    got, got_report = warp.compute_whole()  # (the map read whole: the same)
    assert np.array_equal(got.data, want.data) and got_report == want_report
    assert seen == [(3, want.data.shape[1], want.data.shape[2])]
