"""`volwarp apply` on files ANTs and elastix wrote, against their own resamplers.

antspyx and itk-elastix are not in the test extras (together 1.9 GB, and
antspyx pins numpy < 2.4 and scipy < 1.16): these tests run where they are
installed and skip elsewhere. A quick real registration of two blobs, in one
thread (reproducible files).
"""

from __future__ import annotations

import os
import warnings

import numpy as np
import pytest

from volwarp_cli.io import read_volume


def blobs():
    z, y, x = np.mgrid[:32, :30, :28].astype(np.float32)
    fixed = 100 * np.exp(-(((x - 14) / 6) ** 2 + ((y - 15) / 7) ** 2 + ((z - 16) / 8) ** 2))
    moving = (100 * np.exp(-(((x - 12) / 6.5) ** 2 + ((y - 16) / 6) ** 2
                             + ((z - 15) / 8.5) ** 2))
              + 20 * np.exp(-(((x - 18) / 3) ** 2 + ((y - 10) / 3) ** 2 + ((z - 20) / 3) ** 2)))
    return fixed.astype(np.float32), moving.astype(np.float32)


@pytest.fixture
def one_thread(monkeypatch):
    monkeypatch.setenv("ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS", "1")


def test_ants_warp_and_affine(run, tmp_path, one_thread):
    ants = pytest.importorskip("ants")
    f, m = blobs()
    fi = ants.from_numpy(f.transpose(2, 1, 0).copy(), spacing=(1.1, 1.0, 1.2), origin=(-5., 3., 2.))
    mi = ants.from_numpy(m.transpose(2, 1, 0).copy(), spacing=(1.0, 1.1, 1.0), origin=(-4., 2., 3.))
    reg = ants.registration(fi, mi, type_of_transform="SyN", reg_iterations=(20, 10, 0),
                            outprefix=str(tmp_path / "r_"), random_seed=1)
    warp, aff = reg["fwdtransforms"]
    assert warp.endswith("1Warp.nii.gz") and aff.endswith("0GenericAffine.mat")
    ants.image_write(fi, str(tmp_path / "fixed.nii.gz"))
    ants.image_write(mi, str(tmp_path / "moving.nii.gz"))
    theirs = ants.apply_transforms(fi, mi, [warp, aff], interpolator="linear",
                                   whichtoinvert=[False, False]).numpy().transpose(2, 1, 0)
    span = float(m.max() - m.min())
    for order, close in (((warp, aff), True), ((aff, warp), False)):
        res = run("apply", tmp_path / "moving.nii.gz", "-o", tmp_path / "out.nii.gz",
                  "--reference", tmp_path / "fixed.nii.gz", "-t", order[0], "-t", order[1],
                  "--background-value", "0")
        if not close and res.code == 1:  # the field's extent check caught the order
            assert "wrong order" in res.stderr
            continue
        assert res.code == 0, res
        err = np.abs(read_volume(tmp_path / "out.nii.gz").data - theirs).max()
        assert (err <= 1e-3 * span) if close else (err > 1e-2 * span)
    # points of the moving image into the fixed space: by the chain's inverse
    pts = np.array([[-1.0, 12.0, 18.0], [2.0, 15.0, 20.0], [5.0, 18.0, 22.0]])
    (tmp_path / "p.csv").write_text("x,y,z,t\n" + "".join(f"{a},{b},{c},0\n" for a, b, c in pts))
    res = run("apply", "-t", warp, "-t", aff, "--points-in", tmp_path / "p.csv",
              "--points-to", tmp_path / "q.csv")
    assert res.code == 0, res
    import pandas as pd

    q = pd.read_csv(tmp_path / "q.csv")[["x", "y", "z"]]
    back = ants.apply_transforms_to_points(3, q, [warp, aff], whichtoinvert=[False, False])
    assert np.abs(back.values - pts).max() < 1e-3


@pytest.mark.slow  # (loading itk-elastix takes 15 s)
def test_elastix_chain(run, tmp_path, one_thread):
    # ITK's SWIG modules warn (DeprecationWarning) as they load: as errors, the half-loaded
    # module crashes the process
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        itk = pytest.importorskip("itk")
        if not hasattr(itk, "elastix_registration_method"):
            pytest.skip("itk-elastix is not installed")
        _elastix_chain(run, tmp_path, itk)


def _elastix_chain(run, tmp_path, itk):
    f, m = blobs()
    fi = itk.image_from_array(f)
    fi.SetSpacing((1.1, 1.0, 1.2))
    fi.SetOrigin((-5.0, 3.0, 2.0))
    d = np.eye(3)
    d[:2, :2] = [[np.cos(0.1), -np.sin(0.1)], [np.sin(0.1), np.cos(0.1)]]
    fi.SetDirection(itk.matrix_from_array(d))
    mi = itk.image_from_array(m)
    mi.SetSpacing((1.0, 1.1, 1.0))
    mi.SetOrigin((-4.0, 2.0, 3.0))
    itk.imwrite(mi, str(tmp_path / "moving.nrrd"))
    po = itk.ParameterObject.New()
    for kind in ("rigid", "affine", "bspline"):
        p = po.GetDefaultParameterMap(kind, 1)
        p["MaximumNumberOfIterations"] = ["30"]
        p["NumberOfSpatialSamples"] = ["500"]
        if kind == "bspline":
            p["FinalGridSpacingInPhysicalUnits"] = ["8"]
        po.AddParameterMap(p)
    cwd = os.getcwd()
    os.chdir(tmp_path)  # (elastix names the initial transforms relative to where it ran)
    try:
        _, tp = itk.elastix_registration_method(fi, mi, parameter_object=po,
                                                log_to_console=False, output_directory=".",
                                                number_of_threads=1)
    finally:
        os.chdir(cwd)
    span = float(m.max() - m.min())
    last = tmp_path / "TransformParameters.2.txt"
    for order, interp in ((3, "bspline"), (1, "linear")):
        for i in range(tp.GetNumberOfParameterMaps()):
            tp.SetParameter(i, "FinalBSplineInterpolationOrder", str(order))
        theirs = itk.array_from_image(itk.transformix_filter(mi, tp))
        res = run("apply", tmp_path / "moving.nrrd", "-o", tmp_path / "out.nrrd", "-t", last,
                  "--interpolation", interp, "--background-value", "0")
        assert res.code == 0, res
        out = read_volume(tmp_path / "out.nrrd")  # on the fixed grid the file states
        assert np.allclose(out.direction, d) and np.allclose(out.origin, (-5.0, 3.0, 2.0))
        err = np.abs(out.data - theirs)
        if order == 1:  # transformix's order-1 spline mirrors at the edges, ITK's linear clamps
            err = err[2:-2, 2:-2, 2:-2]
        assert err.max() <= 1e-3 * span
