"""`volwarp apply` against SimpleITK: its transform files, its Resample and its TransformPoint."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.transforms import read_chain
from volwarp_cli.volume import Volume

sitk = pytest.importorskip("SimpleITK")

ANG = np.deg2rad(12)
DIRECTION = np.array([[np.cos(ANG), -np.sin(ANG), 0], [np.sin(ANG), np.cos(ANG), 0], [0, 0, 1]])
RNG = np.random.default_rng(7)


def smooth(shape=(20, 22, 24)):
    nz, ny, nx = shape
    z, y, x = np.mgrid[:nz, :ny, :nx].astype(float)
    data = (100 * np.exp(-((x - 11.5) ** 2 / 50 + (y - 10.5) ** 2 / 40 + (z - 9.5) ** 2 / 30))
            + 20 * np.sin(x / 4) * np.cos(y / 5) + RNG.normal(0, 2, x.shape)).astype(np.float32)
    return Volume(data, spacing=(1.1, 1.0, 1.3), origin=(-10.0, 5.0, 3.0), direction=DIRECTION,
                  space="left-posterior-superior")


def to_sitk(vol: Volume):
    img = sitk.GetImageFromArray(vol.data)
    img.SetSpacing([float(v) for v in vol.spacing])
    img.SetOrigin([float(v) for v in vol.origin])
    img.SetDirection([float(v) for v in vol.direction.ravel()])
    return img


def affine():
    a = sitk.AffineTransform(3)
    a.SetMatrix([1.02, 0.05, 0.0, -0.03, 0.97, 0.04, 0.02, 0.0, 1.05])
    a.SetTranslation([1.0, -1.5, 0.8])
    a.SetCenter([2.0, 14.0, 15.0])
    return a


def euler(zyx=False):
    e = sitk.Euler3DTransform()
    e.SetRotation(0.1, -0.15, 0.2)
    e.SetTranslation([0.5, 1.0, -0.7])
    e.SetCenter([1.0, 12.0, 16.0])
    e.SetComputeZYX(zyx)
    return e


def field_on(vol: Volume, amp=1.5):
    """A smooth displacement field on ``vol``'s grid (float64 vectors, as sitk keeps them)."""
    nz, ny, nx = vol.data.shape
    z, y, x = np.mgrid[:nz, :ny, :nx].astype(float)
    vec = np.stack([amp * np.sin(z / 6), amp * np.cos(x / 8), 0.6 * amp * np.sin(y / 7)], -1)
    img = sitk.GetImageFromArray(vec, isVector=True)
    ref = to_sitk(vol)
    img.CopyInformation(ref)
    return img


def bspline(vol: Volume):
    b = sitk.BSplineTransformInitializer(to_sitk(vol), [4, 4, 3])
    p = np.asarray(b.GetParameters())
    b.SetParameters(RNG.normal(0, 1.0, p.size).tolist())
    return b


def transforms(vol):
    s = sitk.Similarity3DTransform()
    s.SetScale(1.05)
    s.SetRotation([0.2, 0.3, 1.0], 0.25)
    s.SetTranslation([1, 2, -1])
    s.SetCenter([2, 3, 4])
    v = sitk.VersorRigid3DTransform()
    v.SetRotation([1, 1, 0], 0.2)
    v.SetTranslation([1, -2, 3])
    v.SetCenter([2, 0, 4])
    d = sitk.DisplacementFieldTransform(field_on(vol))
    return {"affine.tfm": affine(), "euler.txt": euler(), "euler_zyx.tfm": euler(True),
            "similarity.tfm": s, "versor.tfm": v, "translation.tfm":
                sitk.TranslationTransform(3, [1.0, 2.0, 3.0]),
            "bspline.tfm": bspline(vol), "field.h5": d, "affine.mat": affine(),
            "composite.h5": sitk.CompositeTransform([affine(), d, bspline(vol)]),
            "composite.tfm": sitk.CompositeTransform([affine(), euler()])}


def world_points(vol: Volume, n=200):
    lo, hi = vol.world_bounds()
    return RNG.uniform(lo, hi, (n, 3))


@pytest.mark.parametrize("name", ["affine.tfm", "euler.txt", "euler_zyx.tfm", "similarity.tfm",
                                  "versor.tfm", "translation.tfm", "bspline.tfm", "field.h5",
                                  "affine.mat", "composite.h5", "composite.tfm"])
def test_reader_maps_points_as_transform_point(tmp_path, name):
    vol = smooth()
    tr = transforms(vol)[name]
    path = tmp_path / name
    sitk.WriteTransform(tr, str(path))
    pts = world_points(vol)
    ours = read_chain([str(path)]).map(pts)
    theirs = np.array([tr.TransformPoint(p.tolist()) for p in pts])
    assert np.abs(ours - theirs).max() < 1e-9


def test_damaged_itk_h5_and_mat_files_are_one_line_errors(tmp_path):
    """A composite .h5 with a component deleted was applied without it (ITK refuses the
    file); a missing TransformType, text for numbers, a TransformGroup that is no group
    and a .mat of text were internal errors."""
    import h5py
    import scipy.io

    from volwarp_cli.errors import VolwarpError

    vol = smooth()
    whole = tmp_path / "composite.h5"
    sitk.WriteTransform(transforms(vol)["composite.h5"], str(whole))

    def edited(name, edit):
        path = tmp_path / name
        path.write_bytes(whole.read_bytes())
        with h5py.File(path, "a") as f:
            edit(f)
        return path

    def params_as_text(f):
        del f["TransformGroup/1/TransformParameters"]
        f["TransformGroup/1/TransformParameters"] = np.array([b"abc"])

    def group_as_data(f):
        del f["TransformGroup"]
        f["TransformGroup"] = np.zeros(3)

    cases = {
        edited("gap.h5", lambda f: f["TransformGroup"].__delitem__("2")):
            r"holds \['0', '1', '3'\], not the transforms 0 to 2",
        edited("notype.h5", lambda f: f["TransformGroup/1"].__delitem__("TransformType")):
            "transform 1 has no TransformType",
        edited("text.h5", params_as_text): "has parameters that are not numbers",
        edited("data.h5", group_as_data): "is not a group",
    }
    text_mat = tmp_path / "text.mat"
    scipy.io.savemat(text_mat, {"AffineTransform_double_3_3": "abc",
                                "fixed": np.zeros((3, 1))}, format="4")
    cases[text_mat] = "has parameters that are not numbers"
    for path, words in cases.items():
        with pytest.raises(VolwarpError, match=words):
            read_chain([str(path)])

def test_inverse_of_linear_file(tmp_path):
    path = tmp_path / "c.tfm"
    tr = sitk.CompositeTransform([affine(), euler()])
    sitk.WriteTransform(tr, str(path))
    pts = world_points(smooth())
    ours = read_chain([f"[{path},1]"]).map(pts)
    theirs = np.array([tr.GetInverse().TransformPoint(p.tolist()) for p in pts])
    assert np.abs(ours - theirs).max() < 1e-9


@pytest.fixture
def scene(tmp_path):
    """An input, a reference grid (other spacing, direction), an affine and a field file.

    The field lies on the reference grid (as ANTs' 1Warp on the fixed image); ``expect``
    resamples with SimpleITK the chain -t field -t affine = affine(field(p)).
    """
    vol = smooth()
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    ref = Volume(np.zeros((18, 20, 21), np.uint8), spacing=(1.2, 1.15, 1.25),
                 origin=(-8.0, 6.0, 4.0), direction=np.eye(3), space="left-posterior-superior")
    write_volume(ref, tmp_path / "ref.nrrd")
    sitk.WriteTransform(affine(), str(tmp_path / "a.tfm"))
    fimg = field_on(ref)
    sitk.WriteImage(sitk.Cast(fimg, sitk.sitkVectorFloat32), str(tmp_path / "f.nii.gz"))
    field32 = sitk.Cast(sitk.Cast(fimg, sitk.sitkVectorFloat32), sitk.sitkVectorFloat64)

    def expect(interp, chain=None):
        chain = chain or sitk.CompositeTransform(
            [affine(), sitk.DisplacementFieldTransform(sitk.Image(field32))])
        out = sitk.Resample(to_sitk(vol), to_sitk(ref), chain, interp, 0.0)
        return sitk.GetArrayFromImage(out)

    return tmp_path, vol, expect


