"""What `volwarp warp` does where its user says nothing (issue 28, items 2, 3 and 7).

- A label map (as `volwarp info` hints) is warped as labels: no invented ids
  (a frog-like tissue map warped as intensities wrote ids it does not have).
- A scan comes back on its own grid (a 16x16x5 CT came out 38x16x5), and where
  nothing lands it gets its border value (-1024 HU), not 0 (water).
- A capture that resamples unmoved voxels says so, once.
- Points and meshes go through a warp without a volume, and none is computed.
"""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from volwarp_cli.border import border_label, border_value
from volwarp_cli.errors import VolwarpError
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume
from volwarp_cli.warp.defaults import choose_values, output_grid

#: the frog-like map's ids: far apart, so that a blend of two is a third one's id
IDS = (1, 5, 17, 23, 40)


def frog_like() -> Volume:
    """Tissues as touching blobs with scattered ids (0 the background)."""
    z, y, x = np.mgrid[:20, :24, :28].astype(float)
    lab = np.zeros((20, 24, 28), np.uint8)
    blobs = [(17, (10, 12, 10, 6)), (23, (10, 12, 17, 6)), (5, (6, 8, 14, 4)),
             (40, (14, 16, 14, 4)), (1, (10, 12, 14, 2))]
    for label, (cz, cy, cx, r) in blobs:
        lab[(z - cz) ** 2 + (y - cy) ** 2 + (x - cx) ** 2 <= r * r] = label
    return Volume(lab, spacing=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0))


def ct_like() -> Volume:
    """A 16x16x5 CT: air (-1024) around a body whose values vary voxel to voxel."""
    rng = np.random.default_rng(1)
    data = np.full((5, 16, 16), -1024, np.int16)
    yy, xx = np.mgrid[:16, :16]
    body = (yy - 7.5) ** 2 + (xx - 7.5) ** 2 <= 36
    for k in range(5):
        data[k][body] = rng.integers(400, 700, size=int(body.sum()))
    return Volume(data, spacing=(1.0, 1.0, 2.0), origin=(-10.0, 5.0, 3.0))


FROG_SPEC = ("version: 1\ncapture: {lattice: 6}\nsteps:\n  - drag:\n"
             "      - {from: [14, 12, 10], to: [18, 14, 11]}\n")
# the body's right side pulled 8 mm to the patient's left: part of it leaves the 16 mm box
CT_SPEC = ("version: 1\ncapture: {lattice: 5}\nsteps:\n  - drag:\n"
           "      - {from: [0, 12, 7], to: [8, 12, 7]}\n")


@pytest.fixture
def files(tmp_path):
    frog, ct = tmp_path / "frog.nrrd", tmp_path / "ct.nrrd"
    write_volume(frog_like(), frog)
    write_volume(ct_like(), ct)
    fspec, cspec = tmp_path / "frog.yaml", tmp_path / "ct.yaml"
    fspec.write_text(FROG_SPEC)
    cspec.write_text(CT_SPEC)
    return {"frog": frog, "ct": ct, "frog_spec": fspec, "ct_spec": cspec, "dir": tmp_path}


def _ids(path) -> set[int]:
    return {int(v) for v in np.unique(read_volume(path).data)}


# -- item 2: label maps are labels ----------------------------------------------------------

