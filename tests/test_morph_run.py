"""The morph by blocks' core (volwarp_cli.morph.run.morph_by_blocks), called without click.

The frames it writes by blocks are the in-memory frames
(:func:`~volwarp_cli.morph.frames.morph_frames`) bit for bit; what it refuses
it refuses with the right error class and message, before any work, or
raises the in-memory refusal it stands in for.
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest

from volwarp_cli.engine import open_engine
from volwarp_cli.errors import OutOfMemoryError, VolwarpError
from volwarp_cli.execute import How
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.io.lazy import LazySource, open_volume_header
from volwarp_cli.morph.frames import morph_frames
from volwarp_cli.morph.outputs import MorphOutputs
from volwarp_cli.morph.pipeline import prepare
from volwarp_cli.morph.run import (
    BlocksRefused,
    FrameWrite,
    MorphPlan,
    morph_by_blocks,
    morph_note,
    plan_morph,
    run_morph,
)
from volwarp_cli.morph.spec import AttributeRef, MorphJob, ShapeRef
from volwarp_cli.volume import Volume

GEOMETRY = dict(spacing=np.array([0.8, 0.9, 1.1]), origin=np.array([10.0, -5.0, 3.0]))


@pytest.fixture
def shapes(tmp_path):
    """A binary ball and box, two smooth int16 blobs and a float attribute pair (files)."""
    z, y, x = np.meshgrid(*[np.linspace(-1, 1, n) for n in (17, 21, 15)], indexing="ij")
    data = {
        "ball": (x * x + y * y + z * z < 0.5).astype(np.uint8),
        "box": ((np.abs(x) < 0.6) & (np.abs(y) < 0.3) & (np.abs(z) < 0.7)).astype(np.uint8),
        "blob_a": (1000 * np.exp(-((x - 0.2) ** 2 + y * y + z * z) / 0.2)).astype(np.int16),
        "blob_b": (900 * np.exp(-(x * x + (y - 0.2) ** 2 + z * z) / 0.15)).astype(np.int16),
        "heat_a": (x + 2 * y).astype(np.float32),
        "heat_b": (z * z * 40).astype(np.float32),
    }
    paths = {}
    for name, values in data.items():
        paths[name] = tmp_path / f"{name}.nrrd"
        write_volume(Volume(values, **GEOMETRY), paths[name])
    return paths


def _lazy(path):
    header, array = open_volume_header(path)
    return header, LazySource(path, array=array)


def _outputs(job, tmp_path):
    return MorphOutputs(job, str(tmp_path / "b_{i}.nrrd"))


def _run(job, tmp_path, *, engine_opened=None, **kw):
    """Every frame of ``job`` by blocks into ``tmp_path/b_{i}.nrrd``: the yielded frames."""

    @contextlib.contextmanager
    def engine():
        if engine_opened is not None:
            engine_opened.append(True)
        with open_engine("synchronous") as e:
            yield e

    attrs = {a.name: (_lazy(a.source), _lazy(a.target)) for a in job.attributes}
    gen = morph_by_blocks(job, _lazy(job.source.path), _lazy(job.target.path), attrs,
                          outputs=_outputs(job, tmp_path), meta={"who": "test"},
                          how=How(block=(5, 8, 6), open_engine=engine), **kw)
    return list(gen)


def _job(shapes, source="ball", target="box", iso=0.5, **kw):
    return MorphJob(source=ShapeRef(shapes[source], iso, "above"),
                    target=ShapeRef(shapes[target], iso, "above"), **kw)


@pytest.mark.parametrize("case", ["sdf", "band-density", "attribute"])
def test_frames_by_blocks_are_the_in_memory_frames(shapes, tmp_path, case):
    job = {
        "sdf": lambda: _job(shapes, times=[0.0, 0.3, 1.0]),
        "band-density": lambda: _job(shapes, "blob_a", "blob_b", iso=300.0, times=[0.0, 0.6],
                                     output="density", max_distance=2.5),
        "attribute": lambda: _job(shapes, times=[0.0, 0.4, 1.0], attributes=[
            AttributeRef("heat", shapes["heat_a"], shapes["heat_b"])]),
    }[case]()
    yielded = _run(job, tmp_path)
    assert [f.index for f in yielded] == list(range(len(job.times)))

    source, target = read_volume(job.source.path), read_volume(job.target.path)
    attrs = {a.name: (read_volume(a.source), read_volume(a.target)) for a in job.attributes}
    prepared = prepare(job, source, target, attrs)
    meta = {"volwarp_morph": morph_note(job, prepared.rules),
            "who": "test"}
    for frame in morph_frames(job, prepared, source, attrs, meta=meta):
        written = read_volume(tmp_path / f"b_{frame.index}.nrrd")
        assert written.data.dtype == frame.volume.data.dtype
        assert np.array_equal(written.data, frame.volume.data)
        assert np.allclose(written.index_to_world_matrix, frame.volume.index_to_world_matrix)
        for key, value in frame.volume.meta.items():
            assert written.meta[key] == value
        for name, vol in frame.attributes.items():
            assert np.array_equal(read_volume(tmp_path / f"b_{frame.index}_{name}.nrrd").data,
                                  vol.data)
    # the frames move from source to target
    assert not np.array_equal(read_volume(tmp_path / "b_0.nrrd").data,
                              read_volume(tmp_path / f"b_{len(job.times) - 1}.nrrd").data)


def test_a_landmark_warp_is_refused_before_any_work(shapes, tmp_path):
    job = _job(shapes, times=[0.0, 1.0], grid="source",
               warp_source_points=np.array([[12.0, -9.0, 10.0]]),
               warp_target_points=np.array([[13.0, -9.0, 10.0]]))
    opened = []
    with pytest.raises(BlocksRefused, match=r"^--chunked does not run this morph by blocks: "
                                            r"its landmark warp's .* block by block \(without "
                                            r"--chunked it runs in memory\)$"):
        _run(job, tmp_path, engine_opened=opened)
    assert not opened and not list(tmp_path.glob("b_*"))


def test_the_run_is_decided_before_any_sample_is_read(shapes, tmp_path, monkeypatch):
    """By the in-memory morph's memory against the budget: no try, no catch."""
    from volwarp_cli import memory
    from volwarp_cli.io import read_volume as real_read

    job = _job(shapes, times=[0.0, 1.0])
    outputs = _outputs(job, tmp_path)
    read = []
    monkeypatch.setattr("volwarp_cli.io.read_volume", lambda *a, **k: read.append(a) or
                        real_read(*a, **k))
    assert not plan_morph(job, outputs, FrameWrite(), None).by_blocks
    monkeypatch.setattr(memory, "process_rss", lambda: 0)
    monkeypatch.setattr("volwarp_cli.execute.MIN_BLOCK_BUDGET", 64 << 10)
    with memory.use_memory_limit(150 << 10):
        plan = plan_morph(job, outputs, FrameWrite(), None)
        assert plan.by_blocks and "needs" in plan.in_memory_refusal
        with pytest.raises(OutOfMemoryError, match="needs"):  # --no-chunked
            plan_morph(job, outputs, FrameWrite(), False)
        assert plan_morph(job, outputs, FrameWrite(), True).in_memory_refusal is None
    assert not read  # (the headers only: nothing read whole)


