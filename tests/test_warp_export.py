"""`volwarp warp` exports: resampling and forward fields, Jacobian, ITK transform."""

from __future__ import annotations

import numpy as np
import pytest

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume

sitk = pytest.importorskip("SimpleITK")
nib = pytest.importorskip("nibabel")

ANG = np.deg2rad(20)
DIRECTION = np.array([[np.cos(ANG), -np.sin(ANG), 0], [np.sin(ANG), np.cos(ANG), 0], [0, 0, 1]])


def smooth_volume(shape=(24, 28, 32)):
    nz, ny, nx = shape
    z, y, x = np.mgrid[:nz, :ny, :nx].astype(float)
    data = (100 * np.exp(-((x - 15.5) ** 2 / 80 + (y - 13.5) ** 2 / 60 + (z - 11.5) ** 2 / 40))
            + 20 * np.sin(x / 5) * np.cos(y / 7)).astype(np.float32)
    return Volume(data, spacing=(1.0, 1.2, 1.5), origin=(-10, 5, 3), direction=DIRECTION)


def drag_spec(tmp_path, vol, by=(3.0, -2.0, 2.0), lattice=7, name="w.yaml"):
    c = [float(v) for v in vol.index_to_world([15.5, 13.5, 11.5])]
    t = [a + float(b) for a, b in zip(c, by, strict=True)]
    p = tmp_path / name
    p.write_text(f"version: 1\ncapture: {{lattice: {lattice}}}\nsteps:\n  - drag:\n"
                 f"      - {{from: [{c[0]!r}, {c[1]!r}, {c[2]!r}], "
                 f"to: [{t[0]!r}, {t[1]!r}, {t[2]!r}]}}\n")
    return p


@pytest.fixture
def scene(tmp_path):
    vol = smooth_volume()
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    return src, drag_spec(tmp_path, vol)


def _ncc_rms(a, b):
    a, b = a.astype(np.float64).ravel(), b.astype(np.float64).ravel()
    return np.corrcoef(a, b)[0, 1], np.sqrt(np.mean((a - b) ** 2)) / (b.max() - b.min())


@pytest.mark.parametrize("ext", [".nii.gz", ".nrrd"])
@pytest.mark.parametrize("crop", [False, True])
def test_itk_resamples_with_the_displacement_field_as_volwarp_warps(run, scene, tmp_path, ext,
                                                                    crop):
    src, spec = scene
    out, field = tmp_path / "out.nrrd", tmp_path / f"disp{ext}"
    res = run("warp", src, "--spec", spec, "-o", out, "--displacement-to", field,
              *(["--crop"] if crop else []))
    assert res.code == 0, res.stderr
    ref = sitk.ReadImage(str(out))
    f = sitk.ReadImage(str(field))
    assert f.GetSize() == ref.GetSize()
    assert np.allclose(f.GetOrigin(), ref.GetOrigin(), atol=1e-5)
    assert np.allclose(f.GetDirection(), ref.GetDirection(), atol=1e-6)
    assert np.allclose(f.GetSpacing(), ref.GetSpacing(), atol=1e-6)
    arr = sitk.GetArrayFromImage(f)
    arr = np.nan_to_num(arr)  # outside the lattice's image: no inverse
    f64 = sitk.GetImageFromArray(arr.astype(np.float64), isVector=True)
    f64.CopyInformation(f)
    warped = sitk.Resample(sitk.ReadImage(str(src)), ref,
                           sitk.DisplacementFieldTransform(f64), sitk.sitkLinear, 0.0)
    ncc, rms = _ncc_rms(sitk.GetArrayFromImage(warped), sitk.GetArrayFromImage(ref))
    assert ncc >= 0.995 and rms <= 0.01, (ncc, rms)
    # and a wrong sign (the forward field) would not do
    wrong = sitk.GetImageFromArray(-arr.astype(np.float64), isVector=True)
    wrong.CopyInformation(f)
    bad = sitk.Resample(sitk.ReadImage(str(src)), ref, sitk.DisplacementFieldTransform(wrong),
                        sitk.sitkLinear, 0.0)
    assert _ncc_rms(sitk.GetArrayFromImage(bad), sitk.GetArrayFromImage(ref))[1] > 0.02