@pytest.mark.parametrize("interp", ["linear", "nearest", "bspline"])
def test_resample_matches_simpleitk(run, scene, interp):
    d, vol, expect = scene
    res = run("apply", d / "in.nrrd", "-o", d / "out.nrrd", "--reference", d / "ref.nrrd",
              "-t", d / "f.nii.gz", "-t", d / "a.tfm", "--interpolation", interp,
              "--background-value", "0")
    assert res.code == 0, res
    ours = read_volume(d / "out.nrrd").data
    theirs = expect({"linear": sitk.sitkLinear, "nearest": sitk.sitkNearestNeighbor,
                     "bspline": sitk.sitkBSpline}[interp])
    span = float(vol.data.max() - vol.data.min())
    if interp == "nearest":
        assert np.array_equal(ours, theirs)
    else:
        assert np.abs(ours - theirs).max() <= 1e-4 * span
    assert np.count_nonzero(ours) > 0.5 * ours.size  # (the comparison is not of backgrounds)


def test_nifti_input_read_beside_a_nifti_field_in_a_fresh_process(scene):
    """A NIfTI input, reference and field in a new process (nibabel imported there for
    the input, the input's label scan in a thread beside the field's reading): the
    result is SimpleITK's, twice over."""
    import subprocess
    import sys

    d, vol, expect = scene
    sitk.WriteImage(to_sitk(vol), str(d / "in.nii.gz"))
    sitk.WriteImage(sitk.ReadImage(str(d / "ref.nrrd")), str(d / "ref.nii.gz"))
    for k in range(2):
        res = subprocess.run([sys.executable, "-m", "volwarp_cli", "apply", d / "in.nii.gz",
                              "-o", d / f"out{k}.nrrd", "--reference", d / "ref.nii.gz",
                              "-t", d / "f.nii.gz", "-t", d / "a.tfm", "--threads", "2",
                              "--background-value", "0", "--dtype", "float64"],
                             capture_output=True, text=True)
        assert res.returncode == 0 and res.stderr == "", res.stderr
        ours = read_volume(d / f"out{k}.nrrd").data
        span = float(vol.data.max() - vol.data.min())
        assert np.abs(ours - expect(sitk.sitkLinear)).max() <= 1e-4 * span


def test_every_memory_decision_is_made_in_the_command_thread(run, scene, monkeypatch):
    """The input's label scan runs beside the transforms' reading, but the input and the
    field are each read (and their memory checked) in the command's own thread: two
    threads checking at once would each count the memory left as theirs."""
    import threading

    from volwarp_cli import memory

    d, vol, _ = scene
    sitk.WriteImage(to_sitk(vol), str(d / "in.nii.gz"))
    asked = []
    real = memory._limit

    def limit():
        asked.append(threading.current_thread() is threading.main_thread())
        return real()

    monkeypatch.setattr(memory, "_limit", limit)
    res = run("apply", d / "in.nii.gz", "-o", d / "o.nrrd", "--reference", d / "ref.nrrd",
              "-t", d / "f.nii.gz", "-t", d / "a.tfm", "--threads", "2")
    assert res.code == 0, res.stderr
    assert len(asked) >= 3 and all(asked), asked  # (the input's, the field's, the run's)


def test_wrong_order_fails_the_comparison(run, scene):
    """Two non-commuting transforms: the order listed is the order they act on a point."""
    d, vol, expect = scene
    sitk.WriteTransform(euler(), str(d / "e.tfm"))
    theirs = expect(sitk.sitkLinear, sitk.CompositeTransform([euler(), affine()]))  # a, then e
    span = float(vol.data.max() - vol.data.min())
    for order, close in (((d / "a.tfm", d / "e.tfm"), True), ((d / "e.tfm", d / "a.tfm"), False)):
        res = run("apply", d / "in.nrrd", "-o", d / "out.nrrd", "--reference", d / "ref.nrrd",
                  "-t", order[0], "-t", order[1], "--background-value", "0")
        assert res.code == 0, res
        err = np.abs(read_volume(d / "out.nrrd").data - theirs).max()
        assert (err <= 1e-4 * span) if close else (err > 1e-2 * span)
    # a field listed after the affine that leaves its grid: the spaces do not meet
    res = run("apply", d / "in.nrrd", "-o", d / "out2.nrrd", "--reference", d / "ref.nrrd",
              "-t", d / "a.tfm", "-t", d / "f.nii.gz")
    assert res.code == 1 and "wrong order" in res.stderr
    assert not (d / "out2.nrrd").exists()


@pytest.mark.parametrize("interp", ["linear", "bspline", "nearest"])
@pytest.mark.parametrize("field", [True, False])
def test_by_blocks_same_bytes(run, scene, interp, field):
    d, _, _ = scene
    chain = ["-t", d / "f.nii.gz"] if field else []
    args = ["apply", d / "in.nrrd", "--reference", d / "ref.nrrd", *chain, "-t", d / "a.tfm",
            "--interpolation", interp]
    assert run(*args, "-o", d / "whole.nrrd").code == 0
    res = run(*args, "-o", d / "blocks.nrrd", "--chunked", "--block", "5,7,6")
    assert res.code == 0, res
    assert (d / "whole.nrrd").read_bytes() == (d / "blocks.nrrd").read_bytes()


def test_field_read_by_windows(run, scene, monkeypatch):
    """A field larger than its share of the memory is read by windows: the same bytes."""
    from volwarp_cli import memory

    d, _, _ = scene
    img = sitk.ReadImage(str(d / "f.nii.gz"))
    sitk.WriteImage(img, str(d / "f.nii"))  # (uncompressed: windows are read in place)
    chain = ["-t", d / "f.nii", "-t", d / "a.tfm"]
    args = ["apply", d / "in.nrrd", "--reference", d / "ref.nrrd", *chain]
    assert run(*args, "-o", d / "whole.nrrd").code == 0
    pts = np.random.default_rng(5).uniform([-5, 8, 6], [15, 25, 20], (20, 3))
    write_points(d / "p.csv", pts)
    assert run("apply", *chain, "--points-in", d / "p.csv", "--points-to", d / "q.csv").code == 0
    monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    assert run(*args, "-o", d / "lazy.nrrd").code == 0
    assert run(*args, "-o", d / "lazy_blocks.nrrd", "--chunked", "--block", "5,6,7").code == 0
    assert run("apply", *chain, "--points-in", d / "p.csv", "--points-to", d / "q2.csv").code == 0
    whole = (d / "whole.nrrd").read_bytes()
    assert (d / "lazy.nrrd").read_bytes() == whole
    assert (d / "lazy_blocks.nrrd").read_bytes() == whole
    assert np.abs(read_points(d / "q.csv") - read_points(d / "q2.csv")).max() < 1e-9


def test_bspline_transform_by_blocks(run, scene):
    """A B-spline transform's blocks read the region its coefficients bound: whole = blocks."""
    d, vol, expect = scene
    b = bspline(vol)
    sitk.WriteTransform(b, str(d / "b.tfm"))
    args = ["apply", d / "in.nrrd", "--reference", d / "ref.nrrd", "-t", d / "b.tfm",
            "--background-value", "0"]
    assert run(*args, "-o", d / "whole.nrrd").code == 0
    assert run(*args, "-o", d / "blocks.nrrd", "--chunked", "--block", "4,5,6").code == 0
    assert (d / "whole.nrrd").read_bytes() == (d / "blocks.nrrd").read_bytes()
    span = float(vol.data.max() - vol.data.min())
    theirs = expect(sitk.sitkLinear, b)
    assert np.abs(read_volume(d / "whole.nrrd").data - theirs).max() <= 1e-4 * span


