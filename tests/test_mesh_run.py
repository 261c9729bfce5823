"""The mesh as an operation of the executor (volwarp_cli.surface.run), without click: exact
answers, the same in memory and by blocks."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from volwarp_cli import execute
from volwarp_cli.engine import open_engine
from volwarp_cli.errors import VolwarpError
from volwarp_cli.surface.ops import Cleanup, clean
from volwarp_cli.surface.run import ALL_LABELS, Level, MeshOperation
from volwarp_cli.surface.stats import mesh_stats
from volwarp_cli.volume import Header, Volume

BY_BLOCKS = execute.How(chunked=True, block=(5, 7, 6),
                        open_engine=functools.partial(open_engine, "threads", workers=2))


def surfaces(vol, level=Level(), how=execute.How(), **options):
    """The operation's surfaces of ``vol`` (in memory unless ``how`` says blocks)."""
    ran = execute.run(MeshOperation(vol, vol.data, level, stats=True, **options), how)
    assert ran.by_blocks == (how.chunked is True)
    return ran.output


def surface(vol, level=Level(), how=execute.How(), **options):
    (one,) = surfaces(vol, level, how, **options)
    return one.mesh, one.iso


def _radius(n=32, c=15.5, spacing=(1.0, 1.0, 1.0)):
    z, y, x = np.mgrid[:n, :n, :n].astype(np.float64)
    sx, sy, sz = spacing
    return np.sqrt(((x - c) * sx) ** 2 + ((y - c) * sy) ** 2 + ((z - c) * sz) ** 2)


def assert_same_mesh(a, b):
    for x, y in ((a.vertices, b.vertices), (a.faces, b.faces), (a.normals, b.normals)):
        assert x.dtype == y.dtype and np.array_equal(x.view(np.uint8), y.view(np.uint8))


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (0.8, 1.0, 1.25)])
def test_sphere_area_and_volume_within_one_percent(spacing):
    r = 9.0
    vol = Volume(_radius(spacing=spacing).astype(np.float32), spacing=spacing)
    mesh, iso = surface(vol, Level(r, "below"))
    st = mesh_stats(mesh)
    assert iso == r and st["closed"] and st["components"] == 1
    assert st["area"] == pytest.approx(4 * math.pi * r * r, rel=0.01)
    assert st["volume"] == pytest.approx(4 / 3 * math.pi * r ** 3, rel=0.01)
    blocked, _ = surface(vol, Level(r, "below"), BY_BLOCKS)
    assert_same_mesh(blocked, mesh)


def test_default_level_is_the_middle_of_the_range():
    data = np.zeros((10, 10, 10), np.float32)
    data[3:7, 3:7, 3:7] = 4.0
    mesh, iso = surface(Volume(data))
    assert iso == 2.0 and mesh.n_faces > 0
    assert surface(Volume(data), how=BY_BLOCKS)[1] == 2.0


@pytest.mark.parametrize("how", [execute.How(), BY_BLOCKS], ids=["memory", "blocks"])
def test_a_level_never_crossed_is_an_error_unless_allowed(how):
    vol = Volume(_radius().astype(np.float32))
    with pytest.raises(VolwarpError, match=r"outside the data range.*scan\.nrrd.*--allow-empty"):
        surface(vol, Level(1e6), how, name="scan.nrrd")
    mesh, _ = surface(vol, Level(1e6), how, allow_empty=True)
    assert mesh.is_empty
    # (a volume of one value: said as such, not as a level never crossed)
    with pytest.raises(VolwarpError, match="every voxel of .* is 1: there is no surface"):
        surface(Volume(np.ones((15, 15, 15), np.float32)), Level(1.0), how)


@pytest.mark.parametrize("how", [execute.How(), BY_BLOCKS], ids=["memory", "blocks"])
def test_nan_samples_are_refused(how):
    data = np.ones((16, 16, 16), np.float32)
    data[12, 2, 9] = np.nan
    with pytest.raises(VolwarpError, match="NaN"):
        surface(Volume(data), Level(0.5), how)


def test_cap_closes_a_shape_on_the_border():
    data = np.zeros((12, 12, 12), np.float32)
    data[:6] = 1.0  # a slab touching five faces
    open_mesh, _ = surface(Volume(data), Level(0.5))
    closed, _ = surface(Volume(data), Level(0.5, cap=True))
    assert not mesh_stats(open_mesh)["closed"] and mesh_stats(closed)["closed"]
    assert_same_mesh(surface(Volume(data), Level(0.5, cap=True), BY_BLOCKS)[0], closed)


def test_cleanups_in_order_and_by_blocks():
    big = np.where(_radius(c=22.0) < 7, 1.0, 0.0) + np.where(_radius(c=8.0) < 4, 1.0, 0.0)
    vol = Volume(big.astype(np.float32))
    both, _ = surface(vol, Level(0.5))
    assert mesh_stats(both)["components"] == 2
    one, _ = surface(vol, Level(0.5), cleanup=Cleanup(largest_component=True))
    st = mesh_stats(one)
    assert st["components"] == 1 and st["volume"] > 4 / 3 * math.pi * 6 ** 3
    fewer = clean(one, Cleanup(decimate=0.5))
    assert fewer.n_faces <= one.n_faces * 0.55
    smooth = clean(one, Cleanup(smooth=10))
    assert mesh_stats(smooth)["volume"] == pytest.approx(st["volume"], rel=0.05)
    chain = Cleanup(largest_component=True, smooth=10, decimate=0.5)
    in_memory, _ = surface(vol, Level(0.5), cleanup=chain)
    assert_same_mesh(in_memory, clean(one, chain))
    assert_same_mesh(surface(vol, Level(0.5), BY_BLOCKS, cleanup=chain)[0], in_memory)


