"""`distance`: exact signed Euclidean (vs scipy), min-norm (vs distance_transform_cdt), CLI."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ball
from scipy import ndimage as ndi

from volwarp_cli.distance.exact import signed_edt
from volwarp_cli.distance.field import signed_distance
from volwarp_cli.distance.minnorm import minnorm_signed, passes_needed
from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.volume import Volume


def blobs(shape, seed, sigma=2.5, level=0.5):
    rng = np.random.default_rng(seed)
    return ndi.gaussian_filter(rng.random(shape), sigma) > level


def scipy_signed(mask, sampling):
    return (ndi.distance_transform_edt(~mask, sampling=sampling)
            - ndi.distance_transform_edt(mask, sampling=sampling))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (2.5, 1.0, 0.7), (0.3, 1.7, 1.1)])
def test_signed_edt_matches_scipy_on_random_blobs(seed, spacing):
    mask = blobs((23, 31, 37), seed)
    assert 0.2 < mask.mean() < 0.8
    got = signed_edt(mask, spacing)
    ref = scipy_signed(mask, spacing)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-4)


def test_signed_edt_sign_and_thin_shapes():
    mask = np.zeros((9, 10, 11), bool)
    mask[4, 5, :] = True  # a one-voxel line: every inside voxel is 1 away from outside
    d = signed_edt(mask, (1, 1, 1))
    assert np.all(d[mask] == -1.0)
    assert d[4, 5 + 3, 2] == 3.0 and d[0, 5, 0] == 4.0
    np.testing.assert_allclose(d, scipy_signed(mask, (1, 1, 1)), atol=1e-5)


@pytest.mark.parametrize("seed", [3, 4])
def test_minnorm_equals_cdt_taxicab(seed):
    mask = blobs((19, 33, 40), seed)
    got, passes = minnorm_signed(mask)
    ref = (ndi.distance_transform_cdt(~mask, metric="taxicab")
           - ndi.distance_transform_cdt(mask, metric="taxicab"))
    np.testing.assert_array_equal(got, ref.astype(np.float32))
    # log2 passes per axis (the paper: log2 w + log2 h per side), both sides
    assert passes == 2 * (passes_needed(19) + passes_needed(33) + passes_needed(40))
    assert passes == 2 * (5 + 6 + 6)


def test_minnorm_with_spacing_is_weighted_taxicab():
    mask = np.zeros((6, 7, 8), bool)
    mask[2, 3, 4] = True
    mask[4, 1, 1] = True
    h = (2.0, 0.5, 1.5)  # z, y, x
    got, _ = minnorm_signed(mask, h)
    sites = np.argwhere(mask)
    idx = np.indices(mask.shape).reshape(3, -1).T
    brute = np.min(np.abs(idx[:, None, :] - sites[None]) @ np.array(h), axis=1)
    brute = brute.reshape(mask.shape)
    brute[mask] = -min(h)  # inside: distance to the nearest outside voxel
    np.testing.assert_allclose(got, brute, atol=1e-6)


@pytest.mark.parametrize("metric", ["chessboard", "taxicab"])
def test_cdt_metrics(metric):
    mask = blobs((15, 20, 25), 5)
    got, _ = signed_distance(mask.astype(np.uint8), (2, 2, 2), iso=0.5, metric=metric)
    ref = 2.0 * (ndi.distance_transform_cdt(~mask, metric=metric)
                 - ndi.distance_transform_cdt(mask, metric=metric))
    np.testing.assert_array_equal(got, ref.astype(np.float32))


def test_cdt_metrics_refuse_anisotropic_spacing():
    from volwarp_cli.errors import VolwarpError

    with pytest.raises(VolwarpError, match="isotropic"):
        signed_distance(ball(12).astype(np.uint8), (1, 1, 2), iso=0.5, metric="chessboard")


def test_inside_below_and_iso():
    data = (200 - 150 * ball(20)).astype(np.int16)  # 50 inside, 200 outside
    d_below, _ = signed_distance(data, (1, 1, 1), iso=120, inside="below")
    d_above, _ = signed_distance(ball(20), (1, 1, 1), iso=0.5)
    np.testing.assert_array_equal(d_below, d_above)


# -- command line -------------------------------------------------------------

def write_ball(path, spacing=(1.0, 1.5, 2.0), n=24, origin=(3.0, -2.0, 5.0)):
    vol = Volume((ball(n, n / 3.2) * 200).astype(np.uint8), spacing=spacing, origin=origin)
    write_volume(vol, path)
    return vol


def test_cli_distance_matches_scipy_and_keeps_geometry(run, tmp_path):
    vol = write_ball(tmp_path / "b.nrrd")
    r = run("distance", tmp_path / "b.nrrd", "-o", tmp_path / "d.nrrd", "--iso", 100)
    assert r.code == 0, r.stderr
    out = read_volume(tmp_path / "d.nrrd")
    assert out.data.dtype == np.float32
    assert out.same_grid(vol)
    ref = scipy_signed(vol.data >= 100, vol.spacing[::-1])
    np.testing.assert_allclose(out.data, ref, atol=1e-4)
    assert "metric=euclidean" in out.meta["volwarp_distance"]
    assert out.meta["volwarp_command"] == "distance"
    assert out.meta["volwarp_input"] == "b.nrrd"


def test_cli_distance_is_deterministic(run, tmp_path):
    write_ball(tmp_path / "b.nrrd")
    for name in ("1.nrrd", "2.nrrd"):
        assert run("distance", tmp_path / "b.nrrd", "-o", tmp_path / name, "--iso", 100,
                   "--metric", "minnorm").code == 0
    assert (tmp_path / "1.nrrd").read_bytes() == (tmp_path / "2.nrrd").read_bytes()


def test_cli_unsigned_and_max_distance(run, tmp_path):
    vol = write_ball(tmp_path / "b.nrrd")
    r = run("distance", tmp_path / "b.nrrd", "-o", tmp_path / "u.nrrd", "--iso", 100,
            "--unsigned", "--max-distance", 4)
    assert r.code == 0, r.stderr
    u = read_volume(tmp_path / "u.nrrd").data
    ref = np.minimum(ndi.distance_transform_edt(~(vol.data >= 100), sampling=vol.spacing[::-1]), 4)
    np.testing.assert_allclose(u, ref, atol=1e-4)
    assert u.min() == 0.0 and u.max() == 4.0


def test_cli_real_scan_voxel_mode_matches_scipy(run, tmp_path, data_dir):
    src = data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd"
    r = run("distance", src, "-o", tmp_path / "d.nrrd", "--iso", 40, "--surface", "voxel")
    assert r.code == 0, r.stderr
    vol = read_volume(src)
    out = read_volume(tmp_path / "d.nrrd")
    assert out.same_grid(vol)
    ref = scipy_signed(vol.data >= 40, vol.spacing[::-1])
    np.testing.assert_allclose(out.data, ref, atol=2e-3)


def test_cli_real_scan_subvoxel_is_close_to_voxel_mode(run, tmp_path, data_dir):
    src = data_dir / "mri_t1_head_coronal_2x2x3mm.nrrd"
    assert run("distance", src, "-o", tmp_path / "s.nrrd", "--iso", 40).code == 0
    vol = read_volume(src)
    sub = read_volume(tmp_path / "s.nrrd").data
    mask = vol.data >= 40
    assert np.all(sub[mask] <= 0) and np.all(sub[~mask] >= 0)  # sign from the samples
    vox = scipy_signed(mask, vol.spacing[::-1])
    # the sub-voxel surface lies between the voxel centres the binary field puts at +-h
    assert np.max(np.abs(sub - vox)) < 2 * vol.spacing.max()


def test_cli_errors(run, tmp_path):
    write_ball(tmp_path / "b.nrrd")
    out = tmp_path / "d.nrrd"
    # the ball (0/200 uint8) is a label map: an --iso that selects other voxels than its
    # label is a usage error; as intensities, the shape's own errors
    r = run("distance", tmp_path / "b.nrrd", "-o", out, "--iso", 250)
    assert r.code == 2 and "looks like a label map" in r.stderr and not out.exists()
    r = run("distance", tmp_path / "b.nrrd", "-o", out, "--iso", 250, "--values", "intensity")
    assert r.code == 1 and "empty" in r.stderr and not out.exists()
    r = run("distance", tmp_path / "b.nrrd", "-o", out, "--iso", -1, "--values", "intensity")
    assert r.code == 1 and f"{tmp_path / 'b.nrrd'}: the shape fills the whole grid" in r.stderr
    r = run("distance", tmp_path / "b.nrrd", "-o", out, "--values", "intensity")
    assert r.code == 2 and "--iso" in r.stderr
    write_volume(Volume(ball(12) * np.float32(0.5)), tmp_path / "f.nrrd")  # no label map
    r = run("distance", tmp_path / "f.nrrd", "-o", out)
    assert r.code == 2 and "--iso" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = run("distance", tmp_path / "b.nrrd", "-o", out, "--iso", 1, "--metric", "chessboard")
    assert r.code == 1 and "isotropic" in r.stderr
    r = run("distance", tmp_path / "missing.nrrd", "-o", out, "--iso", 1)
    assert r.code == 1 and "missing.nrrd" in r.stderr
    r = run("distance", tmp_path / "b.nrrd", "-o", tmp_path / "nope" / "d.nrrd", "--iso", 1)
    assert r.code == 1 and "does not exist" in r.stderr
    assert not out.exists()


def test_cli_refuses_what_does_not_fit_in_memory(run, tmp_path, monkeypatch):
    write_ball(tmp_path / "b.nrrd")
    monkeypatch.setenv("VOLWARP_MEMORY_LIMIT", "100000")
    r = run("distance", tmp_path / "b.nrrd", "-o", tmp_path / "d.nrrd", "--iso", 100)
    assert r.code == 1 and "memory" in r.stderr
    assert not (tmp_path / "d.nrrd").exists()


def test_signed_edt_property_against_scipy():
    from hypothesis import given, settings
    from hypothesis import strategies as st
    from hypothesis.extra.numpy import arrays

    @settings(max_examples=40, deadline=None)
    @given(arrays(bool, st.tuples(st.integers(1, 7), st.integers(1, 9), st.integers(1, 11))),
           st.tuples(*[st.floats(0.25, 4.0)] * 3))
    def check(mask, spacing):
        if mask.all() or not mask.any():
            return
        got = signed_edt(mask, spacing)
        np.testing.assert_allclose(got, scipy_signed(mask, spacing), rtol=1e-5, atol=1e-4)
        got_mn, _ = minnorm_signed(mask)
        ref_mn = (ndi.distance_transform_cdt(~mask, metric="taxicab")
                  - ndi.distance_transform_cdt(mask, metric="taxicab"))
        np.testing.assert_array_equal(got_mn, ref_mn)

    check()


def test_cli_nan_samples_are_outside_and_reported(run, tmp_path):
    vol = write_ball(tmp_path / "b.nrrd")
    data = vol.data.astype(np.float32)
    data[0, 0, :4] = np.nan  # corner samples, outside the ball anyway
    data[data.shape[0] // 2, data.shape[1] // 2, data.shape[2] // 2] = np.nan  # the centre
    write_volume(vol.with_data(data), tmp_path / "n.nrrd")
    r = run("distance", tmp_path / "n.nrrd", "-o", tmp_path / "d.nrrd", "--iso", 100)
    assert r.code == 0, r.stderr
    assert "5 NaN samples" in r.stderr and "outside" in r.stderr
    out = read_volume(tmp_path / "d.nrrd").data
    c = tuple(n // 2 for n in data.shape)
    assert out[c] > 0  # the NaN centre is a one-voxel hole: outside
    assert np.isfinite(out).all()


@pytest.mark.parametrize("chunked", [False, True])
def test_nan_samples_leave_a_binary_mask_binary(run, tmp_path, chunked):
    """A 0/1 float mask with two NaN corners (outside anyway) has the distances of the same
    mask without them: voxel-centre ones, as scipy's. The NaN made the samples look
    non-binary, and the surface switched to the sub-voxel one, half a voxel off everywhere
    (3 2 1 -1 -2 became 2.5 1.5 0.5 -0.5 -1.5). Said once, not once per check."""
    from scipy import ndimage

    mask = np.zeros((20, 20, 20), np.float32)
    mask[6:14, 6:14, 6:14] = 1
    with_nan = mask.copy()
    with_nan[0, 0, 0] = with_nan[19, 19, 19] = np.nan
    write_volume(Volume(with_nan), tmp_path / "n.nrrd")
    extra = ["--chunked", "--block", "8"] if chunked else []
    r = run("distance", tmp_path / "n.nrrd", "-o", tmp_path / "d.nrrd", "--iso", "0.5",
            "--values", "intensity", *extra)
    assert r.code == 0, r.stderr
    assert r.stderr.count("2 NaN samples") == 1, r.stderr
    inside = mask > 0.5
    want = ndimage.distance_transform_edt(~inside) - ndimage.distance_transform_edt(inside)
    np.testing.assert_allclose(read_volume(tmp_path / "d.nrrd").data, want, atol=1e-5)


def test_options_that_contradict_each_other_are_a_usage_error(run, data_dir, tmp_path):
    """Exit 2 before any read (a batch's dry run then catches it up front): it was exit 1."""
    res = run("distance", data_dir / "ball_30_uint8.nrrd", "--iso", "100", "--values",
              "intensity", "--surface", "subvoxel", "--metric", "minnorm", "-o",
              tmp_path / "d.nrrd")
    assert res.code == 2 and "need the euclidean metric" in res.stderr, res
    assert not (tmp_path / "d.nrrd").exists()


def test_a_sheared_grid_is_refused_not_measured_along_its_axes(run, tmp_path):
    """The passes measure along the index axes by their spacing: on a grid whose z axis
    leans (a NRRD's space directions, a skewed sform, DICOM with --keep-shear) the field
    was off by 3.5 mm in a 10 mm ball, exit 0. Refused in distance, the API and morph (whose
    shapes' fields are distance's); a grid off a right angle by a DICOM header's rounding
    (a few millionths) is measured as before."""
    from volwarp_cli import api
    from volwarp_cli.errors import VolwarpError

    z, y, x = np.indices((20, 24, 24))
    data = (6.0 - np.sqrt((x - 12.0) ** 2 + (y - 12.0) ** 2 + (z - 10.0) ** 2)).astype(np.float32)
    lean = np.array([[1.0, 0, 0], [0, 1, 0.5], [0, 0, 1]])
    lean[:, 2] /= np.linalg.norm(lean[:, 2])
    sheared = tmp_path / "shear.nrrd"
    write_volume(Volume(data, direction=lean), sheared)
    out = tmp_path / "d.nrrd"
    res = run("distance", sheared, "--iso", "0", "-o", out)
    assert res.code == 1 and "shear.nrrd: its grid is sheared" in res.stderr, res.stderr
    assert not out.exists()
    with pytest.raises(VolwarpError, match="sheared"):
        api.distance(sheared, iso=0)
    res = run("morph", sheared, sheared, "--frames", "2", "--iso", "0",
              "-o", tmp_path / "m_{i}.nrrd")
    assert res.code == 1 and "sheared" in res.stderr and not list(tmp_path.glob("m_*"))
    # rounding off a right angle: measured, the same field as on the exact grid
    near = np.eye(3)
    near[:, 0] = [1.0, 3e-6, 0.0]
    near[:, 0] /= np.linalg.norm(near[:, 0])
    write_volume(Volume(data, direction=near), tmp_path / "near.nrrd")
    write_volume(Volume(data), tmp_path / "exact.nrrd")
    for name in ("near", "exact"):
        assert run("distance", tmp_path / f"{name}.nrrd", "--iso", "0",
                   "-o", tmp_path / f"d_{name}.nrrd").code == 0
    assert np.array_equal(read_volume(tmp_path / "d_near.nrrd").data,
                          read_volume(tmp_path / "d_exact.nrrd").data)
