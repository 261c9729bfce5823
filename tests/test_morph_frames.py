"""The morph's frame loop (volwarp_cli.morph.frames), without click or files."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.morph.frames import RenderSettings, morph_frames, shape_box
from volwarp_cli.morph.interpolate import density
from volwarp_cli.morph.pipeline import prepare
from volwarp_cli.morph.spec import AttributeRef, MorphJob, ShapeRef
from volwarp_cli.volume import Volume

N = 24


def _ball(cx: float, r: float) -> np.ndarray:
    z, y, x = np.mgrid[:N, :N, :N].astype(np.float64)
    d = np.sqrt((x - cx) ** 2 + (y - 11.5) ** 2 + (z - 11.5) ** 2)
    return (1 / (1 + np.exp((d - r) / 0.8)) * 200).astype(np.uint8)


@pytest.fixture
def pair():
    kw = {"spacing": (1.0, 1.0, 1.0), "origin": (-3.0, 1.0, 2.0)}
    return Volume(_ball(8.0, 5.0), **kw), Volume(_ball(15.0, 6.0), **kw)


def _job(times=(0.0, 0.5, 1.0), **kw) -> MorphJob:
    return MorphJob(source=ShapeRef("a.nrrd", 100.0), target=ShapeRef("b.nrrd", 100.0),
                    times=list(times), **kw)


def test_frames_are_the_blended_fields_with_their_time(pair):
    src, tgt = pair
    job = _job()
    prep = prepare(job, src, tgt)
    frames = []
    for f in morph_frames(job, prep, src, meta={"volwarp_command": "morph"}):
        frames.append((f.index, f.t, f.volume.data.copy(), dict(f.volume.meta)))
        assert f.mesh is None and f.image is None and f.attributes == {}
    assert [(i, t) for i, t, _, _ in frames] == [(0, 0.0), (1, 0.5), (2, 1.0)]
    for _, t, data, meta in frames:
        assert data.dtype == np.float32
        assert np.array_equal(data, prep.morph.field(t))
        assert meta == {"volwarp_command": "morph", "volwarp_morph_t": f"{t:.9g}"}
    np.testing.assert_array_equal(frames[0][2] < 0, src.data >= 100)
    np.testing.assert_array_equal(frames[2][2] < 0, tgt.data >= 100)


def test_density_frames_and_the_source_range(pair):
    src, tgt = pair
    job = _job(output="density")
    prep = prepare(job, src, tgt)
    (f0, *_) = [f.volume.data.copy() for f in morph_frames(job, prep, src)]
    np.testing.assert_array_equal(f0, density(prep.morph.field(0.0), 1.0))
    job = _job(output="density", density_range="source")
    prep = prepare(job, src, tgt)
    f0 = next(iter(morph_frames(job, prep, src))).volume.data
    assert f0.dtype == np.uint8 and f0.min() == src.data.min() and f0.max() == src.data.max()
    np.testing.assert_array_equal(f0 >= 100, src.data >= 100)


def test_attributes_are_blended_and_cast(pair):
    src, tgt = pair
    job = _job(times=(0.0, 0.5, 1.0))
    job.attributes = [AttributeRef("grey", "a.nrrd", "b.nrrd"),
                      AttributeRef("f", "a.nrrd", "b.nrrd", dtype="float32")]
    attrs = {"grey": (src, tgt), "f": (src, tgt)}
    prep = prepare(job, src, tgt, attrs)
    got = [{k: v.data.copy() for k, v in f.attributes.items()}
           for f in morph_frames(job, prep, src, attrs)]
    assert got[0]["grey"].dtype == np.uint8 and got[0]["f"].dtype == np.float32
    np.testing.assert_array_equal(got[0]["grey"], src.data)
    np.testing.assert_array_equal(got[2]["grey"], tgt.data)
    mid = 0.5 * src.data.astype(np.float64) + 0.5 * tgt.data
    assert np.abs(got[1]["f"] - mid).max() < 1e-3
    assert np.abs(got[1]["grey"] - mid).max() <= 0.5 + 1e-9


def test_meshes_and_renders_share_one_camera(pair):
    src, tgt = pair
    job = _job()
    prep = prepare(job, src, tgt)
    frames = list((f.mesh, f.image) for f in
                  morph_frames(job, prep, src, render=RenderSettings((-90.0, 0.0), (64, 48))))
    for mesh, image in frames:
        assert mesh.n_faces > 0 and image.shape == (48, 64, 3)
    # one camera for all frames: the shapes are where they are (seen from -y, x to the
    # right, the source is left of the target: the picture's content moves, it is not
    # re-centred on each frame)
    cols = [np.flatnonzero((im != im[0, 0]).any(axis=(0, 2))) for _, im in frames]
    assert cols[0].mean() + 5 < cols[1].mean() < cols[2].mean() - 5
    meshes = [f.mesh for f in morph_frames(job, prep, src, meshes=True)]
    assert all(m.n_faces > 0 for m in meshes)
    # the ball of radius 5 at t = 0
    lo, hi = meshes[0].vertices.min(axis=0), meshes[0].vertices.max(axis=0)
    np.testing.assert_allclose(hi - lo, 10.0, atol=1.0)


def test_shape_box_holds_both_shapes(pair):
    src, tgt = pair
    prep = prepare(_job(), src, tgt)
    box = shape_box(prep)
    assert box.shape == (8, 3)
    lo, hi = box.min(axis=0), box.max(axis=0)
    # source centre x = 8 - 3, radius 5; target centre x = 15 - 3, radius 6 (world mm)
    assert lo[0] == pytest.approx(0.0, abs=1.01) and hi[0] == pytest.approx(18.0, abs=1.01)


def test_shape_box_of_empty_shapes_is_an_error(pair):
    src, tgt = pair
    prep = prepare(_job(), src, tgt)
    prep.morph.source = np.ones_like(prep.morph.source)
    prep.morph.target = np.ones_like(prep.morph.target)
    with pytest.raises(VolwarpError, match="neither shape"):
        shape_box(prep)