def test_a_nifti_field_with_nan_vectors_says_what_itk_reads(run, scene, tmp_path):
    """Voxels without an inverse are NaN; ITK's NIfTI reader gives them as 0 (no move), so
    a resampling with the .nii.gz field differed from the warp where the .nrrd's did not
    (a review: 7.07 against 2.99). Said when a NIfTI field holds NaN, not for NRRD."""
    import json

    src, spec = scene
    said = {}
    for ext in (".nii.gz", ".nrrd"):
        res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--grid", "grow",
                  "--displacement-to", tmp_path / f"d{ext}", "--json")
        assert res.code == 0, res.stderr
        nan = json.loads(res.stdout)["displacement"]["no_preimage"]
        said[ext] = "ITK's NIfTI reader takes for 0" in res.stderr
    assert nan > 0 and said == {".nii.gz": True, ".nrrd": False}


def test_field_files_say_their_direction_and_layout(run, scene, tmp_path):
    import nibabel as nib
    import nrrd

    src, spec = scene
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd",
              "--forward-field-to", tmp_path / "f.nii.gz", "--displacement-to",
              tmp_path / "d.nii.gz")
    assert res.code == 0, res.stderr
    img = nib.load(tmp_path / "d.nii.gz")
    assert img.shape[3:] == (1, 3) and int(img.header["intent_code"]) == 1007
    assert b"resampling" in img.header["descrip"].tobytes()
    fimg = nib.load(tmp_path / "f.nii.gz")
    assert b"forward" in fimg.header["descrip"].tobytes()
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd",
              "--displacement-to", tmp_path / "d.nrrd", "--forward-field-to", tmp_path / "f.nrrd")
    assert res.code == 0, res.stderr
    _, hdr = nrrd.read(str(tmp_path / "d.nrrd"))
    assert hdr["kinds"] == ["vector", "domain", "domain", "domain"]
    assert hdr["volwarp_field"] == "resampling"
    assert hdr["displacement field type"] == "resampling"
    assert hdr["volwarp_command"] == "warp"
    _, fh = nrrd.read(str(tmp_path / "f.nrrd"))
    assert fh["volwarp_field"] == "forward" and "displacement field type" not in fh


def test_tfm_matches_the_forward_map_at_random_points(run, scene, tmp_path):
    from volwarp_cli.bspline.handles import map_params
    from volwarp_cli.bspline.lattice import Lattice

    src, spec = scene
    tfm = tmp_path / "f.tfm"
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--transform-to", tfm,
              "--forward-field-to", tmp_path / "f.nrrd")
    assert res.code == 0, res.stderr
    t = sitk.ReadTransform(str(tfm))
    assert "BSplineTransform" in t.GetName() or "BSpline" in str(t)
    # volwarp's forward map, independently: the lattice from the planned spec
    from volwarp_cli.bspline.plan import SpecUnits, plan, read_warp_spec
    from volwarp_cli.spec.loader import load_schema, load_spec, validate

    vol = read_volume(src)
    doc = load_spec(spec)
    validate(doc, load_schema("warp"))
    ws = read_warp_spec(doc)
    grid = Lattice.create(vol.shape_xyz, ws.capture.lattice, ws.capture.oversample)
    dq = plan(doc, ws, grid, np.zeros(grid.lattice[::-1] + (3,)), SpecUnits(vol))[-1].dq
    rng = np.random.default_rng(7)
    lo, hi = grid.origin, grid.origin + grid.spacing_h * np.array(grid.regions)
    s = rng.uniform(0, np.array(grid.regions), size=(10_000, 3))
    x = grid.origin + grid.spacing_h * s
    assert np.all((x >= lo) & (x <= hi))
    want = vol.index_to_world(map_params(dq, grid, s))
    p = vol.index_to_world(x)
    got = np.array([t.TransformPoint(q.tolist()) for q in p])
    assert np.max(np.abs(got - want)) <= 1e-6
    assert np.max(np.abs(want - p)) > 0.5  # the map does move points
    # the forward field file agrees at the voxel centres
    fwd = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "f.nrrd")))
    nz, ny, nx = vol.data.shape
    zz, yy, xx = np.mgrid[:nz, :ny, :nx]
    xi = np.stack([xx, yy, zz], -1).reshape(-1, 3).astype(float)
    pts = vol.index_to_world(xi)
    got = np.array([t.TransformPoint(q.tolist()) for q in pts[::97]])
    assert np.max(np.abs(got - pts[::97] - fwd.reshape(-1, 3)[::97])) <= 1e-4