def test_label_map_gains_no_label(run, tmp_path):
    vol = smooth()
    labels = np.digitize(vol.data, [10, 40, 80]).astype(np.uint8) * 3 + 2  # ids 2 5 8 11
    lab = vol.with_data(labels)
    write_volume(lab, tmp_path / "seg.nrrd")
    sitk.WriteTransform(affine(), str(tmp_path / "a.tfm"))
    res = run("apply", tmp_path / "seg.nrrd", "-o", tmp_path / "out.nrrd", "-t",
              tmp_path / "a.tfm", "-v")
    assert res.code == 0, res
    assert "values: labels" in res.stderr
    out = read_volume(tmp_path / "out.nrrd").data
    assert out.dtype == np.uint8
    assert set(np.unique(out)) <= set(np.unique(labels))
    border = np.bincount(np.concatenate([labels[0].ravel(), labels[-1].ravel(),
                                         labels[:, 0].ravel(), labels[:, -1].ravel(),
                                         labels[:, :, 0].ravel(), labels[:, :, -1].ravel()]))
    theirs = sitk.GetArrayFromImage(sitk.Resample(to_sitk(lab), to_sitk(lab), affine(),
                                                  sitk.sitkNearestNeighbor,
                                                  float(np.argmax(border))))
    assert np.array_equal(out, theirs)
    res = run("apply", tmp_path / "seg.nrrd", "-o", tmp_path / "o2.nrrd", "-t",
              tmp_path / "a.tfm", "--interpolation", "linear")
    assert res.code == 2 and "label map" in res.stderr
    assert not (tmp_path / "o2.nrrd").exists()


@pytest.mark.parametrize("command", ["apply", "convert"])
def test_a_dtype_that_would_merge_label_ids_is_refused(run, tmp_path, command):
    """--dtype clips intensities to the type's range; on a label map that merged ids 300 and
    1000 into one id 255 of uint8 (exit 0, before). A type that holds every id is fine."""
    vol = smooth()
    ids = np.array([0, 1, 300, 1000], np.uint16)
    lab = vol.with_data(ids[np.digitize(vol.data, [10, 40, 80])])
    write_volume(lab, tmp_path / "seg.nrrd")
    sitk.WriteTransform(affine(), str(tmp_path / "a.tfm"))
    extra = ["-t", tmp_path / "a.tfm"] if command == "apply" else []
    old = tmp_path / "o8.nrrd"
    old.write_bytes(b"an earlier output")
    res = run(command, tmp_path / "seg.nrrd", "-o", old, *extra, "--dtype", "uint8")
    assert res.code == 2 and "cannot hold its label ids 300, 1000" in res.stderr, res.stderr
    assert old.read_bytes() == b"an earlier output"
    res = run(command, tmp_path / "seg.nrrd", "-o", tmp_path / "o16.nrrd", *extra,
              "--dtype", "int16")
    assert res.code == 0, res.stderr
    out = read_volume(tmp_path / "o16.nrrd").data
    assert out.dtype == np.int16 and set(np.unique(out)) == {0, 1, 300, 1000}
    if command == "convert":
        assert np.array_equal(out, lab.data)
    # the way out the message names: the ids taken as intensities, clipped
    nearest = ["--interpolation", "nearest"] if command == "apply" else []
    res = run(command, tmp_path / "seg.nrrd", "-o", tmp_path / "oi.nrrd", *extra,
              "--dtype", "uint8", "--values", "intensity", *nearest)
    assert res.code == 0, res.stderr
    assert set(np.unique(read_volume(tmp_path / "oi.nrrd").data)) == {0, 1, 255}


@pytest.mark.parametrize("chunked", [False, True])
def test_nearest_keeps_a_background_the_output_type_holds_as_sitk(run, tmp_path, chunked):
    """Nearest samples in the input's type: a -1000 background of a uint8 scan's int16 output
    was clipped to 0 there (SimpleITK gives -1000, as asked)."""
    vol = smooth()
    scan = vol.with_data(np.clip(vol.data + 30, 0, 255).astype(np.uint8))
    write_volume(scan, tmp_path / "s.nrrd")
    shift = sitk.TranslationTransform(3, (8.0, 0.0, 0.0))
    sitk.WriteTransform(shift, str(tmp_path / "t.tfm"))
    res = run("apply", tmp_path / "s.nrrd", "-t", tmp_path / "t.tfm", "-o", tmp_path / "o.nrrd",
              "--interpolation", "nearest", "--values", "intensity", "--background-value",
              "-1000", "--dtype", "int16", *(["--chunked", "--block", "8"] if chunked else []))
    assert res.code == 0, res.stderr
    out = read_volume(tmp_path / "o.nrrd").data
    img = to_sitk(scan)
    theirs = sitk.GetArrayFromImage(sitk.Resample(img, img, shift, sitk.sitkNearestNeighbor,
                                                  -1000.0, sitk.sitkInt16))
    assert (theirs == -1000).sum() > 100
    assert out.dtype == np.int16 and np.array_equal(out, theirs)


def test_api_write_keeps_a_label_map_s_ids_as_convert_does(tmp_path):
    from volwarp_cli import api
    from volwarp_cli.errors import BadUsage

    ids = np.array([0, 1, 300, 1000], np.uint16)
    lab = smooth().with_data(ids[np.digitize(smooth().data, [10, 40, 80])])
    with pytest.raises(BadUsage, match="cannot hold its label ids 300, 1000"):
        api.write(lab, tmp_path / "a.nrrd", dtype="uint8")
    with pytest.raises(BadUsage, match="cannot hold"):
        api.write(lab, tmp_path / "a.nrrd", dtype="uint8", labels=True)
    assert not (tmp_path / "a.nrrd").exists()
    api.write(lab, tmp_path / "b.nrrd", dtype="uint8", labels=False)  # intensities: clipped
    assert set(np.unique(read_volume(tmp_path / "b.nrrd").data)) == {0, 1, 255}


def test_a_given_background_of_a_label_map_is_a_label_the_output_holds(run, tmp_path):
    """--background-value 300 on a uint8 map was clipped into label 255 (which then grew)."""
    ids = np.array([0, 3, 7, 255], np.uint8)
    lab = smooth().with_data(ids[np.digitize(smooth().data, [10, 40, 80])])
    write_volume(lab, tmp_path / "seg.nrrd")  # (a shift: part of the output falls outside)
    sitk.WriteTransform(sitk.TranslationTransform(3, (8.0, 0.0, 0.0)), str(tmp_path / "a.tfm"))
    args = ["apply", tmp_path / "seg.nrrd", "-t", tmp_path / "a.tfm", "-o", tmp_path / "o.nrrd"]
    res = run(*args, "--background-value", "300")
    assert res.code == 2 and "does not fit the output's uint8 ids" in res.stderr, res.stderr
    res = run(*args, "--background-value", "2.5")
    assert res.code == 2 and "is not a label id" in res.stderr, res.stderr
    assert not (tmp_path / "o.nrrd").exists()
    res = run(*args, "--background-value", "300", "--dtype", "uint16")
    assert res.code == 0, res.stderr
    out = read_volume(tmp_path / "o.nrrd").data
    assert out.dtype == np.uint16 and 300 in np.unique(out)
    assert set(np.unique(out)) <= {0, 3, 7, 255, 300}


def test_intensity_keeps_type_unless_dtype(run, tmp_path):
    vol = smooth()
    write_volume(vol.with_data(np.rint(vol.data * 10).astype(np.int16)), tmp_path / "ct.nrrd")
    sitk.WriteTransform(affine(), str(tmp_path / "a.tfm"))
    assert run("apply", tmp_path / "ct.nrrd", "-o", tmp_path / "o.nrrd", "-t",
               tmp_path / "a.tfm", "--values", "intensity").code == 0
    assert read_volume(tmp_path / "o.nrrd").data.dtype == np.int16
    assert run("apply", tmp_path / "ct.nrrd", "-o", tmp_path / "f.nrrd", "-t",
               tmp_path / "a.tfm", "--values", "intensity", "--dtype", "float32").code == 0
    assert read_volume(tmp_path / "f.nrrd").data.dtype == np.float32


def test_nrrd_vector_field(run, scene):
    d, vol, expect = scene
    fimg = sitk.ReadImage(str(d / "f.nii.gz"))
    sitk.WriteImage(fimg, str(d / "f.nrrd"))
    res = run("apply", d / "in.nrrd", "-o", d / "out.nrrd", "--reference", d / "ref.nrrd",
              "-t", d / "f.nrrd", "-t", d / "a.tfm", "--background-value", "0")
    assert res.code == 0, res
    span = float(vol.data.max() - vol.data.min())
    assert np.abs(read_volume(d / "out.nrrd").data - expect(sitk.sitkLinear)).max() <= 1e-4 * span


def write_points(path, pts):
    rows = ["x,y,z,name"] + [",".join(repr(float(v)) for v in p) + f",p{k}"
                             for k, p in enumerate(pts)]
    path.write_text("\n".join(rows) + "\n")


