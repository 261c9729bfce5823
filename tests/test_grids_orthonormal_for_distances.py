"""Grids whose direction's columns are not unit vectors at right angles, where distances are measured.

A morph spec's explicit ``grid: direction`` was taken as given: a sheared or
scaled one put the frames where the spec said, but the fill of the voxels no
input covers stepped by the spacing along the axes, as if they were unit and
at right angles (against scipy's exact EDT on the same world points: 26 to
46 % off on a grid whose z axis leans 45 degrees, up to 50 % under and 74 %
over on scaled columns), and the density's default width was the spacing, not
the voxel's world step. Such a grid is now a spec error at ``grid.direction``.
A MetaImage's ``TransformMatrix`` may hold scaled columns too (ITK keeps them):
``distance`` measured by the spacing there, 50 % off, and now refuses it, as
``distance --update`` now refuses a sheared or scaled field.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

from volwarp_cli.io import read_volume, write_volume
from volwarp_cli.morph.grid import GridError, explicit_grid
from volwarp_cli.morph.pipeline import prepare
from volwarp_cli.morph.spec import MorphJob, ShapeRef
from volwarp_cli.volume import Volume

S = float(np.sqrt(0.5))
CENTRE, RADIUS, N = 8.0, 4.0, 17


def ball(n=N, origin=0.0):
    """The ball of RADIUS about (8, 8, 8) on a 1 mm grid of ``n`` voxels from ``origin``."""
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float64) + origin
    return (np.sqrt((x - CENTRE) ** 2 + (y - CENTRE) ** 2 + (z - CENTRE) ** 2)
            <= RADIUS).astype(np.uint8) * 100


SPEC = """\
version: 1
source: {volume: ball.nrrd, iso: 50}
target: {volume: ball.nrrd, iso: 50}
frames: 2
grid:
  origin: [-4, -4, -4]
  spacing: 1
  size: [30, 30, 30]
  direction: DIRECTION