def test_jacobian_against_finite_differences(run, scene, tmp_path):
    src, spec = scene
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--jacobian-to",
              tmp_path / "j.nrrd", "--forward-field-to", tmp_path / "f.nii.gz", "-v")
    assert res.code == 0, res.stderr
    assert "det dF/dx min" in res.stderr
    vol = read_volume(src)
    jac = read_volume(tmp_path / "j.nrrd").data.astype(np.float64)
    assert read_volume(tmp_path / "j.nrrd").meta["volwarp_field"] == "jacobian"
    f = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "f.nii.gz"))).astype(np.float64)
    # F(x) in world mm at voxel centres; d/d(index) by central differences, then
    # det dF_world/dx_world = det(dF_world/di) / det(M)
    pw = f.copy()
    nz, ny, nx = vol.data.shape
    zz, yy, xx = np.mgrid[:nz, :ny, :nx]
    pw += vol.index_to_world(np.stack([xx, yy, zz], -1).reshape(-1, 3).astype(float)).reshape(
        f.shape)
    d = [np.gradient(pw, axis=a) for a in (2, 1, 0)]  # d/di, d/dj, d/dk: [..., m]
    j = np.stack(d, axis=-1)  # [..., m, axis]
    m = vol.direction * vol.spacing[None, :]
    fd = np.linalg.det(j) / np.linalg.det(m)
    inner = (slice(2, -2),) * 3
    assert np.max(np.abs(fd[inner] - jac[inner])) < 0.02
    assert jac.min() < 0.95 and jac.max() > 1.05


@pytest.mark.parametrize("scale", [1.0, 1.1, 0.8])
def test_jacobian_of_affine_lattices(scale):
    from volwarp_cli.bspline.lattice import Lattice
    from volwarp_cli.warp.export import ForwardMap

    vol = smooth_volume()
    grid = Lattice.create(vol.shape_xyz, (7, 8, 9), 2)
    uni = grid.uniform_positions()
    centre = np.array(vol.shape_xyz) / 2.0
    dq = (scale - 1.0) * (uni - centre)  # every control point scaled about the centre
    fm = ForwardMap(grid, dq, vol)
    assert np.allclose(fm.jacobian(), scale ** 3, atol=1e-5)
    ff = fm.forward_field()
    nz, ny, nx = vol.data.shape
    zz, yy, xx = np.mgrid[:nz, :ny, :nx]
    x = np.stack([xx, yy, zz], -1).astype(float)
    want = (x - centre) * (scale - 1.0) @ fm.matrix.T
    assert np.allclose(ff, want, atol=1e-4)


def test_unmoved_lattice_exports_identity(run, tmp_path):
    vol = smooth_volume()
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    spec = tmp_path / "e.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 7}\nsteps: []\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--jacobian-to",
              tmp_path / "j.nii.gz", "--displacement-to", tmp_path / "d.nrrd", "--crop")
    assert res.code == 0, res.stderr
    assert np.all(read_volume(tmp_path / "j.nii.gz").data == 1.0)
    d = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "d.nrrd")))
    assert np.nanmax(np.abs(d)) < 1e-5 and not np.isnan(d).any()


