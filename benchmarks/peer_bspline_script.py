"""The peers' whole job as a process: read a NRRD, resample it through a B-spline, write it.

    python benchmarks/peer_bspline_script.py sitk|vtk IN.nrrd COEFF.npy OUT

``COEFF.npy``: the offsets (voxels, ``[k, j, i, 3]``, (x, y, z) last) of a c^3
lattice spanning the volume, as ``volwarp warp`` moves its control points; each
peer gets the inverse (they pull back), as the in-process rows of
``bench_threads.py`` give them. SimpleITK writes an uncompressed NRRD, VTK an
uncompressed MetaImage (VTK has no NRRD writer); each imports only what it uses.
This is the like-for-like peer of a whole ``volwarp warp`` command: start-up,
reading and writing included.
"""

from __future__ import annotations

import sys

import numpy as np


def sitk_job(src: str, coeff: np.ndarray, dst: str) -> None:
    import SimpleITK as sitk

    img = sitk.ReadImage(src)
    c = coeff.shape[0]
    tx = sitk.BSplineTransformInitializer(img, [c - 3] * 3, 3)
    tx.SetParameters(np.concatenate([-coeff[..., d].ravel() for d in range(3)]).tolist())
    sitk.WriteImage(sitk.Resample(img, img, tx, sitk.sitkLinear, 0.0), dst, False)


def vtk_job(src: str, coeff: np.ndarray, dst: str) -> None:
    from vtkmodules.util import numpy_support as ns
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkFiltersHybrid import vtkBSplineTransform
    from vtkmodules.vtkImagingCore import vtkImageReslice
    from vtkmodules.vtkIOImage import vtkMetaImageWriter, vtkNrrdReader

    reader = vtkNrrdReader()
    reader.SetFileName(src)
    reader.Update()
    n = reader.GetOutput().GetDimensions()[0]
    c = coeff.shape[0]
    h = n / (c - 3.0)
    cimg = vtkImageData()
    cimg.SetDimensions(c, c, c)
    cimg.SetSpacing(h, h, h)
    cimg.SetOrigin(-0.5 - h, -0.5 - h, -0.5 - h)
    cimg.GetPointData().SetScalars(
        ns.numpy_to_vtk(np.asarray(-coeff, np.float32).reshape(-1, 3), deep=True))
    tr = vtkBSplineTransform()
    tr.SetCoefficientData(cimg)
    tr.SetBorderModeToZero()
    rs = vtkImageReslice()
    rs.SetInputConnection(reader.GetOutputPort())
    rs.SetResliceTransform(tr)
    rs.SetInterpolationModeToLinear()
    writer = vtkMetaImageWriter()
    writer.SetCompression(False)
    writer.SetFileName(dst)
    writer.SetInputConnection(rs.GetOutputPort())
    writer.Write()


if __name__ == "__main__":
    kind, src, coeff, dst = sys.argv[1:5]
    {"sitk": sitk_job, "vtk": vtk_job}[kind](src, np.load(coeff), dst)