def test_a_label_map_warped_with_defaults_invents_no_ids(run, files):
    """The frog-like map: as intensities the warp writes ids it does not have; with the
    defaults every output id is one of the input's, -v and --json say why, and by
    blocks the file is the same bytes."""
    d = files["dir"]
    res = run("warp", files["frog"], "--spec", files["frog_spec"], "-o", d / "old.nrrd",
              "--values", "intensity")
    assert res.code == 0, res.stderr
    invented = _ids(d / "old.nrrd") - {0, *IDS}
    assert invented  # (what the defaults did before)
    res = run("warp", files["frog"], "--spec", files["frog_spec"], "-o", d / "new.nrrd",
              "-v", "--json")
    assert res.code == 0, res.stderr
    assert _ids(d / "new.nrrd") <= {0, *IDS}
    assert "values: labels (looks like a label map: 6 labels)" in res.stderr
    summary = json.loads(res.stdout)
    assert summary["values"] == "labels"
    assert summary["values_why"] == "looks like a label map: 6 labels"
    assert {r["label"] for r in summary["labels"]} == set(IDS)
    res = run("warp", files["frog"], "--spec", files["frog_spec"], "-o", d / "blocks.nrrd",
              "--chunked", "--json")
    assert res.code == 0, res.stderr
    assert (d / "blocks.nrrd").read_bytes() == (d / "new.nrrd").read_bytes()
    assert json.loads(res.stdout)["values_why"] == "looks like a label map: 6 labels"
    # --labels and the spec's values: labels are the rule's answer given
    res = run("warp", files["frog"], "--spec", files["frog_spec"], "-o", d / "given.nrrd",
              "--labels", "--json")
    assert res.code == 0 and json.loads(res.stdout)["values_why"] == "given"
    assert (d / "given.nrrd").read_bytes() == (d / "new.nrrd").read_bytes()
    spec = d / "intensity.yaml"
    spec.write_text(FROG_SPEC.replace("version: 1\n", "version: 1\nvalues: intensity\n"))
    res = run("warp", files["frog"], "--spec", spec, "-o", d / "spec.nrrd", "--json")
    assert res.code == 0 and json.loads(res.stdout)["values"] == "intensity"
    assert _ids(d / "spec.nrrd") == _ids(d / "old.nrrd")


@pytest.mark.parametrize("given", [["--labels"], ["--values", "labels"]])
def test_labels_asked_for_on_a_scan_warn_once(run, files, given):
    """A volume that does not look like a label map, warped as labels as asked: one
    warning line; nothing for a label map."""
    d = files["dir"]
    still = d / "still.yaml"  # (moved, single-voxel labels vanish: a line each)
    still.write_text("version: 1\ncapture: {lattice: 5}\nsteps: []\n")
    res = run("warp", files["ct"], "--spec", still, "-o", d / "o.nrrd", *given)
    assert res.code == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("volwarp: warning: ")
    assert "does not look like a label map" in lines[0] and str(files["ct"]) in lines[0]
    assert _ids(d / "o.nrrd") <= {int(v) for v in np.unique(ct_like().data)}
    res = run("warp", files["frog"], "--spec", files["frog_spec"], "-o", d / "f.nrrd", *given)
    assert res.code == 0 and res.stderr == ""


def test_what_a_label_map_cannot_have_names_the_way_out(run, files):
    """Options for intensities on a map the rule took for labels: a usage error (exit 2)
    saying so and how to warp its samples as intensities; --labels with --values
    intensity contradict."""
    d = files["dir"]
    for extra in (["--dtype", "float32"], ["--background-value", "3.5"]):
        res = run("warp", files["frog"], "--spec", files["frog_spec"], "-o", d / "o.nrrd",
                  *extra)
        assert res.code == 2 and "looks like a label map" in res.stderr, res.stderr
        assert "--values intensity" in res.stderr
    res = run("warp", files["frog"], "--spec", files["frog_spec"], "-o", d / "o.nrrd",
              "--labels", "--values", "intensity")
    assert res.code == 2
    res = run("warp", files["ct"], "--spec", files["ct_spec"], "-o", d / "o.nrrd",
              "--preserve-labels")
    assert res.code == 2 and "--values labels" in res.stderr
    assert not (d / "o.nrrd").exists()