def read_points(path):
    lines = path.read_text().splitlines()
    assert lines[0] == "x,y,z,name"
    rows = [r.split(",") for r in lines[1:]]
    assert [r[3] for r in rows] == [f"p{k}" for k in range(len(rows))]
    return np.array([[float(v) for v in r[:3]] for r in rows])


def test_points_go_by_the_inverse_linear(run, tmp_path):
    sitk.WriteTransform(affine(), str(tmp_path / "a.tfm"))
    sitk.WriteTransform(euler(), str(tmp_path / "e.tfm"))
    pts = world_points(smooth(), 30)
    write_points(tmp_path / "p.csv", pts)
    res = run("apply", "-t", tmp_path / "a.tfm", "-t", tmp_path / "e.tfm", "--points-in",
              tmp_path / "p.csv", "--points-to", tmp_path / "q.csv")
    assert res.code == 0, res
    q = read_points(tmp_path / "q.csv")
    chain = sitk.CompositeTransform([euler(), affine()])  # a first, then e
    back = np.array([chain.TransformPoint(p.tolist()) for p in q])
    assert np.abs(back - pts).max() < 1e-6


def test_points_through_a_field_and_mesh(run, scene):
    from volwarp_cli.surface.mesh import Mesh
    from volwarp_cli.surface.mesh_io import read_mesh, write_mesh

    d, vol, _ = scene
    ref = read_volume(d / "ref.nrrd")
    lo, hi = ref.world_bounds()
    pts = np.random.default_rng(11).uniform(lo + 2, hi - 2, (40, 3))
    write_points(d / "p.csv", pts)
    faces = np.array([[0, 1, 2], [1, 2, 3]])
    write_mesh(Mesh(pts[:4], faces), d / "m.ply")
    res = run("apply", "-t", d / "f.nii.gz", "-t", d / "a.tfm", "--points-in", d / "p.csv",
              "--points-to", d / "q.csv", "--mesh-in", d / "m.ply", "--mesh-to", d / "m2.ply",
              "-v")
    assert res.code == 0, res
    assert "largest residual" in res.stderr
    q = read_points(d / "q.csv")
    field = sitk.Cast(sitk.ReadImage(str(d / "f.nii.gz")), sitk.sitkVectorFloat64)
    chain = sitk.CompositeTransform([affine(), sitk.DisplacementFieldTransform(field)])
    back = np.array([chain.TransformPoint(p.tolist()) for p in q])
    assert np.abs(back - pts).max() < 1e-3
    moved = read_mesh(d / "m2.ply")
    assert np.array_equal(moved.faces, faces)
    assert np.abs(moved.vertices - q[:4]).max() < 1e-4  # (PLY stores float32)


def _signed_volume(mesh) -> float:
    v = mesh.vertices[mesh.faces]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6)


def test_a_mirroring_chain_keeps_a_meshs_faces_outward(run, scene):
    """A left-right flip (an affine of determinant -1: onto an atlas's other side) turned
    every triangle of a moved mesh inside out: volume negative, every normal inward (exit
    0). Its faces are turned back; through a field and the flip too (the Jacobian's sign
    by differences), and a chain that keeps orientation keeps the faces as they were."""
    from volwarp_cli.io import read_volume as read
    from volwarp_cli.surface.isosurface import isosurface
    from volwarp_cli.surface.mesh_io import read_mesh, write_mesh

    d, vol, _ = scene
    z, y, x = np.mgrid[:18, :20, :21]
    ball = read(d / "ref.nrrd").with_data(
        (((x - 10) ** 2 + (y - 10) ** 2 + (z - 9) ** 2) < 36).astype(np.float32))
    mesh = isosurface(ball, 0.5)
    write_mesh(mesh, d / "ball.ply")
    flip = sitk.AffineTransform(3)
    flip.SetMatrix([-1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0])
    flip.SetCenter([3.0, 17.0, 14.0])
    sitk.WriteTransform(flip, str(d / "flip.tfm"))
    before = _signed_volume(mesh)
    assert before > 0
    for chain, flipped in (([d / "flip.tfm"], True), ([d / "f.nii.gz", d / "flip.tfm"], True),
                           ([d / "a.tfm"], False)):
        args = [a for t in chain for a in ("-t", t)]
        res = run("apply", *args, "--mesh-in", d / "ball.ply", "--mesh-to", d / "out.ply")
        assert res.code == 0, res.stderr
        out = read_mesh(d / "out.ply")
        assert np.array_equal(out.faces, mesh.faces[:, ::-1] if flipped else mesh.faces)
        after = _signed_volume(out)
        assert after > 0 and abs(after - before) < 0.1 * before, (chain, after, before)
        centre = out.vertices.mean(axis=0)
        outward = np.einsum("ij,ij->i", out.normals, out.vertices - centre) > 0
        assert outward.mean() > 0.99, chain


def test_volwarp_displacement_export(run, tmp_path):
    """volwarp's own `warp --displacement-to` field is read as ITK reads it."""
    vol = smooth()
    write_volume(vol, tmp_path / "in.nrrd")
    c = [float(v) for v in vol.index_to_world([11.5, 10.5, 9.5])]
    (tmp_path / "w.yaml").write_text(
        f"version: 1\ncapture: {{lattice: 6}}\nsteps:\n  - drag:\n      - {{from: {c}, to: "
        f"{[c[0] + 2.0, c[1] - 1.0, c[2] + 1.0]}}}\n")
    res = run("warp", tmp_path / "in.nrrd", "--spec", tmp_path / "w.yaml",
              "--displacement-to", tmp_path / "disp.nii.gz")
    assert res.code == 0, res
    assert run("apply", tmp_path / "in.nrrd", "-o", tmp_path / "out.nrrd", "-t",
               tmp_path / "disp.nii.gz", "--background-value", "0").code == 0
    field = sitk.Cast(sitk.ReadImage(str(tmp_path / "disp.nii.gz")), sitk.sitkVectorFloat64)
    theirs = sitk.GetArrayFromImage(sitk.Resample(to_sitk(vol), to_sitk(vol),
                                                  sitk.DisplacementFieldTransform(field),
                                                  sitk.sitkLinear, 0.0))
    ours = read_volume(tmp_path / "out.nrrd").data
    ok = np.isfinite(theirs)
    assert np.abs(ours[ok] - theirs[ok]).max() <= 1e-4 * float(np.ptp(vol.data))


# -- errors: one line, nothing written, an existing output untouched ------------------------
@pytest.fixture
def inputs(tmp_path):
    vol = smooth()
    write_volume(vol, tmp_path / "in.nrrd")
    (tmp_path / "out.nrrd").write_bytes(b"old output")
    return tmp_path


def _refused(run, d, *args, code=1, says=""):
    res = run("apply", d / "in.nrrd", "-o", d / "out.nrrd", *args)
    assert res.code == code, res
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("volwarp: error: ")
    assert says in res.stderr
    assert (d / "out.nrrd").read_bytes() == b"old output"
    assert sorted(p.name for p in d.iterdir() if p.name.startswith("out")) == ["out.nrrd"]
    return res


def test_2d_transform_refused(run, inputs):
    sitk.WriteTransform(sitk.AffineTransform(2), str(inputs / "a2.tfm"))
    _refused(run, inputs, "-t", inputs / "a2.tfm", says="2-D")


def test_not_a_transform_refused(run, inputs):
    (inputs / "notes.txt").write_text("hello\n")
    _refused(run, inputs, "-t", inputs / "notes.txt", says="not a transform")
    _refused(run, inputs, "-t", inputs / "in.nrrd", says="not a displacement field")


def test_field_not_covering_the_grid_refused(run, inputs):
    far = Volume(np.zeros((6, 6, 6), np.uint8), origin=(500.0, 500.0, 500.0))
    sitk.WriteImage(field_on(far), str(inputs / "far.nii.gz"))
    _refused(run, inputs, "-t", inputs / "far.nii.gz", says="outside its 6x6x6 samples")
    # a field after another field is checked too (it passed silently when only the first
    # non-linear step was)
    sitk.WriteImage(field_on(read_volume(inputs / "in.nrrd")), str(inputs / "near.nii.gz"))
    _refused(run, inputs, "-t", inputs / "near.nii.gz", "-t", inputs / "far.nii.gz",
             says="far.nii.gz (displacement field): the output grid's points reach it")


