"""The label-map rule (:mod:`volwarp_cli.labelmap`): what it takes for labels, what not.

A reviewer's cases, each wrong before:

1. Antialiased (smooth-edged) densities are no label maps: volwarp's own
   intensity warp of the bundled ball (132 values) and a supersampled ball
   were taken for labels, so a default warp of them ran a label pass per
   value and their distance demanded a label.
2. Small labelled structures are label maps (landmarks of 2x2x2 voxels,
   1-voxel-wide vessels: a label/0 pair counted as unequal), and so are
   segmentations stored as integer-valued floats (nibabel's, MONAI's).

Every real scan stays out (the bundled ones, nibabel's and pydicom's test
files, CTs with -1024 air, windowed, a distance field), and read box by box the
rule gives the whole array's answer.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage as ndi

from volwarp_cli.box import Box
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.labelmap import (
    label_map_hint,
    looks_like_labels,
    looks_like_labels_by_blocks,
    scan_labels,
    value_counts,
)
from volwarp_cli.volume import Volume

DATA = Path(__file__).parent / "data"
SPECS = Path(__file__).parent.parent / "specs"
STILL = "version: 1\ncapture: {lattice: 5}\nsteps: []\n"


def supersampled_ball(n=30, radius=10.3, k=3, value=255) -> np.ndarray:
    """A ball rendered with k^3 samples a voxel: its edge voxels have the covered share."""
    g = (np.arange(n * k) + 0.5) / k - n / 2
    inside = (g[:, None, None] ** 2 + g[None, :, None] ** 2 + g[None, None, :] ** 2
              <= radius * radius)
    cover = inside.reshape(n, k, n, k, n, k).mean(axis=(1, 3, 5))
    return np.round(cover * value).astype(np.uint8)


def landmarks(count=20, shape=(60, 64, 64), seed=3) -> np.ndarray:
    """``count`` cubes of 2x2x2 voxels, ids 10 ... 200, in a large 0 background."""
    rng = np.random.default_rng(seed)
    out = np.zeros(shape, np.uint8)
    for i in np.linspace(10, 200, count).astype(int):
        z, y, x = (int(rng.integers(0, s - 2)) for s in shape)
        out[z:z + 2, y:y + 2, x:x + 2] = i
    return out


def vessels(shape=(48, 48, 48), seed=4) -> np.ndarray:
    """Three 1-voxel-wide random walks (6-connected), ids 1, 2, 3."""
    rng = np.random.default_rng(seed)
    out = np.zeros(shape, np.uint8)
    for label in (1, 2, 3):
        p = np.array(shape) // 2
        for _ in range(300):
            out[tuple(p)] = label
            axis = int(rng.integers(0, 3))
            p[axis] = np.clip(p[axis] + rng.choice([-1, 1]), 0, shape[axis] - 1)
    return out


def segmentation(shape=(30, 32, 34), labels=4, seed=0) -> np.ndarray:
    """A piecewise-constant map: 0 and ``labels`` ids, the argmax of smoothed noise."""
    rng = np.random.default_rng(seed)
    fields = np.stack([ndi.gaussian_filter(rng.random(shape), 2.5) for _ in range(labels + 1)])
    return np.argmax(fields, axis=0).astype(np.uint8)


def ct(seed=1, window=None) -> np.ndarray:
    """A CT: -1024 HU air around a noisy body with lungs and a bone (``window``: clipped)."""
    rng = np.random.default_rng(seed)
    z, y, x = np.mgrid[:24, :80, :80]
    body = ((x - 40) ** 2 / 34 ** 2 + (y - 40) ** 2 / 22 ** 2) < 1
    lung = (((x - 25) ** 2 + (y - 38) ** 2) < 80) | (((x - 55) ** 2 + (y - 38) ** 2) < 80)
    bone = ((x - 40) ** 2 + (y - 52) ** 2) < 25
    out = np.full(body.shape, -1024.0)
    out[body] = rng.normal(40, 30, body.sum())
    out[lung & body] = rng.normal(-850, 40, (lung & body).sum())
    out[bone] = rng.normal(900, 200, bone.sum())
    out = np.clip(out, -1024, 3071) if window is None else np.clip(out, *window)
    return out.astype(np.int16)


def voronoi_atlas(n=1000, shape=(40, 48, 48), seed=2) -> np.ndarray:
    """A parcellation of n cells (ids 1 ... n) inside an ellipsoid: more than 256 labels."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    z, y, x = np.indices(shape)
    _, cell = cKDTree(rng.random((n, 3)) * shape).query(np.stack([z, y, x], -1).reshape(-1, 3))
    out = (cell + 1).reshape(shape).astype(np.int16)
    c = (np.array(shape) - 1) / 2
    out[((z - c[0]) / c[0]) ** 2 + ((y - c[1]) / c[1]) ** 2 + ((x - c[2]) / c[2]) ** 2 > 1] = 0
    return out