def test_a_capture_file_of_a_label_map_is_warped_as_labels(run, files):
    """A capture on the subdivision grid holds its input's samples: the rule applies to
    them, and the warp equals the label map's own (in memory and by blocks). A capture
    on the spanning grid holds blends: labels from it are refused."""
    d = files["dir"]
    vwc = d / "frog.vwc"
    assert run("capture", files["frog"], "-o", vwc, "--lattice", "6").code == 0
    res = run("warp", files["frog"], "--spec", files["frog_spec"], "-o", d / "direct.nrrd")
    assert res.code == 0, res.stderr
    for extra in ([], ["--chunked"]):
        out = d / f"cap{len(extra)}.nrrd"
        res = run("warp", vwc, "--spec", files["frog_spec"], "-o", out, "--json", *extra)
        assert res.code == 0, res.stderr
        assert json.loads(res.stdout)["values"] == "labels"
        assert np.array_equal(read_volume(out).data, read_volume(d / "direct.nrrd").data)
    # the spanning grid blends a label map's ids for good: refused at capture (a warp of it
    # averaged ids 1, 2, 7 into 5 and 6, exit 0), unless its samples are asked for as
    # intensities; a warp of that capture cannot take it for labels
    tripled = d / "tripled.vwc"
    res = run("capture", files["frog"], "-o", tripled, "--lattice", "6", "--placement",
              "tripled")
    assert res.code == 2 and "looks like a label map" in res.stderr and "--values intensity" \
        in res.stderr and not tripled.exists()
    res = run("capture", files["frog"], "-o", tripled, "--lattice", "6", "--placement",
              "tripled", "--values", "intensity")
    assert res.code == 0, res.stderr
    res = run("capture", files["frog"], "-o", d / "l.vwc", "--lattice", "6", "--oversample",
              "1.5", "--values", "labels")
    assert res.code == 2 and "--values labels needs" in res.stderr
    spec = d / "plain.yaml"
    spec.write_text("version: 1\nsteps: []\n")
    res = run("warp", tripled, "--spec", spec, "-o", d / "t.nrrd", "--labels")
    assert res.code == 2 and "blended" in res.stderr and not (d / "t.nrrd").exists()


def test_choose_values_reads_nothing_for_intensity_and_counts_labels():
    class Refusing:
        shape, dtype = (2, 3, 4), np.dtype(np.uint8)

        def __getitem__(self, key):
            raise AssertionError("read")

    assert choose_values(Refusing(), "intensity").why == "given"
    choice = choose_values(frog_like().data)
    assert choice.is_labels and choice.labels == 6 and choice.warning is None
    assert not choose_values(ct_like().data).is_labels
    assert not choose_values(ct_like().data.astype(np.float32)).is_labels
    assert choose_values(ct_like().data, "labels").warning
    # a segmentation stored as floats (nibabel's, MONAI's): labels; a fraction is no id
    floats = frog_like().data.astype(np.float32)
    assert choose_values(floats).is_labels and choose_values(floats).labels == 6
    floats[0, 0, 0] = 0.5
    assert not choose_values(floats).is_labels
    with pytest.raises(VolwarpError, match="not all integers"):
        choose_values(floats, "labels")


def test_sparse_ids_taken_for_intensities_are_said(run, tmp_path):
    """Landmarks, one voxel each with ids 1..20 in zeros, have no regions for the rule: it
    answers intensities, and apply or warp blended the ids away without a word (a review:
    20 landmarks became values 0..7 over 103 voxels). Said at the default verbosity, with
    the way out; a scan, a mask and an intensity image that is not sparse say nothing."""
    rng = np.random.default_rng(1)
    marks = np.zeros((40, 40, 40), np.uint8)
    for i, (z, y, x) in enumerate(rng.integers(3, 37, (20, 3)), start=1):
        marks[z, y, x] = i
    choice = choose_values(marks, name="lm.nrrd")
    assert not choice.is_labels
    assert choice.warning.startswith("warning: lm.nrrd: its 20 voxels of 20 integer values "
                                     "besides 0 are taken for intensities")
    assert "--values labels" in choice.warning
    assert choose_values(marks, "labels").warning is None  # (asked: no doubt left)
    assert choose_values(ct_like().data).warning is None
    assert choose_values(frog_like().data).warning is None
    spread = rng.integers(0, 5, (40, 40, 40)).astype(np.uint8)  # 5 values everywhere
    assert choose_values(spread).warning is None
    # a sparse intensity image: its values many, or spread out (a review: 441 voxels of
    # 350 values warned)
    sparse = np.zeros((40, 40, 40), np.int16)
    where = rng.integers(0, 40, (441, 3))
    sparse[tuple(where.T)] = rng.integers(1, 4000, 441)
    assert choose_values(sparse).warning is None
    few = np.zeros((40, 40, 40), np.int16)
    few[tuple(where[:20].T)] = rng.choice(np.arange(100, 4000, 150), 20, replace=False)
    assert choose_values(few).warning is None
    # landmarks beside a mask (0 and 1 the two most frequent values): as few, said too
    masked = np.zeros((40, 40, 40), np.uint8)
    masked[10:30, 10:30, 10:30] = 1
    masked[2, 2, 2], masked[37, 3, 5], masked[4, 36, 36] = 5, 7, 9
    choice = choose_values(masked, name="m.nrrd")
    assert not choice.is_labels
    assert choice.warning.startswith("warning: m.nrrd: its 3 voxels of 3 integer values "
                                     "besides 0 and 1 are taken for intensities")
    src = tmp_path / "lm.nrrd"
    write_volume(Volume(marks), src)
    tfm = tmp_path / "t.tfm"
    tfm.write_text("#Insight Transform File V1.0\n#Transform 0\n"
                   "Transform: TranslationTransform_double_3_3\nParameters: 0.4 0.3 0\n"
                   "FixedParameters:\n")
    res = run("apply", src, "-o", tmp_path / "a.nrrd", "-t", tfm)
    assert res.code == 0 and res.stderr.count("taken for intensities") == 1, res.stderr
    res = run("apply", src, "-o", tmp_path / "b.nrrd", "-t", tfm, "--values", "labels")
    assert res.code == 0 and res.stderr == "", res.stderr
    moved = read_volume(tmp_path / "b.nrrd").data
    assert set(np.unique(moved)) <= set(range(21))


