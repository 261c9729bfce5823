"""Registrations and resamplings by ANTs and elastix themselves, for tests/test_apply_tools.py.

Runs in the peers' own environment (`make test` installs it in .venv-peers: antspyx pins
numpy < 2.4 and scipy < 1.16, which volwarp's environment is past), never imports volwarp,
and leaves in OUT the files those tools wrote and their own results as .npy arrays:

    python registrations.py ants OUT        fixed/moving images, 1Warp.nii.gz and
                                            0GenericAffine.mat, ants.apply_transforms'
                                            linear result (ants_linear.npy)
    python registrations.py ants-points OUT IN.csv OUT.csv WARP AFFINE
                                            ants.apply_transforms_to_points (LPS mm)
    python registrations.py elastix OUT     moving.nrrd, TransformParameters.0-2.txt (rigid,
                                            affine, B-spline), transformix's results with
                                            the final B-spline order 3 and 1

One thread, a fixed seed: the same files on every run.
"""

from __future__ import annotations

import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

os.environ["ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"] = "1"


def blobs():
    """A fixed blob and a moved, reshaped one with a second small blob: (z, y, x) arrays."""
    z, y, x = np.mgrid[:32, :30, :28].astype(np.float32)
    fixed = 100 * np.exp(-(((x - 14) / 6) ** 2 + ((y - 15) / 7) ** 2 + ((z - 16) / 8) ** 2))
    moving = (100 * np.exp(-(((x - 12) / 6.5) ** 2 + ((y - 16) / 6) ** 2
                             + ((z - 15) / 8.5) ** 2))
              + 20 * np.exp(-(((x - 18) / 3) ** 2 + ((y - 10) / 3) ** 2 + ((z - 20) / 3) ** 2)))
    return fixed.astype(np.float32), moving.astype(np.float32)


def ants_register(out: Path) -> None:
    import ants

    f, m = blobs()
    fi = ants.from_numpy(f.transpose(2, 1, 0).copy(), spacing=(1.1, 1.0, 1.2),
                         origin=(-5.0, 3.0, 2.0))
    mi = ants.from_numpy(m.transpose(2, 1, 0).copy(), spacing=(1.0, 1.1, 1.0),
                         origin=(-4.0, 2.0, 3.0))
    reg = ants.registration(fi, mi, type_of_transform="SyN", reg_iterations=(20, 10, 0),
                            outprefix=str(out / "r_"), random_seed=1)
    warp, aff = reg["fwdtransforms"]
    ants.image_write(fi, str(out / "fixed.nii.gz"))
    ants.image_write(mi, str(out / "moving.nii.gz"))
    theirs = ants.apply_transforms(fi, mi, [warp, aff], interpolator="linear",
                                   whichtoinvert=[False, False])
    np.save(out / "ants_linear.npy", theirs.numpy().transpose(2, 1, 0))
    (out / "transforms.json").write_text(json.dumps({"warp": warp, "affine": aff}))


def ants_points(src: Path, dst: Path, warp: str, aff: str) -> None:
    import ants
    import pandas as pd

    pts = pd.read_csv(src)[["x", "y", "z"]]
    back = ants.apply_transforms_to_points(3, pts, [warp, aff], whichtoinvert=[False, False])
    back.to_csv(dst, index=False)


def elastix_register(out: Path) -> None:
    # ITK's SWIG modules warn (DeprecationWarning) as they load
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        import itk
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
    itk.imwrite(mi, str(out / "moving.nrrd"))
    po = itk.ParameterObject.New()
    for kind in ("rigid", "affine", "bspline"):
        p = po.GetDefaultParameterMap(kind, 1)
        p["MaximumNumberOfIterations"] = ["30"]
        p["NumberOfSpatialSamples"] = ["500"]
        if kind == "bspline":
            p["FinalGridSpacingInPhysicalUnits"] = ["8"]
        po.AddParameterMap(p)
    os.chdir(out)  # (elastix names the initial transforms relative to where it ran)
    _, tp = itk.elastix_registration_method(fi, mi, parameter_object=po,
                                            log_to_console=False, output_directory=".",
                                            number_of_threads=1)
    for order in (3, 1):
        for i in range(tp.GetNumberOfParameterMaps()):
            tp.SetParameter(i, "FinalBSplineInterpolationOrder", str(order))
        np.save(out / f"transformix_order{order}.npy",
                itk.array_from_image(itk.transformix_filter(mi, tp)))
    (out / "fixed_grid.json").write_text(json.dumps(
        {"direction": d.tolist(), "origin": [-5.0, 3.0, 2.0]}))


def main(argv: list[str]) -> None:
    what, out = argv[0], Path(argv[1]).resolve()
    if what == "ants":
        ants_register(out)
    elif what == "ants-points":
        ants_points(Path(argv[2]), Path(argv[3]), argv[4], argv[5])
    elif what == "elastix":
        elastix_register(out)
    else:
        raise SystemExit(f"unknown job {what!r}")


if __name__ == "__main__":
    main(sys.argv[1:])