def test_a_landmark_warp_that_does_not_fit_is_refused_with_both_reasons(shapes, tmp_path,
                                                                         monkeypatch):
    """Unasked blocks that cannot run: one refusal with both reasons, before any work."""
    from volwarp_cli import memory

    job = _job(shapes, times=[0.0, 1.0], grid="source",
               warp_source_points=np.array([[12.0, -9.0, 10.0]]),
               warp_target_points=np.array([[13.0, -9.0, 10.0]]))
    outputs = _outputs(job, tmp_path)
    monkeypatch.setattr(memory, "process_rss", lambda: 0)
    monkeypatch.setattr("volwarp_cli.execute.MIN_BLOCK_BUDGET", 64 << 10)
    with memory.use_memory_limit(150 << 10), pytest.raises(OutOfMemoryError) as info:
        plan_morph(job, outputs, FrameWrite(), None)
    message = str(info.value)
    assert message.startswith("a morph on a 15x21x17 grid needs ")
    assert message.endswith(", and by blocks: a morph with a landmark warp runs in memory only")
    assert not list(tmp_path.glob("b_*")) and not list(tmp_path.glob(".*"))


def test_what_blocks_refuse_completes_the_in_memory_refusal(shapes, tmp_path):
    """A refusal found on the block path (an output written whole) after an unasked switch."""
    job = _job(shapes, times=[0.0, 1.0])
    outputs = MorphOutputs(job, str(tmp_path / "b_{i}.nrrd"))
    plan = MorphPlan(True, in_memory_refusal="a morph on a 15x21x17 grid needs 1 TiB")
    outputs.frames[1] = str(tmp_path / "b_1.nii.gz")  # (NIfTI: written whole)
    with pytest.raises(OutOfMemoryError) as info:
        run_morph(job, outputs, plan, meta={}, write_kw={},
                  how=How(open_engine=lambda: open_engine("synchronous")))
    assert str(info.value).startswith("a morph on a 15x21x17 grid needs 1 TiB, and by blocks: ")
    assert "b_1.nii.gz" in str(info.value)
    assert not list(tmp_path.glob("b_*")) and not list(tmp_path.glob(".*"))