# -- item 3: a scan stays where it was ------------------------------------------------------

def test_a_ct_keeps_its_grid_and_gets_air_where_nothing_lands(run, files):
    """Defaults: the input's shape, origin and spacing; where nothing of the body lands,
    -1024 (the border's value), never 0; in memory and by blocks the same bytes.
    --grid grow is the old padded grid; --crop is --grid input."""
    d, ct = files["dir"], ct_like()
    res = run("warp", files["ct"], "--spec", files["ct_spec"], "-o", d / "o.nrrd", "-v",
              "--json")
    assert res.code == 0, res.stderr
    assert "background: -1024 (the median of the input's border)" in res.stderr
    assert "output grid: input (default)" in res.stderr
    summary = json.loads(res.stdout)
    assert summary["grid"] == "input" and summary["background"] == -1024
    assert summary["values"] == "intensity" and summary["shape"] == [16, 16, 5]
    out = read_volume(d / "o.nrrd")
    assert out.same_grid(ct) and np.allclose(out.origin, ct.origin)
    # where nothing lands: a sentinel background finds those voxels
    res = run("warp", files["ct"], "--spec", files["ct_spec"], "-o", d / "s.nrrd",
              "--background-value", "5000")
    assert res.code == 0
    empty = read_volume(d / "s.nrrd").data == 5000
    assert empty.any() and np.all(out.data[empty] == -1024)
    assert np.count_nonzero(out.data == 0) == 0
    for extra in (["--chunked"], ["--crop"], ["--grid", "input"]):
        res = run("warp", files["ct"], "--spec", files["ct_spec"], "-o", d / "b.nrrd", *extra)
        assert res.code == 0, res.stderr
        assert np.array_equal(read_volume(d / "b.nrrd").data, out.data), extra
    res = run("warp", files["ct"], "--spec", files["ct_spec"], "-o", d / "g.nrrd", "--grid",
              "grow", "--json")
    assert res.code == 0 and json.loads(res.stdout)["grid"] == "grow"
    grown = read_volume(d / "g.nrrd")
    assert grown.shape_xyz[0] > 16 and grown.origin[0] < ct.origin[0]
    res = run("warp", files["ct"], "--spec", files["ct_spec"], "-o", d / "g.nrrd", "--crop",
              "--grid", "grow")
    assert res.code == 2