def test_capture_file_input_exports_the_same(run, scene, tmp_path):
    src, spec = scene
    vwc = tmp_path / "s.vwc"
    assert run("capture", src, "--lattice", "7", "-o", vwc).code == 0
    for name, inp in (("a", src), ("b", vwc)):
        res = run("warp", inp, "--spec", spec, "-o", tmp_path / f"{name}.nrrd",
                  "--displacement-to", tmp_path / f"{name}_d.nrrd", "--transform-to",
                  tmp_path / f"{name}.tfm", "--jacobian-to", tmp_path / f"{name}_j.nrrd")
        assert res.code == 0, res.stderr
    da = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "a_d.nrrd")))
    db = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "b_d.nrrd")))
    assert np.array_equal(np.isnan(da), np.isnan(db))
    assert np.nanmax(np.abs(da - db)) == 0
    ta = (tmp_path / "a.tfm").read_text().split("#Transform 0")[1]
    tb = (tmp_path / "b.tfm").read_text().split("#Transform 0")[1]
    assert ta == tb


def test_folds_are_nan_and_reported(run, tmp_path):
    vol = smooth_volume()
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    spec = tmp_path / "fold.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 7}\nsteps:\n  - move:\n"
                    "      - {index: [3, 3, 3], by: [30.0, 0.0, 0.0]}\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--jacobian-to",
              tmp_path / "j.nrrd", "--displacement-to", tmp_path / "d.nrrd", "-v")
    assert res.code == 0, res.stderr
    assert read_volume(tmp_path / "j.nrrd").data.min() < 0
    assert "the map folds" in res.stderr and "below 0" in res.stderr
    d = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "d.nrrd")))
    assert np.isnan(d).any()


def test_unknown_field_extension_is_a_usage_error_before_any_work(run, scene, tmp_path):
    src, spec = scene
    for opt in ("--displacement-to", "--forward-field-to", "--jacobian-to", "--transform-to"):
        res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", opt,
                  tmp_path / "f.xyz")
        assert res.code == 2, (opt, res.stderr)
        assert not any(tmp_path.glob("o.nrrd")) and not any(tmp_path.glob("f.*"))
        assert not any(p.name.startswith(".") for p in tmp_path.iterdir())


def test_tripled_placement_is_refused(run, tmp_path):
    vol = smooth_volume()
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    spec = tmp_path / "t.yaml"
    spec.write_text("version: 1\ncapture: {lattice: 7, placement: tripled}\nsteps: []\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--transform-to",
              tmp_path / "f.tfm")
    assert res.code == 1
    assert "uniform placement" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o.nrrd").exists() and not (tmp_path / "f.tfm").exists()


def _random_map(n=40, sigma=1.5, seed=0, lattice=9, spacing=(1.0, 1.2, 1.5)):
    from volwarp_cli.bspline.lattice import Lattice
    from volwarp_cli.warp.export import ForwardMap

    grid = Lattice.create((n, n + 4, n - 3), (lattice,) * 3, 2)
    dq = np.random.default_rng(seed).normal(0, sigma, grid.lattice[::-1] + (3,))
    vol = Volume(np.zeros((n - 3, n + 4, n), np.uint8), spacing=spacing, direction=DIRECTION)
    return ForwardMap(grid, dq, vol)


@pytest.mark.parametrize("warm", [True, False])
@pytest.mark.parametrize("threads", [1, 2])
def test_fast_inverse_matches_the_numpy_reference(warm, threads):
    """The numba kernel and the vectorised Newton reference: the same voxels solved, the same
    field to float32 rounding, on a padded output (many voxels without a preimage)."""
    fm = _random_map()
    nx, ny, nz = fm.grid.input_shape
    pad = 5
    shape, shift = (nx + 2 * pad, ny + 2 * pad, nz + 2 * pad), np.full(3, -pad)
    ref, rc = fm._resampling_field_numpy(shape, shift)
    got, gc = fm.resampling_field(shape, shift, warm=warm, threads=threads)
    assert got.shape == ref.shape and got.dtype == np.float32
    assert gc == rc and 0 < rc["no_inverse"] < rc["voxels"]
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    ok = ~np.isnan(ref)
    assert np.max(np.abs(got[ok] - ref[ok])) <= 1e-5