"""


@pytest.fixture
def ball_file(tmp_path):
    write_volume(Volume(ball()), tmp_path / "ball.nrrd")
    return tmp_path


@pytest.mark.parametrize("direction, said", [
    ([[1, 0, S], [0, 1, 0], [0, 0, S]], "x-z 45"),      # z leans 45 degrees towards x
    ([[1, 0, 1], [0, 1, 0], [0, 0, 1]], "z 1.41421"),   # and is sqrt(2) long
    ([[2, 0, 0], [0, 1, 0], [0, 0, 1]], "x 2,"),        # x steps 2 mm on a spacing of 1
    ([[0.5, 0, 0], [0, 0.5, 0], [0, 0, 0.5]], "x 0.5"),
])
def test_a_frame_grid_not_orthonormal_is_a_spec_error_at_grid_direction(run, ball_file,
                                                                         direction, said):
    (ball_file / "m.yaml").write_text(SPEC.replace("DIRECTION", str(direction)))
    r = run("morph", "--spec", ball_file / "m.yaml", "-o", ball_file / "f_{i}.nrrd")
    assert r.code == 2, r.stderr
    assert "m.yaml:9: grid.direction:" in r.stderr and said in r.stderr, r.stderr
    assert "lengths" in r.stderr and "angles" in r.stderr
    assert not list(ball_file.glob("f_*"))
    with pytest.raises(GridError) as err:
        explicit_grid({"origin": [0, 0, 0], "spacing": 1, "size": [4, 4, 4],
                       "direction": direction})
    assert err.value.key == ("grid", "direction")


def test_a_rounded_rotation_is_a_frame_grid_and_its_fill_is_the_world_distance():
    """(Kept right) six decimals of a 45 degree turn pass; the fill is within the scheme's own error.

    The reference: scipy's exact EDT of the same ball on a 1 mm grid covering
    every frame voxel's world point, sampled there as the morph samples its
    input's field (trilinear).
    """
    r6 = round(S, 6)
    grid = {"origin": [-4.0, -4.0, -4.0], "spacing": 1.0, "size": [30, 30, 30],
            "direction": [[r6, -r6, 0], [r6, r6, 0], [0, 0, 1]]}
    src = Volume(ball())
    job = MorphJob(source=ShapeRef(Path("s"), 50.0), target=ShapeRef(Path("t"), 50.0),
                   times=[0.0], grid=grid)
    prep = prepare(job, src, src)
    field = prep.morph.field(0.0)
    g = prep.grid
    k, j, i = np.mgrid[:g.shape[0], :g.shape[1], :g.shape[2]]
    world = np.stack([i, j, k], -1).astype(np.float64) @ g.matrix.T + g.origin_array
    off, n = -40.0, 121
    inside = ball(n, off) > 0
    exact = ndi.distance_transform_edt(~inside) - ndi.distance_transform_edt(inside)
    idx = (world - off)[..., ::-1].reshape(-1, 3).T
    ref = ndi.map_coordinates(exact, idx, order=1).reshape(field.shape)
    uncovered = np.any((world < -0.5) | (world > N - 0.5), axis=-1)
    assert uncovered.sum() > 10000
    rel = (field - ref)[uncovered] / ref[uncovered]
    assert -0.1 < rel.min() and rel.max() < 0.15, (rel.min(), rel.max())


def _scaled_mha(path, data, x_length=2.0):
    """A MetaImage whose TransformMatrix's x column is ``x_length`` long (ITK keeps it so)."""
    n = data.shape
    header = (f"ObjectType = Image\nNDims = 3\nBinaryData = True\n"
              f"BinaryDataByteOrderMSB = False\nCompressedData = False\n"
              f"TransformMatrix = {x_length} 0 0 0 1 0 0 0 1\nOffset = 0 0 0\n"
              f"ElementSpacing = 1 1 1\nDimSize = {n[2]} {n[1]} {n[0]}\n"
              f"ElementType = MET_UCHAR\nElementDataFile = LOCAL\n")
    path.write_bytes(header.encode() + np.ascontiguousarray(data, np.uint8).tobytes())


def test_distance_refuses_a_metaimage_whose_direction_is_scaled(run, tmp_path):
    """Before: exit 0 and a field 4 mm (50 %) off scipy's EDT with the world steps (2, 1, 1)."""
    import SimpleITK as sitk

    _scaled_mha(tmp_path / "b.mha", ball())
    im = sitk.ReadImage(str(tmp_path / "b.mha"))
    assert im.TransformIndexToPhysicalPoint((1, 0, 0)) == (2.0, 0.0, 0.0)  # ITK's world step
    r = run("distance", tmp_path / "b.mha", "--iso", 50, "-o", tmp_path / "d.nrrd")
    assert r.code == 1, r.stderr
    assert "b.mha" in r.stderr and "not unit vectors (lengths 2, 1, 1" in r.stderr
    assert not (tmp_path / "d.nrrd").exists()
    # what the message says to do gives the world distance
    assert run("convert", tmp_path / "b.mha", "-o", tmp_path / "b.nrrd").code == 0
    assert run("distance", tmp_path / "b.nrrd", "--iso", 50, "-o", tmp_path / "d.nrrd").code == 0
    got = read_volume(tmp_path / "d.nrrd").data
    mask = ball() > 0
    step = (1.0, 1.0, 2.0)  # (z, y, x)
    ref = (ndi.distance_transform_edt(~mask, sampling=step)
           - ndi.distance_transform_edt(mask, sampling=step))
    np.testing.assert_allclose(got, ref, atol=1e-5)


@pytest.mark.parametrize("direction", [[[1, 0, S], [0, 1, 0], [0, 0, S]],
                                       [[2, 0, 0], [0, 1, 0], [0, 0, 1]]])
