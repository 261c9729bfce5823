"""The mesh chain (volwarp_cli.surface.pipeline), without click or files: exact answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from volwarp_cli.errors import VolwarpError
from volwarp_cli.surface.pipeline import (
    Cleanup,
    clean,
    label_indicator,
    label_meshes,
    labels_of,
    surface_mesh,
)
from volwarp_cli.surface.stats import mesh_stats
from volwarp_cli.volume import Volume


def _radius(n=32, c=15.5, spacing=(1.0, 1.0, 1.0)):
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float64)
    sx, sy, sz = spacing
    return np.sqrt(((x - c) * sx) ** 2 + ((y - c) * sy) ** 2 + ((z - c) * sz) ** 2)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.8, 1.0, 1.25)])
def test_sphere_area_and_volume_within_one_percent(spacing):
    r = 9.0
    vol = Volume(_radius(spacing=spacing).astype(np.float32), spacing=spacing)
    mesh, iso = surface_mesh(vol, r, inside="below")
    st = mesh_stats(mesh)
    assert iso == r and st["closed"] and st["components"] == 1
    assert st["area"] == pytest.approx(4 * math.pi * r * r, rel=0.01)
    assert st["volume"] == pytest.approx(4 / 3 * math.pi * r ** 3, rel=0.01)


def test_default_level_is_the_middle_of_the_range():
    data = np.zeros((10, 10, 10), np.float32)
    data[3:7, 3:7, 3:7] = 4.0
    mesh, iso = surface_mesh(Volume(data))
    assert iso == 2.0 and mesh.n_faces > 0


def test_a_level_never_crossed_is_an_error_unless_allowed():
    vol = Volume(_radius().astype(np.float32))
    with pytest.raises(VolwarpError, match=r"outside the data range.*scan\.nrrd.*--allow-empty"):
        surface_mesh(vol, 1e6, name="scan.nrrd")
    mesh, _ = surface_mesh(vol, 1e6, allow_empty=True)
    assert mesh.is_empty
    with pytest.raises(VolwarpError, match="never crossed"):
        surface_mesh(Volume(np.ones((5, 5, 5), np.float32)), 1.0)


def test_nan_samples_are_refused():
    data = np.ones((6, 6, 6), np.float32)
    data[2, 2, 2] = np.nan
    with pytest.raises(VolwarpError, match="NaN"):
        surface_mesh(Volume(data), 0.5)


def test_cap_closes_a_shape_on_the_border():
    data = np.zeros((12, 12, 12), np.float32)
    data[:6] = 1.0  # a slab touching three faces
    open_mesh, _ = surface_mesh(Volume(data), 0.5)
    closed, _ = surface_mesh(Volume(data), 0.5, cap=True)
    assert not mesh_stats(open_mesh)["closed"] and mesh_stats(closed)["closed"]


def test_cleanups_in_order():
    big = np.where(_radius(c=22.0) < 7, 1.0, 0.0) + np.where(_radius(c=8.0) < 4, 1.0, 0.0)
    vol = Volume(big.astype(np.float32))
    both, _ = surface_mesh(vol, 0.5)
    assert mesh_stats(both)["components"] == 2
    one, _ = surface_mesh(vol, 0.5, cleanup=Cleanup(largest_component=True))
    st = mesh_stats(one)
    assert st["components"] == 1 and st["volume"] > 4 / 3 * math.pi * 6 ** 3
    fewer = clean(one, Cleanup(decimate=0.5))
    assert fewer.n_faces <= one.n_faces * 0.55
    smooth = clean(one, Cleanup(smooth=10))
    assert mesh_stats(smooth)["volume"] == pytest.approx(st["volume"], rel=0.05)


def _labels():
    lab = np.zeros((16, 16, 16), np.uint16)
    lab[2:6, 2:7, 2:5] = 4  # 3 x 5 x 4 voxels (x y z)
    lab[8:14, 3:9, 5:11] = 9  # 6 x 6 x 6
    return Volume(lab, spacing=(0.5, 1.0, 2.0))


def test_label_indicator_and_its_refusals():
    vol = _labels()
    ind = label_indicator(vol, 9)
    assert ind.data.dtype == np.float32 and ind.data.sum() == 6 ** 3
    np.testing.assert_allclose(ind.spacing, vol.spacing)
    with pytest.raises(VolwarpError, match="label 5 does not occur"):
        label_indicator(vol, 5, name="seg.nrrd")
    with pytest.raises(VolwarpError, match="needs a label map"):
        label_indicator(Volume(np.zeros((4, 4, 4), np.float32)), 1)
    with pytest.raises(VolwarpError, match="no label other than 0"):
        labels_of(Volume(np.zeros((4, 4, 4), np.int8)))


def test_label_meshes_are_closed_boxes_of_the_labels_volume():
    """A box of a x b x c voxels: its indicator's surface at 0.5 runs along the voxels'
    faces, each of the 12 edges bevelled (a prism of cross-section 1/8 voxel face lost)
    and each of the 8 corners giving 1/12 voxel back: exactly abc - (a + b + c)/2 + 2/3
    voxels."""
    vol = _labels()
    got = dict(label_meshes(vol))
    assert list(got) == [4, 9] == labels_of(vol)
    voxel = 0.5 * 1.0 * 2.0
    for label, (a, b, c) in ((4, (3, 5, 4)), (9, (6, 6, 6))):
        st = mesh_stats(got[label])
        assert st["closed"] and st["components"] == 1
        exact = (a * b * c - (a + b + c) / 2 + 2 / 3) * voxel
        assert st["volume"] == pytest.approx(exact, rel=1e-9)