@pytest.mark.parametrize("spec", [False, True])
def test_smooth_samples_without_a_band_are_refused_in_morph_terms(shapes, tmp_path, spec):
    """The distance's refusal names the morph's settings, not `volwarp distance --surface`."""
    job = _job(shapes, "blob_a", "blob_b", iso=300.0, times=[0.0, 1.0])
    if spec:
        job.doc = object()  # (a spec's job carries its document)
    with pytest.raises(VolwarpError) as info:
        _run(job, tmp_path)
    message = str(info.value)
    assert message.startswith(f"{shapes['blob_a']}: smooth samples")
    assert "--surface" not in message and "surface: voxel" in message
    assert ("max_distance: D in the spec" in message) == spec
    assert ("--max-distance D" in message) == (not spec)
    assert not list(tmp_path.glob("b_*")) and not list(tmp_path.glob(".*"))


def _two_shapes(tmp_path):
    from volwarp_cli import api
    from volwarp_cli.volume import Volume

    z, y, x = np.mgrid[:160, :160, :160]
    ball = (((x - 80) / 50) ** 2 + ((y - 80) / 40) ** 2 + ((z - 80) / 45) ** 2 <= 1)
    block = (abs(x - 80) < 40) & (abs(y - 80) < 50) & (abs(z - 80) < 30)
    api.write(Volume(ball.astype(np.uint8) * 100), tmp_path / "a.nrrd")
    api.write(Volume(block.astype(np.uint8) * 100), tmp_path / "b.nrrd")
    spec = tmp_path / "m.yaml"
    spec.write_text("version: 1\nsource: {volume: a.nrrd, iso: 50}\n"
                    "target: {volume: b.nrrd, iso: 50}\ngrid: union\nframes: 2\n")
    return spec


def _morph(spec, out, limit):
    from peaks import volwarp_peak

    return volwarp_peak("morph", "--spec", spec, "-o", out, "--memory-limit", limit,
                        timeout=120)


def test_an_in_memory_morph_is_not_refused_halfway_by_its_resampling(tmp_path):
    """A 164^3 frame grid's resampling was counted whole (its coordinates 32 bytes a voxel,
    135 MiB) where it goes by parts of 2^20 voxels: the morph the plan chose in memory (its
    measured need) was refused at `target resampled onto the frame grid`, its work half done,
    at 250M and 300M; it runs at 210M, under its limit."""
    spec = _two_shapes(tmp_path)
    code, err, peak = _morph(spec, tmp_path / "f_{i}.nrrd", "210M")
    assert code == 0, err
    assert peak <= 210 << 20, f"{peak / 2**20:.1f} MiB"
    assert (tmp_path / "f_1.nrrd").exists()


def test_a_morph_whose_store_frames_cannot_be_written_is_refused_before_any_work(tmp_path):
    """The in-memory morph counted no write, nor the libraries it loads (scipy's ndimage,
    zarr): at 230M it made every field and frame, then its first OME-Zarr frame's write was
    refused. Now the plan refuses it (this grid has no form by blocks), one line, nothing
    written."""
    spec = _two_shapes(tmp_path)
    code, err, peak = _morph(spec, tmp_path / "f_{i}.ome.zarr", "230M")
    assert code == 1
    line = err.strip().splitlines()[-1]
    assert line.startswith("volwarp: error: a morph on a 164x164x164 grid needs "), line
    assert not list(tmp_path.glob("f_*"))
    assert peak <= 230 << 20