# -- 1. antialiased densities ---------------------------------------------------------------

def test_volwarps_own_antialiased_warp_is_not_a_label_map(run, tmp_path):
    """The modelling chain: the ball warped as intensities is a smooth-edged density (132
    values). It was taken for a label map: `info` said so, a default warp of it ran 131
    label passes, and `distance --iso 100` exited 2 (the ids' level refused)."""
    w1 = tmp_path / "w1.nrrd"
    res = run("warp", DATA / "ball_30_uint8.nrrd", "--spec", SPECS / "warp-ball.yaml",
              "--values", "intensity", "-o", w1)
    assert res.code == 0, res.stderr
    data = read_volume(w1).data
    assert len(np.unique(data)) > 100
    assert not looks_like_labels(data) and label_map_hint(data) is None
    res = run("info", w1)
    assert res.code == 0 and "label map" not in res.stdout
    spec = tmp_path / "still.yaml"
    spec.write_text(STILL)
    res = run("warp", w1, "--spec", spec, "-o", tmp_path / "again.nrrd", "--json")
    assert res.code == 0, res.stderr
    assert json.loads(res.stdout)["values"] == "intensity"
    res = run("distance", w1, "--iso", "100", "-o", tmp_path / "d.nrrd")
    assert res.code == 0, res.stderr


@pytest.mark.parametrize("n, radius, k", [(30, 10.3, 3), (40, 14.2, 4)])
def test_supersampled_balls_are_not_label_maps(n, radius, k):
    ball = supersampled_ball(n, radius, k)
    assert 10 < len(np.unique(ball)) < 100
    assert not looks_like_labels(ball) and label_map_hint(ball) is None
    assert looks_like_labels((ball > 127).astype(np.uint8))  # its mask is one


# -- 2a. small structures -------------------------------------------------------------------

def test_landmarks_and_thin_vessels_are_label_maps(run, tmp_path):
    marks = landmarks()
    assert len(np.unique(marks)) == 21
    assert looks_like_labels(marks)
    assert label_map_hint(marks)["labels"] == 21
    assert looks_like_labels(vessels())
    path = tmp_path / "marks.nrrd"
    write_volume(Volume(marks), path)
    res = run("info", path)
    assert "looks like a label map (21 distinct values" in res.stdout


# -- 2b. integer-valued floats --------------------------------------------------------------

def test_integer_valued_floats_are_candidates():
    seg = segmentation()
    for dtype in (np.float32, np.float64):
        f = seg.astype(dtype)
        assert looks_like_labels(f) and label_map_hint(f) == label_map_hint(seg)
        looks, values, counts = scan_labels(f)
        assert looks and np.array_equal(values, np.unique(seg))
        assert counts.sum() == seg.size
    f = seg.astype(np.float32)
    f[3, 4, 5] = 1.5  # one fraction: no ids
    assert not looks_like_labels(f) and scan_labels(f) == (False, None, None)
    f[3, 4, 5] = np.nan
    assert not looks_like_labels(f)
    f[3, 4, 5] = 2.0 ** 25  # beyond float32's exact integers
    assert not looks_like_labels(f)