def test_inverse_of_field_refused(run, inputs, scene):
    d, _, _ = scene
    _refused(run, inputs, "-t", f"[{d / 'f.nii.gz'},1]", says="only a linear")


def test_output_over_a_transform_refused(run, inputs):
    sitk.WriteTransform(affine(), str(inputs / "a.tfm"))
    before = (inputs / "a.tfm").read_bytes()
    (inputs / "t.nrrd").write_bytes(before)  # a "transform" named like a volume output
    res = run("apply", inputs / "in.nrrd", "-o", inputs / "t.nrrd", "-t", inputs / "t.nrrd")
    assert res.code == 2 and "never replaces an input" in res.stderr
    assert (inputs / "t.nrrd").read_bytes() == before


def test_slicer_markups_points(run, tmp_path):
    """A Slicer .mrk.json in RAS moves as the same points in a CSV (LPS)."""
    import json

    sitk.WriteTransform(affine(), str(tmp_path / "a.tfm"))
    pts = world_points(smooth(), 5)
    write_points(tmp_path / "p.csv", pts)
    ras = [{"position": [-p[0], -p[1], p[2]]} for p in pts]
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "RAS", "controlPoints": ras}]}
    (tmp_path / "p.mrk.json").write_text(json.dumps(doc))
    for src, dst in (("p.csv", "q.csv"), ("p.mrk.json", "q.mrk.json")):
        assert run("apply", "-t", tmp_path / "a.tfm", "--points-in", tmp_path / src,
                   "--points-to", tmp_path / dst).code == 0
    q = read_points(tmp_path / "q.csv")
    moved = json.loads((tmp_path / "q.mrk.json").read_text())["markups"][0]["controlPoints"]
    got = np.array([[-m["position"][0], -m["position"][1], m["position"][2]] for m in moved])
    assert np.abs(got - q).max() < 1e-9


# -- NaN vectors, label-map wording, a folder as a transform -------------------------------
def write_field(path, vectors, origin, spacing=(1.1, 1.0, 1.3), direction=DIRECTION):
    """A displacement field image of ``vectors`` (z, y, x, 3) on the grid given (SimpleITK)."""
    img = sitk.GetImageFromArray(np.asarray(vectors, np.float64), isVector=True)
    img.SetOrigin([float(v) for v in origin])
    img.SetSpacing([float(v) for v in spacing])
    img.SetDirection([float(v) for v in np.ravel(direction)])
    sitk.WriteImage(sitk.Cast(img, sitk.sitkVectorFloat32), str(path))


def smooth_vectors(shape, amp=1.5):
    nz, ny, nx = shape
    z, y, x = np.mgrid[:nz, :ny, :nx].astype(float)
    return np.stack([amp * np.sin(z / 6), amp * np.cos(x / 8), 0.6 * amp * np.sin(y / 7)], -1)


@pytest.mark.parametrize("how", ["in memory", "by blocks", "by windows", "by processes"])
def test_nan_vectors_map_outside_as_in_itk_and_are_said(run, inputs, monkeypatch, how):
    """A NaN vector where the output samples the field: its voxels take the background, said once.

    Such a point maps to NaN, outside the input (ITK's rule for a point
    outside every image; SimpleITK itself gives other values there, its
    interpolation of a NaN index being undefined); the warning gives the
    count, the index box and a point. The NaN sits between the lattice of
    points checked before any work (x = 13), so it is the block that samples
    it that finds it.
    """
    from volwarp_cli import memory

    vol = read_volume(inputs / "in.nrrd")
    vec = smooth_vectors(vol.data.shape)
    vec[7, 9, 13] = np.nan  # (z, y, x)
    name = "nan.nii" if how == "by windows" else "nan.nii.gz"
    write_field(inputs / name, vec, vol.origin)
    args = ["-t", inputs / name, "--background-value", "-7"]
    if how in ("by blocks", "by processes"):  # (a worker process's warning: said once too)
        args += ["--chunked", "--block", "6,7,5"]
    if how == "by processes":
        args += ["--scheduler", "processes"]
    if how == "by windows":
        monkeypatch.setattr(memory, "READ_BY_BOX_SHARE", 0.0)
    res = run("apply", inputs / "in.nrrd", "-o", inputs / "o.nrrd", *args)
    assert res.code == 0, res.stderr
    said = (f"{name} (displacement field): 1 of its 10560 vectors are NaN or infinite (at "
            "indices x 13, y 9, z 7) and points mapped through it reach them (the first at LPS ")
    assert res.stderr.count(said) == 1 and "fill the vectors (0 is no displacement)" in res.stderr
    ours = read_volume(inputs / "o.nrrd").data
    # the same field without its NaN: the same voxels but those whose trilinear support
    # holds the NaN vector, which map outside the input (the background). The output's
    # voxels lie on the field's nodes, but for its NIfTI header's float32 origin (1e-6
    # voxel off): a voxel that close to a finite node takes that node's vector, not 1e-6
    # of the NaN beside it (which sent all 8 neighbours to the background)
    write_field(inputs / "clean.nii.gz", smooth_vectors(vol.data.shape), vol.origin)
    assert run("apply", inputs / "in.nrrd", "-o", inputs / "c.nrrd", "-t",
               inputs / "clean.nii.gz", "--background-value", "-7").code == 0
    clean = read_volume(inputs / "c.nrrd").data
    lost = (ours == -7.0) & (clean != -7.0)
    assert np.argwhere(lost).tolist() == [[7, 9, 13]]
    np.testing.assert_allclose(ours[~lost], clean[~lost], rtol=0, atol=1e-4 * np.ptp(clean))


def test_nan_vectors_the_output_never_reaches_ignored(run, inputs):
    """NaN vectors in a field's margin that no output point samples do not stop the resampling.

    The output's samples are those of the same field with those vectors zero.
    """
    vol = read_volume(inputs / "in.nrrd")
    shape = tuple(n + 12 for n in vol.data.shape)
    origin = vol.index_to_world([-6.0, -6.0, -6.0])  # 6 voxels of margin on every side
    vec = smooth_vectors(shape, amp=1.0)
    vec[:, :, :2] = 0.0
    write_field(inputs / "zero.nii.gz", vec, origin)
    vec[:, :, :2] = np.nan  # (the grid's points reach x >= 6 - 1 mm / 1.1 mm, no lower)
    write_field(inputs / "nan.nii.gz", vec, origin)
    for name in ("zero", "nan"):
        res = run("apply", inputs / "in.nrrd", "-o", inputs / f"{name}.nrrd", "-t",
                  inputs / f"{name}.nii.gz", "--background-value", "0")
        assert res.code == 0, res
    ours = read_volume(inputs / "nan.nrrd").data
    assert np.array_equal(ours, read_volume(inputs / "zero.nrrd").data)
    assert np.isfinite(ours).all() and np.count_nonzero(ours) > 0.9 * ours.size