def _labels():
    lab = np.zeros((16, 16, 16), np.uint16)
    lab[2:6, 2:7, 2:5] = 4  # 3 x 5 x 4 voxels (x y z)
    lab[8:14, 3:9, 5:11] = 9  # 6 x 6 x 6
    return Volume(lab, spacing=(0.5, 1.0, 2.0))


@pytest.mark.parametrize("how", [execute.How(), BY_BLOCKS], ids=["memory", "blocks"])
def test_label_surfaces_are_closed_boxes_of_the_labels_volume(how):
    """A box of a x b x c voxels: its indicator's surface at 0.5 runs along the voxels'
    faces, each of the 12 edges bevelled (a prism of cross-section 1/8 voxel face lost)
    and each of the 8 corners giving 1/12 voxel back: exactly abc - (a + b + c)/2 + 2/3
    voxels."""
    vol = _labels()
    got = {s.label: s for s in surfaces(vol, how=how, labels=ALL_LABELS)}
    assert list(got) == [4, 9]
    voxel = 0.5 * 1.0 * 2.0
    for label, (a, b, c) in ((4, (3, 5, 4)), (9, (6, 6, 6))):
        st = got[label].stats
        assert got[label].mesh is None and got[label].iso == 0.5  # (not kept: stats only)
        assert st["closed"] and st["components"] == 1
        exact = (a * b * c - (a + b + c) / 2 + 2 / 3) * voxel
        assert st["volume"] == pytest.approx(exact, rel=1e-9)
    one, iso = surface(vol, how=how, labels=9)
    assert iso == 0.5 and mesh_stats(one) == got[9].stats


def test_label_refusals():
    vol = _labels()
    with pytest.raises(VolwarpError, match="label 5 does not occur"):
        surface(vol, labels=5, name="seg.nrrd")
    with pytest.raises(VolwarpError, match="--label needs a label map"):
        surface(Volume(np.zeros((4, 4, 4), np.complex64)), labels=1)
    # (a float map of whole ids is one, as distance takes it; of other values, not)
    with pytest.raises(VolwarpError, match="label 1 does not occur"):
        surface(Volume(np.zeros((4, 4, 4), np.float32)), labels=1)
    with pytest.raises(VolwarpError, match=r"--labels needs a label map \(integer ids\)"):
        surfaces(Volume(np.full((4, 4, 4), 0.5, np.float32)), labels=ALL_LABELS)
    with pytest.raises(VolwarpError, match="no label other than 0"):
        surfaces(Volume(np.zeros((4, 4, 4), np.int8)), labels=ALL_LABELS)


def test_memory_is_the_volumes_side_and_blocks_are_slabs():
    """What the decision reads before any sample: the samples read, their working copy and
    flying edges' bytes per voxel; the blocks are whole planes, as deep as fits."""
    header = Header((40, 30, 20), np.uint8)

    class Lazy:  # a source read on slicing (its samples cost memory when read)
        shape, dtype = (40, 30, 20), np.dtype(np.uint8)

    box = header.shape
    plain = MeshOperation(header, Lazy(), Level(1.0))
    capped = MeshOperation(header, Lazy(), Level(1.0, cap=True))
    labels = MeshOperation(header, Lazy(), labels=ALL_LABELS)
    in_memory = MeshOperation(header, np.zeros(box, np.uint8), Level(1.0))
    whole = plain.grid.box
    assert plain.memory(whole) == whole.size * (1 + 4)
    assert capped.memory(whole) == whole.size * (1 + 4 + 4)  # the padded float32 copy
    assert labels.memory(whole) == whole.size * (1 + 5 + 4 + 4)
    assert in_memory.memory(whole) == whole.size * 4
    # 32-bit integers run as float64 (VTK's s1 - s0 would wrap in their own type): the
    # widened copy is 8 bytes a voxel, beside the samples read
    wide = Header((40, 30, 20), np.uint32)
    lazy_wide = type("LazyWide", (Lazy,), {"dtype": np.dtype(np.uint32)})()
    assert MeshOperation(wide, lazy_wide, Level(1.0)).memory(whole) == whole.size * (4 + 8 + 4)
    assert MeshOperation(wide, np.zeros(box, np.uint32), Level(1.0)).memory(whole) == \
        whole.size * (8 + 4)
    per_plane = 30 * 20 * (1 + 4 + 32)
    assert plain.block_shape(10 * per_plane, 2) == (10, 30, 20)
    assert plain.block_shape(per_plane, 2) == (8, 30, 20)  # 8 planes at least
    assert plain.block_shape(1000 * per_plane, 1) == (20, 30, 20)  # two blocks a worker