def test_a_float_with_fractions_is_read_no_further_than_a_few_rows():
    """A scan's fractions in the middle rows end the count before any box is read; where
    those rows are integers (a background), no further than the first box with one."""
    reads = []

    class Source:
        shape, dtype = (64, 32, 32), np.dtype(np.float32)

        def __init__(self, data):
            self.data = data

        def __getitem__(self, key):
            part = self.data[key]
            reads.append(part.size)
            return part

    scan = np.full((64, 32, 32), 0.5, np.float32)
    assert scan_labels(Source(scan), box_voxels=32 * 32 * 8) == (False, None, None)
    assert reads == [16 * 32]  # (the middle plane's 16 central rows)
    reads.clear()
    scan[32] = 0.0  # the middle plane integers: the boxes decide, the first one here
    assert scan_labels(Source(scan), box_voxels=32 * 32 * 8) == (False, None, None)
    assert reads == [16 * 32, 32 * 32 * 8]


# -- 1b. densities aligned with the axes (test 3) --------------------------------------------

def smooth_step(n=48, width=20, axis=2) -> np.ndarray:
    """0 to 255 across ``width`` voxels along ``axis``: each level a flat region one voxel thick."""
    ramp = np.clip((np.arange(n) - (n - width) / 2) / width, 0, 1) * 255
    shape = [1, 1, 1]
    shape[axis] = n
    return np.broadcast_to(np.round(ramp).astype(np.uint8).reshape(shape), (n, n, n)).copy()