def test_points_reaching_nan_vectors_are_nan_and_said(run, tmp_path):
    """A point whose only preimage samples a NaN vector is NaN (named); one beside it is solved.

    ``near``: the image of a point an output voxel away from the NaN node,
    whose trilinear support does not hold it: Newton's first guess lands on
    the NaN, its start is moved to finite vectors, and the answer is the
    clean field's. ``lost``: the image of the NaN node itself, which no point
    with finite vectors reaches: NaN, not Newton's last guess.
    """
    from volwarp_cli.transforms.fields import read_field

    vol = smooth()
    vec = smooth_vectors(vol.data.shape)
    vec[7, 9, 13] = np.nan
    write_field(tmp_path / "nan.nii.gz", vec, vol.origin)
    write_field(tmp_path / "clean.nii.gz", smooth_vectors(vol.data.shape), vol.origin)
    clean = read_field(str(tmp_path / "clean.nii.gz"), "nifti")
    beside, node = vol.index_to_world([15.0, 9.0, 7.0]), vol.index_to_world([13.0, 9.0, 7.0])
    near, lost = clean.map(np.array([beside, node]))
    far = vol.index_to_world([3.0, 4.0, 2.0])
    write_points(tmp_path / "p.csv", np.array([near, far, lost]))
    res = run("apply", "-t", tmp_path / "nan.nii.gz", "--points-in", tmp_path / "p.csv",
              "--points-to", tmp_path / "q.csv")
    assert res.code == 0, res.stderr
    assert "1 of its 10560 vectors are NaN or infinite (at indices x 13, y 9, z 7)" in res.stderr
    assert "p.csv: 1 points could not be solved" in res.stderr and ": points 3" in res.stderr
    q = read_points(tmp_path / "q.csv")
    assert np.isfinite(q[:2]).all() and np.isnan(q[2]).all()
    np.testing.assert_allclose(q[0], beside, rtol=0, atol=1e-6)
    # the other points move as through the field without the NaN
    assert run("apply", "-t", tmp_path / "clean.nii.gz", "--points-in", tmp_path / "p.csv",
               "--points-to", tmp_path / "r.csv").code == 0
    r = read_points(tmp_path / "r.csv")
    np.testing.assert_allclose(q[:2], r[:2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(r[2], node, rtol=0, atol=1e-6)


@pytest.mark.parametrize("suffix", [".nrrd", ".nii.gz"])
def test_points_near_a_nan_margin_are_solved_exactly(run, tmp_path, suffix):
    """A field with a NaN margin, as a warp's ``--displacement-to`` exports: every point solved.

    The field resamples through an affine map F (so its trilinear
    interpolation is exact), NaN over its first 4 planes in x (no preimage).
    Points F^-1(y) for y just inside the finite part lie, taken as output
    points, over the NaN: each is solved to y, none is left NaN or off. A
    point whose preimage is in the margin is NaN and named. A NIfTI field's
    warning says ITK reads its NaN as 0.
    """
    vol = smooth()
    nz, ny, nx = vol.data.shape
    k, j, i = np.mgrid[:nz, :ny, :nx].astype(float)
    world = vol.index_to_world(np.stack([i, j, k], -1).reshape(-1, 3)).reshape(nz, ny, nx, 3)
    m = np.array([[1.02, 0.03, 0.0], [-0.02, 0.97, 0.04], [0.01, 0.0, 1.05]])
    shift = np.array([-3.0, 1.5, 0.8])
    vec = world @ m.T + shift - world  # (u(y) = F(y) - y, F the map output -> input)
    vec[:, :, :4] = np.nan
    write_field(tmp_path / f"f{suffix}", vec, vol.origin)
    rng = np.random.default_rng(3)
    inside = vol.index_to_world(np.column_stack([rng.uniform(4.0, 6.0, 40),
                                                 rng.uniform(1, ny - 2, 40),
                                                 rng.uniform(1, nz - 2, 40)]))
    margin = vol.index_to_world([3.0, 10.0, 9.0])
    pts = np.vstack([inside, margin]) @ m.T + shift  # F(y): the input points
    # (the margin point's image is on the field, over its NaN: no point off the field, its
    # own image, answers it)
    assert 0 <= vol.world_to_index(pts[40])[0] < 3.5
    write_points(tmp_path / "p.csv", pts)
    res = run("apply", "-t", tmp_path / f"f{suffix}", "--points-in", tmp_path / "p.csv",
              "--points-to", tmp_path / "q.csv")
    assert res.code == 0, res.stderr
    q = read_points(tmp_path / "q.csv")
    np.testing.assert_allclose(q[:40], inside, rtol=0, atol=1e-5)
    assert np.isnan(q[40]).all() and "1 points could not be solved" in res.stderr
    assert ("ITK and ANTs, reading NaN in a NIfTI file as 0 (no move), differ there" in res.stderr) == (suffix == ".nii.gz")


def test_a_point_nothing_maps_to_is_nan_not_newtons_last_guess(run, tmp_path):
    """No point maps to it: NaN in the output (named), never Newton's last, finite guess.

    The field halves x about the grid's first plane (F(y) = y0 + (y - y0) / 2
    along x): on the field no point reaches beyond half its width, and a
    point there is on the field, so not its own image either. Newton swung
    between the field and beyond it, and its last guess (several mm off, a
    plausible coordinate) was written as the answer.
    """
    vol = smooth()
    nz, ny, nx = vol.data.shape
    k, j, i = np.mgrid[:nz, :ny, :nx].astype(float)
    world = vol.index_to_world(np.stack([i, j, k], -1).reshape(-1, 3)).reshape(nz, ny, nx, 3)
    x0 = vol.index_to_world([0.0, 0.0, 0.0])
    axis = vol.index_to_world([1.0, 0.0, 0.0]) - x0
    axis /= np.linalg.norm(axis)
    along = (world - x0) @ axis
    write_field(tmp_path / "half.nrrd", -0.5 * along[..., None] * axis, vol.origin)
    reached = vol.index_to_world([6.0, 10.0, 9.0])  # (the image of x index 12)
    beyond = vol.index_to_world([18.0, 10.0, 9.0])
    write_points(tmp_path / "p.csv", np.array([reached, beyond]))
    res = run("apply", "-t", tmp_path / "half.nrrd", "--points-in", tmp_path / "p.csv",
              "--points-to", tmp_path / "q.csv")
    assert res.code == 0, res.stderr
    assert "p.csv: 1 points could not be solved" in res.stderr and ": points 2" in res.stderr
    q = read_points(tmp_path / "q.csv")
    np.testing.assert_allclose(q[0], vol.index_to_world([12.0, 10.0, 9.0]), rtol=0, atol=1e-6)
    assert np.isnan(q[1]).all()
    # a Slicer markups file: the point without a position says so as Slicer does (JSON has
    # no NaN), and reads back as no point
    import json

    from volwarp_cli.warp.export import read_points as read_any

    # (a point given without a position is none to solve, not one that failed; a NaN
    # elsewhere in the file, a measurement's, is the file's own and kept)
    doc = {"markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "controlPoints": [
        {"label": "a", "position": list(reached)}, {"label": "b", "position": list(beyond)},
        {"label": "c", "position": [0.0, 0.0, 0.0], "positionStatus": "undefined"}],
        "measurements": [{"name": "length", "value": float("nan")}]}]}
    (tmp_path / "p.mrk.json").write_text(json.dumps(doc))
    res = run("apply", "-t", tmp_path / "half.nrrd", "--points-in", tmp_path / "p.mrk.json",
              "--points-to", tmp_path / "q.mrk.json")
    assert res.code == 0, res.stderr
    assert "p.mrk.json: 1 points could not be solved" in res.stderr and ": points 2" in res.stderr
    moved = json.loads((tmp_path / "q.mrk.json").read_text())
    a, b, c = moved["markups"][0]["controlPoints"]
    assert all(np.isfinite(p["position"]).all() for p in (a, b, c))  # (JSON has no NaN)
    np.testing.assert_allclose(a["position"], q[0], rtol=0, atol=1e-9)
    assert a.get("positionStatus", "defined") == "defined"
    assert b["positionStatus"] == "undefined" and c["positionStatus"] == "undefined"
    back = read_any(str(tmp_path / "q.mrk.json")).points
    assert np.isfinite(back[0]).all() and np.isnan(back[1:]).all()


def test_newton_never_steps_onto_nan_vectors():
    """A full Newton step past the solution into NaN vectors is halved back, not taken.

    Along x, F(x) = x + x^2 / 10 (convex: from the left, the tangent's root lies
    beyond the solution) and the field is NaN for 2.001 < x < 2.3. For the image
    of x = 2 (2.4, finite), Newton starts at 1.824 and its first step lands at
    2.0023: taken, the point was stuck on NaN and left unsolved; halved, it
    converges to 2.
    """
    from volwarp_cli.transforms import model

    class Convex:
        def map(self, p):
            p = np.asarray(p, float)
            out = p.copy()
            out[:, 0] = p[:, 0] + p[:, 0] ** 2 / 10
            out[(p[:, 0] > 2.001) & (p[:, 0] < 2.3)] = np.nan
            return out

        def displacement(self, p):
            return self.map(p) - np.asarray(p, float)

    target = np.array([[2.0 + 0.4, 1.0, -3.0]])
    q = model._newton(Convex(), target)
    np.testing.assert_allclose(q, [[2.0, 1.0, -3.0]], rtol=0, atol=1e-9)