def test_the_spec_says_grid_and_a_pad_asks_for_growth(run, files):
    d = files["dir"]
    for text, shape in (("grid: grow\n", None), ("capture: {pad: 3}\n", [22, 22, 11]),
                        ("grid: input\n", [16, 16, 5])):
        spec = d / "g.yaml"
        spec.write_text(CT_SPEC.replace("capture: {lattice: 5}\n", "")
                        .replace("version: 1\n", f"version: 1\n{text}"))
        res = run("warp", files["ct"], "--spec", spec, "-o", d / "o.nrrd", "--json")
        assert res.code == 0, res.stderr
        got = json.loads(res.stdout)["shape"]
        assert got == shape if shape else got[0] > 16
    spec.write_text("version: 1\ngrid: input\ncapture: {pad: 3}\nsteps: []\n")
    res = run("warp", files["ct"], "--spec", spec, "-o", d / "o.nrrd")
    assert res.code == 2 and "capture.pad" in res.stderr
    res = run("warp", files["ct"], "--spec", files["ct_spec"], "-o", d / "o.nrrd",
              "--allow-growth")
    assert res.code == 2 and "--grid grow" in res.stderr


def test_border_value_of_scans():
    assert border_value(ct_like().data) == -1024
    assert border_value(frog_like().data) == 0
    data = np.zeros((3, 4, 5), np.float32)
    data[1:-1, 1:-1, 1:-1] = 7  # the inside never counts
    assert border_value(data) == 0
    data[:] = np.nan
    data[0, 0, :] = 2.5
    assert border_value(data) == 2.5  # NaN never wins over a number
    data[:] = np.nan
    assert np.isnan(border_value(data))  # (only when there is nothing else)


def slab_distance_field(shape=(20, 20, 20), depth=6) -> np.ndarray:
    """The signed distance (negative inside) of the slab z < ``depth``: it touches a face.

    Its z = 0 face is one value inside the shape (the most frequent on the border),
    while most of the border lies outside.
    """
    z = np.arange(shape[0], dtype=np.float32)[:, None, None]
    return np.broadcast_to(z + 0.5 - depth, shape).astype(np.float32).copy()


def noisy_ct(seed=2) -> np.ndarray:
    """A 16x16x5 CT whose body touches its border: air with wide noise around a body
    with narrow noise (a body value is the border's most frequent)."""
    rng = np.random.default_rng(seed)
    data = np.round(rng.normal(-1000, 40, (5, 16, 16))).astype(np.int16)
    data[:, :, 10:] = np.round(rng.normal(-5, 3, (5, 16, 6)))
    return data


def test_a_distance_fields_background_is_outside_and_a_noisy_airs_is_air():
    """The border's most frequent value was inside a distance field (the face it touches)
    and a body value for a CT with a noisy air border: the median is outside and air."""
    field = slab_distance_field()
    assert Counter(_faces(field).tolist()).most_common(1)[0][0] < 0  # (the old answer)
    assert border_value(field) > 0
    ct = noisy_ct()
    assert -20 < Counter(_faces(ct).tolist()).most_common(1)[0][0] < 10  # (the old answer)
    assert border_value(ct) < -900


def test_a_grown_distance_fields_margin_stays_outside(run, tmp_path):
    """A distance field warped on the grown grid: where nothing lands it is outside."""
    src, spec = tmp_path / "sdf.nrrd", tmp_path / "w.yaml"
    write_volume(Volume(slab_distance_field()), src)
    spec.write_text("version: 1\ncapture: {lattice: 5}\nsteps:\n  - drag:\n"
                    "      - {from: [10, 10, 12], to: [13, 10, 14]}\n")
    out = tmp_path / "o.nrrd"
    res = run("warp", src, "--spec", spec, "--grid", "grow", "-o", out, "-v", "--json")
    assert res.code == 0, res.stderr
    background = json.loads(res.stdout)["background"]
    assert background > 0 and f"background: {background:.9g} (the median" in res.stderr
    sentinel = tmp_path / "s.nrrd"
    assert run("warp", src, "--spec", spec, "--grid", "grow", "-o", sentinel,
               "--background-value", "1000").code == 0
    empty = read_volume(sentinel).data == 1000
    got = read_volume(out).data
    assert empty.sum() > 1000 and np.all(got[empty] == background)