def test_fast_inverse_residual_is_within_tolerance():
    """F(x) = y to < 1e-3 voxel (in fact ~1e-8) at every solved output voxel."""
    fm = _random_map(n=32, seed=4)
    nx, ny, nz = fm.grid.input_shape
    field, counts = fm.resampling_field((nx, ny, nz), np.zeros(3))
    zz, yy, xx = np.mgrid[:nz, :ny, :nx]
    y = np.stack([xx, yy, zz], -1).reshape(-1, 3).astype(float)
    d = field.reshape(-1, 3).astype(np.float64)
    ok = ~np.isnan(d).any(axis=1)
    assert ok.sum() == counts["voxels"] - counts["no_inverse"] - counts["folded"] > 0.95 * len(y)
    x = y[ok] + d[ok] @ fm.inverse.T  # world mm -> input voxels
    res = np.abs(fm.map_index(x) - y[ok]).max()
    assert res < 1e-3, res


def test_fast_jacobian_is_the_jacobian():
    fm = _random_map(sigma=3.0, seed=2)
    assert np.max(np.abs(fm._jacobian_fast(threads=2) - fm.jacobian())) <= 1e-5


def test_fast_inverse_folds_are_at_least_as_strict():
    """A folding map: every voxel the reference leaves NaN for a fold is NaN here too; where
    both are solved the preimage is the reference's (the fold image is unchanged), and every
    voxel the reference solves is solved (the warm start falls back to its start)."""
    fm = _random_map(n=30, sigma=8.0, seed=3, lattice=7)
    assert fm.jacobian().min() < 0
    nx, ny, nz = fm.grid.input_shape
    shape, shift = (nx + 4, ny + 4, nz + 4), np.full(3, -2)
    ref, rc = fm._resampling_field_numpy(shape, shift)
    got, gc = fm.resampling_field(shape, shift)
    assert rc["folded"] > 0 and gc["folded"] >= rc["folded"]
    rn, gn = np.isnan(ref).any(-1), np.isnan(got).any(-1)
    assert not (gn & ~rn).any()  # nothing the reference solves is lost
    assert gc["no_inverse"] <= rc["no_inverse"]
    # the reference's fold marks (status 2) are NaN here
    flat = fm._fold_image(shape, shift).reshape(rn.shape)
    assert np.all(gn[flat])


def test_json_reports_the_exports_figures(run, tmp_path):
    """`warp --json` with exports: the Jacobian's extremes and fractions are those of the
    written map, the displacement's folded count that of its NaN voxels."""
    import json

    vol = smooth_volume()
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    spec = tmp_path / "fold.yaml"
    spec.write_text("version: 1\nunits: voxel\ncapture: {lattice: 7}\nsteps:\n  - move:\n"
                    "      - {index: [3, 3, 3], by: [30.0, 0.0, 0.0]}\n")
    res = run("warp", src, "--spec", spec, "-o", tmp_path / "o.nrrd", "--jacobian-to",
              tmp_path / "j.nrrd", "--displacement-to", tmp_path / "d.nrrd", "--json", "-v")
    assert res.code == 0, res.stderr

    def no_constant(name):
        raise AssertionError(f"non-strict JSON token {name}")

    doc = json.loads(res.stdout, parse_constant=no_constant)
    assert "the map folds" in res.stderr and "volwarp:" not in res.stdout
    jac = read_volume(tmp_path / "j.nrrd").data.astype(np.float64)
    j = doc["jacobian"]
    assert j["path"] == str(tmp_path / "j.nrrd")
    assert j["min"] == pytest.approx(jac.min()) and j["max"] == pytest.approx(jac.max())
    assert j["below_0"] == pytest.approx(np.mean(jac < 0)) and j["below_0"] > 0
    assert j["below_0_1"] == pytest.approx(np.mean(jac < 0.1))
    assert j["below_0_1"] >= j["below_0"]
    d = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "d.nrrd")))
    disp = doc["displacement"]
    assert disp["voxels"] == d.shape[0] * d.shape[1] * d.shape[2]
    nan = np.isnan(d).any(axis=-1)
    assert disp["folded"] > 0 and disp["folded"] + disp["no_preimage"] == int(nan.sum())
    assert doc["handles"] == []