def test_label_map_refusal_says_why_once(run, tmp_path):
    """The refusal of a blending interpolation on a label map: its exact words, said once."""
    from volwarp_cli.apply import plan_resample
    from volwarp_cli.errors import BadUsage
    from volwarp_cli.transforms.model import Chain

    vol = smooth()
    labels = (np.digitize(vol.data, [10, 40, 80]).astype(np.uint8) * 3 + 2)
    write_volume(vol.with_data(labels), tmp_path / "seg.nrrd")
    sitk.WriteTransform(affine(), str(tmp_path / "a.tfm"))
    res = run("apply", tmp_path / "seg.nrrd", "-o", tmp_path / "o.nrrd", "-t",
              tmp_path / "a.tfm", "--interpolation", "bspline")
    assert res.code == 2
    said = (f"volwarp: error: {tmp_path / 'seg.nrrd'} looks like a label map (4 labels): "
            "--interpolation bspline would blend its ids; give --values intensity to resample "
            "it as intensities (see '")
    assert res.stderr.startswith(said) and res.stderr.endswith(" apply --help')\n")
    assert res.stderr.count("label map") == 1 and res.stderr.count("\n") == 1
    with pytest.raises(BadUsage) as exc:  # labels asked for (the library's path)
        plan_resample(vol.header, labels, Chain(), values="labels", interpolation="linear",
                      name="seg.nrrd")
    assert str(exc.value) == ("seg.nrrd is resampled as labels (as asked): --interpolation "
                              "linear would blend its ids; a label map is resampled by nearest "
                              "neighbour")


def test_a_field_that_misses_the_grid_is_said_before_a_label_refusal(run, tmp_path):
    """The input's label rule runs beside the transforms' reading, but its refusal comes
    where it came before: after the field's coverage check, and after -v says the choice."""
    vol = smooth()
    labels = vol.with_data((vol.data > 40).astype(np.uint8) + (vol.data > 80))
    write_volume(labels, tmp_path / "lab.nrrd")
    sitk.WriteImage(field_on(smooth((6, 6, 6))), str(tmp_path / "small.nii.gz"))
    sitk.WriteImage(field_on(vol), str(tmp_path / "f.nii.gz"))
    res = run("apply", tmp_path / "lab.nrrd", "-o", tmp_path / "o.nrrd", "-t",
              tmp_path / "small.nii.gz", "--interpolation", "linear")
    assert res.code == 1 and "outside its 6x6x6 samples" in res.stderr, res.stderr
    res = run("apply", tmp_path / "lab.nrrd", "-o", tmp_path / "o.nrrd", "-t",
              tmp_path / "f.nii.gz", "--interpolation", "linear", "-v")
    lines = res.stderr.strip().splitlines()
    assert res.code == 2 and "would blend its ids" in lines[-1], res.stderr
    assert any(line.startswith("volwarp: values: labels (looks like a label map")
               for line in lines[:-1]), res.stderr
    assert not any("background:" in line for line in lines)
    assert not (tmp_path / "o.nrrd").exists()


@pytest.mark.parametrize("inside", [True, False])
def test_folder_as_transform_refused(run, inputs, inside):
    """``-t FOLDER``: it is not a transform (exit 1), whatever the output's place.

    With the output inside the folder it was refused as overwriting an input folder (exit 2).
    """
    folder = inputs / "reg"
    folder.mkdir()
    sitk.WriteTransform(affine(), str(folder / "0GenericAffine.mat"))
    (folder / "notes.txt").write_text("x\n")
    out = folder / "out.nrrd" if inside else inputs / "out.nrrd"
    res = run("apply", inputs / "in.nrrd", "-o", out, "-t", folder)
    assert res.code == 1
    assert res.stderr == (f"volwarp: error: {folder}: is a folder, not a transform file "
                          "(transform files in it: 0GenericAffine.mat)\n")
    assert not (folder / "out.nrrd").exists()
    assert (inputs / "out.nrrd").read_bytes() == b"old output"


def _centred():
    """One transform of each class with a centre (its FixedParameters), as SimpleITK makes them."""
    s = sitk.ScaleTransform(3, [1.1, 0.9, 1.05])
    s.SetCenter([2.0, 3.0, 4.0])
    v = sitk.VersorRigid3DTransform()
    v.SetRotation([1, 1, 0], 0.2)
    v.SetCenter([2.0, 0.0, 4.0])
    m = sitk.Similarity3DTransform()
    m.SetScale(1.05)
    m.SetCenter([2.0, 3.0, 4.0])
    return {"affine": affine(), "euler": euler(), "versor": v, "similarity": m, "scale": s}


@pytest.mark.parametrize("kept", [1, 2])
@pytest.mark.parametrize("fmt", ["tfm", "h5", "mat"])
@pytest.mark.parametrize("cls", ["affine", "euler", "versor", "similarity", "scale"])
def test_a_centre_cut_short_is_refused_as_itk_does(run, inputs, cls, fmt, kept):
    """FixedParameters of 1 or 2 values (a file cut inside the centre): ITK refuses the file;
    volwarp took the centre as 0 and resampled about the wrong point."""
    tr = _centred()[cls]
    path = inputs / f"cut.{fmt}"
    sitk.WriteTransform(tr, str(path))
    fixed = list(tr.GetFixedParameters())[:kept]
    if fmt == "tfm":
        text = path.read_text()
        head = text[:text.index("FixedParameters:")]
        path.write_text(head + "FixedParameters: " + " ".join(map(str, fixed)) + "\n")
    elif fmt == "h5":
        import h5py

        with h5py.File(path, "a") as f:
            g = f["TransformGroup/0"]
            del g["TransformFixedParameters"]
            g["TransformFixedParameters"] = np.array(fixed)
    else:
        import scipy.io

        doc = {k: v for k, v in scipy.io.loadmat(path).items() if not k.startswith("__")}
        doc["fixed"] = np.array(fixed).reshape(-1, 1)
        scipy.io.savemat(path, doc, format="4")
    with pytest.raises(RuntimeError):  # (SimpleITK: "parameters array size ... is less")
        sitk.ReadTransform(str(path))
    _refused(run, inputs, "-t", path, says=f"{path}: ")
    res = run("apply", inputs / "in.nrrd", "-o", inputs / "out.nrrd", "-t", path)
    assert f"has {kept} fixed parameters" in res.stderr, res.stderr


def test_a_text_file_without_fixed_parameters_is_refused(run, inputs):
    """No FixedParameters line: ITK reads the file as the identity (it drops the Parameters),
    where volwarp took them about the centre 0; neither is what the file says: refused."""
    path = inputs / "nofixed.tfm"
    sitk.WriteTransform(euler(), str(path))
    text = path.read_text()
    path.write_text(text[:text.index("FixedParameters:")])
    tr = sitk.ReadTransform(str(path))
    assert tr.TransformPoint([1.0, 2.0, 3.0]) == (1.0, 2.0, 3.0)  # (ITK: the identity)
    _refused(run, inputs, "-t", path,
             says=f"{path}: Euler3DTransform has Parameters but no FixedParameters line")


@pytest.mark.parametrize("versor", [(0.6, 0.6, 0.6), (0.0, 0.8, 0.6), (0.5, -0.5, 0.7071067811)])
@pytest.mark.parametrize("cls", ["VersorRigid3DTransform", "Similarity3DTransform"])
def test_a_versor_of_norm_1_or_above_is_normalised_as_itk_does(run, inputs, cls, versor):
    """ITK reads a versor whose norm is not below 1 (a hand-edited or rounded file) by
    normalising it (its SetParameters: a rotation near a half turn); volwarp refused it
    without naming the file. The same resampling as sitk.Resample."""
    extra = " 1.05" if cls == "Similarity3DTransform" else ""
    path = inputs / "big_versor.tfm"
    path.write_text("#Insight Transform File V1.0\n#Transform 0\n"
                    f"Transform: {cls}_double_3_3\n"
                    f"Parameters: {' '.join(map(str, versor))} 1 2 3{extra}\n"
                    "FixedParameters: 2 14 15\n")
    tr = sitk.ReadTransform(str(path))
    vol = read_volume(inputs / "in.nrrd")
    pts = world_points(vol)
    theirs = np.array([tr.TransformPoint(p.tolist()) for p in pts])
    assert np.abs(read_chain([str(path)]).map(pts) - theirs).max() < 1e-9
    res = run("apply", inputs / "in.nrrd", "-o", inputs / "o.nrrd", "-t", path,
              "--background-value", "0")
    assert res.code == 0, res
    ours = read_volume(inputs / "o.nrrd").data
    expect = sitk.GetArrayFromImage(sitk.Resample(to_sitk(vol), to_sitk(vol), tr,
                                                  sitk.sitkLinear, 0.0))
    assert np.abs(ours - expect).max() <= 1e-4 * float(np.ptp(vol.data))
    assert np.count_nonzero(ours) > 0.2 * ours.size  # (not a comparison of backgrounds)