def _faces(a: np.ndarray) -> np.ndarray:
    nz, ny, nx = a.shape
    faces = [a[0], a[nz - 1], a[:, 0], a[:, ny - 1], a[:, :, 0], a[:, :, nx - 1]]
    return np.concatenate([np.ravel(f) for f in faces])


class _Lazy:
    """``a`` read only through slicing (as a file read box by box)."""

    def __init__(self, a):
        self.a, self.shape, self.dtype = a, a.shape, a.dtype

    def __getitem__(self, key):
        return np.array(self.a[key])


SHAPES = hnp.array_shapes(min_dims=3, max_dims=3, min_side=1, max_side=6)


@settings(max_examples=80, deadline=None)
@given(a=hnp.arrays(np.int16, SHAPES, elements=st.integers(-3, 3)),
       inside=st.integers(-100, 100))
def test_border_value_is_the_faces_lower_median(a, inside):
    """The lower median of the six faces' samples (each face's voxels counted); the inside
    changes nothing; a lazy source gives the same; the mode where it covers more than
    half of the border."""
    faces = np.sort(_faces(a))
    got = border_value(a)
    assert got == faces[(faces.size - 1) // 2]
    value, count = Counter(faces.tolist()).most_common(1)[0]
    if 2 * count > faces.size:
        assert got == value
    b = a.copy()
    b[1:-1, 1:-1, 1:-1] = inside
    assert border_value(b) == got
    assert border_value(_Lazy(a)) == got


@settings(max_examples=60, deadline=None)
@given(a=hnp.arrays(np.float32, SHAPES,
                    elements=st.one_of(st.floats(-1e6, 1e6, width=32), st.just(np.nan))))
def test_border_value_is_never_nan_while_a_number_is_there(a):
    faces = _faces(a)
    got = border_value(a)
    if np.isnan(faces).all():
        assert np.isnan(got)
    else:
        finite = np.sort(faces[~np.isnan(faces)])
        assert got == finite[(finite.size - 1) // 2]


@settings(max_examples=60, deadline=None)
@given(a=hnp.arrays(np.int16, SHAPES, elements=st.integers(-3, 3)))
def test_border_label_is_the_faces_mode(a):
    """A label map's background: the most frequent label of the faces, the smallest of a
    tie; a lazy source gives the same."""
    count = Counter(_faces(a).tolist())
    top = max(count.values())
    assert border_label(a) == min(v for v, c in count.items() if c == top)
    assert border_label(_Lazy(a)) == border_label(a)


def test_output_grid_rule():
    assert output_grid(None, None, None) == ("input", "default")
    assert output_grid(None, None, "capture.pad")[0] == "grow"
    assert output_grid(None, "input", "the capture file's pad")[0] == "input"
    assert output_grid("input", "grow", "capture.pad") == ("input", "given")


# -- item 3: resampling said once -----------------------------------------------------------

@pytest.mark.parametrize("capture, warned", [("{lattice: 5, oversample: 1.5}", "oversample 1.5"),
                                             ("{lattice: 6, placement: tripled}", "tripled"),
                                             ("{lattice: 5, oversample: 1}", None)])
def test_a_capture_that_resamples_unmoved_voxels_warns_once(run, files, capture, warned):
    d = files["dir"]
    spec = d / "r.yaml"
    spec.write_text(f"version: 1\ncapture: {capture}\nsteps:\n  - move:\n"
                    "      - {index: [2, 2, 2], by: [0.5, 0, 0]}\n    frames: 2\n")
    for extra in ([], ["--frames-to", str(d / "f{frame}.nrrd")], ["--chunked"]):
        res = run("warp", files["ct"], "--spec", spec, "-o", d / "o.nrrd", *extra)
        assert res.code == 0, res.stderr
        lines = res.stderr.strip().splitlines()
        if warned is None:
            assert lines == []
        else:
            assert len(lines) == 1 and lines[0].startswith("volwarp: warning: ")
            assert warned in lines[0] and "exact" in lines[0]


# -- item 7: points and meshes without a volume ---------------------------------------------

def test_points_go_through_a_warp_without_a_volume(run, files, monkeypatch):
    """No -o: the moved points are those of the warp with -o, and no volume is read,
    captured or warped (for a volume input and a capture file)."""
    from volwarp_cli.bspline import capture as capture_mod
    from volwarp_cli.bspline.scene import Scene
    from volwarp_cli.cli import warp as warp_cli
    from volwarp_cli.warp import capture_file

    d = files["dir"]
    pts = d / "p.csv"
    pts.write_text("x,y,z\n0,12,7\n-4,9,5\n2,2,9\n")
    vwc = d / "ct.vwc"
    assert run("capture", files["ct"], "-o", vwc, "--lattice", "5").code == 0
    res = run("warp", files["ct"], "--spec", files["ct_spec"], "-o", d / "o.nrrd",
              "--points-in", pts, "--points-to", d / "with.csv")
    assert res.code == 0, res.stderr

    def refuse(*a, **k):
        raise AssertionError("a volume was computed")

    for name in ("load_input",):
        monkeypatch.setattr(warp_cli, name, refuse)
    for name in ("capture_volume", "capture_source"):
        monkeypatch.setattr(capture_mod, name, refuse)
    for name in ("read_capture", "open_capture_lazy"):
        monkeypatch.setattr(capture_file, name, refuse)
    for name in ("compute", "contribute"):
        monkeypatch.setattr(Scene, name, refuse)
    for src in (files["ct"], vwc):
        out = d / f"without_{src.suffix[1:]}.csv"
        res = run("warp", src, "--spec", files["ct_spec"], "--points-in", pts,
                  "--points-to", out, "--json")
        assert res.code == 0, res.stderr
        assert out.read_bytes() == (d / "with.csv").read_bytes()
        summary = json.loads(res.stdout)
        assert summary["output"] is None and summary["points"]["count"] == 3
    assert not (d / "o2.nrrd").exists()


def test_a_warp_needs_an_output_and_no_volume_option_is_ignored(run, files):
    d = files["dir"]
    res = run("warp", files["ct"], "--spec", files["ct_spec"])
    assert res.code == 2 and "nothing to write" in res.stderr
    pts = d / "p.csv"
    pts.write_text("x,y,z\n0,12,7\n")
    for extra in (["--dtype", "float32"], ["--background-value", "1"], ["--labels"],
                  ["--grid", "grow"]):
        res = run("warp", files["ct"], "--spec", files["ct_spec"], "--points-in", pts,
                  "--points-to", d / "q.csv", *extra)
        assert res.code == 2 and "none is written" in res.stderr, (extra, res.stderr)
    assert not (d / "q.csv").exists()
    res = run("warp", files["ct"], "--spec", files["ct_spec"], "--frames-to",
              str(d / "f{frame}.nrrd"), "--json")  # frames alone: no -o needed either
    assert res.code == 0 and json.loads(res.stdout)["frames"] == 2
    assert sorted(p.name for p in d.glob("f?.nrrd")) == ["f0.nrrd", "f1.nrrd"]


def test_a_capture_error_naming_its_file_is_not_named_twice():
    """A reader's error names the input already ("in.nrrd: file is truncated ..."): the
    capture's wrapper said "in.nrrd: in.nrrd: ..." (a review, with the input replaced
    during a warp). Other errors get the input's name."""
    import pytest

    from volwarp_cli.bspline.plan import CaptureSettings
    from volwarp_cli.errors import FormatError, VolwarpError
    from volwarp_cli.warp.prepare import capture_as_spec

    settings = CaptureSettings()

    def truncated(*_, **__):
        raise FormatError("in.nrrd: file is truncated (plane 0 ends 131072 bytes short)")

    def other(*_, **__):
        raise VolwarpError("the volume has NaN or infinite samples")

    with pytest.raises(VolwarpError) as err:
        capture_as_spec(truncated, settings, "in.nrrd")
    assert str(err.value) == "in.nrrd: file is truncated (plane 0 ends 131072 bytes short)"
    with pytest.raises(VolwarpError) as err:
        capture_as_spec(other, settings, "in.nrrd")
    assert str(err.value) == "in.nrrd: the volume has NaN or infinite samples"