def rounded_distance() -> np.ndarray:
    z, y, x = np.mgrid[:40, :40, :40]
    m = ((x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2) < 100
    field = ndi.distance_transform_edt(~m) - ndi.distance_transform_edt(m)
    return np.round(field - field.min()).astype(np.int16)


@pytest.mark.parametrize("name, make", [
    ("smooth step along x", lambda: smooth_step(axis=2)),
    ("smooth step along z", lambda: smooth_step(axis=0)),
    ("steeper step along y", lambda: smooth_step(width=16, axis=1)),
    ("integer-rounded distance field", rounded_distance),
])
def test_densities_aligned_with_the_axes_are_not_label_maps(name, make):
    """Each level of such a density is a flat region one voxel thick, so tests 1 and 2 took
    them for labels (the tree-wind example's leaf map: `distance` measured the surface of
    "ids" 1, 2, 3, ... of a 0..255 step); their levels lie between their neighbours'."""
    data = make()
    assert len(np.unique(data)) >= 16
    assert not looks_like_labels(data), name
    assert label_map_hint(data) is None
    # by boxes of a few planes: the same answer
    assert not looks_like_labels_by_blocks(data, list(Box.from_shape(data.shape).blocks((7, 40, 40))))


def head_layers() -> np.ndarray:
    """A head at 3 mm: scalp 1 (2 voxels), skull 2 and CSF 3 (1 voxel each), brain 4."""
    z, y, x = np.mgrid[:64, :72, :60].astype(float)
    out = np.zeros(z.shape, np.uint8)
    a, b, c = 26, 32, 28
    for label, step in ((1, 0), (2, 2), (3, 1), (4, 1)):
        a, b, c = a - step, b - step, c - step
        out[((x - 30.3) / a) ** 2 + ((y - 36.2) / b) ** 2 + ((z - 32.1) / c) ** 2 < 1] = label
    return out


def nested_shell() -> np.ndarray:
    """A core 3, a shell 2 one voxel thick around it, and 1 around that: ids in thin order."""
    z, y, x = np.mgrid[:72, :72, :72]
    r = np.sqrt((x - 35.7) ** 2 + (y - 35.9) ** 2 + (z - 35.8) ** 2)
    out = np.zeros(r.shape, np.uint8)
    out[r < 32], out[r < 31], out[r < 30] = 1, 2, 3
    return out


def otsu_classes(classes: int) -> np.ndarray:
    sitk = pytest.importorskip("SimpleITK")
    image = sitk.ReadImage(str(DATA / "mri_t1_head_coronal_2x2x3mm.nrrd"))  # (2x2x3 mm)
    return sitk.GetArrayFromImage(sitk.OtsuMultipleThresholds(
        image, numberOfThresholds=classes - 1, labelOffset=0, numberOfHistogramBins=32))


@pytest.mark.parametrize("name, make", [
    ("head in thin layers", head_layers), ("a shell one voxel thick", nested_shell),
    ("Otsu, 7 classes of the bundled T1", lambda: otsu_classes(7)),
])
def test_a_few_ordered_labels_in_thin_layers_stay_label_maps(name, make):
    """Their layers one voxel thick lie between a lower and a higher id as a density's levels
    do (graded crossings 0.35 to 0.75 a voxel, a review measured): test 3 is for what has
    levels to step through, 16 values or more, and these have 3 to 7."""
    data = make()
    assert len(np.unique(data)) < 16
    assert looks_like_labels(data), name


def test_a_step_is_a_density_in_distance_and_a_label_map_still_a_label_map(run, tmp_path):
    write_volume(Volume(smooth_step()), tmp_path / "step.nrrd")
    res = run("distance", tmp_path / "step.nrrd", "--iso", "127.5", "-o", tmp_path / "d.nrrd")
    assert res.code == 0, res.stderr  # (a label map: --iso refused, exit 2)
    out = read_volume(tmp_path / "d.nrrd")
    assert "values=intensity" in out.meta["volwarp_distance"]
    field = out.data
    # the level 127.5 is the plane x = 23.5 (voxel centres): a signed distance along x
    x = np.arange(48)
    assert np.allclose(field[5, 7], np.abs(x - 23.5) * np.sign(23.5 - x), atol=0.51)
    labels = segmentation()
    write_volume(Volume(labels), tmp_path / "seg.nrrd")
    res = run("distance", tmp_path / "seg.nrrd", "-o", tmp_path / "ds.nrrd")
    assert res.code == 0, res.stderr
    assert "values=labels" in read_volume(tmp_path / "ds.nrrd").meta["volwarp_distance"]


# -- scans stay out -------------------------------------------------------------------------

def _nibabel(name):
    nib = pytest.importorskip("nibabel")
    path = Path(nib.__file__).parent / "tests" / "data" / name
    data = np.asanyarray(nib.load(str(path)).dataobj)
    if data.ndim == 4:
        data = data[..., 0]
    return np.ascontiguousarray(data.transpose(2, 1, 0)).astype(data.dtype.newbyteorder("="))


def _pydicom(name, hu=False):
    pydicom = pytest.importorskip("pydicom")
    from pydicom.data import get_testdata_file

    ds = pydicom.dcmread(get_testdata_file(name))
    data = ds.pixel_array
    if hu:
        data = (data * float(ds.RescaleSlope) + float(ds.RescaleIntercept)).astype(np.int16)
    return data if data.ndim == 3 else data[None]


def _ct_small_fov():
    """CT_small in HU with -1024 outside a circular field of view (the CT's padding)."""
    data = _pydicom("CT_small.dcm", hu=True)
    yy, xx = np.mgrid[:128, :128]
    return np.where((yy - 64) ** 2 + (xx - 64) ** 2 > 60 ** 2, -1024, data).astype(np.int16)


def _distance_field():
    z, y, x = np.mgrid[:40, :40, :40]
    m = ((x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2) < 100
    return (ndi.distance_transform_edt(~m) - ndi.distance_transform_edt(m)).astype(np.float32)


SCANS = {
    "colin27": lambda: read_volume(DATA / "mri_colin27_brain_1mm.nrrd").data,
    "t1 head": lambda: read_volume(DATA / "mri_t1_head_coronal_2x2x3mm.nrrd").data,
    "block ramp": lambda: read_volume(DATA / "block_int16_aniso.nrrd").data,
    "anatomical.nii": lambda: _nibabel("anatomical.nii"),
    "example4d": lambda: _nibabel("example4d.nii.gz"),
    "CT_small": lambda: _pydicom("CT_small.dcm"),
    "MR_small": lambda: _pydicom("MR_small.dcm"),
    "emri_small": lambda: _pydicom("emri_small.dcm"),
    "CT_small in HU, -1024 outside": _ct_small_fov,
    "CT -1024 air": ct,
    "CT windowed": lambda: ct(window=(-160, 240)),  # (taken for labels before)
    "CT windowed, float64": lambda: ct(window=(-160, 240)).astype(np.float64),
    "distance field": _distance_field,
    "smoothed mask": lambda: np.round(ndi.gaussian_filter(
        (_distance_field() < 2) * 255.0, 2.0)).astype(np.uint8),
}


@pytest.mark.parametrize("name", list(SCANS))
def test_scans_are_not_label_maps(name):
    data = SCANS[name]()
    assert not looks_like_labels(data)
    assert label_map_hint(data) is None


# -- label maps are ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def kmeans():
    """SimpleITK's k-means (4 classes) of the bundled T1 head: a third-party label map."""
    sitk = pytest.importorskip("SimpleITK")
    data = read_volume(DATA / "mri_t1_head_coronal_2x2x3mm.nrrd").data.astype(np.uint8)
    image = sitk.GetImageFromArray(data)
    return sitk.GetArrayFromImage(sitk.ScalarImageKmeans(image, [10, 60, 120, 200], False)
                                  ).astype(np.uint8)


def test_real_and_varied_label_maps_are(kmeans):
    rng = np.random.default_rng(0)
    ids = np.concatenate([[0], rng.choice(np.arange(1, 60000), 3, replace=False)])
    cases = {"k-means": kmeans, "ids permuted": ids.astype(np.uint16)[kmeans],
             "no 0": kmeans + 1, "float32": kmeans.astype(np.float32),
             "atlas": voronoi_atlas()}
    assert len(np.unique(cases["atlas"])) > 256
    for name, data in cases.items():
        assert looks_like_labels(data), name


# -- by blocks: the whole array's answer ---------------------------------------------------

KINDS = ["labels", "noise", "antialiased", "float labels", "float fraction"]


def _sample(kind, rng, shape):
    if kind == "labels":
        block = rng.integers(0, 6, (max(1, shape[0] // 3), max(1, shape[1] // 2), 1))
        return np.kron(block, np.ones((3, 2, shape[2]), int))[:shape[0], :shape[1]] * 17
    if kind == "noise":
        return rng.integers(0, 9, shape)
    if kind == "antialiased":
        n = max(shape)
        ball = supersampled_ball(n, n / 3, 2)
        return ball[:shape[0], :shape[1], :shape[2]]
    data = _sample("labels", rng, shape).astype(np.float32)
    if kind == "float fraction":
        data.flat[int(rng.integers(0, data.size))] += 0.25
    return data


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(KINDS), seed=st.integers(0, 2 ** 31 - 1),
       block=st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 9)),
       box_voxels=st.sampled_from([7, 100, 1 << 22]))
def test_by_blocks_is_the_whole_arrays_answer(kind, seed, block, box_voxels):
    rng = np.random.default_rng(seed)
    shape = tuple(int(v) for v in rng.integers(1, 24, 3))
    data = np.ascontiguousarray(_sample(kind, rng, shape))
    want = looks_like_labels(data)
    assert looks_like_labels_by_blocks(data, Box.from_shape(data.shape).blocks(block)) == want
    assert scan_labels(data, box_voxels=box_voxels)[0] == want


@settings(max_examples=60, deadline=None)
@given(dtype=st.sampled_from(["uint8", "int8", "uint16", "int16", "int32", "int64", "bool",
                              "float32"]),
       lo=st.integers(-300, 300), span=st.sampled_from([1, 2, 3, 8, 9, 40, 300, 70000]),
       shape=st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 9)),
       seed=st.integers(0, 2**16))
def test_value_counts_is_numpys_unique(dtype, lo, span, shape, seed):
    """Every way value_counts counts (a comparison a value up to 8 values, a table, a sort)."""
    info = np.iinfo(dtype) if dtype not in ("bool", "float32") else None
    lo, hi = (0, 1) if dtype == "bool" else (lo, lo + span - 1)
    if info is not None:
        lo = min(max(lo, int(info.min)), int(info.max))
        hi = max(lo, min(hi, int(info.max)))
    data = np.random.default_rng(seed).integers(lo, hi + 1, size=shape).astype(dtype)
    values, counts = value_counts(data)
    want_values, want_counts = np.unique(data.astype(np.int64), return_counts=True)
    assert values.dtype == counts.dtype == np.int64
    assert np.array_equal(values, want_values) and np.array_equal(counts, want_counts)