def test_distance_update_refuses_a_sheared_or_scaled_field(run, tmp_path, direction):
    """Before: exit 0, the uncovered voxels filled by the spacing along axes that are not the world's."""
    mask = ball() > 0
    sdf = (ndi.distance_transform_edt(~mask) - ndi.distance_transform_edt(mask)).astype(np.float32)
    write_volume(Volume(sdf, direction=np.array(direction, float)), tmp_path / "f.nrrd")
    if np.allclose(np.linalg.norm(direction, axis=0), 1):
        old = tmp_path / "f.nrrd"
    else:  # (NRRD folds the lengths into the spacing: a MetaImage keeps them)
        old = tmp_path / "f.mha"
        write_volume(Volume(sdf, direction=np.array(direction, float)), old)
    (tmp_path / "t.yaml").write_text("version: 1\ntranslate: [3.0, 0.0, 0.0]\n")
    r = run("distance", "--update", old, "--transform", tmp_path / "t.yaml",
            "--metric", "euclidean", "-o", tmp_path / "new.nrrd")
    assert r.code == 1, r.stderr
    assert str(old) in r.stderr and ("sheared" in r.stderr or "not unit" in r.stderr)
    assert not (tmp_path / "new.nrrd").exists()


# -- the other grids a user gives (kept right: these pass before the fix too) --------------
def test_a_sweep_grid_takes_no_direction(run, tmp_path):
    (tmp_path / "s.yaml").write_text(
        "version: 1\ngrid: {spacing: 1, direction: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}\n"
        "fields:\n  opacity: 1\ntrajectory:\n  - line: {from: [0, 0, 0], to: [10, 0, 0]}\n"
        "scale: [4, 4]\n")
    r = run("sweep", tmp_path / "s.yaml", "-o", tmp_path / "o.nrrd")
    assert r.code == 2 and "direction" in r.stderr, r.stderr
    assert not (tmp_path / "o.nrrd").exists()


@pytest.mark.parametrize("direction, ext", [([[1, 0, S], [0, 1, 0], [0, 0, S]], "nrrd"),
                                            ([[2, 0, 0], [0, 1, 0], [0, 0, 1]], "mha")])
def test_apply_onto_a_sheared_or_scaled_reference_is_simpleitk_s_resample(run, tmp_path,
                                                                         direction, ext):
    import SimpleITK as sitk

    z, y, x = np.mgrid[:24, :24, :24].astype(np.float64)
    write_volume(Volume((np.sin(x / 3) + np.cos(y / 4) + z / 10).astype(np.float32),
                        spacing=(1.0, 1.0, 1.5)), tmp_path / "in.nrrd")
    write_volume(Volume(np.zeros((10, 12, 11), np.float32), spacing=(0.9, 1.1, 1.2),
                        origin=(3.0, 2.0, 4.0), direction=np.array(direction, float)),
                 tmp_path / f"ref.{ext}")
    sitk.WriteTransform(sitk.AffineTransform(3), str(tmp_path / "id.tfm"))
    r = run("apply", tmp_path / "in.nrrd", "--reference", tmp_path / f"ref.{ext}", "-t",
            tmp_path / "id.tfm", "--interpolation", "linear", "-o", tmp_path / "out.nrrd")
    assert r.code == 0, r.stderr
    ref = sitk.ReadImage(str(tmp_path / f"ref.{ext}"))
    expected = sitk.Resample(sitk.ReadImage(str(tmp_path / "in.nrrd")), ref, sitk.Transform(),
                             sitk.sitkLinear, 0.0)
    out = sitk.ReadImage(str(tmp_path / "out.nrrd"))
    corner = (10, 11, 9)
    np.testing.assert_allclose(out.TransformIndexToPhysicalPoint(corner),
                               ref.TransformIndexToPhysicalPoint(corner), atol=1e-9)
    e = sitk.GetArrayFromImage(expected)
    covered = e != 0
    assert covered.sum() > 1000
    np.testing.assert_allclose(sitk.GetArrayFromImage(out)[covered], e[covered], atol=1e-5)