def _several(kind: str, ref3):
    """A file of ``kind`` holding several volumes (or components) on ``ref3``'s 3-D grid."""
    if kind == "vector":  # a displacement field (5-D NIfTI, vector NRRD and MetaImage)
        img = sitk.GetImageFromArray(np.zeros((*ref3.GetSize()[::-1], 3), np.float32),
                                     isVector=True)
        img.CopyInformation(ref3)
        return img
    img = sitk.GetImageFromArray(np.zeros((3, *ref3.GetSize()[::-1]), np.float32),
                                 isVector=False)  # (fMRI, DWI: x, y, z, t)
    img.SetSpacing([*ref3.GetSpacing(), 2.0])
    img.SetOrigin([*ref3.GetOrigin(), 0.0])
    direction = np.eye(4)
    direction[:3, :3] = np.reshape(ref3.GetDirection(), (3, 3))
    img.SetDirection(direction.ravel().tolist())
    return img


@pytest.mark.parametrize("name", ["ref4d.nii.gz", "ref4d.mha", "field.nii.gz", "field.nrrd",
                                  "field.mha"])
def test_a_reference_of_several_volumes_gives_its_3d_grid(run, inputs, name):
    """A 4-D (fMRI, DWI) or vector (a field) reference: its first three dimensions are the
    grid, as antsApplyTransforms takes them. It was refused ("choose one with
    --volume-index N"), and --volume-index chooses the input's volume, not the reference's."""
    ref3 = to_sitk(Volume(np.zeros((18, 20, 21), np.float32), spacing=(1.2, 1.15, 1.25),
                          origin=(-8.0, 6.0, 4.0), direction=DIRECTION.T))
    sitk.WriteImage(ref3, str(inputs / "ref3.nrrd"))
    sitk.WriteImage(_several("vector" if name.startswith("field") else "4d", ref3),
                    str(inputs / name))
    sitk.WriteTransform(affine(), str(inputs / "a.tfm"))
    res = run("apply", inputs / "in.nrrd", "-o", inputs / "o.nrrd", "-t", inputs / "a.tfm",
              "--reference", inputs / name, "--background-value", "0")
    assert res.code == 0, res
    out = read_volume(inputs / "o.nrrd")
    assert out.shape_xyz == ref3.GetSize()
    assert np.allclose(out.spacing, ref3.GetSpacing())
    assert np.allclose(out.origin, ref3.GetOrigin())
    assert np.allclose(out.direction.ravel(), ref3.GetDirection())
    expect = sitk.Resample(to_sitk(read_volume(inputs / "in.nrrd")), ref3, affine(),
                           sitk.sitkLinear, 0.0)
    theirs = sitk.GetArrayFromImage(expect)
    assert np.abs(out.data - theirs).max() <= 1e-4 * float(np.ptp(theirs))
    assert np.count_nonzero(out.data) > 0.5 * out.data.size


def test_allow_outside_field_takes_itk_s_identity_past_the_field(run, tmp_path):
    """A template's field resampling a subject whose scan covers more (ANTs' inverse warp
    into a wider field of view) was refused with no way through; ITK and antsApplyTransforms
    take the field as the identity past its samples. --allow-outside-field asks for that,
    and the output equals SimpleITK's; without it the refusal names the flag."""
    vol = smooth()
    write_volume(vol, tmp_path / "in.nrrd")
    small = Volume(np.zeros((8, 9, 10), np.float32), spacing=(1.1, 1.0, 1.3),
                   origin=vol.index_to_world([6, 6, 5]), direction=DIRECTION)
    field = field_on(small)
    sitk.WriteImage(field, str(tmp_path / "small.nii.gz"))
    out = tmp_path / "out.nrrd"
    res = run("apply", tmp_path / "in.nrrd", "-o", out, "-t", tmp_path / "small.nii.gz",
              "--background-value", "0")
    assert res.code == 1 and "--allow-outside-field" in res.stderr and not out.exists()
    res = run("apply", tmp_path / "in.nrrd", "-o", out, "-t", tmp_path / "small.nii.gz",
              "--background-value", "0", "--allow-outside-field")
    assert res.code == 0, res.stderr
    theirs = sitk.GetArrayFromImage(sitk.Resample(
        to_sitk(vol), to_sitk(vol),
        sitk.DisplacementFieldTransform(sitk.Cast(sitk.ReadImage(str(tmp_path / "small.nii.gz")),
                                                  sitk.sitkVectorFloat64)),
        sitk.sitkLinear, 0.0))
    ours = read_volume(out).data
    assert np.abs(ours - theirs).max() <= 1e-4 * float(np.ptp(vol.data))
    assert not np.array_equal(ours, vol.data)  # (the field moved its part)
    res = run("apply", "-t", tmp_path / "small.nii.gz", "--allow-outside-field",
              "--points-in", tmp_path / "p.csv", "--points-to", tmp_path / "q.csv")
    assert res.code == 2 and "applies to the resampled volume" in res.stderr


@pytest.mark.parametrize("how", ["in memory", "by blocks", "by processes"])
@pytest.mark.parametrize("interp", ["linear", "bspline"])
def test_nan_samples_spread_as_in_itk_and_are_said(run, inputs, how, interp):
    """One NaN sample of a float input: the voxels ITK's Resample makes NaN, and a warning once.

    Linear and cubic interpolation blend a NaN into every point whose support
    reaches it (for cubic through the prefilter: many voxels). The output is
    ITK's there and the clean input's elsewhere; the count said is the
    output's (one block holds them all); nearest copies the sample and says
    nothing.
    """
    vol = read_volume(inputs / "in.nrrd")
    data = vol.data.copy()
    data[9, 10, 11] = np.nan  # (z, y, x)
    write_volume(Volume(data, spacing=vol.spacing, origin=vol.origin, direction=vol.direction,
                        space=vol.space), inputs / "nan.nrrd")
    sitk.WriteTransform(affine(), str(inputs / "a.tfm"))
    args = ["-t", inputs / "a.tfm", "--interpolation", interp, "--background-value", "0"]
    if how != "in memory":
        args += ["--chunked", "--block", "5,6,7"]
    if how == "by processes":
        args += ["--scheduler", "processes"]
    res = run("apply", inputs / "nan.nrrd", "-o", inputs / "o.nrrd", *args)
    assert res.code == 0, res.stderr
    ours = read_volume(inputs / "o.nrrd").data
    lost = np.isnan(ours)
    assert lost.any()
    said = (f"nan.nrrd: NaN or infinite samples (one at index x y z = 11 10 9), which {interp} "
            "interpolation blends into their neighbours: ")
    assert res.stderr.count(said) == 1, res.stderr
    if how == "in memory":
        assert f"{np.count_nonzero(lost)} voxels of {inputs / 'o.nrrd'} are NaN" in res.stderr
    theirs = sitk.GetArrayFromImage(sitk.Resample(
        to_sitk(Volume(data, spacing=vol.spacing, origin=vol.origin, direction=vol.direction,
                       space=vol.space)), to_sitk(vol), affine(),
        sitk.sitkLinear if interp == "linear" else sitk.sitkBSpline, 0.0))
    assert np.array_equal(lost, np.isnan(theirs))
    assert run("apply", inputs / "in.nrrd", "-o", inputs / "c.nrrd", *args).code == 0
    clean = read_volume(inputs / "c.nrrd").data
    assert np.array_equal(ours[~lost], clean[~lost])
    res = run("apply", inputs / "nan.nrrd", "-o", inputs / "n.nrrd", "-t", inputs / "a.tfm",
              "--interpolation", "nearest", "--background-value", "0")
    assert res.code == 0 and "NaN" not in res.stderr
    assert np.count_nonzero(np.isnan(read_volume(inputs / "n.nrrd").data)) <= 1