def test_apply_of_a_grown_grid_s_field_in_another_format_keeps_the_input_s_rim(run, tmp_path):
    """A ``--grid grow`` field (NaN where a node has no preimage) in a .nii.gz, applied onto
    the warp's .nrrd output: the same as through a .nrrd field.

    The NIfTI's float32 origin puts its nodes a few 1e-6 voxel off the output's: every
    output voxel on the input's outer layer blended a NaN node with a weight of 1e-6 and
    took the background (the review's oblique 44x50x36 case: 2026 voxels off by over 1%).
    """
    vol = smooth_volume()
    vol.origin = (-67.5064, -24.7584, -33.7148)  # (float32's rounding needs a large origin)
    src = tmp_path / "in.nrrd"
    write_volume(vol, src)
    spec = drag_spec(tmp_path, vol, by=(6.0, -4.0, 3.0))
    outs = {}
    for ext in (".nii.gz", ".nrrd"):
        out, field = tmp_path / f"out{ext[:4]}.nrrd", tmp_path / f"disp{ext}"
        res = run("warp", src, "--spec", spec, "--grid", "grow", "-o", out,
                  "--displacement-to", field)
        assert res.code == 0, res.stderr
        vectors = (nib.load(field).get_fdata() if ext == ".nii.gz"
                   else read_volume(field, volume_index=0).data)
        assert np.isnan(vectors).any()  # (the nodes with no preimage)
        res = run("apply", src, "-o", tmp_path / f"a{ext[:4]}.nrrd", "--reference", out,
                  "-t", field, "--background-value", "-1000")
        assert res.code == 0, res.stderr
        outs[ext] = read_volume(tmp_path / f"a{ext[:4]}.nrrd").data
    assert np.count_nonzero(outs[".nrrd"] == -1000) > 0
    assert np.count_nonzero(outs[".nii.gz"] == -1000) == np.count_nonzero(outs[".nrrd"] == -1000)
    np.testing.assert_allclose(outs[".nii.gz"], outs[".nrrd"], atol=1e-3 * np.ptp(vol.data))


@pytest.mark.parametrize("name", [b"s\xc3\xa4.nrrd", b"caf\xe9.nrrd"])
def test_an_input_name_beyond_ascii_is_kept_in_the_transform_file(run, tmp_path, name):
    """A .tfm's comments name the input: "sä.nrrd" (UTF-8) was an internal error, as was a
    name that is not UTF-8 at all. The transform reads in SimpleITK as the ASCII-named one."""
    import os

    vol = smooth_volume()
    src = tmp_path / os.fsdecode(name)
    write_volume(vol, src)
    write_volume(vol, tmp_path / "plain.nrrd")
    spec = drag_spec(tmp_path, vol)
    params = {}
    for inp, tfm in ((src, tmp_path / "named.tfm"), (tmp_path / "plain.nrrd", tmp_path / "p.tfm")):
        res = run("warp", inp, "--spec", spec, "--transform-to", tfm)
        assert res.code == 0, res.stderr
        params[tfm.name] = sitk.BSplineTransform(sitk.ReadTransform(str(tfm))).GetParameters()
    assert params["named.tfm"] == params["p.tfm"]
    comment = [ln for ln in (tmp_path / "named.tfm").read_bytes().decode("utf-8").splitlines()
               if ln.startswith("#volwarp_input")]
    assert comment == ["#volwarp_input: " + (os.fsdecode(name) if name.isascii() or
                                             b"\xc3" in name else "caf\\udce9.nrrd")]
