"""NIfTI's float32 matrices: a grid they move by a hundredth of a voxel or more is said.

Within the format's precision, but silent: the writers hunt's grid of 1e-3 mm voxels
1e5 mm from the origin was written 1.23 voxels off (:func:`volwarp_cli.io.nifti._say_float32_shift`).
"""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest


def test_a_nifti_whose_float32_matrix_moves_the_grid_says_so(run, tmp_path):
    """1e-3 mm voxels 1e5 mm out: float32's step there is 0.008 mm, and the written grid
    lay 1.23 voxels off without a word (the writers hunt). Said now, with the shift
    nibabel reads; a usual grid says nothing."""
    from volwarp_cli.io import write_volume
    from volwarp_cli.volume import Volume

    far = Volume(np.zeros((4, 5, 6), np.float32), spacing=(1e-3, 1e-3, 1e-3),
                 origin=(1e5 + 0.00123, 0.0, 0.0))
    src = tmp_path / "far.nrrd"
    write_volume(far, src)
    r = run("convert", src, "-o", tmp_path / "far.nii")
    assert r.code == 0
    said = float(r.stderr.split("by up to ")[1].split(" voxels")[0])
    aff = nib.load(str(tmp_path / "far.nii")).affine
    moved = abs(-aff[0, 3] - (1e5 + 0.00123)) / 1e-3  # (RAS x is -LPS x)
    assert said == pytest.approx(moved, rel=0.01) and moved > 1
    near = tmp_path / "near.nrrd"
    write_volume(Volume(np.zeros((4, 5, 6), np.float32), origin=(100.3, 5.0, 0.0)), near)
    r = run("convert", near, "-o", tmp_path / "near.nii")
    assert r.code == 0 and r.stderr == ""
